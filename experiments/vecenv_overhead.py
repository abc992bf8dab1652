"""What the vector env wrapper costs per env step on a one-env MuJoCo task (docs/gymnasium.md,
"Observation and reward normalisation").

Times ``--steps`` env steps of ``--env`` (zero actions, one env) three ways, ``--repeats`` times
interleaved: the raw Gymnasium vector env, :class:`~safenav.envs.vector.TorchVecEnv` through
NumPy (``numpy_step``, the default on the CPU) and through torch, both with observation and
reward normalisation (``--no-normalize`` without). Prints the median and each repeat in ms.

Run: ``.venv/bin/python experiments/vecenv_overhead.py [--env Hopper-v5] [--steps 3000]
[--repeats 5] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from safenav.common.jsonout import write_json
from safenav.common.normalize import make_normalization
from safenav.envs.vector import TorchVecEnv, make_vec_env, obs_layout


def time_steps(step, action, steps: int) -> float:
    """Milliseconds per call of ``step(action)``."""
    start = time.perf_counter()
    for _ in range(steps):
        step(action)
    return (time.perf_counter() - start) / steps * 1e3


def wrapper(env_id: str, numpy_step: bool, normalize: bool) -> TorchVecEnv:
    envs = make_vec_env(env_id, 1)
    norm = (make_normalization(obs_layout(envs.single_observation_space), 1, 0.99, True, True)
            if normalize else None)  # fmt: skip
    env = TorchVecEnv(envs, "cpu", norm)
    env.numpy_step = numpy_step
    env.reset(seed=0)
    return env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="Hopper-v5")
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-normalize", action="store_true")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    torch.set_num_threads(1)
    times: dict[str, list[float]] = {"raw": [], "numpy": [], "torch": []}
    for _ in range(args.repeats):
        envs = make_vec_env(args.env, 1)
        envs.reset(seed=0)
        zeros = np.zeros((1, *envs.single_action_space.shape), np.float32)
        times["raw"].append(time_steps(envs.step, zeros, args.steps))
        for mode in ("numpy", "torch"):
            env = wrapper(args.env, mode == "numpy", not args.no_normalize)
            action = torch.zeros(1, env.action_dim)
            times[mode].append(time_steps(env.step, action, args.steps))
    summary = {k: {"median_ms": float(np.median(v)), "repeats_ms": v} for k, v in times.items()}
    for k, v in summary.items():
        print(
            f"{k:>6}: {v['median_ms']:.3f} ms per env step  ({', '.join(f'{x:.2f}' for x in v['repeats_ms'])})"
        )
    if args.json:
        write_json(args.json, {"env": args.env, "steps": args.steps,
                               "normalize": not args.no_normalize, **summary})  # fmt: skip


if __name__ == "__main__":
    main()
