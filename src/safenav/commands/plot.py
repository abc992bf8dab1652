"""``safenav plot``: the paper's figures (Fig. 3 learning curves, Fig. 4 test results) as PNG."""

from __future__ import annotations

from pathlib import Path

import tyro

from safenav.cli import app


@app.command(name="plot")
def plot(
    dirs: tyro.conf.Positional[tuple[Path, ...]],
    out: Path | None = None,
    smooth: int = 1,
) -> None:
    """Plot learning curves (mean ± std over seeds), test-result bars beside the paper's, and λ/d.

    DIRS are run directories of safenav train (with eval.json from safenav eval for Fig. 4) or
    directories holding them, such as a safenav reproduce output.

    Args:
        dirs: Run directories, or directories that contain run directories.
        out: Where to write the PNGs; default DIR/figures for one DIR, else ./figures.
        smooth: Moving-average window over logged rows applied to each seed's curves (1 = none).
    """
    from rich.console import Console

    from safenav.errors import SafenavError
    from safenav.experiments.plots import find_runs, plot_all

    if not dirs:
        raise SafenavError("no directories given: safenav plot DIR... (run or reproduce dirs)")
    if smooth < 1:
        raise SafenavError(f"--smooth {smooth}: the window must be >= 1 logged rows")
    out_dir = (
        out if out is not None else (dirs[0] / "figures" if len(dirs) == 1 else Path("figures"))
    )
    from safenav.common.checks import check_output_dir

    check_output_dir(out_dir, "--out")
    console = Console()
    runs = find_runs(dirs)
    algos = sorted({r.algo for r in runs})
    console.print(f"{len(runs)} runs of {', '.join(algos)}")
    written = plot_all(dirs, out_dir, window=smooth, runs=runs)
    if not any(r.eval for r in runs):
        console.print("no eval.json in these runs: Fig. 4 needs safenav eval CHECKPOINT --json "
                      "RUN_DIR/eval.json")  # fmt: skip
    for path in written:
        console.print(f"wrote {path}")
