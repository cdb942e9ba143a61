#!/usr/bin/env bash
# The default job of each scene trained without recorded masses (ablation=unsupervised), then
# evaluated as the headline tables are (mass_frames=400 on test), then summary.py's table.
#
#   bash examples/unsupervised/run.sh spring:0 gravity_r1:0 gravity_r2:0     # scene:seed ...
#
# A finished run (its eval.done) is kept; runs land in outputs/unsupervised/<scene>_s<seed>.
set -euo pipefail
cd "$(dirname "$0")/../.."
out=${OUT:-outputs/unsupervised}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
mkdir -p "$out"
runs=()
for spec in "$@"; do
  scene=${spec%:*} seed=${spec#*:}
  run=$out/${scene}_s$seed
  runs+=("$run")
  [ -f "$run/eval.done" ] && { echo "kept $run"; continue; }
  resume=()
  [ -f "$run/checkpoints/last.ckpt" ] && resume=(ckpt_path=last)
  python -m bgn.train dataset="$scene" ablation=unsupervised seed="$seed" hydra.run.dir="$run" \
      "${resume[@]}" > "$run.log" 2>&1
  python -m bgn.evaluate "$run" mass_frames=400 progress=false out_dir="$run/eval400" \
      >> "$run.log" 2>&1
  touch "$run/eval.done"
  echo "done $run"
done
python examples/unsupervised/summary.py "${runs[@]}"
