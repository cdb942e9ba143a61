#!/bin/bash
# Behaviour unchanged across a refactor: the default spring job and a collisions
# experiment=smoke run, each with a fixed number of steps (no time budget), trained at two
# commits in fresh clones of this repository; then every metric of the two metrics.json
# compared (diff_metrics.py).
#
#   bash docs/notes/behaviour/same_metrics.sh BEFORE AFTER [WORKDIR]
#
# Run it alone on the machine (the runs are short: about a minute in all on 2 cores, plus
# data generation). The spring data are shared (paths.data_dir=WORKDIR/data); each side
# generates its own collisions data. Collisions pins optimizer.lr=3e-3 and the auxiliary loss
# weights 0.1, its defaults before they became every model's lr 1e-3 and Eq. 12's equal
# weights (changes of behaviour chosen on validation, not refactors).
set -euo pipefail
before=$1 after=$2 work=${3:-outputs/behaviour}
repo=$(git rev-parse --show-toplevel)
mkdir -p "$work"; work=$(cd "$work" && pwd)
for side in before after; do
  rev=${!side}; d=$work/$side
  rm -rf "$d"; git clone -q "$repo" "$d"; git -C "$d" checkout -q "$rev"
  (cd "$d" && PYTHONPATH=$d python -m bgn.train seed=0 trainer.max_time=null \
     trainer.max_steps=300 paths.data_dir="$work/data" hydra.run.dir="$d/outputs/spring" \
     callbacks.progress_bar=null > "$work/$side.spring.log" 2>&1)
  (cd "$d" && PYTHONPATH=$d python -m bgn.train dataset=collisions experiment=smoke seed=0 \
     trainer.max_time=null trainer.max_steps=100 optimizer.lr=3e-3 model.loss_weights.contact=0.1 \
     model.loss_weights.type=0.1 model.loss_weights.mass_nll=0.1 model.loss_weights.relmass=0.1 \
     paths.data_dir="$d/data" \
     hydra.run.dir="$d/outputs/collisions" callbacks.progress_bar=null \
     > "$work/$side.collisions.log" 2>&1)
done
for job in spring collisions; do
  python "$repo/docs/notes/behaviour/diff_metrics.py" "$job" \
    "$work/before/outputs/$job/metrics.json" "$work/after/outputs/$job/metrics.json"
done
