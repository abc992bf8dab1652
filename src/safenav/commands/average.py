"""``safenav average``: one policy file, the weight average of a run's kept policies."""

from __future__ import annotations

from pathlib import Path

import tyro

from safenav.cli import app


@app.command(name="average")
def average(
    policies: tyro.conf.Positional[list[Path]],
    steps: tuple[int, int] | None = None,
    out: Path = Path("average.pt"),
) -> None:
    """Average the parameters of several policies of one run (stochastic weight averaging) into
    one policy file that ``safenav eval``, ``export`` and ``fly`` read.

    Typical use, after ``safenav train ... --keep-policies --run-dir RUN``:
    ``safenav average RUN/policies --steps 3000000 5000192 --out policy.pt`` averages the
    policies kept at the periodic evaluations from 3.0 M to 5.0 M env steps (docs/csac.md,
    "Weight averaging of the late policies").

    Args:
        policies: Policy or checkpoint files, or directories of them (``RUN/policies``).
        steps: Keep only the policies with ``LO <= global_step <= HI``.
        out: The averaged policy file (written atomically).
    """
    from safenav.algos.averaging import average_policies
    from safenav.common.checkpoint import save_checkpoint

    state = average_policies(policies, steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(out, state)
    averaged = state["averaged_steps"]
    print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB): the {state['algo']} policy averaged "
          f"over {len(averaged)} snapshots at steps {', '.join(f'{s:,}' for s in averaged)}")  # fmt: skip
