"""The terminal view of a training run: a Rich progress bar on a TTY, plain log lines otherwise."""

from __future__ import annotations

import math
import sys
import time
from collections import deque

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


class ProgressDisplay:
    """``advance(step)`` every iteration, ``metrics(...)`` at each log row, ``note(text)`` for events.

    The bar shows step, SPS, success and collision rates (last 100 episodes), lambda, d, alpha. When
    stderr is not a terminal (``nohup``, CI), each log row becomes one printed line instead.
    """

    def __init__(
        self, total: int, start: int = 0, enabled: bool = True, title: str = "train"
    ) -> None:
        self.console = Console(stderr=True)
        self.live = enabled and self.console.is_terminal
        self.enabled = enabled
        self.title = title
        self._last = 0.0
        self.progress = None
        if self.live:
            self.progress = Progress(
                TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                console=self.console, transient=False,
            )  # fmt: skip
            self.task = self.progress.add_task(title, total=total, completed=start, info="")
            self.progress.start()

    def advance(self, step: int) -> None:
        if self.progress is not None:
            now = time.monotonic()
            if now - self._last > 0.2:
                self.progress.update(self.task, completed=step)
                self._last = now

    def metrics(
        self, step: int, row: dict[str, float], recent: dict[str, deque], d: float | None
    ) -> None:
        mean = lambda k: (sum(recent[k]) / len(recent[k])) if recent[k] else math.nan  # noqa: E731
        succ = [s for s in recent["success"] if not math.isnan(s)]
        info = (f"sps {_fmt(row.get('perf/sps'), '.0f')} succ {_fmt(sum(succ) / len(succ) if succ else math.nan)} "
                f"coll {_fmt(mean('collision'))} ret {_fmt(mean('return'), '.1f')} "
                f"λ {_fmt(row.get('constraint/lambda'), '.3g')} d {_fmt(d, '.3g')} "
                f"α {_fmt(row.get('charts/alpha'), '.3g')}")  # fmt: skip
        if self.progress is not None:
            self.progress.update(self.task, completed=step, info=info)
        elif self.enabled:
            print(f"[{self.title}] step {step} {info}", file=sys.stderr, flush=True)

    def note(self, text: str) -> None:
        if self.progress is not None:
            self.progress.console.print(text)
        elif self.enabled:
            print(f"[{self.title}] {text}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()
            self.progress = None


__all__ = ["ProgressDisplay"]
