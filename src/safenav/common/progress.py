"""The terminal view of a training run: a one-line Rich status bar on a TTY, plain log lines
otherwise.

The bar is one line that never wraps: what matters comes first and always shows (step/total,
ETA, steps/s, success and collision rates of the last 100 episodes, lambda and d: 67 characters
with a 10-character bar), the rest (run title, return, alpha, elapsed time) only where the
terminal is wide enough.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque

from rich.console import Console, ConsoleOptions, RenderResult
from rich.live import Live
from rich.text import Text

MIN_BAR = 10


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _count(n: float) -> str:
    """4 significant characters: 999, 12.3k, 1.23M."""
    if n < 10_000:
        return f"{n:.0f}"
    for div, unit in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if n >= div:
            v = n / div
            return f"{v:.3g}{unit}" if v < 1000 else f"{v:.0f}{unit}"
    return f"{n:.0f}"  # pragma: no cover


def _clock(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "-:--:--"
    s = int(seconds)
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class ProgressDisplay:
    """``advance(step)`` every iteration, ``metrics(...)`` at each log row, ``note(text)`` for events.

    On a terminal: the one-line bar of the module docstring. When stderr is not a terminal
    (``nohup``, CI), each log row becomes one printed line instead.
    """

    def __init__(self, total: int, start: int = 0, enabled: bool = True, title: str = "train",
                 console: Console | None = None) -> None:  # fmt: skip
        self.console = console or Console(stderr=True)
        self.enabled = enabled
        self.title = title
        self.total, self.step, self.start = total, start, start
        self.t0 = time.monotonic()
        self._samples: deque[tuple[float, int]] = deque(maxlen=50)  # (time, step) for the rate
        self._samples.append((self.t0, start))
        self._last = 0.0
        self.fields: dict[str, float | None] = {}
        self.live: Live | None = None
        if enabled and self.console.is_terminal:
            self.live = Live(self, console=self.console, refresh_per_second=4, transient=False)
            self.live.start()

    # -- what the line says ---------------------------------------------------------------
    def rate(self) -> float | None:
        """Env steps per second over the last samples (up to ~50 updates)."""
        (t_a, s_a), (t_b, s_b) = self._samples[0], self._samples[-1]
        return (s_b - s_a) / (t_b - t_a) if t_b > t_a and s_b > s_a else None

    def eta(self) -> float | None:
        rate = self.rate()
        return (self.total - self.step) / rate if rate else None

    def line(self, width: int) -> str:
        """The status line for a terminal ``width`` columns wide (never longer)."""
        f = self.fields
        rate = self.rate()
        core = [f"{_count(self.step)}/{_count(self.total)}", f"ETA {_clock(self.eta())}",
                f"{_count(rate) if rate else '-'} steps/s", f"succ {_fmt(f.get('success'))}",
                f"coll {_fmt(f.get('collision'))}", f"λ {_fmt(f.get('lambda'), '.3g')}",
                f"d {_fmt(f.get('d'), '.3g')}"]  # fmt: skip
        extra = [f"ret {_fmt(f.get('return'), '.1f')}", f"α {_fmt(f.get('alpha'), '.3g')}",
                 _clock(time.monotonic() - self.t0)]  # fmt: skip
        text = " ".join(core)
        room = width - len(text) - 1  # one space before the bar's text
        for part in (self.title, *extra):  # the optional parts, while a 10+ bar still fits
            if room - len(part) - 1 >= MIN_BAR + 12:
                text = f"{self.title} {text}" if part is self.title else f"{text} {part}"
                room -= len(part) + 1
        bar_width = min(room, 40)
        if bar_width < 4:
            return text[:width]
        done = min(max(self.step / self.total, 0.0), 1.0) if self.total else 1.0
        filled = int(round(done * bar_width))
        return ("━" * filled + "─" * (bar_width - filled) + " " + text)[:width]

    def __rich_console__(self, console: Console, options: ConsoleOptions) -> RenderResult:
        yield Text(self.line(options.max_width), no_wrap=True, overflow="crop")

    # -- updates --------------------------------------------------------------------------
    def advance(self, step: int) -> None:
        self.step = step
        now = time.monotonic()
        if now - self._last > 0.2:
            self._samples.append((now, step))
            self._last = now

    def metrics(
        self, step: int, row: dict[str, float], recent: dict[str, deque], d: float | None
    ) -> None:
        mean = lambda k: (sum(recent[k]) / len(recent[k])) if recent[k] else math.nan  # noqa: E731
        succ = [s for s in recent["success"] if not math.isnan(s)]
        self.advance(step)
        self.fields = {"success": sum(succ) / len(succ) if succ else math.nan,
                       "collision": mean("collision"), "return": mean("return"),
                       "lambda": row.get("constraint/lambda"), "d": d,
                       "alpha": row.get("charts/alpha")}  # fmt: skip
        if self.live is None and self.enabled:
            sps = row.get("perf/sps")
            f = self.fields
            print(f"[{self.title}] step {step}/{self.total} sps {_fmt(sps, '.0f')} "
                  f"succ {_fmt(f['success'])} coll {_fmt(f['collision'])} ret {_fmt(f['return'], '.1f')} "
                  f"λ {_fmt(f['lambda'], '.3g')} d {_fmt(d, '.3g')} α {_fmt(f['alpha'], '.3g')}",
                  file=sys.stderr, flush=True)  # fmt: skip

    def note(self, text: str) -> None:
        if self.live is not None:
            self.live.console.print(text, highlight=False)
        elif self.enabled:
            print(f"[{self.title}] {text}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None

    @property
    def progress(self) -> Live | None:  # the name the trainers knew
        return self.live


__all__ = ["ProgressDisplay"]
