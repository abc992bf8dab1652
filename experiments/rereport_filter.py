"""Report finished ``--flight-filter`` runs again behind the planner filter adopted since they
trained: what the default command would now report for the same policies.

Training and the selection on validation maps fly without the planner filter
(``RunConfig.flight_filter``): a run's ``policy.pt`` does not depend on it; only the filter the
policy records (``meta["flight_filter"]``, :func:`~safenav.envs.planner.filter_spec` at the end of
training) and its report behind it (``final.json``: test, held-out, NavRL's rule, the test without
the filter; ``eval.json``: ``safenav eval``'s test) do. For each run directory this script
re-records the filter as the default recipe now writes it (``filter_spec(view)``, the view the
policy recorded), keeps what it recorded before in ``meta["flight_filter_before"]``, flies the
report of :func:`~safenav.experiments.selection.report_policy` again into ``final.json`` (the
selection and its record untouched, the earlier report under ``"report_before"``) and
``safenav eval``'s test into ``eval.json``; then ``safenav reproduce`` with the sweep's own
command re-aggregates (every trial done: nothing trains, the sweep's record is kept).

    python experiments/rereport_filter.py results/csac/runs/csac/seed{1..5}
    safenav reproduce --algos csac --seeds 1-5

A fresh clone has no run directories (they are ignored), but ``safenav reproduce`` commits each
trial's record and its policy (``OUT/trials/<label>-s<S>.json`` and ``.pt``): given those
records, the script flies the committed policy the same way and rewrites the record's report
fields (:data:`~safenav.experiments.aggregate.REPORT_FIELDS`; the earlier ones under
``"report_before"``), and ``safenav reproduce`` re-aggregates them:

    python experiments/rereport_filter.py results/csac/trials/csac-s{1..5}.json

Each step is skipped where it is done already (the policy's record, the report, the test), so a
killed run resumes; a run directory without a ``--select`` report, a record without its policy,
or a policy without a recorded filter, is refused.
"""

from __future__ import annotations

import argparse
import contextlib
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

from safenav.common.checkpoint import load_checkpoint, save_checkpoint
from safenav.common.jsonout import write_json
from safenav.envs.planner import filter_spec
from safenav.errors import SafenavError
from safenav.experiments.aggregate import REPORT_FIELDS, read_json, report_fields
from safenav.experiments.selection import report_policy

REPORT_KEYS = ("test", "heldout", "test_navrl_rule", "shield", "flight_shield", "flight_filter",
               "test_without_filter")  # fmt: skip


def fly_test(policy: Path, eval_path: Path, episodes: int, device: str) -> None:
    """``safenav eval``'s test of ``policy`` (behind the filter it records) into ``eval_path``."""
    subprocess.run([sys.executable, "-m", "safenav", "eval", str(policy), "--env-seed", "1",
                    "--episodes", str(episodes), "--device", device, "--json", str(eval_path)],
                   check=True)  # fmt: skip


def rerecord(policy: Path) -> tuple[dict, dict] | None:
    """Re-record the adopted filter in ``policy`` (atomically): ``(before, now)``, or None
    where it records it already."""
    state = load_checkpoint(policy)
    meta = state["policy"]["meta"]
    before = meta.get("flight_filter")
    if not before:
        raise SafenavError(f"{policy}: records no planner filter (not a --flight-filter run)")
    now = filter_spec(before["view"])
    if before == now:
        return None
    meta["flight_filter"] = now
    meta["flight_filter_before"] = before
    save_checkpoint(policy, state)
    return before, now


def rereport(run_dir: Path, episodes: int, device: str) -> None:
    """Each step skipped where it is done (a killed run resumes where it stopped): the policy's
    record, then ``final.json``'s report, then ``eval.json``, each behind the adopted filter."""
    final_path, policy, eval_path = (
        run_dir / name for name in ("final.json", "policy.pt", "eval.json")
    )
    final = read_json(final_path)
    if not final or not policy.exists():
        raise SafenavError(f"{run_dir}: no --select report (final.json, policy.pt) to redo")
    changed = rerecord(policy)
    now = load_checkpoint(policy)["policy"]["meta"]["flight_filter"]
    if final.get("flight_filter") != now:
        before = changed[0] if changed else final.get("flight_filter")
        t0 = time.perf_counter()
        report = report_policy(policy, episodes=episodes, device=device)
        final["report_before"] = {k: final.pop(k) for k in REPORT_KEYS if k in final}
        final |= report | {"rereported": {
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "why": "the planner filter adopted since the run was reported (docs/csac-v1.md)",
            "command": f"python experiments/rereport_filter.py {run_dir}",
            "flight_filter_before": before,
            "report_wall_clock_s": round(time.perf_counter() - t0, 1)}}  # fmt: skip
        write_json(final_path, final)
    if (read_json(eval_path) or {}).get("planner_filter_spec") != now:
        fly_test(policy, eval_path, episodes, device)
    test, held = final["test"], final["heldout"]
    print(f"{run_dir}: test {test['success_rate']:.3f} / {test['collision_rate']:.3f}, held-out "
          f"{held['success_rate']:.3f} / {held['collision_rate']:.3f} (was "
          f"{final['report_before']['test']['success_rate']:.3f} / "
          f"{final['report_before']['test']['collision_rate']:.3f})")  # fmt: skip


def rereport_record(record_path: Path, episodes: int, device: str) -> None:
    """:func:`rereport` for a committed trial record and its policy (a fresh clone): the report
    and the test are written beside the record (``trials/rereport/<name>-final.json`` and
    ``-eval.json``, so that a killed run resumes), then folded into it and removed."""
    rec = read_json(record_path)
    if not rec or not rec.get("policy"):
        raise SafenavError(f"{record_path}: no trial record naming its policy (safenav reproduce "
                           "keeps it since 2026-12-05)")  # fmt: skip
    policy = record_path.parent.parent / rec["policy"]  # relative to the sweep's OUT
    if not policy.exists():
        raise SafenavError(f"{record_path}: its policy {policy} is missing")
    changed = rerecord(policy)
    now = load_checkpoint(policy)["policy"]["meta"]["flight_filter"]
    if rec.get("planner_filter") == now:
        print(f"{record_path}: reported behind {now} already")
        return
    side = record_path.parent / "rereport"  # not OUT/trials/*.json: no record of a sweep
    side.mkdir(exist_ok=True)
    final_path, eval_path = (
        side / f"{record_path.stem}-final.json",
        side / f"{record_path.stem}-eval.json",
    )
    t0 = time.perf_counter()
    final = read_json(final_path)
    if (final or {}).get("flight_filter") != now:
        final = report_policy(policy, episodes=episodes, device=device)
        side.mkdir(exist_ok=True)  # again: another record's run may have removed it meanwhile
        write_json(final_path, final)
    if (read_json(eval_path) or {}).get("planner_filter_spec") != now:
        side.mkdir(exist_ok=True)
        fly_test(policy, eval_path, episodes, device)
    before = {k: rec.get(k) for k in REPORT_FIELDS}
    rec |= report_fields(read_json(eval_path) or {}, final) | {
        "report_before": before,
        "rereported": {
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "why": "the planner filter adopted since the trial was reported (docs/csac-v1.md)",
            "command": f"python experiments/rereport_filter.py {record_path}",
            "flight_filter_before": changed[0] if changed else before["planner_filter"],
            "report_wall_clock_s": round(time.perf_counter() - t0, 1)}}  # fmt: skip
    write_json(record_path, rec)
    final_path.unlink()
    eval_path.unlink()
    with contextlib.suppress(OSError):
        side.rmdir()  # where no other record's re-report is under way
    print(f"{record_path}: test {rec['success_rate']:.3f} / {rec['collision_rate']:.3f}, "
          f"held-out {rec['heldout']['success_rate']:.3f} / {rec['heldout']['collision_rate']:.3f} "
          f"(was {before['success_rate']:.3f} / {before['collision_rate']:.3f})")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dirs", nargs="+", type=Path,
                        help="run directories, or trial records (OUT/trials/*.json)")  # fmt: skip
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    for path in args.run_dirs:
        if path.suffix == ".json":
            rereport_record(path, args.episodes, args.device)
        else:
            rereport(path, args.episodes, args.device)


if __name__ == "__main__":
    main()
