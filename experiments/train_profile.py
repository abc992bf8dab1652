"""Where the minutes of a CSAC/SAC training run go (docs/csac-v1.md, "Where the minutes go").

Runs ``safenav train`` in this process with a timer around each of these functions and splits
its wall-clock into disjoint parts (a timed call inside another one counts for the outer part):

- ``env step``: ``TorchVecEnv.step`` while collecting (physics, moving obstacles, sensing, reward,
  autoreset); ``of which sensing``: ``SafeNavVectorEnv._sense`` inside it (range image, tracked
  obstacles);
- ``shield (training)``: ``MemoryShield.__call__`` while collecting, the velocity-obstacle
  shield's correction of each action when the run trains behind it (``--shield``, the default
  ``csac`` recipe); its own evaluations' shield counts in ``periodic evaluation``;
- ``actor forward``: ``CSAC.act`` while collecting; ``replay add``: ``ReplayBuffer.add``;
- ``gradient updates``: ``CSAC.update`` (Algorithm 1, lines 12-15); ``replay sample``:
  ``ReplayBuffer.sample``;
- ``periodic evaluation``, ``checkpoints``, ``progress rows``: ``Trainer.evaluate``,
  ``Trainer.checkpoint`` (the last one included), ``Trainer.log``;
- with ``--select``: ``selection (validation)``, the greedy soup on validation maps (part of the
  time to a run's policy), and ``report (test, held-out)``, its flights on the test and held-out
  scenarios (after the choice; since 2026-12-01 also the test under NavRL's collision rule);
- ``other``: the rest of ``safenav train`` (set-up, curricula, Python between the parts).

Run it alone on the machine: the figures are wall-clock seconds.

Run: ``.venv/bin/python experiments/train_profile.py [--json OUT] -- --algo csac --total-steps
100000 --seed 1 --run-dir runs/profile`` (everything after ``--`` goes to ``safenav train``).
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

from safenav.algos.csac import CSAC
from safenav.cli import main as safenav_main
from safenav.common.buffer import ReplayBuffer
from safenav.common.jsonout import write_json
from safenav.deploy.shield import MemoryShield
from safenav.envs.nav import SafeNavVectorEnv
from safenav.envs.vector import TorchVecEnv
from safenav.experiments import selection
from safenav.training.trainer import Trainer

PARTS = {
    "env step": (TorchVecEnv, "step"),
    "shield (training)": (MemoryShield, "__call__"),
    "actor forward": (CSAC, "act"),
    "replay add": (ReplayBuffer, "add"),
    "gradient updates": (CSAC, "update"),
    "replay sample": (ReplayBuffer, "sample"),
    "periodic evaluation": (Trainer, "evaluate"),
    "checkpoints": (Trainer, "checkpoint"),
    "progress rows": (Trainer, "log"),
    "selection (validation)": (selection, "select_final_policy"),
    "report (test, held-out)": (selection, "report_policy"),
}
NESTED = ("of which sensing", "env step", SafeNavVectorEnv, "_sense")
"""A share of ``env step``, timed only there."""


class Timers:
    """Seconds per part; ``active`` is the part whose call is running (None between parts)."""

    def __init__(self) -> None:
        order = list(PARTS)
        order.insert(order.index(NESTED[1]) + 1, NESTED[0])
        self.seconds = dict.fromkeys(order, 0.0)
        self.active: str | None = None

    def wrap(self, part: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if self.active is not None:  # inside another part: its time is that part's
                return fn(*args, **kwargs)
            self.active, t0 = part, time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[part] += time.perf_counter() - t0
                self.active = None

        return timed

    def wrap_nested(self, fn):
        name, outer = NESTED[0], NESTED[1]

        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if self.active != outer:
                return fn(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] += time.perf_counter() - t0

        return timed


def profile(train_args: list[str]) -> tuple[float, dict[str, float]]:
    """Run ``safenav train train_args`` with the timers in place; (total seconds, seconds per part
    with ``other`` = the rest)."""
    timers, saved = Timers(), []
    for part, (owner, name) in PARTS.items():
        saved.append((owner, name, getattr(owner, name)))
        setattr(owner, name, timers.wrap(part, getattr(owner, name)))
    owner, name = NESTED[2], NESTED[3]
    saved.append((owner, name, getattr(owner, name)))
    setattr(owner, name, timers.wrap_nested(getattr(owner, name)))
    t0 = time.perf_counter()
    try:
        safenav_main(["train", "--no-progress", *train_args])
    except SystemExit as err:
        if err.code not in (0, None):
            raise
    finally:
        total = time.perf_counter() - t0
        for owner, name, fn in saved:
            setattr(owner, name, fn)
    parts = dict(timers.seconds)
    parts["other"] = total - sum(v for k, v in parts.items() if k != NESTED[0])
    return total, parts


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("train_args", nargs=argparse.REMAINDER,
                    help="-- then the options of safenav train")  # fmt: skip
    args = ap.parse_args()
    train_args = [a for a in args.train_args if a != "--"]
    total, parts = profile(train_args)
    print(f"safenav train {' '.join(train_args)}: {total:.1f} s")
    for part, seconds in parts.items():
        indent = "    " if part == NESTED[0] else "  "
        print(f"{indent}{part:24s} {seconds:8.1f} s  {seconds / total:6.1%}")
    if args.json:
        write_json(args.json, {"train_args": train_args, "total_s": round(total, 2),
                               "parts_s": {k: round(v, 2) for k, v in parts.items()}})  # fmt: skip


if __name__ == "__main__":
    main()
