"""Not a test: short deterministic CPU training runs of every algorithm, recorded before a change
to the training code and compared after it (behaviour kept = identical numbers).

    nice -n 19 .venv/bin/python tests/training_reference.py run /tmp/ref --rev HEAD~1  # before
    nice -n 19 .venv/bin/python tests/training_reference.py run /tmp/new --rev HEAD    # after
    .venv/bin/python tests/training_reference.py compare /tmp/ref /tmp/new

``run OUT [--rev REV] [CASE ...]`` trains each case below (or those named) through ``safenav
train``, one at a time on one torch thread (about ten minutes on the 2-core dev machine): with
``--rev``, the ``src/`` of that git revision (``git archive``, first on ``PYTHONPATH``), so that
two commits compare whatever else the working tree holds; without it, the working tree.
``compare`` checks, per case: every progress.csv value
but the wall-clock columns, every events.jsonl entry but its time stamp (evaluations, curriculum
and density changes, best policies), config.json, the final console line, and every tensor and
number of checkpoint.pt, best.pt and policies/*.pt but ``elapsed_s``. It prints each difference and
exits 1 if there is one. ``compare REF NEW --ignore-key KEY`` leaves out a config key that only
one side has (a field added between the two revisions, e.g. ``cost_fn``).
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SAFENAV = ROOT / ".venv" / "bin" / "safenav"

COMMON = ["--seed", "3", "--total-steps", "3000", "--num-envs", "8", "--torch-threads", "1",
          "--no-progress", "--no-tensorboard", "--log-every", "500", "--eval-every", "1000",
          "--eval-episodes", "4", "--checkpoint-every", "1000"]  # fmt: skip
NAV = ["--preset", "easy"]
SAC_SMALL = ["--csac.learning-starts", "500", "--csac.batch-size", "64"]
PPO_SMALL = ["--ppo.rollout-steps", "16", "--ppo.num-minibatches", "4"]
CSAC_PLAIN = ["--config", "none", *SAC_SMALL, "--csac.cost-n-step", "3", "--map-refresh-every",
              "1000", "--csac.net.hidden", "64", "64"]  # fmt: skip
LAG_EVERY = ["--csac.lambda-every", "400"]

# name -> argument lists: one run, or a run and its --resume (first to 2000 steps, then to 3000)
CASES: dict[str, list[list[str]]] = {
    "csac": [["--algo", "csac", *NAV, *SAC_SMALL]],
    "csac-plain": [["--algo", "csac", *NAV, *CSAC_PLAIN]],
    "sac": [["--algo", "sac", *NAV, *SAC_SMALL]],
    "sac_lag": [["--algo", "sac_lag", *NAV, *SAC_SMALL, *LAG_EVERY]],
    "ppo": [["--algo", "ppo", *NAV, *PPO_SMALL]],
    "ppo_lag": [["--algo", "ppo_lag", *NAV, *PPO_SMALL, "--ppo.target-kl", "0.02"]],
    "sac-pendulum": [["--algo", "sac", "--env", "Pendulum-v1", "--config", "none", *SAC_SMALL]],
    "csac-resume": [["--algo", "csac", *NAV, *SAC_SMALL, "--total-steps", "2000"],
                    ["--algo", "csac", "--total-steps", "3000"]],
    "csac-plain-resume": [["--algo", "csac", *NAV, *CSAC_PLAIN, "--save-buffer",
                           "--total-steps", "2000"], ["--algo", "csac", "--total-steps", "3000"]],
    "sac_lag-resume": [["--algo", "sac_lag", *NAV, *SAC_SMALL, *LAG_EVERY, "--total-steps", "2000"],
                       ["--algo", "sac_lag", "--total-steps", "3000"]],
    "ppo_lag-resume": [["--algo", "ppo_lag", *NAV, *PPO_SMALL, "--total-steps", "2000"],
                       ["--algo", "ppo_lag", "--total-steps", "3000"]],
}  # fmt: skip

WALL_CLOCK = {"time/elapsed_s", "perf/sps", "perf/updates_per_s"}


def run(out: Path, names: list[str], rev: str | None = None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if rev is not None:
        src = Path(tempfile.mkdtemp(prefix="safenav-src-"))
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "src"], check=True,
                                 capture_output=True).stdout  # fmt: skip
        subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
        env["PYTHONPATH"] = str(src / "src")
    for name in names or list(CASES):
        run_dir = out / name
        lines = []
        for i, args in enumerate(CASES[name]):
            # a resumed run takes its options from its config.json, but --total-steps
            where = (
                ["--run-dir", str(run_dir), "--overwrite"] if i == 0 else ["--resume", str(run_dir)]
            )
            cmd = [str(SAFENAV), "train", *(COMMON if i == 0 else ["--no-progress"]), *args, *where]
            proc = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
            if proc.returncode != 0:
                sys.exit(f"{name}: {' '.join(cmd)}\n{proc.stderr}")
            lines.append(proc.stdout.strip().splitlines()[-1].replace(str(run_dir), "RUN_DIR"))
        (run_dir / "console.txt").write_text("\n".join(lines) + "\n")
        print(f"{name}: {lines[-1]}", flush=True)


IGNORED: set[str] = set()  # compare --ignore-key


def same(a, b, where: str, out: list[str]) -> None:
    """Append to ``out`` every difference between two loaded checkpoint values."""
    if isinstance(a, dict) and isinstance(b, dict):
        if (set(a) ^ set(b)) - IGNORED:
            out.append(f"{where}: keys {sorted(set(a) ^ set(b), key=str)} differ")
        for k in set(a) & set(b):
            if k != "elapsed_s":
                same(a[k], b[k], f"{where}[{k!r}]", out)
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            out.append(f"{where}: lengths {len(a)} != {len(b)}")
        for i, (x, y) in enumerate(zip(a, b, strict=False)):
            same(x, y, f"{where}[{i}]", out)
    elif isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        if a.shape != b.shape or a.dtype != b.dtype or not torch.equal(a, b):
            out.append(f"{where}: tensors differ")
    elif isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        pass
    elif type(a) is not type(b) or a != b:
        out.append(f"{where}: {a!r} != {b!r}")


def rows(path: Path) -> list[dict[str, str]]:
    with path.open() as f:
        return [{k: v for k, v in r.items() if k not in WALL_CLOCK} for r in csv.DictReader(f)]


def events(path: Path) -> list[dict]:
    """The entries of events.jsonl without their time stamps; paths relative to the run dir."""
    text = path.read_text().replace(str(path.parent), "RUN_DIR")
    return [
        {k: v for k, v in json.loads(line).items() if k != "time"} for line in text.splitlines()
    ]


def compare(ref: Path, new: Path) -> int:
    problems: list[str] = []
    for name in CASES:
        a, b = ref / name, new / name
        if not (a / "console.txt").exists() or not (b / "console.txt").exists():
            problems.append(f"{name}: no finished run in {ref if not a.is_dir() else new}")
            continue
        files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
        files_b = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
        if files_a != files_b:
            problems.append(f"{name}: files {sorted(set(files_a) ^ set(files_b))} differ")
        ra, rb = rows(a / "progress.csv"), rows(b / "progress.csv")
        if ra != rb:
            for i, (x, y) in enumerate(zip(ra, rb, strict=False)):
                diff = {k: (x.get(k), y.get(k)) for k in set(x) | set(y) if x.get(k) != y.get(k)}
                if diff:
                    problems.append(f"{name}: progress.csv row {i}: {diff}")
            if len(ra) != len(rb):
                problems.append(f"{name}: progress.csv has {len(ra)} vs {len(rb)} rows")
        ea, eb = events(a / "events.jsonl"), events(b / "events.jsonl")
        if ea != eb:
            problems.append(f"{name}: events.jsonl differs: "
                            f"{[e for e in ea if e not in eb][:3]} vs {[e for e in eb if e not in ea][:3]}")  # fmt: skip
        if (a / "console.txt").read_text() != (b / "console.txt").read_text():
            problems.append(f"{name}: console.txt differs")
        config: list[str] = []
        same(json.loads((a / "config.json").read_text()), json.loads((b / "config.json").read_text()),
             "config.json", config)  # fmt: skip
        problems += [f"{name}: {p}" for p in config]
        for rel in files_a:
            if rel.suffix == ".pt" and (b / rel).exists():
                out: list[str] = []
                same(torch.load(a / rel, weights_only=True), torch.load(b / rel, weights_only=True),
                     str(rel), out)  # fmt: skip
                problems += [f"{name}: {p}" for p in out]
        print(
            f"{name}: {'same' if not any(p.startswith(name + ':') for p in problems) else 'DIFFERS'}"
        )
    for p in problems:
        print(p)
    return 1 if problems else 0


def main(argv: list[str]) -> int:
    if len(argv) >= 2 and argv[0] == "run":
        rest, rev = argv[2:], None
        if "--rev" in rest:
            i = rest.index("--rev")
            rev, rest = rest[i + 1], rest[:i] + rest[i + 2 :]
        run(Path(argv[1]), rest, rev)
        return 0
    if len(argv) >= 3 and argv[0] == "compare" and len(argv) % 2 == 1:
        pairs = argv[3:]
        if any(flag != "--ignore-key" for flag in pairs[::2]):
            print(__doc__, file=sys.stderr)
            return 2
        IGNORED.update(pairs[1::2])
        return compare(Path(argv[1]), Path(argv[2]))
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
