#!/usr/bin/env bash
# GPU timings of the SE(2)+velocity chain and of the disk training step, for a
# lent GPU machine (issue 17: "where one is available, also record GPU
# timings for the chain and the training step"). Run from the repository root
# with OUT set to an output folder and, in .whl/, the wheels of the pure-Python
# dependencies at the versions this project is tested with (the machine has
# its own JAX; nothing can be fetched there):
#   python -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     -d .whl equinox==0.13.8 lineax==0.1.1 optimistix==0.1.0 optax==0.2.8 \
#     jaxtyping==0.3.11 beartype==0.23.1 wadler-lindig
#   OUT=/tmp/gpu bash benchmarks/run_gpu.sh
# Each benchmark writes its JSON record by record, so a run cut short keeps
# what it measured; each has its own time limit.
set -u
PY=${PY:-python3}
SITE=${SITE:-/tmp/site}
mkdir -p "$OUT"
if ls .whl/*.whl >/dev/null 2>&1; then
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target "$SITE" .whl/*.whl || exit 1
  export PYTHONPATH=$SITE:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1
nvidia-smi -L 2>&1 | tee "$OUT/devices.txt"
"$PY" -c "import jax, equinox, lineax, optimistix, eqsmooth; \
print('jax', jax.__version__, jax.devices(), 'equinox', equinox.__version__, \
'lineax', lineax.__version__, 'optimistix', optimistix.__version__)" \
  2>&1 | tee -a "$OUT/devices.txt"
cd benchmarks
SIZES=${CHAIN_SIZES:-10000 100000}
TRAIN_SIZES=${TRAIN_SIZES:-200 2000}
timeout "${CHAIN_LIMIT:-200}" "$PY" chain.py --problems se2vel \
  --solvers BlockTridiagonal --sizes $SIZES --json "$OUT/chain_gpu.json" \
  2>&1 | tee "$OUT/chain_gpu.log"
timeout "${TRAIN_LIMIT:-200}" "$PY" train_step.py --sizes $TRAIN_SIZES \
  --steps 3 --solvers BlockTridiagonal --adjoints unrolled implicit \
  --no-reference --repeats 5 --json "$OUT/train_step_gpu.json" \
  2>&1 | tee "$OUT/train_step_gpu.log"
