#!/usr/bin/env bash
# Issue 13: one run before the solver redesign (git 1ab278a) and one after,
# interleaved benchmark by benchmark so both see the same machine load.
#   git -C /work/main worktree add /work/wt13before 1ab278a
#   git -C /work/main worktree add --detach /work/wt13after 5b3d35b  # the branch, frozen
#   AFTER=/work/wt13after RESULTS=$PWD/benchmarks/results bash benchmarks/run_issue13_before_after.sh \
#     > benchmarks/results/issue13_before_after.log 2>&1
# chain.py changed its solver call with the API, so each tree runs its own
# chain.py; train_step.py and pgo.py are the same harness for both, and only
# PYTHONPATH picks the library (the JSON's machine.eqsmooth_git says which).
set -u
B=${BEFORE:-/work/wt13before}
A=${AFTER:-$(cd "$(dirname "$0")/.." && pwd)}
PY=${PY:-/work/main/.venv/bin/python}
R=${RESULTS:-$A/benchmarks/results}
log() { echo "== $(date -u +%FT%TZ) $1 loadavg: $(cat /proc/loadavg)"; }
run() { nice -n 10 env OPENBLAS_NUM_THREADS=1 "$@"; }
cd "$A/benchmarks" || exit 1
for arm in before after; do
  lib=$B; [ $arm = after ] && lib=$A
  log "chain $arm"
  (cd "$lib/benchmarks" && run PYTHONPATH="$lib" "$PY" chain.py --problems se2vel \
    --sizes 10000 100000 --solvers BlockTridiagonal --json "$R/chain_issue13_$arm.json")
done
log "chain done"
for arm in before after; do
  lib=$B; [ $arm = after ] && lib=$A
  log "train_step $arm"
  run PYTHONPATH="$lib" "$PY" train_step.py --sizes 20 200 --steps 3 \
    --solvers BlockTridiagonal --no-reference --json "$R/train_step_issue13_$arm.json"
done
log "train_step done"
for arm in before after; do
  lib=$B; [ $arm = after ] && lib=$A
  log "pgo $arm"
  run PYTHONPATH="$lib" "$PY" pgo.py --files intel sphere2500 \
    --json "$R/pgo_issue13_$arm.json"
done
log "pgo done"
log "xla_cpu_hang (after)"
run PYTHONPATH="$A" "$PY" xla_cpu_hang.py --trials 6 --json "$R/xla_cpu_hang_issue13_after.json"
log "all done"
