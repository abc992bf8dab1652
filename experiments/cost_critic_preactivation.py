"""Is a cost critic still alive? Its pre-activation on every replayed transition.

Loads a CSAC *training* checkpoint that keeps its replay buffer (``RUN/checkpoint.pt`` of a run
with ``--save-buffer``, the default of the Gymnasium recipes) and evaluates each cost critic's
linear output ``z`` (before the ``softplus`` or ``clipped`` read-out) at the stored ``(s, a)``,
in slices of the buffer in storage order (the order collected, until a full buffer wraps). For a
softplus critic the gradient of ``Q_C = softplus(z)`` is ``sigmoid(z)``: once ``z`` lies far below
0 on every transition (``sigmoid`` below Adam's ``eps`` of 1e-8 relative to the loss), no target
brings it back, and Q_C stays ~0 whatever the episodes cost (docs/gymnasium-results.md, the lambda warm-up
screen).

Run: ``.venv/bin/python experiments/cost_critic_preactivation.py RUN/checkpoint.pt
[--slices 10000 60000 ...] [--json OUT]``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from safenav.algos.config import CSACConfig
from safenav.algos.csac import CSAC
from safenav.common.checkpoint import load_checkpoint, restore_agent
from safenav.common.config import from_dict
from safenav.common.jsonout import write_json


@torch.no_grad()
def measure(path: Path, bounds: list[int]) -> dict:
    state = load_checkpoint(path)
    if "agent" not in state or "buffer" not in state:
        raise SystemExit(f"{path}: needs a training checkpoint with its replay buffer")
    cfg = from_dict(CSACConfig, state["config"]["csac"])
    buf = state["buffer"]
    n = int(buf["size"])
    if n == 0:
        raise SystemExit(f"{path}: an empty replay buffer: nothing to read")
    obs = {k: v[:n].float() for k, v in buf["obs"].items()}
    actions, costs = buf["actions"][:n].float(), buf["costs"][:n].float()
    agent = CSAC({k: tuple(v.shape[1:]) for k, v in obs.items()}, actions.shape[-1], cfg)
    restore_agent(agent, state, path)
    if agent.qc is None:
        raise SystemExit(f"{path}: an unconstrained run has no cost critic")
    x = agent.encoder(obs) if agent.encoder is not None else obs
    z = agent.qc.preactivation(x, actions)
    q_c = agent.qc.read(z)
    edges = sorted({0, *(b for b in bounds if 0 < b < n), n})
    slices = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        zz = z[:, lo:hi]
        slices.append({"from": lo, "to": hi, "cost_rate": float(costs[lo:hi].mean()),
                       "z_mean": float(zz.mean()), "z_min": float(zz.min()),
                       "z_max": float(zz.max()),
                       "sigmoid_z_max": float(torch.sigmoid(zz).max()),
                       "q_c_mean": float(q_c[:, lo:hi].mean())})  # fmt: skip
    return {"checkpoint": str(path), "global_step": int(state["global_step"]),
            "cost_critic_output": cfg.cost_critic_output, "transitions": n, "slices": slices}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--slices", type=int, nargs="*", default=[10_000, 60_000, 70_000],
                    help="buffer positions where a new slice starts")  # fmt: skip
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    res = measure(args.checkpoint, args.slices)
    print(
        f"{res['checkpoint']}: step {res['global_step']}, {res['cost_critic_output']} cost critics"
    )
    for s in res["slices"]:
        print(f"  transitions {s['from']:>7,}-{s['to']:<7,} cost rate {s['cost_rate']:.2f}  "
              f"z mean {s['z_mean']:9.1f} min {s['z_min']:9.1f} max {s['z_max']:7.1f}  "
              f"sigmoid(z) max {s['sigmoid_z_max']:.1e}  Q_C mean {s['q_c_mean']:.3g}")  # fmt: skip
    if args.json:
        write_json(args.json, res)


if __name__ == "__main__":
    main()
