#!/usr/bin/env bash
# One lever of the csac recipe across training seeds, one run at a time (docs/csac-v1.md,
# "Levers on all five seeds"). Each seed trains with the recipe's budget STEPS (schedules that
# scale with the budget, like the density ramp, stay those of the recipe) and validation
# evaluations every 250 k (400 episodes of the validation maps; no selection, no test scenario).
# With STOP_AT set, the run is stopped (Ctrl-C: it checkpoints) after its evaluation at that step,
# so a lever can be screened early and continued later with a larger STOP_AT. Each seed's config,
# progress and events are copied to results/csac-v1/levers/NAME-sSEED-* as it stops, so that a
# finished seed survives the session (commit them). A rerun skips seeds already evaluated at
# STOP_AT (or finished) and resumes the others from their checkpoints.
#
#   bash experiments/seed_levers.sh NAME STEPS "SEEDS" [TRAIN OPTIONS...]
#   STOP_AT=500000 bash experiments/seed_levers.sh rc50 1000000 "1 2 3 4 5" \
#       --env-kwargs reward_collision -50
#   ALGO=sac bash experiments/seed_levers.sh sacshieldml 1000000 "1 2 3 4 5" \
#       --config sac-shielded-memory      # another algorithm (default ALGO=csac)
#
# Runs go to RUNS (default runs/levers, ignored by git). Keep the machine's CPUs to it: a 2-thread
# trainer beside another job slows down many times over (docs/reproduce.md).
set -euo pipefail
NAME=${1:?usage: seed_levers.sh NAME STEPS SEEDS [OPTIONS...]}
STEPS=${2:?steps}
SEEDS=${3:?seeds}
shift 3
STOP_AT=${STOP_AT:-$STEPS}
cd "$(dirname "$0")/.."
RUNS=${RUNS:-runs/levers}
OUT=results/csac-v1/levers
SAFENAV=${SAFENAV:-.venv/bin/safenav}
mkdir -p "$RUNS" "$OUT"

# 0 when EVENTS holds an evaluation at or after step $2 (or the run's end at or after it)
reached() {
  [[ -f "$1" ]] && python3 -c 'import json, sys
events = [json.loads(line) for line in open(sys.argv[1])]
sys.exit(0 if any(e["event"] in ("eval", "end") and e["global_step"] >= int(sys.argv[2])
                  for e in events) else 1)' "$1" "$2"
}

# Background jobs of a script inherit SIGINT ignored; restore it so Ctrl-C checkpoints the run.
# exec: the background subshell becomes the trainer, so $! is the process that gets the signal.
with_sigint() { exec python3 -c 'import os, signal, sys
signal.signal(signal.SIGINT, signal.SIG_DFL); os.execvp(sys.argv[1], sys.argv[1:])' "$@"; }

for seed in $SEEDS; do
  dir="$RUNS/$NAME-s$seed"
  if reached "$OUT/$NAME-s$seed-events.jsonl" "$STOP_AT"; then
    echo "$NAME seed $seed: done"; continue
  fi
  if [[ -f "$dir/checkpoint.pt" ]]; then
    with_sigint $SAFENAV train --resume "$dir" --total-steps "$STEPS" --no-progress \
      >> "$dir.log" 2>&1 &
  else
    with_sigint $SAFENAV train --algo "${ALGO:-csac}" --seed "$seed" --total-steps "$STEPS" \
      --eval-every 250000 --eval-episodes 400 --checkpoint-every 250000 --no-progress \
      --run-dir "$dir" "$@" > "$dir.log" 2>&1 &
  fi
  pid=$!
  while kill -0 "$pid" 2>/dev/null; do
    if [[ "$STOP_AT" -lt "$STEPS" ]] && reached "$dir/events.jsonl" "$STOP_AT"; then
      kill -INT "$pid"; break
    fi
    sleep 15
  done
  wait "$pid" || true
  reached "$dir/events.jsonl" "$STOP_AT" || { echo "$NAME seed $seed: failed, see $dir.log"; exit 1; }
  for f in config.json progress.csv events.jsonl; do cp "$dir/$f" "$OUT/$NAME-s$seed-$f"; done
  echo "$NAME seed $seed: stopped at $STOP_AT $(date -u +%H:%M)"
done
