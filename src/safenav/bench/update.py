"""``safenav bench update``: gradient updates per second of CSAC and SAC, with Stable-Baselines3's
SAC measured side by side in the same process as the reference.

What one "update" is, for every learner: sample a batch of 256 from a filled replay buffer, then
one full SAC step - target computation, critic step, actor step, temperature step (and for CSAC the
cost critics and the Lagrange multiplier), Polyak update of the targets.

- ``csac``/``sac``: the paper architecture on the SafeNav observation (range-image CNN + dynamic
  MLP + state -> 200 features, 256x256 MLPs), four critics (2 reward + 2 cost) or two.
- ``sb3_sac``: ``stable_baselines3.SAC("MlpPolicy")`` with ``net_arch=[256, 256]`` on a ``Box``
  observation of the same size (8 + 4*36 + 5*10 = 202 values, flattened), timed through its own
  ``SAC.train(gradient_steps, batch_size=256)``.

All three run with the same ``torch.set_num_threads``; the trials are interleaved (a load change
on the machine hits all alike) and the medians reported.
"""

from __future__ import annotations

import os
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safenav.common.jsonout import write_json
from safenav.common.machine import machine_description

SAFENAV_SHAPES = {"state": (8,), "lidar": (4, 36), "dynamic": (5, 10)}
BATCH = 256


def _our_learner(constrained: bool, shared_extractor: bool = True, device: str = "cpu"):
    from safenav.algos.config import CSACConfig
    from safenav.algos.csac import CSAC
    from safenav.common.buffer import ReplayBuffer
    from safenav.nn.config import NetConfig

    cfg = CSACConfig(constrained=constrained, net=NetConfig(shared_extractor=shared_extractor))
    agent = CSAC(SAFENAV_SHAPES, 3, cfg).to(device)
    buf = ReplayBuffer(20_000, SAFENAV_SHAPES, 3, device)
    gen = torch.Generator().manual_seed(0)
    n = 20_000
    obs = {k: torch.rand(n, *s, generator=gen) for k, s in SAFENAV_SHAPES.items()}
    nxt = {k: torch.rand(n, *s, generator=gen) for k, s in SAFENAV_SHAPES.items()}
    buf.add(obs, torch.rand(n, 3, generator=gen) * 2 - 1, torch.randn(n, generator=gen),
            (torch.rand(n, generator=gen) < 0.05).float(), nxt, torch.rand(n, generator=gen) < 0.01)  # fmt: skip

    def run(k: int) -> None:
        for _ in range(k):
            agent.update(buf.sample(BATCH), 0.1)
        if device == "cuda":
            torch.cuda.synchronize()

    return run


def _sb3_learner(device: str = "cpu"):
    import gymnasium as gym
    from stable_baselines3 import SAC

    dim = sum(int(np.prod(s)) for s in SAFENAV_SHAPES.values())

    class FlatEnv(gym.Env):
        observation_space = gym.spaces.Box(-1.0, 1.0, (dim,), np.float32)
        action_space = gym.spaces.Box(-1.0, 1.0, (3,), np.float32)

        def reset(self, *, seed=None, options=None):
            return self.observation_space.sample(), {}

        def step(self, action):
            return self.observation_space.sample(), 0.0, False, False, {}

    model = SAC("MlpPolicy", FlatEnv(), batch_size=BATCH, buffer_size=20_000, learning_starts=0,
                policy_kwargs={"net_arch": [256, 256]}, device=device, seed=0, verbose=0)  # fmt: skip
    from stable_baselines3.common.logger import Logger

    model.set_logger(Logger(folder=None, output_formats=[]))  # configure() makes a /tmp directory
    rng = np.random.default_rng(0)
    for _ in range(20):  # 20 x 1000 random transitions
        o = rng.random((1000, dim), dtype=np.float32)
        for i in range(1000):
            model.replay_buffer.add(o[i : i + 1], o[(i + 1) % 1000 : (i + 1) % 1000 + 1],
                                    rng.uniform(-1, 1, (1, 3)).astype(np.float32),
                                    np.array([rng.standard_normal()], np.float32), np.array([False]), [{}])  # fmt: skip

    def run(k: int) -> None:
        model.train(gradient_steps=k, batch_size=BATCH)
        if device == "cuda":
            torch.cuda.synchronize()

    return run


def bench_update(json_out: Path | None, repeats: int = 5, updates: int = 40,
                 threads: int | None = None, include_sb3: bool = True, device: str = "cpu",
                 bf16: bool = True) -> dict[str, Any]:  # fmt: skip
    """Measure updates/s (medians of ``repeats`` interleaved trials of ``updates`` updates each)
    and process CPU ms per update (robust to other load on the machine with one thread); with
    ``bf16`` also under ``torch.set_float32_matmul_precision("medium")`` (``*_bf16_*`` keys: bfloat16
    matmuls with float32 accumulation, AMX on recent Intel CPUs). Print a table, write
    ``json_out`` if given, return the figures."""
    from rich.console import Console
    from rich.table import Table

    threads = threads or os.cpu_count() or 1
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    learners = {"csac": _our_learner(True, device=device), "sac": _our_learner(False, device=device),
                "csac_separate_extractors": _our_learner(True, False, device)}  # fmt: skip
    sb3_version = None
    if include_sb3:
        try:
            import stable_baselines3

            sb3_version = stable_baselines3.__version__
            learners["sb3_sac"] = _sb3_learner(device)
        except ImportError:
            pass
    precisions = ("highest", "medium") if bf16 else ("highest",)
    suffix = {"highest": "", "medium": "_bf16"}
    for precision in precisions:  # warm-up (allocator, oneDNN primitives)
        torch.set_float32_matmul_precision(precision)
        for run in learners.values():
            run(5)
    rates: dict[str, list[float]] = {}
    cpu_ms: dict[str, list[float]] = {}
    for _ in range(repeats):  # interleaved: a change of load on the machine hits every learner
        for precision in precisions:
            torch.set_float32_matmul_precision(precision)
            for name, run in learners.items():
                key = name + suffix[precision]
                t0, c0 = time.perf_counter(), time.process_time()
                run(updates)
                rates.setdefault(key, []).append(updates / (time.perf_counter() - t0))
                cpu_ms.setdefault(key, []).append((time.process_time() - c0) / updates * 1e3)
    torch.set_float32_matmul_precision("highest")
    result: dict[str, Any] = {f"{k}_updates_per_s": statistics.median(r) for k, r in rates.items()}
    from safenav.bench.ppo import bench_ppo  # PPO: env steps/s, collection + update (paper preset)

    result["ppo_steps_per_s"] = bench_ppo(rollouts=repeats, device=device)
    result.update({f"{k}_cpu_ms_per_update": statistics.median(r) for k, r in cpu_ms.items()})
    result.update({
        "batch_size": BATCH, "threads": threads, "repeats": repeats, "updates_per_trial": updates,
        "all_trials": rates, "torch": torch.__version__, "stable_baselines3": sb3_version,
        "cpu": machine_description(), "device": device,
        "architecture": "paper: 3-layer circular CNN on lidar (4x36) -> 128, MLP on dynamic (5x10) -> 64, "
                        "+ state 8 = 200 features; actor and critics 256x256; shared extractor",
        "sb3_architecture": "MlpPolicy net_arch [256, 256] on a flattened Box(202) observation",
    })  # fmt: skip
    for sfx in [suffix[p] for p in precisions]:
        sb3 = result.get(f"sb3_sac{sfx}_updates_per_s")
        if sb3:
            result[f"sac{sfx}_vs_sb3{sfx}"] = result[f"sac{sfx}_updates_per_s"] / sb3
            result[f"csac{sfx}_vs_sb3{sfx}"] = result[f"csac{sfx}_updates_per_s"] / sb3
    title = f"gradient updates/s, batch {BATCH}, {threads} torch threads, {device} (median of {repeats})"
    table = Table(title=title)
    table.add_column("learner")
    table.add_column("matmuls")
    table.add_column("updates/s", justify="right")
    table.add_column("ms/update", justify="right")
    table.add_column("CPU ms/update", justify="right")
    for precision in precisions:
        for name in learners:
            key = name + suffix[precision]
            r = result[f"{key}_updates_per_s"]
            table.add_row(name, "float32" if precision == "highest" else "bf16", f"{r:.1f}",
                          f"{1000 / r:.2f}", f"{result[f'{key}_cpu_ms_per_update']:.2f}")  # fmt: skip
    Console().print(table)
    Console().print(f"PPO training (bench/ppo.py): {result['ppo_steps_per_s']:.0f} env steps/s")
    if json_out is not None:
        write_json(json_out, result)
    return result


__all__ = ["bench_update"]
