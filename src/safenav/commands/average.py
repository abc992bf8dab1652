"""``safenav average``: one policy file, the weight average of a run's kept policies."""

from __future__ import annotations

from pathlib import Path

import tyro

from safenav.cli import app


@app.command(name="average")
def average(
    policies: tyro.conf.Positional[list[Path]],
    steps: tuple[int, int] | None = None,
    greedy: bool = False,
    val_episodes: int = 512,
    out: Path = Path("average.pt"),
) -> None:
    """Average the parameters of several policies of one run (stochastic weight averaging) into
    one policy file that ``safenav eval``, ``export`` and ``fly`` read.

    Typical use, after ``safenav train ... --keep-policies --run-dir RUN``:
    ``safenav average RUN/policies --steps 3000000 5000192 --out policy.pt`` averages the
    policies kept at the periodic evaluations from 3.0 M to 5.0 M env steps; with ``--greedy``
    only those that help on validation (the greedy soup: policies added in decreasing order of
    their validation success while the average's does not drop; ~2 minutes for nine SafeNav
    policies on 2 cores). docs/csac.md, "Weight averaging of the late policies".

    Args:
        policies: Policy or checkpoint files, or directories of them (``RUN/policies``).
        steps: Keep only the policies with ``LO <= global_step <= HI``.
        greedy: Greedy soup, decided on ``--val-episodes`` episodes of the evaluation maps (never
            the test scenario) instead of averaging every policy.
        val_episodes: With ``--greedy``: validation episodes per candidate.
        out: The averaged policy file (written atomically).
    """
    from rich.console import Console

    from safenav.algos.averaging import average_policies, load_policy_states
    from safenav.common.checkpoint import save_checkpoint
    from safenav.common.checks import at_least, check_output_file
    from safenav.errors import SafenavError

    if not policies:
        raise SafenavError("no POLICIES given: safenav average RUN/policies --steps LO HI --out "
                           "policy.pt (files or directories of kept policies)")  # fmt: skip
    check_output_file(out, "--out", "average.pt")
    if any(out.exists() and out.resolve() == Path(p).resolve() for p in policies):
        raise SafenavError(f"--out {out} is one of the policies it averages: name another file")
    if steps is not None:
        at_least("--steps LO", steps[0], 0)
    at_least("--val-episodes", val_episodes, 1)
    console = Console()
    if greedy:
        from safenav.experiments.soup import greedy_soup, validation_score

        if val_episodes < 1:
            raise SafenavError(f"--val-episodes must be >= 1, got {val_episodes}")

        def show(row: dict) -> None:
            what = "alone" if row["kind"] == "single" else ("kept" if row["kept"] else "dropped")
            listed = ", ".join(f"{s / 1e6:.2f} M" for s in row["steps"])
            console.print(f"  validation success {row['score']:.3f}  {what:7s}  [{listed}]")

        console.print(f"greedy soup: each candidate flies {val_episodes} validation episodes")
        state, _ = greedy_soup(
            load_policy_states(policies, steps), validation_score(val_episodes), show
        )
    else:
        state = average_policies(policies, steps)
    save_checkpoint(out, state)
    averaged = state["averaged_steps"]
    console.print(f"wrote {out} ({out.stat().st_size / 1e6:.2f} MB): the {state['algo']} policy averaged "
                  f"over {len(averaged)} snapshots at steps {', '.join(f'{s:,}' for s in averaged)}",
                  highlight=False)  # fmt: skip
