"""``safenav bench {env,update,latency,soak}``: the benchmarks whose figures the README quotes."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import tyro

from safenav.cli import app


@app.command(name="bench")
def bench(
    which: tyro.conf.Positional[Literal["env", "update", "latency", "soak"]],
    json_out: Annotated[Path | None, tyro.conf.arg(name="json")] = None,
    repeats: int = 5,
    preset: str = "paper",
    num_envs: tuple[int, ...] = (1, 64, 256, 1024),
    env_steps: int = 10_000_000,
    updates: int = 100_000,
) -> None:
    """Measure throughput or latency and print a table; ``--json OUT`` writes the figures.

    env: env-steps/s at 1, 64, 256, 1024 envs (cpu, and cuda when present) and the grid ray
    caster's speed-up over a brute-force reference. update: gradient updates/s of CSAC and SAC
    beside Stable-Baselines3's SAC, and PPO's training throughput. latency: batch-1 policy and
    sensor-to-setpoint latency on one CPU thread. soak: ``--env-steps`` env steps and
    ``--updates`` CSAC updates, resident memory at the start and the end (no growth beyond the
    replay buffer).

    Args:
        which: The benchmark.
        json_out: Also write the figures here as JSON; the directory must exist.
        repeats: Repeats per measurement (1-1000; the median is reported).
        preset: Env preset of env and soak.
        num_envs: env: the env counts to measure.
        env_steps: soak: env steps.
        updates: soak: CSAC updates.
    """
    from safenav.common.checks import at_least, check_memory, check_output_file, in_range
    from safenav.common.memory import env_bytes
    from safenav.envs.config import make_config

    cfg = make_config(preset)  # ValueError for an unknown preset: exit 2
    in_range("--repeats", repeats, 1, 1000)
    at_least("--env-steps", env_steps, 1)
    at_least("--updates", updates, 1)
    if not num_envs:
        from safenav.errors import SafenavError

        raise SafenavError("--num-envs: give at least one count, e.g. --num-envs 1 64 256")
    for n in num_envs:
        at_least("--num-envs", n, 1)
    check_memory(env_bytes(max(num_envs), cfg), f"--num-envs {max(num_envs):,}",
                 "benchmark fewer envs")  # fmt: skip
    if json_out is not None:
        check_output_file(json_out, "--json", f"{which}.json")
    if which == "env":
        from safenav.bench.env import bench_env

        bench_env(json_out, num_envs=num_envs, repeats=repeats, preset=preset)
    elif which == "update":
        from safenav.bench.update import bench_update

        bench_update(json_out, repeats=repeats)
    elif which == "soak":
        from safenav.bench.soak import bench_soak

        bench_soak(json_out, env_steps=env_steps, updates=updates, preset=preset)
    else:
        from safenav.bench.latency import bench_latency

        bench_latency(json_out)
