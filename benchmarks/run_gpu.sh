#!/usr/bin/env bash
# Small-graph batches on a lent GPU, GTSAM on the same host's CPU, in one
# command (first run 2026-11-28, commit 1a1f8c2). Run from the repository
# root on the device machine, with the GTSAM wheel in .whl/ (see
# docs/performance.md, "On a GPU"):
#     bash benchmarks/run_gpu.sh
# Writes its JSON to $OUT (the device tool's output folder) or benchmarks/results;
# the output of the 2026-11-28 calls is in benchmarks/results/run_gpu.log and
# run_gpu_second.log.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
    --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
python3 -c "import jax, equinox, lineax, optimistix, gtsam, eqsmooth; print(jax.devices(), jax.__version__, equinox.__version__, lineax.__version__, optimistix.__version__, gtsam.__file__)" || exit 1
out=${OUT:-$PWD/benchmarks/results}
if [ "${1:-}" = "pgo" ]; then
  # Large pose graphs on the GPU path, LevenbergMarquardt(PCG(
  # TwoLevelPreconditioner())), float64, against GTSAM's LM on this host's
  # CPU (added 2026-11-29; docs/performance.md, "Large sparse graphs on a
  # GPU"): `bash benchmarks/run_gpu.sh pgo`. Time per LM iteration:
  # median_s / num_steps of each record.
  timeout 200 python3 -m benchmarks.pgo --gtsam-files --solver pcg --preconditioner twolevel --files w10000.graph --repeats 3 --budget-s 30 --json $out/pgo_gpu_w10000.json
  timeout 330 python3 -m benchmarks.pgo --gtsam-files --solver pcg --preconditioner twolevel --damping-update fixed --max-steps 300 --files sphere_smallnoise.graph --repeats 1 --budget-s 1 --json $out/pgo_gpu_sphere_smallnoise.json
  exit
fi
if [ "${1:-}" != "second" ]; then
  timeout 120 python3 -m benchmarks.small_graph --batch 1000 --floor --repeats 5 --json $out/small_graph_batch_gpu.json
  timeout 60 python3 -m benchmarks.small_graph --repeats 100 --json $out/small_graph_gpu.json
  JAX_PLATFORMS=cpu timeout 90 python3 -m benchmarks.small_graph --batch 1000 --floor --repeats 5 --json $out/small_graph_batch_devcpu.json
fi
if [ "${1:-}" = "tenk" ]; then
  # The 10,000-graph batch alone, its graphs built on the host (added
  # 2026-11-28, commit 3b36e1c).
  timeout 400 python3 -m benchmarks.small_graph --batch 10000 --floor --repeats 5 --json $out/small_graph_batch_10000_gpu.json
  exit
fi
# The first call ran the three above; its 10,000-graph and mixed runs hit
# their time limits in `stack_trees` (now stacked on the host): `second`.
timeout 190 python3 -m benchmarks.small_graph --batch 10000 --floor --repeats 5 --json $out/small_graph_batch_10000_gpu.json
timeout 150 python3 -m benchmarks.small_graph --batch 1000 --mixed --repeats 5 --json $out/small_graph_batch_mixed_gpu.json
