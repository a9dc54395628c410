#!/bin/sh
# Before/after in one command: the same benchmark with main's eqsmooth (before
# the lean SE(2)/SO(2) compose and inverse) and with this checkout's.
# Usage: sh benchmarks/run_kitti_compile.sh DIR, DIR holding the earlier eqsmooth/
set -e
BEFORE=${1:?give a checkout of the code before (e.g. git archive 560994c eqsmooth)}
HERE=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-python}
PYTHONPATH=$BEFORE nice -n 10 $PY "$HERE/benchmarks/kitti_compile.py" --compile --breakdown \
    --json "$HERE/benchmarks/results/kitti_compile_before.json"
PYTHONPATH=$HERE nice -n 10 $PY "$HERE/benchmarks/kitti_compile.py" --compile --breakdown \
    --json "$HERE/benchmarks/results/kitti_compile_after.json"
