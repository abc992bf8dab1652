"""Can CSAC's actor fly SafeNav-v1 as well as the planner it cannot see? DAgger, as a diagnostic
(docs/csac-v1.md, "What the actor can learn: imitating the planner").

The privileged planner (:mod:`oracle_planner`, restricted to what an observation holds:
``--privileged-range 4``, 5 tracked obstacles, no map) reaches 0.909 success / 0.029 collision on
the validation maps; CSAC's policies reach about 0.55 / 0.43. Either the actor's network and
observation cannot represent a good policy, or reinforcement learning does not find it. DAgger
(Ross, Gordon & Bagnell, AISTATS 2011) separates the two: the student (the ``csac`` recipe's
actor, encoder included, the network that CSAC trains) is fitted by regression to the planner's
actions on the states the student itself visits.

Each iteration ``i``:

1. **Roll out** ``--envs`` training envs (maps from seeds >= 200000, a fresh draw per iteration,
   never a validation, test or held-out map) for ``--steps`` control steps; each env flies the
   planner's action with probability ``beta_i = --beta ** i`` per step, else the student's
   deterministic action. Every visited observation is recorded with the planner's action there.
2. **Fit** the student on all data so far: ``--updates`` Adam steps of the mean squared error
   between ``tanh(mean)`` and the planner's action (batch ``--batch``).
3. **Validate**: the deterministic student on the validation maps (``--val-episodes`` in all),
   the protocol of ``safenav eval``; its policy is written to ``OUT/student-iI.pt``
   (``safenav eval`` reads it).

At the end, :func:`agreement` measures how well the last student predicts the planner on the
planner's own flights (R^2 per action axis); ``--agreement-of STUDENT.pt`` measures it alone.

Run (about 4 min per iteration on the 2-core machine):
``.venv/bin/python experiments/teacher_student.py --out /work/runs/dagger --iterations 6``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from oracle_planner import OracleConfig, OraclePlanner  # noqa: F401 (OraclePlanner: tests)

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.algos.policy import POLICY_FORMAT_VERSION, load_policy, policy_from_state
from safenav.common.checkpoint import policy_state, save_checkpoint
from safenav.common.config import RunConfig, to_dict
from safenav.common.jsonout import write_json
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.planner import AutoresetPlanner
from safenav.experiments.evaluate import evaluate
from safenav.experiments.selection import VALIDATION_SEEDS
from safenav.recipes import apply, load_recipe

TRAIN_SEED0 = 200_000  # DAgger's maps: >= 100000 like training, apart from RunConfig's draws


Teacher = AutoresetPlanner
"""The planner as a labeller on auto-resetting envs (its per-episode memory restarts per env)."""


def build_student(recipe: str, env: SafeNavVectorEnv) -> tuple[CSAC, CSACConfig, RunConfig]:
    r = load_recipe(recipe)
    run = apply(RunConfig(), r.section("run"), "run.")
    cfg = apply(CSACConfig(), r.section("csac"), "csac.")
    shapes = {k: tuple(env.single_observation_space[k].shape) for k in env.single_observation_space}
    return CSAC(shapes, 3, cfg), cfg, run


def policy_file(agent: CSAC, cfg: CSACConfig, run: RunConfig, env: SafeNavVectorEnv,
                step: int) -> dict:  # fmt: skip
    meta = {"format_version": POLICY_FORMAT_VERSION, "algo": "csac", "env_id": "SafeNav-v1",
            "env_config": to_dict(env.cfg.replace(density=1.0)),
            "obs_shapes": {k: list(v) for k, v in agent.obs_shapes.items()}, "action_dim": 3,
            "action_low": [-1.0] * 3, "action_high": [1.0] * 3, "net": to_dict(cfg.net),
            "global_step": step, "trained_by": "dagger"}  # fmt: skip
    config = {"algo": "csac", "run": to_dict(run), "csac": to_dict(cfg)}
    return policy_state("csac", step, 0, 0.0, config, meta, agent.policy_module())


def validate(state: dict, episodes: int) -> dict:
    policy = policy_from_state(state, "student")
    cfg = policy.env_config()
    per = max(1, episodes // len(VALIDATION_SEEDS))
    res = [evaluate(policy, cfg, env_seed=s, episodes=per) for s in VALIDATION_SEEDS]
    keys = ("success_rate", "collision_rate", "timeout_rate", "collision_dynamic_rate",
            "collision_static_rate", "mean_speed")  # fmt: skip
    return {k: float(np.mean([r[k] for r in res])) for k in keys} | {"episodes": per * len(res)}


@torch.no_grad()
def agreement(policy, envs: int = 64, steps: int = 200, seed: int = TRAIN_SEED0 - 1000,
              privileged_range: float = 4.0) -> dict:  # fmt: skip
    """How well a student predicts the planner on the planner's own flights (fresh training
    maps): per action axis (goal-frame forward, lateral, vertical) the labels' variance, the
    student's mean squared error and R^2 = 1 - MSE / variance."""
    env = SafeNavVectorEnv(envs, preset="paper", output="torch")
    obs, _ = env.reset(seed=seed)
    teacher = Teacher(OracleConfig(privileged_range=privileged_range))
    labels, preds = [], []
    for _ in range(steps):
        label = teacher(obs, env)
        labels.append(label)
        preds.append(policy(obs))
        obs, *_ = env.step(label)
    y, p = torch.cat(labels), torch.cat(preds)
    var, mse = y.var(0), ((y - p) ** 2).mean(0)
    return {"axes": ["forward", "lateral", "vertical"], "label_var": var.tolist(),
            "mse": mse.tolist(), "r2": (1 - mse / var).tolist(), "samples": len(y)}  # fmt: skip


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--recipe", default="csac", help="whose actor network the student is")
    ap.add_argument("--iterations", type=int, default=6)
    ap.add_argument("--envs", type=int, default=128)
    ap.add_argument("--steps", type=int, default=400, help="control steps per iteration")
    ap.add_argument("--beta", type=float, default=0.5, help="planner share at iteration i: beta^i")
    ap.add_argument("--updates", type=int, default=3000, help="Adam steps per iteration")
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--val-episodes", type=int, default=416)
    ap.add_argument("--privileged-range", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--agreement-of",
        type=Path,
        default=None,
        help="only measure this student's agreement with the planner (then exit)",
    )
    ap.add_argument("--agreement-steps", type=int, default=200)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.agreement_of is not None:
        out = agreement(load_policy(args.agreement_of), steps=args.agreement_steps,
                        privileged_range=args.privileged_range)  # fmt: skip
        print(json.dumps(out))
        return [out]
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    args.out.mkdir(parents=True, exist_ok=True)

    env = SafeNavVectorEnv(args.envs, preset="paper", output="torch")
    agent, cfg, run = build_student(args.recipe, env)
    student = agent.policy_module()
    params = list(dict.fromkeys(student.parameters()))
    opt = torch.optim.Adam(params, lr=args.lr)
    teacher = Teacher(OracleConfig(privileged_range=args.privileged_range))
    names = student.input_names
    data: dict[str, list[torch.Tensor]] = {k: [] for k in (*names, "label")}
    log, t_start = [], time.perf_counter()
    for it in range(args.iterations):
        t0 = time.perf_counter()
        obs, _ = env.reset(seed=TRAIN_SEED0 + 1000 * (args.seed * 100 + it))
        beta = args.beta**it
        ends = {"success": 0, "collision": 0, "timeout": 0}
        for _ in range(args.steps):
            label = teacher(obs, env)
            with torch.no_grad():
                mine = student(*(obs[k] for k in names))
            use_teacher = torch.rand(args.envs, 1, generator=gen) < beta
            for k in names:
                data[k].append(obs[k].clone())
            data["label"].append(label.clone())
            obs, _, _, _, info = env.step(torch.where(use_teacher, label, mine))
            if "episode" in info:
                done = info["_episode"]
                for k in ends:
                    ends[k] += int(info["episode"][k][done].sum())
        t_roll = time.perf_counter() - t0
        tensors = {k: torch.cat(v) for k, v in data.items()}
        n = len(tensors["label"])
        student.train()
        losses = []
        for _ in range(args.updates):
            idx = torch.randint(n, (args.batch,), generator=gen)
            pred = student(*(tensors[k][idx] for k in names))
            loss = F.mse_loss(pred, tensors["label"][idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            losses.append(loss.item())
        student.eval()
        t_fit = time.perf_counter() - t0 - t_roll
        state = policy_file(agent, cfg, run, env, n)
        save_checkpoint(args.out / f"student-i{it}.pt", state)
        val = validate(state, args.val_episodes)
        row = {"iteration": it, "beta": beta, "samples": n, "rollout_episodes": ends,
               "loss": float(np.mean(losses[-200:])), "validation": val,
               "rollout_s": round(t_roll, 1), "fit_s": round(t_fit, 1),
               "wall_s": round(time.perf_counter() - t_start, 1)}  # fmt: skip
        log.append(row)
        print(f"iter {it} beta {beta:.3f} samples {n} episodes {ends} loss {row['loss']:.4f} | "
              f"validation success {val['success_rate']:.3f} collision {val['collision_rate']:.3f} "
              f"timeout {val['timeout_rate']:.3f} | {row['wall_s']:.0f} s", flush=True)  # fmt: skip
        record = {"settings": {**vars(args), "out": str(args.out), "machine": platform.node(),
                               "date": time.strftime("%Y-%m-%d")}, "iterations": log}  # fmt: skip
        write_json(args.out / "dagger.json", record)
    record["agreement"] = agreement(
        policy_from_state(state, "student"),
        steps=args.agreement_steps,
        privileged_range=args.privileged_range,
    )
    print(f"agreement with the planner on its own flights: R^2 {record['agreement']['r2']}")
    write_json(args.out / "dagger.json", record)
    return log


if __name__ == "__main__":
    main()
