#!/usr/bin/env bash
# CSAC tuning sweep on the paper preset at a fixed wall-clock budget (docs/csac.md, "What was tuned").
#
# Eight CSAC configurations train side by side, each pinned to its own pair of cores (16 cores in
# all), for MINUTES of wall-clock; then each is stopped with Ctrl-C (it checkpoints), its last
# checkpoint is evaluated on the fixed test scenario (env seed 1, 200 episodes), and a table of
# test success / collision, env steps and updates reached is written to OUT/summary.md.
# Equal wall-clock, not equal steps: the question is which settings learn most per CPU minute.
#
#   bash experiments/csac_sweep.sh OUT [MINUTES=24]
#
# Needs 16 cores (on a 2-core machine run one configuration at a time with `safenav train`).
# SAFENAV overrides the command (default: `python3 -m safenav`, with src/ on PYTHONPATH).
set -euo pipefail
OUT=${1:?usage: csac_sweep.sh OUT [MINUTES]}
MINUTES=${2:-24}
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
SAFENAV=${SAFENAV:-python3 -m safenav}
mkdir -p "$OUT"

# The committed csac-paper command's settings (README), then one change per row.
COMMON="--algo csac --preset paper --seed 1 --num-envs 256 --total-steps 3000000 --torch-threads 2
  --eval-every 250000 --eval-episodes 50 --checkpoint-every 250000 --density.ramp-fraction 0.33
  --csac.actor-lr 3e-4 --csac.alpha-lr 3e-4"
declare -A CFG=(
  [A]="--csac.updates-per-step 0.03125"
  [B]="--csac.updates-per-step 0.03125 --csac.lambda-lr 1e-3"
  [C]="--csac.updates-per-step 0.0625 --csac.net.hidden 128 128"
  [D]="--csac.updates-per-step 0.0625 --csac.net.hidden 128 128 --csac.lambda-lr 1e-3"
  [E]="--csac.updates-per-step 0.125 --csac.net.hidden 128 128 --csac.lambda-lr 1e-3"
  [F]="--csac.updates-per-step 0.0625 --csac.net.hidden 128 128 --csac.lambda-lr 1e-3 --csac.batch-size 512"
  [G]="--csac.updates-per-step 0.0625 --csac.net.hidden 128 128 --csac.lambda-lr 1e-2"
  [H]="--csac.updates-per-step 0.0625 --csac.lambda-lr 1e-3"
)
NAMES="A B C D E F G H"

# Background jobs of a script inherit SIGINT ignored; restore it so Ctrl-C checkpoints the runs.
with_sigint() { python3 -c 'import os, signal, sys
signal.signal(signal.SIGINT, signal.SIG_DFL); os.execvp(sys.argv[1], sys.argv[1:])' "$@"; }

i=0
for k in $NAMES; do
  echo "$k: ${CFG[$k]}" >> "$OUT/configs.txt"
  # shellcheck disable=SC2086
  with_sigint taskset -c $((2 * i)),$((2 * i + 1)) $SAFENAV train $COMMON ${CFG[$k]} \
    --run-dir "$OUT/$k" > "$OUT/$k.log" 2>&1 < /dev/null &
  i=$((i + 1))
done
sleep $((MINUTES * 60))
pkill -INT -f "safenav train .*--run-dir $OUT/" || true
wait || true

i=0
for k in $NAMES; do
  # shellcheck disable=SC2086
  taskset -c $((2 * i)),$((2 * i + 1)) $SAFENAV eval "$OUT/$k/checkpoint.pt" \
    --json "$OUT/$k/test.json" > "$OUT/$k.eval.log" 2>&1 &
  i=$((i + 1))
done
wait

python3 - "$OUT" $NAMES <<'EOF'
import csv, json, sys
from pathlib import Path
out, names = Path(sys.argv[1]), sys.argv[2:]
configs = dict(line.split(": ", 1) for line in (out / "configs.txt").read_text().splitlines())
rows = ["| run | change from the committed command | env steps | updates | minutes | test success | test collision |",
        "|---|---|---|---|---|---|---|"]
summary = {}
for k in names:
    last = list(csv.DictReader(open(out / k / "progress.csv")))[-1]
    test = json.loads((out / k / "test.json").read_text())
    summary[k] = {"args": configs[k].strip(), "global_step": int(last["global_step"]),
                  "updates": int(float(last["perf/updates"])), "elapsed_s": float(last["time/elapsed_s"]),
                  "success_rate": test["success_rate"], "collision_rate": test["collision_rate"]}
    s = summary[k]
    rows.append(f"| {k} | `{s['args']}` | {s['global_step']:,} | {s['updates']:,} | {s['elapsed_s'] / 60:.1f} "
                f"| {s['success_rate']:.3f} | {s['collision_rate']:.3f} |")
(out / "summary.json").write_text(json.dumps(summary, indent=2))
(out / "summary.md").write_text("\n".join(rows) + "\n")
print("\n".join(rows))
EOF
