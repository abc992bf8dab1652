"""Eval success (periodic, 64 episodes) and lambda against wall-clock minutes for the sweep runs.

Run: ``.venv/bin/python results/csac-sweep/plot.py`` (writes results/csac-sweep/sweep.png).
"""

import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

here = Path(__file__).parent
summary = json.loads((here / "summary.json").read_text())
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
for k, s in summary.items():
    with open(here / f"{k}-progress.csv") as f:
        rows = list(csv.DictReader(f))
    minutes = {int(r["global_step"]): float(r["time/elapsed_s"]) / 60 for r in rows}
    ev = [r for r in rows if r.get("eval/success_rate")]
    label = f"{k}: {s['args'].replace('--csac.', '')}"
    ax1.plot([minutes[int(r["global_step"])] for r in ev], [float(r["eval/success_rate"]) for r in ev],
             marker="o", label=label)
    ax2.plot([float(r["time/elapsed_s"]) / 60 for r in rows], [float(r["constraint/lambda"] or 0) for r in rows])
ax1.set(xlabel="wall-clock minutes (2 cores per run)", ylabel="eval success (64 episodes)", ylim=(0, 1))
ax2.set(xlabel="wall-clock minutes", ylabel="lambda", yscale="symlog")
ax1.legend(fontsize=6)
fig.tight_layout()
fig.savefig(here / "sweep.png", dpi=110)
