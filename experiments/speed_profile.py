"""Does the policy slow down near obstacles, and do its critics know that slowing down is safer?
(docs/csac-v1.md, "Why the constraint does not change the flight")

Flies a CSAC/SAC policy deterministically (the protocol of ``safenav eval``) on one validation map
and records, at every step, the UAV's speed and its clearance to the nearest surface (pillar,
moving obstacle or wall, after the 0.3 m body radius; ``info["clearance"]``). Reports:

- ``speed_by_clearance``: mean speed (m/s) and step count per clearance bin;
- ``saturated``: per action axis (goal frame x, y, z), the share of steps whose pre-tanh mean
  ``|mu|`` exceeds 2 (``tanh(2) = 0.96``; there ``d tanh / d mu < 0.071``: the reparameterised
  actor gradient reaching ``mu`` is cut >14x, and the sampled actions barely vary);
- with a *training* checkpoint (``RUN/checkpoint.pt``, which holds the critics): per clearance
  bin, how the critics value the same state with the action halved (half the commanded velocity):
  ``dqc_half = 1/2 sum_j Q_C,j(s, a/2) - 1/2 sum_j Q_C,j(s, a)`` (negative: the cost critics
  expect slowing down to be safer) beside ``qc``, the cost critics' value of the action flown, and
  ``dqr_half`` the same for ``min_j Q_R,j``.

Validation maps only (the test and held-out seeds are refused): it is a diagnostic for choices.

Run: ``.venv/bin/python experiments/speed_profile.py runs/NAME/checkpoint.pt [--episodes 100]
[--env-seed 12345] [--json OUT]`` (a ``policy.pt`` / ``best.pt`` works too, without the critics).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.algos.policy import policy_from_state
from safenav.common.checkpoint import load_checkpoint, restore_agent
from safenav.common.config import from_dict
from safenav.common.jsonout import write_json
from safenav.envs.nav import SafeNavVectorEnv
from safenav.experiments.evaluate import fixed_test_scenario
from safenav.experiments.selection import RESERVED_SEEDS, VALIDATION_SEEDS

BINS = (0.0, 0.5, 1.0, 2.0, 4.0, float("inf"))
"""Clearance bins in metres (surface to surface)."""


def _networks(path: Path):
    """(encoder, actor, qr or None, qc or None, env config) of a training checkpoint or a policy."""
    state = load_checkpoint(path)
    policy = policy_from_state(state, path)  # the file read once, for the policy and the critics
    if not hasattr(policy.actor.actor, "sample"):
        raise SystemExit(f"{path}: not a CSAC/SAC policy (tanh-Gaussian actor)")
    if "agent" not in state:
        return policy.actor.encoder, policy.actor.actor, None, None, policy.env_config()
    cfg = from_dict(CSACConfig, state["config"]["csac"])
    agent = CSAC(policy.obs_shapes, 3, cfg)
    restore_agent(agent, state, path)
    return agent.encoder, agent.actor, agent.qr, agent.qc, policy.env_config()


@torch.no_grad()
def profile(path: Path, env_seed: int, episodes: int) -> dict:
    if env_seed in RESERVED_SEEDS:
        raise SystemExit(f"env seed {env_seed} is a test or held-out map: choose on validation maps "
                         f"({', '.join(map(str, VALIDATION_SEEDS))})")  # fmt: skip
    encoder, actor, qr, qc, env_cfg = _networks(path)
    cfg, starts, goals = fixed_test_scenario(env_cfg, env_seed, episodes)
    env = SafeNavVectorEnv(episodes, config=cfg, output="torch", autoreset_mode="Disabled")
    obs, _ = env.reset(seed=env_seed, options={"starts": starts, "goals": goals})
    done = torch.zeros(episodes, dtype=torch.bool)
    # the start (at rest, in its clear disc) is left out: clearance comes with the first step
    clearance = torch.full((episodes,), float("nan"))
    rows: dict[str, list[np.ndarray]] = {
        k: [] for k in ("clear", "speed", "mu", "qc", "dqc", "dqr")
    }
    for _ in range(cfg.max_episode_steps):
        x = encoder(obs) if encoder is not None else obs
        mu, _ = actor(x)
        action = torch.tanh(mu)
        live = ~done & clearance.isfinite()
        rows["clear"].append(clearance[live].numpy())
        rows["speed"].append(env.vel[live].norm(dim=-1).numpy())
        rows["mu"].append(mu[live].abs().numpy())
        if qc is not None:
            half, q_c = 0.5 * action, qc(x, action).mean(0)
            rows["qc"].append(q_c[live].numpy())
            rows["dqc"].append((qc(x, half).mean(0) - q_c)[live].numpy())
            rows["dqr"].append(
                (qr(x, half).min(0).values - qr(x, action).min(0).values)[live].numpy()
            )
        obs, _, term, trunc, info = env.step(torch.where(done[:, None], 0.0, action))
        clearance = info["clearance"].float()
        done |= term | trunc
        if bool(done.all()):
            break
    data = {k: np.concatenate(v) for k, v in rows.items() if v}
    bins = []
    for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
        sel = (data["clear"] >= lo) & (data["clear"] < hi)
        row = {"clearance_m": [lo, hi], "steps": int(sel.sum()),
               "mean_speed": float(data["speed"][sel].mean()) if sel.any() else None}  # fmt: skip
        if "dqc" in data and sel.any():
            row["qc"] = float(data["qc"][sel].mean())
            row["dqc_half"] = float(data["dqc"][sel].mean())
            row["dqr_half"] = float(data["dqr"][sel].mean())
        bins.append(row)
    return {"checkpoint": str(path), "env_seed": env_seed, "episodes": episodes,
            "steps": int(data["speed"].size), "mean_speed": float(data["speed"].mean()),
            "saturated": (data["mu"] > 2.0).mean(0).round(4).tolist(),
            "critics": qc is not None, "speed_by_clearance": bins}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--env-seed", type=int, default=VALIDATION_SEEDS[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    res = profile(args.checkpoint, args.env_seed, args.episodes)
    print(f"{res['checkpoint']}: {res['steps']} steps, mean speed {res['mean_speed']:.2f} m/s, "
          f"|mu| > 2 on x/y/z: {res['saturated']}")  # fmt: skip
    for b in res["speed_by_clearance"]:
        extra = (f"  Q_C {b['qc']:.4f}  dQ_C(a/2) {b['dqc_half']:+.4f}  dQ_R(a/2) {b['dqr_half']:+.2f}"
                 if "dqc_half" in b else "")  # fmt: skip
        speed = f"{b['mean_speed']:.2f}" if b["mean_speed"] is not None else "  - "
        print(f"  clearance {b['clearance_m'][0]:.1f}-{b['clearance_m'][1]:.1f} m: "
              f"{b['steps']:6d} steps, speed {speed}{extra}")  # fmt: skip
    if args.json:
        write_json(args.json, res)


if __name__ == "__main__":
    main()
