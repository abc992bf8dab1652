"""End training runs as ``safenav train --select`` ends one: the policy chosen on validation maps
only (greedy soup of the policies kept in the run's last half, ``RUN/policy.pt``,
``selection.json``), then its report on the test scenario and the held-out maps (``final.json``),
behind the shield the policy flies behind, if any (``meta["flight_shield"]``, else the one it
trained behind). For runs trained without ``--select`` but
with ``--keep-policies`` (``experiments/seed_levers.sh``); copies ``selection.json`` and
``final.json`` to ``OUT/<run name>-{selection,final}.json``.

    .venv/bin/python experiments/finish_runs.py runs/levers/shield1map03-s{1,5,2} \\
        --out results/csac-v1/levers
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

from safenav.commands.train import finish_run


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("results/csac-v1/levers"))
    ap.add_argument("--report-episodes", type=int, default=200)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    args.out.mkdir(parents=True, exist_ok=True)
    for run in args.runs:
        finish_run(run, report_episodes=args.report_episodes)
        for name in ("selection", "final"):
            shutil.copy(run / f"{name}.json", args.out / f"{run.name}-{name}.json")


if __name__ == "__main__":
    main()
