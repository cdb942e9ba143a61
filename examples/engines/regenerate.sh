#!/usr/bin/env bash
# Every run behind docs/results.md's "Data from other engines" tables, then the tables:
#
#   bash examples/engines/regenerate.sh
#
# The datasets must be generated and imported first (README.md beside this script,
# "Commands"). First, per dataset of NAMES, the default job (model.dynamics=auto) for each
# seed of SEEDS, timed whole by equal_time.py (<run>/job_time.json), evaluated on test with
# its decoder, GNS and Cranmer GN candidates, its rollouts extended to 104 steps and measured
# by the engine's own energy (engine_energy.py, the engines that conserve one). Then each
# model of BASELINES alone (seed 0) for BGN's wall time: the steps it fits in the seed-0 BGN
# job's whole wall time at the steps/s its auto candidate had in that job (equal_time.py
# steps; its reasoning in the baseline's log and <run>/equal_time.json), so the budget
# repeats on any machine; SEEDS must include 0 (refused up front otherwise; BASELINES="" runs
# none and needs no seed 0). Then summary.py
# writes the tables into RESULTS_MD's block `engines`. JOBS runs at a time, each with
# OMP_NUM_THREADS torch threads. A finished run (its regenerate.done) is kept (delete the
# folder to redo it; a baseline's budget is its BGN run's: redo both); a failed run is named
# and the script exits non-zero after the others, without writing the tables. Logs:
# OUT/<run>.log. MAX_TIME is every run's trainer.max_time, a safety cap far above the work:
# the default 40 minutes cut the 64-atom Morse gas's default job at 1 137 of its 2 920 steps
# on one core (docs/results.md, "Budgets"), and a cut run's figures depend on the load.
set -euo pipefail
cd "$(dirname "$0")/../.."
NAMES=${NAMES:-"rebound_nbody ase_morse_gas pymunk_granular"}
SEEDS=${SEEDS:-"0 1 2"}
BASELINES=${BASELINES-"gns cranmer_gn"}  # BASELINES="": none
JOBS=${JOBS:-2}
MAX_TIME=${MAX_TIME:-"00:04:00:00"}
OUT=${OUT:-outputs/engines}
RESULTS_MD=${RESULTS_MD:-docs/results.md}
DATA=${DATA:-data/external}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1} OUT DATA MAX_TIME
if [ -n "$BASELINES" ] && [[ " $SEEDS " != *" 0 "* ]]; then  # every baseline would fail
  echo "regenerate.sh: SEEDS=\"$SEEDS\" lacks seed 0, whose BGN job gives each baseline" \
    "($BASELINES) its budget: add 0 to SEEDS" >&2
  exit 2
fi
mkdir -p "$OUT"

one() {  # <name> <seed> <model>: train, evaluate, the engine's energy
  local name=$1 seed=$2 model=$3 run
  if [ "$model" = bgn ]; then run=$OUT/${name}_s$seed; else run=$OUT/${name}_${model}_s$seed; fi
  [ -f "$run/regenerate.done" ] && { echo "kept $run"; return 0; }
  (
    train=(python -m bgn.train dataset=imported dataset.name="$name" model="$model" \
      seed="$seed" trainer.max_time="$MAX_TIME" hydra.run.dir="$run")
    if [ "$model" = bgn ]; then  # the whole job's wall time: the baselines' budget
      python examples/engines/equal_time.py time "$run" -- "${train[@]}" || exit 1
    else  # the steps of the seed-0 BGN job's wall time
      steps=$(python examples/engines/equal_time.py steps "$OUT/${name}_s0" "$model" \
        --json "$run.equal_time.json") || exit 1
      # a failed training leaves no budget record behind (it moves into the run when done)
      "${train[@]}" trainer.max_steps="$steps" || { rm -f "$run.equal_time.json"; exit 1; }
      mv "$run.equal_time.json" "$run/equal_time.json" || exit 1
    fi
    python -m bgn.evaluate "$run" progress=false || exit 1
    [ "$model" = bgn ] || exit 0
    for c in decoder gns cranmer_gn; do  # the candidates auto trained beside the winner
      [ -d "$run/auto/$c" ] || continue
      python -m bgn.evaluate "$run/auto/$c" progress=false || exit 1
    done
    python examples/engines/engine_energy.py "$DATA/$name" --conserved || exit 0  # dissipative
    python -m bgn.evaluate "$run" progress=false figures=false rollout.steps=104 \
      out_dir="$run/eval_104" || exit 1
    for key in predicted true; do
      python examples/engines/engine_energy.py "$DATA/$name" --key "$key" \
        --positions "$run/eval_104/rollouts.npz" --json "$run/energy_$key.json" || exit 1
    done
  ) > "$run.log" 2>&1 || { echo "FAILED $run (log: $run.log)"; return 1; }
  touch "$run/regenerate.done"
  echo "done $run"
}
export -f one

bgn=() baselines=()
for seed in $SEEDS; do for name in $NAMES; do bgn+=("$name $seed bgn"); done; done
for model in $BASELINES; do for name in $NAMES; do baselines+=("$name 0 $model"); done; done
status=0
# every BGN job first: a baseline's budget is its dataset's seed-0 job's wall time
printf '%s\n' "${bgn[@]}" | xargs -P "$JOBS" -L 1 bash -c 'one "$@"' _ || status=$?
if [ ${#baselines[@]} -gt 0 ]; then
  printf '%s\n' "${baselines[@]}" | xargs -P "$JOBS" -L 1 bash -c 'one "$@"' _ || status=$?
fi
if [ "$status" -ne 0 ]; then
  echo "some runs failed (above); the tables are not written" >&2
  exit "$status"
fi
runs=()
for name in $NAMES; do
  for seed in $SEEDS; do runs+=("$OUT/${name}_s$seed"); done
  for model in $BASELINES; do runs+=("$OUT/${name}_${model}_s0"); done
done
python examples/engines/summary.py "${runs[@]}" --out "$OUT/summary" \
  --results-md "$RESULTS_MD"
