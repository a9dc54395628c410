#!/usr/bin/env bash
# Run the whole test suite on a GPU machine and write a summary.
#
#   bash tests/run_on_gpu.sh [OUTDIR] [-- PYTEST ARGS...]
#   bash tests/run_on_gpu.sh -- tests/test_linear_solvers.py   # to $OUT
#
# From the repository root of a checkout, with the machine's own python3 and
# JAX (a GPU image's). Only what that Python lacks is installed: from wheels
# in .whl/ when the folder exists (machines without a package index; carry
# them as the device tool's README says), otherwise from the package index.
# Writes OUTDIR/gpu_suite.log, junit.xml and summary.md (default: $OUT when
# set, else results/gpu_suite). The summary names the GPU, JAX and jaxlib, the
# counts and every failure; commit it with docs/performance.md's
# "GPU test-suite results" updated from it.
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-results/gpu_suite}
if [ $# -gt 0 ] && [ "$1" != "--" ]; then
  out=$1
  shift
fi
if [ "${1:-}" = "--" ]; then shift; fi
mkdir -p "$out"
python=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
# One GPU shared by several pytest workers: no process may take most of its
# memory up front (XLA's default preallocates 75% per process).
export XLA_PYTHON_CLIENT_PREALLOCATE=false

# module name -> distribution name, for what the suite imports
missing=()
for pair in jax:jax equinox:equinox optimistix:optimistix lineax:lineax \
    optax:optax jaxtyping:jaxtyping beartype:beartype pytest:pytest \
    xdist:pytest-xdist hypothesis:hypothesis jaxlie:jaxlie scipy:scipy \
    tqdm:tqdm numpy:numpy matplotlib:matplotlib; do
  "$python" -c "import ${pair%%:*}" 2>/dev/null || missing+=("${pair#*:}")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "missing here: ${missing[*]}"
  if [ -d .whl ]; then
    "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
        --upgrade --target /tmp/eqsmooth-site .whl/*.whl || exit 1
    export PYTHONPATH=/tmp/eqsmooth-site${PYTHONPATH:+:$PYTHONPATH}
  else
    "$python" -m pip install -q "${missing[@]}" || exit 1
  fi
fi

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader \
    > "$out/gpu.txt" 2>/dev/null || echo "no nvidia-smi" > "$out/gpu.txt"
start=$(date +%s)
"$python" -m pytest -p no:cacheprovider -q -rfEs -n "${WORKERS:-8}" \
    --junitxml="$out/junit.xml" "$@" 2>&1 | tee "$out/gpu_suite.log"
status=${PIPESTATUS[0]}
seconds=$(( $(date +%s) - start ))

"$python" - "$out" "$status" "$seconds" <<'PY'
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import jax
import jaxlib

out, status, seconds = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
suites = ET.parse(out / "junit.xml").getroot()
suites = [suites] if suites.tag == "testsuite" else list(suites)
count = {k: sum(int(s.get(k, 0)) for s in suites) for k in ("tests", "failures", "errors", "skipped")}
passed = count["tests"] - count["failures"] - count["errors"] - count["skipped"]
bad = []
for case in (c for s in suites for c in s.iter("testcase")):
    for kind in ("failure", "error"):
        node = case.find(kind)
        if node is not None:
            first = (node.get("message") or "").strip().splitlines()[:1]
            bad.append(f"- {kind}: `{case.get('classname')}::{case.get('name')}`: {first[0][:200] if first else ''}")
device = jax.devices()[0]
lines = [
    "# eqsmooth test suite on a GPU",
    "",
    f"- GPU: {(out / 'gpu.txt').read_text().strip()} (JAX sees `{device.device_kind}`, backend `{jax.default_backend()}`)",
    f"- jax {jax.__version__}, jaxlib {jaxlib.__version__}, Python {sys.version.split()[0]}",
    f"- command: `bash tests/run_on_gpu.sh` (pytest exit status {status}, {seconds} s)",
    f"- {passed} passed, {count['failures']} failed, {count['errors']} errors, {count['skipped']} skipped",
    "",
] + (["## Failures", ""] + bad if bad else ["No failures."])
(out / "summary.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
PY
exit "$status"
