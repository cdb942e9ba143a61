#!/usr/bin/env bash
# bgn against LagrangeBench's GNS and SEGNN on one LagrangeBench-layout dataset, at equal wall
# time, every model's test rollouts scored by score.py; then summary.py's table.
#
#   bash examples/fluids/run.sh data/external/sph_tgv            # seeds 0 1 2
#   SEEDS="0" BGN_OVERRIDES="trainer.max_steps=20" bash examples/fluids/run.sh <data>   # a trial
#
# Per seed: bgn's default job (dataset.history=4: the six frames LagrangeBench's models read),
# timed whole (start-up, every candidate of auto, the formula stage, the test); then each peer
# model gets the optimiser steps that fit in the same wall time on this machine: its seconds
# per step and its fixed cost (start-up, compilation) from `peer.py time`, measured once per
# model, steps = (bgn's seconds - fixed) / seconds per step. Finished runs are kept (a rerun
# continues); everything lands in outputs/fluids/<name>_*.
set -euo pipefail
data="${1:?give a LagrangeBench-layout dataset folder}"
name="$(basename "$data")"
peer="${PEER_ENV:-.venv-peer}/bin/python"
out="outputs/fluids"
export OMP_NUM_THREADS=1 XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
mkdir -p "$out"
[ -x "$peer" ] || { echo "no peer environment at ${PEER_ENV:-.venv-peer}: bash examples/fluids/setup_peer.sh" >&2; exit 2; }

# imported once: a rerun keeps the import (delete data/imported/<name> to redo it)
[ -f "data/imported/$name/train.h5" ] || python -m bgn.data.import "$data" name="$name" ${IMPORT_OVERRIDES:-}
python examples/fluids/reference_rollouts.py "$data" --out "$out/${name}_reference/rollouts.npz"
"$peer" examples/fluids/score.py "$data" "$out/${name}_reference/rollouts.npz" \
    --json "$out/${name}_reference/score.json" >/dev/null
for m in gns segnn; do
  [ -f "$out/${name}_${m}_time.json" ] || "$peer" examples/fluids/peer.py time "$data" "$m" \
      --steps "${TIME_STEPS:-30}" --json "$out/${name}_${m}_time.json" >/dev/null
done
for seed in ${SEEDS:-0 1 2}; do
  run="$out/${name}_bgn_s$seed"
  if [ ! -f "$run/metrics.json" ]; then
    start=$(date +%s.%N)
    python -m bgn.train dataset=imported dataset.name="$name" dataset.history=4 seed="$seed" \
        hydra.run.dir="$run" ${BGN_OVERRIDES:-}
    python -c "import json,sys; json.dump({'seconds': $(date +%s.%N) - $start}, open(sys.argv[1], 'w'))" \
        "$run/job_time.json"
  fi
  python examples/fluids/bgn_rollouts.py "$run" "$data" --out "$run/rollouts_lb.npz"
  "$peer" examples/fluids/score.py "$data" "$run/rollouts_lb.npz" --json "$run/score.json" >/dev/null
  for m in gns segnn; do
    prun="$out/${name}_${m}_s$seed"
    if [ ! -f "$prun/peer.json" ]; then
      steps=$(python - "$run/job_time.json" "$out/${name}_${m}_time.json" <<'PY'
import json, sys
bgn = json.load(open(sys.argv[1]))["seconds"]
t = json.load(open(sys.argv[2]))
fixed = t["seconds"][0] - t["timed_steps"][0] * t["seconds_per_step"]
print(max(1, round((bgn - fixed) / t["seconds_per_step"])))
PY
)
      "$peer" examples/fluids/peer.py train "$data" "$m" --steps "$steps" --seed "$seed" \
          --out "$prun" >/dev/null
    fi
    "$peer" examples/fluids/score.py "$data" "$prun/rollouts.npz" --json "$prun/score.json" >/dev/null
  done
done
python examples/fluids/summary.py "$out" "$name"

# speed against error against the engine (speed.py), one thread each: the engine at its step,
# the first seed's bgn at its frame spacing; the periodic case tiled to 1, 4 and 9 times its
# particles, a walled case at its own count with the periodic case's exponents where measured
seeds=(${SEEDS:-0 1 2})
first="$out/${name}_bgn_s${seeds[0]}"
case=$(python -c "import json, sys; print(json.load(open(sys.argv[1]))['case'])" "$data/metadata.json")
tiles="1"; borrow=()
if [ "$case" = tgv ]; then tiles="1 2 3"
elif [ -f "$out/sph_tgv_speed_fit.json" ]; then borrow=(--exponents-from sph_tgv); fi
[ -f "$out/${name}_speed_engine.json" ] || "$peer" examples/fluids/speed.py engine "$case" \
    --tiles $tiles --json "$out/${name}_speed_engine.json"
[ -f "$out/${name}_speed_bgn.json" ] || python examples/fluids/speed.py learned "$first" "$data" \
    --tiles $tiles --json "$out/${name}_speed_bgn.json"
python examples/fluids/speed.py table "$out" "$name" "${borrow[@]}"
