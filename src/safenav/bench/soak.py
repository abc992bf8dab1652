"""``safenav bench soak``: long runs that would expose leaks -- memory at the start and the end.

Two phases in one process, resident memory (RSS) sampled by a background thread:

1. **env**: the vector env steps ``env_steps`` env-steps with random actions (autoreset, the
   density curriculum's map refreshes included); RSS must stay flat after the first 10 % (one-time
   allocations): ``env_growth_after_warmup_mb``.
2. **train**: CSAC trains for ``updates`` gradient updates through the real trainer
   (``safenav.training.train``: replay buffer, logging, TensorBoard, periodic evaluation and
   atomic checkpoints), with a replay buffer of ``buffer_size`` transitions that fills in the first
   half and then wraps around. RSS may grow while the buffer fills (its pages are touched then),
   and must be flat afterwards: ``train_growth_after_buffer_full_mb`` is the median RSS over the
   last 10 % of training minus the median over the 10 % just after the buffer filled (medians:
   evaluations and checkpoint writes make short peaks).

The networks are small (``--hidden``, ``--batch-size``) so that 10^5 updates fit in minutes on a
laptop CPU: leaks come from the loop (lists that grow, tensors kept alive, file handles), not
from the layer widths.
"""

from __future__ import annotations

import platform
import statistics
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from safenav.common.jsonout import write_json
from safenav.common.machine import machine_description


def rss_mb() -> float:
    """Resident memory of this process in MiB (Linux /proc; elsewhere the peak from getrusage)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource  # pragma: no cover -- non-Linux

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # pragma: no cover


class RssSampler:
    """Samples :func:`rss_mb` every ``period`` seconds in a daemon thread."""

    def __init__(self, period: float = 0.5) -> None:
        self.period = period
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._t0 = time.perf_counter()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.perf_counter() - self._t0, rss_mb()))
            self._stop.wait(self.period)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append((time.perf_counter() - self._t0, rss_mb()))

    def at(self, fraction: float) -> float:
        """RSS at ``fraction`` of the sampled time span."""
        t_end = self.samples[-1][0]
        return next(r for t, r in self.samples if t >= fraction * t_end)

    def median(self, start: float, end: float) -> float:
        """Median RSS over ``[start, end]`` fractions of the time span: robust to the transient
        peaks of evaluations and checkpoint writes."""
        t_end = self.samples[-1][0]
        window = [r for t, r in self.samples if start * t_end <= t <= end * t_end]
        return float(statistics.median(window or [self.samples[-1][1]]))


def soak_env(env_steps: int, num_envs: int, preset: str) -> dict[str, Any]:
    from rich.progress import Progress

    from safenav.envs import SafeNavVectorEnv, make_config

    env = SafeNavVectorEnv(num_envs, config=make_config(preset), output="torch")
    env.reset(seed=0)
    gen = torch.Generator().manual_seed(0)
    iters = max(1, env_steps // num_envs)
    episodes = 0
    start = rss_mb()
    with RssSampler() as rss, Progress(transient=True) as bar:
        task = bar.add_task(f"soak env: {iters * num_envs:,} env-steps", total=iters)
        t0 = time.perf_counter()
        for i in range(iters):
            action = torch.rand(num_envs, 3, generator=gen) * 2 - 1
            _, _, term, trunc, _ = env.step(action)
            episodes += int((term | trunc).sum())
            if i % 64 == 0:
                env.set_density(0.2 + 0.8 * i / iters)  # curriculum map refreshes, as in training
                bar.update(task, completed=i + 1)
        seconds = time.perf_counter() - t0
    return {
        "env_steps": iters * num_envs, "env_episodes": episodes, "env_seconds": round(seconds, 1),
        "env_steps_per_s": round(iters * num_envs / seconds), "env_rss_start_mb": round(start, 1),
        "env_rss_end_mb": round(rss_mb(), 1), "env_rss_max_mb": round(max(r for _, r in rss.samples), 1),
        "env_rss_growth_mb": round(rss_mb() - start, 1),
        # One-time allocations (caches, the first maps) happen early; a leak grows to the end.
        "env_rss_after_warmup_mb": round(rss.at(0.1), 1),
        "env_growth_after_warmup_mb": round(rss_mb() - rss.at(0.1), 1),
    }  # fmt: skip


def soak_train(updates: int, preset: str, hidden: tuple[int, ...], batch_size: int,
               buffer_size: int, num_envs: int) -> dict[str, Any]:  # fmt: skip
    from safenav import training
    from safenav.algos.config import CSACConfig
    from safenav.common.config import RunConfig

    learning_starts = 1_000
    total = learning_starts + updates  # one update per env step
    run = RunConfig(env="SafeNav-v1", preset=preset, num_envs=num_envs, seed=0, total_steps=total,
                    torch_threads=torch.get_num_threads(), log_every=max(1_000, total // 50),
                    eval_every=max(1, total // 4), eval_episodes=16, checkpoint_every=max(1, total // 10))  # fmt: skip
    cfg = CSACConfig()
    cfg = replace(cfg, batch_size=batch_size, buffer_size=buffer_size, learning_starts=learning_starts,
                  updates_per_step=1.0, net=replace(cfg.net, hidden=tuple(hidden)))  # fmt: skip
    start = rss_mb()
    with tempfile.TemporaryDirectory() as tmp, RssSampler() as rss:  # sampled while training
        t0 = time.perf_counter()
        final = training.train("csac", run, cfg, Path(tmp) / "run", progress=True)
        seconds = time.perf_counter() - t0
    # The buffer is full after buffer_size env steps: at that fraction of the run (env steps are
    # ~uniform in time, one update each). Compare the median RSS just after it with the last 10 %.
    full = min(0.85, buffer_size / total + 0.02)
    after_full, last = rss.median(full, full + 0.1), rss.median(0.9, 1.0)
    return {
        "updates": int(final.get("perf/updates", updates)), "train_env_steps": total,
        "train_seconds": round(seconds, 1), "buffer_size": buffer_size,
        "buffer_mb": round(buffer_size * transition_bytes(preset) / 2**20, 1),
        "train_rss_start_mb": round(start, 1), "train_rss_after_buffer_full_mb": round(after_full, 1),
        "train_rss_last_10pct_mb": round(last, 1), "train_rss_max_mb": round(max(r for _, r in rss.samples), 1),
        "train_growth_after_buffer_full_mb": round(last - after_full, 1),
    }  # fmt: skip


def transition_bytes(preset: str) -> int:
    """Bytes of one replay-buffer row (obs, next obs, action, reward, cost, terminated), from the
    buffer's own layout."""
    from safenav.common.buffer import ReplayBuffer
    from safenav.envs import make_config
    from safenav.envs.config import observation_shapes

    return ReplayBuffer(1, observation_shapes(make_config(preset)), 3).storage[0].nbytes


def bench_soak(
    json_out: Path | None = None,
    env_steps: int = 10_000_000,
    updates: int = 100_000,
    num_envs: int = 1024,
    preset: str = "paper",
    hidden: tuple[int, ...] = (64, 64),
    batch_size: int = 64,
    buffer_size: int = 50_000,
) -> dict[str, Any]:
    """Run both phases, print a table, write ``json_out``; returns the figures."""
    out: dict[str, Any] = {"preset": preset, "num_envs": num_envs}
    if env_steps > 0:
        out.update(soak_env(env_steps, num_envs, preset))
    if updates > 0:
        out.update(soak_train(updates, preset, hidden, batch_size, buffer_size, num_envs=16))
    out["machine"] = {"python": platform.python_version(), "torch": torch.__version__,
                      "processor": platform.processor() or platform.machine(),
                      "description": machine_description(),
                      "threads": torch.get_num_threads()}  # fmt: skip
    for k, v in out.items():
        if k != "machine":
            print(f"{k:<36}{v:>14}")
    if json_out is not None:
        write_json(json_out, out)
    return out


__all__ = ["RssSampler", "bench_soak", "rss_mb"]
