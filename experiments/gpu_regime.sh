#!/usr/bin/env bash
# The `csac` recipe in the massively parallel regime (issue 20, item 5): --device cuda, 1024
# envs, batch 4096, everything else the recipe's (1/32 update per env step, so 32 updates of
# 4096 transitions per vector step). The same two phases as the recipe's CPU measurement
# (1 M steps, then resumed to 2.5 M), each stopped by SIGINT at a wall-clock deadline (the run
# checkpoints and keeps its policies), so the whole script fits a short GPU lease.
#
#   bash experiments/gpu_regime.sh OUT_DIR [SEED] [DEADLINE_S] [RESUME_TO]
#
# RESUME_TO 0 skips the second phase (the first then gets the whole deadline). More safenav train
# options for the first phase in $GPU_REGIME_ARGS, e.g. GPU_REGIME_ARGS="--csac.batch-size 256"
# (later options win) to run the envs of the regime with the recipe's batch.
#
# OUT_DIR gets the run directory as a tarball (policies/, events.jsonl, progress.csv,
# config.json; not the 10 MB checkpoint) and nvidia-smi's line. Periodic evaluations keep a
# policy every 250 k steps but use only 32 validation episodes (they run on the GPU, in the
# lease); the policies are re-evaluated on 400 validation episodes and the run's policy is
# chosen on the CPU afterwards (docs/csac-v1.md, "The GPU regime"):
#   python experiments/checkpoint_sweep.py ... ; python -c "from safenav.commands.train import
#   finish_run; finish_run(Path(RUN_DIR))"
#
# On a machine whose Python has torch but not the project's other dependencies (the lent GPU
# machines: Python 3.12, torch 2.11), the committed run was started from the repository root as
#   pip install --no-index --no-deps --target /tmp/site .whl/*.whl   # gymnasium, tyro, ... wheels
#   PYTHONPATH=$PWD/src:/tmp/site bash experiments/gpu_regime.sh $OUT 2 450 0
# with .whl/ holding gymnasium, farama-notifications, tyro, docstring-parser, typeguard,
# typing-extensions and colorednoise (pip download --python-version 3.12 --only-binary=:all:).
set -uo pipefail
out=${1:?usage: gpu_regime.sh OUT_DIR [SEED] [DEADLINE_S] [RESUME_TO]}
seed=${2:-2}
deadline=${3:-470}
resume_to=${4:-2.5M}
# One run dir per OUT_DIR, so that two of these can share a GPU (each is launch-bound).
run=/tmp/gpu-regime-$(basename "$out")-s$seed
start=$(date +%s)
mkdir -p "$out"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$out/gpu.txt"
python3 -c "import torch, sys; print('torch', torch.__version__, 'python', sys.version.split()[0])" \
  | tee -a "$out/gpu.txt"
left() { echo $((deadline - ($(date +%s) - start))); }

rm -rf "$run"
share=2; [ "$resume_to" = 0 ] && share=1
timeout -s INT $(( $(left) / share )) python3 -m safenav train --algo csac --seed "$seed" \
  --device cuda --num-envs 1024 --csac.batch-size 4096 \
  --total-steps 1M --eval-every 250000 --eval-episodes 32 --checkpoint-every 250000 \
  --keep-policies --no-progress --run-dir "$run" ${GPU_REGIME_ARGS:-}
echo "phase 1 exit $? at $(( $(date +%s) - start )) s"
if [ "$resume_to" != 0 ] && [ "$(left)" -gt 30 ]; then
  timeout -s INT "$(left)" python3 -m safenav train --resume "$run" --total-steps "$resume_to" --no-progress
  echo "phase 2 exit $? at $(( $(date +%s) - start )) s"
fi
tar -czf "$out/run.tar.gz" -C /tmp --exclude checkpoint.pt --exclude tb "$(basename "$run")"
ls -la "$out"
