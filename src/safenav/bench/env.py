"""``safenav bench env``: env steps per second of the batched simulator, and the ray caster's
speed-up over a brute-force reference (every beam against every pillar) measured in the same run.
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import torch
from rich.console import Console
from rich.progress import track
from rich.table import Table

from safenav.common.jsonout import write_json
from safenav.common.machine import machine_description
from safenav.envs.nav import SafeNavVectorEnv


def _steps_per_s(env: SafeNavVectorEnv, steps: int, repeats: int) -> float:
    """Median over ``repeats`` of env-steps per second over ``steps`` batched steps."""
    gen = torch.Generator(device="cpu").manual_seed(0)
    actions = (torch.rand(steps, env.num_envs, 3, generator=gen) * 2 - 1).to(env.device)
    env.reset(seed=0)
    for i in range(3):  # warm-up
        env.step(actions[i])
    rates = []
    for _ in range(repeats):
        if env.device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for i in range(steps):
            env.step(actions[i])
        if env.device.type == "cuda":
            torch.cuda.synchronize()
        rates.append(steps * env.num_envs / (time.perf_counter() - t0))
    return statistics.median(rates)


def range_error(num_envs: int = 64, steps: int = 50, preset: str = "paper") -> dict[str, float]:
    """Grid ray caster vs the brute-force reference on identical trajectories (metres)."""
    grid = SafeNavVectorEnv(num_envs, preset=preset, output="torch")
    brute = SafeNavVectorEnv(num_envs, preset=preset, output="torch", raycaster="bruteforce")
    grid.reset(seed=0)
    brute.reset(seed=0)
    gen = torch.Generator().manual_seed(1)
    errs = []
    for _ in range(steps):
        a = torch.rand(num_envs, 3, generator=gen) * 2 - 1
        og, ob = grid.step(a)[0], brute.step(a)[0]
        errs.append(((og["lidar"] - ob["lidar"]).abs() * grid.cfg.lidar_range).flatten())
    err = torch.cat(errs)
    return {
        "max_abs_range_error": float(err.max()),
        "p99_abs_range_error": float(err.quantile(0.99)),
        "median_abs_range_error": float(err.median()),
        "fraction_within_resolution": float(
            (err <= grid.cfg.grid_resolution + 1e-4).float().mean()
        ),
    }


def bench_env(
    json_out: Path | None = None,
    num_envs: tuple[int, ...] = (1, 64, 256, 1024),
    repeats: int = 5,
    preset: str = "paper",
    devices: tuple[str, ...] | None = None,
    console: Console | None = None,
) -> dict:
    console = console or Console()
    if devices is None:
        devices = ("cpu", "cuda") if torch.cuda.is_available() else ("cpu",)
    results = []
    jobs = [(d, n) for d in devices for n in num_envs]
    for device, n in track(jobs, description="bench env", console=console):
        env = SafeNavVectorEnv(n, preset=preset, device=device, output="torch")
        steps = 200 if n <= 64 else 40
        results.append({"device": device, "num_envs": n,
                        "steps_per_s": _steps_per_s(env, steps, repeats)})  # fmt: skip
    # The brute-force reference at a size it can handle, beside the grid caster at the same size.
    ref_n = 64
    brute = SafeNavVectorEnv(ref_n, preset=preset, output="torch", raycaster="bruteforce")
    grid = SafeNavVectorEnv(ref_n, preset=preset, output="torch")
    brute_rate = _steps_per_s(brute, 20, repeats)
    grid_rate = _steps_per_s(grid, 20, repeats)
    report = {
        "preset": preset,
        "results": results,
        "bruteforce_num_envs": ref_n,
        "bruteforce_steps_per_s": brute_rate,
        "grid_steps_per_s_at_bruteforce_size": grid_rate,
        "speedup_vs_bruteforce": grid_rate / brute_rate,
        **range_error(preset=preset),
        "torch_threads": torch.get_num_threads(),
        "machine": f"{machine_description()}; {torch.get_num_threads()} threads",
        "date": time.strftime("%Y-%m-%d"),
    }
    table = Table(title=f"SafeNav-v1 ({preset}) env-steps/s, median of {repeats}")
    for col in ("device", "num_envs", "steps/s"):
        table.add_column(col, justify="right")
    for r in results:
        table.add_row(r["device"], str(r["num_envs"]), f"{r['steps_per_s']:,.0f}")
    console.print(table)
    console.print(
        f"brute-force reference at {ref_n} envs: {brute_rate:,.0f} steps/s; grid: {grid_rate:,.0f} "
        f"({report['speedup_vs_bruteforce']:.1f}x); range error max {report['max_abs_range_error']:.3f} m, "
        f"p99 {report['p99_abs_range_error']:.3f} m, {100 * report['fraction_within_resolution']:.1f} % "
        "of beams within one cell"
    )
    if json_out is not None:
        write_json(json_out, report)
    return report
