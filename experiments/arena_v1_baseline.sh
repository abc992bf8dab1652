#!/usr/bin/env bash
# Where SafeNav-v1 starts: the committed policies (trained on SafeNav-v0, the open arena) and the
# scripted baselines on the v1 test scenario (env seed 1, 200 episodes), plus the v0 policies'
# flights rendered. Writes results/arena-v1/*.json and docs/img/v1-*.gif; ~3 min on 2 cores.
# Run from the repository root: bash experiments/arena_v1_baseline.sh
set -euo pipefail
SAFENAV=${SAFENAV:-.venv/bin/safenav}
OUT=results/arena-v1
mkdir -p "$OUT"
for name in csac-paper ppo-paper sac-paper; do
  "$SAFENAV" eval "checkpoints/$name.pt" --json "$OUT/$name-v0-policy.json"
  "$SAFENAV" eval "checkpoints/$name.pt" --shield --json "$OUT/$name-v0-policy-shield.json"
done
for policy in scripted straight border; do
  "$SAFENAV" eval --policy "$policy" --json "$OUT/$policy.json"
  "$SAFENAV" eval --policy "$policy" --shield --json "$OUT/$policy-shield.json"
done
"$SAFENAV" render checkpoints/csac-paper.pt --episode 0 --out docs/img/v1-csac-v0-policy.gif
"$SAFENAV" render --policy border --episode 0 --out docs/img/v1-border-probe.gif
