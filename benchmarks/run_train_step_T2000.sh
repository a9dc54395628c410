#!/usr/bin/env bash
# train_step.py at T = 2000, one (solver, adjoint, K) per process, because
# jaxlib's batched LAPACK kernels can deadlock XLA's CPU thread pool (see
# docs/getting-started.md): a process silent for longer than its timeout is
# killed, logged as hung, and the configuration is run again (3 tries).
#   cd benchmarks && OPENBLAS_NUM_THREADS=1 bash run_train_step_T2000.sh results/train_step_T2000_s4
set -u
out=${1:-results/train_step_T2000_s4}
mkdir -p "$out"
for K in 3 5; do
  for solver in BlockTridiagonal PCG; do
    for adjoint in "unrolled" "truncated(k=1)" "implicit"; do
      name="${solver}_${adjoint//[()=]/}_K${K}"
      limit=$([ "$solver" = PCG ] && echo 400 || echo 120)
      for try in 1 2 3; do
        timeout "$limit" python train_step.py --sizes 2000 --steps "$K" \
          --theseus-max-T 200 --solvers "$solver" --adjoints "$adjoint" \
          --repeats 3 --json "$out/$name.json" > "$out/$name.log" 2>&1
        rc=$?
        echo "$name try $try rc $rc" | tee -a "$out/attempts.txt"
        [ $rc -eq 0 ] && break
      done
    done
  done
done
