#!/bin/bash
# The GPU check of docs/results.md, "On a GPU", as run on a lent GPU machine from the
# repository root. That machine reaches no registry: the wheels it lacks are downloaded here
# into .whl/ (ignored through .git/info/exclude) and carried there:
#   for p in hydra-core==1.3.8 omegaconf==2.3.1 zuko==1.6.0 pot==0.9.7.post1; do
#     python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#       --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
#       -d .whl $p; done
#   pip wheel --no-deps -w .whl antlr4-python3-runtime==4.9.3   # an sdist only
# Then on the machine: bash docs/notes/gpu/check.sh tests, then bash docs/notes/gpu/check.sh main
# (two calls: a lease's 15 minutes hold both and a machine's start; logs under $OUT, or
# ./gpu_check).
# What it runs: the GPU tests (every model and structured head against the CPU; trainer=gpu
# end to end; model.dynamics=auto on imported data without masses, its candidates on the
# GPU), then the README's main job on the GPU with a shorter step budget (STEPS), spring's
# formula stage included, and evaluate on that run.
export PYTHONUNBUFFERED=1
OUT=${OUT:-gpu_check}; mkdir -p "$OUT"
PART=${1:-all}     # tests | main | all: each part fits one call of the device tool (10 min)
STEPS=${STEPS:-1000}
t0=$(date +%s)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
export PYTHONPATH=/tmp/site:$PWD
{ python3 -c "import torch, lightning; print(torch.__version__, lightning.__version__, torch.cuda.get_device_name())"; nvidia-smi --query-gpu=driver_version --format=csv,noheader; nproc; git log --oneline -1 2>/dev/null; } > $OUT/env.txt 2>&1
echo "install $(( $(date +%s) - t0 )) s" >> $OUT/times.txt
if [ "$PART" != main ]; then  # 2026-11-29 at 7140937: about 90 s, then 130 s for auto's test
  t=$(date +%s)
  timeout 330 python3 -m pytest -q -m "" -p no:cacheprovider -rs --durations=10 \
    tests/model/test_cuda.py "tests/test_train.py::test_trainer_gpu_trains_and_evaluates_end_to_end" \
    "tests/training/test_module_masses.py::test_every_auto_candidate_trains_without_nan_on_data_without_masses" \
    > $OUT/gpu_tests.log 2>&1
  echo "gpu tests rc=$? $(( $(date +%s) - t )) s" >> $OUT/times.txt
  tail -3 $OUT/gpu_tests.log
fi
if [ "$PART" != tests ]; then  # spring's data made there (about 2 min), STEPS steps (12/s), the
  t=$(date +%s)                # formula stage and the test
  timeout 420 python3 -m bgn.train trainer=gpu trainer.max_steps=$STEPS hydra.run.dir=/tmp/gpurun > $OUT/main_job.log 2>&1
  echo "main job rc=$? $(( $(date +%s) - t )) s" >> $OUT/times.txt
  cp /tmp/gpurun/metrics.json $OUT/ 2>/dev/null; cp /tmp/gpurun/laws/report.md $OUT/laws_report.md 2>/dev/null
  t=$(date +%s)
  timeout 90 python3 -m bgn.evaluate /tmp/gpurun > $OUT/evaluate.log 2>&1
  echo "evaluate rc=$? $(( $(date +%s) - t )) s" >> $OUT/times.txt
  tail -25 $OUT/main_job.log
fi
echo "total $(( $(date +%s) - t0 )) s" >> $OUT/times.txt
cat $OUT/times.txt
