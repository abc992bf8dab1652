"""How a training run stops before its last step, the same way in every trainer.

- **Ctrl-C / SIGINT**: checkpoint.pt is written at the current step, an ``interrupted`` event is
  logged, and the CLI exits with code 130; ``safenav train --resume DIR`` continues the run.
  :func:`enable_sigint` first makes sure the signal reaches the trainer at all.
- **Divergence**: a NaN or Inf in the update metrics (checked at every progress.csv row) or in the
  agent's weights (checked at every row and before every checkpoint write) stops training with
  :class:`TrainingDiverged` (one line, exit code 2) and a ``diverged`` event. Nothing is saved, so
  checkpoint.pt keeps the last good state.
- **Any other error**: if the weights are no longer finite, the divergence it was (NaN actions
  make the env fail before the next row); else an ``error`` event, then the exception propagates.
  Nothing is saved (the state may be half-updated).

A SIGKILL (or power loss) skips all of this: checkpoint.pt is then the last periodic checkpoint,
which :func:`~safenav.common.checkpoint.save_checkpoint` never leaves half-written.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import threading
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from safenav.common.checkpoint import save_checkpoint
from safenav.common.logger import RunLogger
from safenav.errors import SafenavError, one_line


class TrainingDiverged(SafenavError):
    """A loss or a weight became NaN/Inf; checkpoint.pt holds the last finite state."""


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, a cluster's preemption, Ray cancelling a trial): stop like Ctrl-C,
    with a checkpoint; the CLI exits with 143 (128 + SIGTERM)."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def process_running(pid: int) -> bool:
    """Whether ``pid`` is a process that has not exited (a zombie has, though ``kill(pid, 0)``
    still finds it)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return stat.rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):  # no /proc (macOS) or the process is gone
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True


def die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """Linux: this (child) process gets SIGTERM when the process that started it dies (a Ray
    worker, ``safenav bench``), so that a trainer never trains on as an orphan. ``preexec_fn``."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def enable_sigint() -> None:
    """Let SIGINT (Ctrl-C, ``kill -INT``) raise ``KeyboardInterrupt`` and SIGTERM
    :class:`Terminated` (a ``KeyboardInterrupt``) in this process: both checkpoint and stop.

    A child process inherits its parent's signal mask, and Ray's worker threads block SIGINT: a
    trainer started by ``safenav reproduce`` (a Ray task running ``python -m safenav train``)
    had SIGINT blocked, so the signal stayed pending and training went on. Unblocking it here
    (which also delivers a SIGINT that arrived while it was blocked) makes every trainer stop the
    same way however it was started. A SIGINT that was *ignored* (``SIG_IGN``, what a shell does
    for ``cmd &`` in a script) stays ignored: that was the caller's choice.
    """
    if hasattr(signal, "pthread_sigmask"):  # POSIX; the mask is per thread, this is the main one
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    # An embedding program may have left the OS default (terminate, no checkpoint) in place.
    main = threading.current_thread() is threading.main_thread()
    if main and signal.getsignal(signal.SIGINT) is signal.SIG_DFL:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # SIGTERM, by default an immediate exit (the last periodic checkpoint), stops like Ctrl-C.
    if main and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _raise_terminated)


@contextlib.contextmanager
def sigint_deferred() -> Iterator[None]:
    """Hold back a SIGINT or SIGTERM that arrives inside the block until the block is done.

    Around checkpoint writes: a ``KeyboardInterrupt`` raised inside ``torch.save`` makes its zip
    writer fail on exit with a ``RuntimeError`` that replaces the interrupt, so the trainer
    crashed instead of checkpointing and stopping (measured: Ctrl-C during a write).
    """
    if threading.current_thread() is not threading.main_thread():
        yield  # only the main thread receives signals (and may set handlers)
        return
    received: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {
        sig: signal.signal(sig, lambda signum, frame: received.append(signum)) for sig in held
    }
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    for sig in dict.fromkeys(received):  # each held signal once, in arrival order
        if callable(previous[sig]):
            previous[sig](sig, None)  # e.g. default_int_handler: KeyboardInterrupt, now


def nonfinite_metrics(metrics: Mapping[str, float]) -> list[str]:
    """Names of the metrics that are NaN or +-Inf."""
    return [k for k, v in metrics.items() if not math.isfinite(float(v))]


def nonfinite_tensors(module: nn.Module) -> list[str]:
    """Names of the floating-point parameters and buffers of ``module`` holding a NaN or Inf."""
    named = [(k, t) for k, t in module.state_dict().items() if t.is_floating_point()]
    if not named:
        return []
    finite = torch.stack([torch.isfinite(t).all() for _, t in named]).tolist()  # one sync
    return [k for (k, _), ok in zip(named, finite, strict=True) if not ok]


class RunGuard:
    """Checkpoint writes and early stops of one training run (see the module docstring).

    ``last_saved`` is the step of the checkpoint already on disk (a resumed run's), or None.
    """

    def __init__(self, run_dir: Path, logger: RunLogger, agent: nn.Module,
                 last_saved: int | None = None) -> None:  # fmt: skip
        self.path = Path(run_dir) / "checkpoint.pt"
        self.logger, self.agent, self.last_saved = logger, agent, last_saved

    def check(self, step: int, metrics: Mapping[str, float] | None = None) -> None:
        """Raise :class:`TrainingDiverged` if a metric or a weight is NaN/Inf (a few
        microseconds per tensor: meant for log and checkpoint times, not every update)."""
        bad = nonfinite_metrics(metrics or {}) or nonfinite_tensors(self.agent)
        if not bad:
            return
        shown = ", ".join(bad[:4]) + (f" and {len(bad) - 4} more" if len(bad) > 4 else "")
        kept = (f"{self.path} keeps the last good state (step {self.last_saved})"
                if self.last_saved is not None else "no checkpoint had been written yet")  # fmt: skip
        raise TrainingDiverged(
            f"training diverged at step {step}: {shown} became NaN/Inf; stopped without saving, "
            f"{kept}; lower the learning rates (or check the env's rewards) and retrain"
        )

    def save(self, step: int, state: dict[str, Any]) -> None:
        """Write checkpoint.pt atomically, unless the weights are no longer finite."""
        self.check(step)
        with sigint_deferred():
            save_checkpoint(self.path, state)
            self.last_saved = step

    def stopped(self, err: BaseException, step: int, checkpoint: Callable[[], None]) -> None:
        """Record why the loop ended early; on ``KeyboardInterrupt`` save first. The caller
        re-raises ``err``, unless this raises :class:`TrainingDiverged` (the weights are NaN)."""
        if isinstance(err, KeyboardInterrupt):
            try:
                checkpoint()
            except TrainingDiverged as diverged:
                self.logger.event(step, "diverged", error=str(diverged))
                raise
            self.logger.event(
                step, "interrupted", signal="SIGTERM" if isinstance(err, Terminated) else "SIGINT"
            )
        elif isinstance(err, TrainingDiverged):
            self.logger.event(step, "diverged", error=str(err))
        else:
            # NaN weights often fail elsewhere first (the env rejects NaN actions): name the cause
            try:
                self.check(step)
            except TrainingDiverged as diverged:
                self.logger.event(step, "diverged", error=str(diverged))
                raise diverged from err
            self.logger.event(step, "error", error=one_line(f"{type(err).__name__}: {err}", 500))


__all__ = ["RunGuard", "Terminated", "TrainingDiverged", "enable_sigint", "nonfinite_metrics",
           "nonfinite_tensors", "sigint_deferred"]  # fmt: skip
