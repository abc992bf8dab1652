"""Which of a run's policies to keep? Every policy of a run on the evaluation maps and on the test
scenario, side by side (docs/csac.md, "Three runs of the 60-minute budget, and choosing a run's policy").

A run's periodic evaluations (``--eval-episodes``; 400, i.e. 416 flown, in the committed command)
pick ``best.pt``; with few episodes that choice is noisy. This flies each kept policy (a run's
``policies/step_*.pt`` from ``safenav train --keep-policies``, or any checkpoint files) on

- the **evaluation maps** (``EVAL_SEED``, the maps the periodic evaluations use: a validation set),
  ``--val-episodes`` episodes, and
- the **fixed test scenario** (env seed 1, 200 episodes, as ``safenav eval``),

with deterministic actions, optionally the **greedy soup** (``--greedy-soup``, as
``safenav average --greedy``: the weight average of the policies added one by one in decreasing
order of validation success while validation success does not drop), and optionally the
**weight average** of the policies whose steps lie in ``--average LO HI`` (all parameters of the
policy module averaged: stochastic weight averaging over the run's late policies, as ``safenav
average``; ``--averages-only`` flies only those). Choosing by the test columns would overfit the
test scenario: choose by the validation ones and read the test ones. ``--sampled`` also flies
each policy on the evaluation maps with actions *sampled* from its squashed Gaussian, as in
training (CSAC/SAC policies): equal timeouts mean caution, not a deadlock of the deterministic
mean action.

Run: ``.venv/bin/python experiments/checkpoint_sweep.py runs/NAME/policies [--average 3000000 5000000]
[--sampled] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch
from rich.console import Console
from rich.table import Table

from safenav.algos.averaging import average_policy_states, between_steps, policy_files
from safenav.algos.policy import load_policy
from safenav.common.checkpoint import load_checkpoint, save_checkpoint
from safenav.common.jsonout import write_json
from safenav.experiments.evaluate import evaluate
from safenav.experiments.flight import resolve_policy
from safenav.experiments.soup import greedy_soup, validation_score
from safenav.training.evaluation import EVAL_SEED

KEYS = ("success_rate", "collision_rate", "timeout_rate")


def sampled_actions(path: Path):
    """The policy of ``path`` acting with ``tanh(mean + std * noise)`` instead of ``tanh(mean)``."""
    actor = load_policy(path).actor
    if not hasattr(actor.actor, "sample"):
        raise SystemExit(f"--sampled: {path} is not a squashed-Gaussian (CSAC/SAC) policy")

    def act(obs: dict[str, torch.Tensor]) -> torch.Tensor:
        obs = {k: obs[k] for k in actor.input_names}
        return actor.actor.sample(actor.encoder(obs) if actor.encoder is not None else obs)[0]

    return act


def fly(path: Path, val_episodes: int, test_episodes: int, sampled: bool = False) -> dict[str, dict[str, float]]:  # fmt: skip
    fn, cfg = resolve_policy(path, "checkpoint", "cpu")
    runs = [("val", fn, EVAL_SEED, val_episodes)]
    if test_episodes > 0:
        runs.append(("test", fn, 1, test_episodes))
    if sampled:
        runs.append(("val_sampled", sampled_actions(path), EVAL_SEED, val_episodes))
    out = {}
    for name, act, seed, episodes in runs:
        if name == "val_sampled":
            torch.manual_seed(0)  # the sampled actions' noise
        res = evaluate(act, cfg, env_seed=seed, episodes=episodes, device="cpu")
        out[name] = {k: float(res[k]) for k in KEYS}
    return out


def soup_row(states: dict[Path, dict], singles: list[dict], val_episodes: int, test_episodes: int, sampled: bool = False) -> dict:  # fmt: skip
    """The greedy soup (``safenav average --greedy``, :mod:`safenav.experiments.soup`) of the
    policies of ``singles``, reusing their validation figures; its test columns flown once."""
    val_of = {r["global_step"]: r["val"]["success_rate"] for r in singles}
    fly_val = validation_score(val_episodes)

    def score(state: dict) -> float:
        return fly_val(state) if "averaged_steps" in state else val_of[int(state["global_step"])]

    soup, _ = greedy_soup(list(states.values()), score)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "soup.pt"
        save_checkpoint(path, soup)
        return {"policy": f"greedy soup of {len(soup['averaged_steps'])}",
                "global_step": soup["global_step"], "soup_steps": soup["averaged_steps"],
                **fly(path, val_episodes, test_episodes, sampled)}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("paths", nargs="+", type=Path, help="checkpoint files or directories of them")
    ap.add_argument("--val-episodes", type=int, default=512)
    ap.add_argument("--test-episodes", type=int, default=200)
    ap.add_argument(
        "--average",
        nargs=2,
        type=int,
        metavar=("LO", "HI"),
        action="append",
        default=[],
        help="also fly the weight average of the policies with LO <= step <= HI (repeatable)",
    )
    ap.add_argument("--sampled", action="store_true",
                    help="also fly the evaluation maps with sampled (training) actions")  # fmt: skip
    ap.add_argument("--averages-only", action="store_true",
                    help="fly only the --average policies, not each policy on its own")  # fmt: skip
    ap.add_argument("--greedy-soup", action="store_true",
                    help="also fly the greedy soup of the policies (chosen on validation)")  # fmt: skip
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.greedy_soup and args.averages_only:
        raise SystemExit(
            "--greedy-soup needs each policy's validation figures: drop --averages-only"
        )

    states = {f: load_checkpoint(f) for f in policy_files(args.paths)}
    rows = []
    singles = (
        [] if args.averages_only else sorted(states.items(), key=lambda kv: kv[1]["global_step"])
    )
    for f, st in singles:
        rows.append({"policy": str(f), "global_step": int(st["global_step"]),
                     **fly(f, args.val_episodes, args.test_episodes, args.sampled)})  # fmt: skip
    for lo, hi in args.average:
        chosen = between_steps(states.values(), lo, hi)
        if not chosen:
            raise SystemExit(f"--average {lo} {hi}: no policy in that range of steps")
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "average.pt"
            save_checkpoint(path, average_policy_states(chosen))
            rows.append({"policy": f"average of {len(chosen)} ({lo}..{hi})", "global_step": hi,
                         **fly(path, args.val_episodes, args.test_episodes, args.sampled)})  # fmt: skip

    if args.greedy_soup:
        rows.append(
            soup_row(
                states, rows[: len(singles)], args.val_episodes, args.test_episodes, args.sampled
            )
        )

    table = Table(title=f"validation: evaluation maps, {args.val_episodes} episodes; "
                        f"test: env seed 1, {args.test_episodes} episodes")  # fmt: skip
    parts = ("val", "test", "val_sampled") if args.sampled else ("val", "test")
    table.add_column("policy", justify="left")
    table.add_column("step", justify="right")
    for part in parts:
        for k in ("success", "collision", "timeout"):
            table.add_column(f"{part.replace('_', ' ')} {k}", justify="right")
    for r in rows:
        table.add_row(Path(r["policy"]).name, f"{r['global_step']:,}",
                      *(f"{r[part][k]:.3f}" for part in parts for k in KEYS))  # fmt: skip
    Console(width=150).print(table)
    if args.json:
        write_json(args.json, rows)


if __name__ == "__main__":
    main()
