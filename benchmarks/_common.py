"""Shared helpers for the benchmark scripts (timing, machine info, output)."""

import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax


def _git_hash(where: Path) -> str:
    """The short hash of HEAD of the checkout holding `where`."""
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=where,
        ).stdout.strip()
    except OSError:
        return "unknown"


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except OSError:
        pass
    # The eqsmooth actually imported (PYTHONPATH may point at another checkout
    # than the one holding this script, e.g. for a before/after comparison).
    lib = sys.modules.get("eqsmooth")
    lib_dir = Path(lib.__file__).parent if lib is not None else None
    git = _git_hash(Path(__file__).parent)
    lib_git = _git_hash(lib_dir) if lib_dir is not None else "not imported"
    return {
        "cores": os.cpu_count(),
        "memory": mem,
        "cpu": cpu,
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": sorted({d.device_kind for d in jax.devices()}),
        "git": git,
        "eqsmooth": str(lib_dir),
        "eqsmooth_git": lib_git,
        "command": " ".join([Path(sys.executable).name] + sys.argv),
        # Thread settings and load change timings by large factors on a
        # shared 2-core machine (an oversubscribed OpenBLAS made a 400 x 400
        # Cholesky 10-100x slower), so they are part of the record.
        "env": {
            k: os.environ[k]
            for k in (
                "OPENBLAS_NUM_THREADS",
                "OMP_NUM_THREADS",
                "XLA_FLAGS",
                "GLIBC_TUNABLES",
            )
            if k in os.environ
        },
        "load_average": os.getloadavg(),
    }


def loaded_blas() -> list[str]:
    """The BLAS libraries mapped into this process, other than NumPy's own.

    CHOLMOD's supernodal factorisation spends its time in the system BLAS that
    SuiteSparse was linked against: the reference (netlib) BLAS made torus3D's
    factorisation 4x slower than OpenBLAS on this machine, so the report says
    which one was used.
    """
    found = set()
    try:
        lines = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return []
    for line in lines:
        path = line.split()[-1]
        name = Path(path).name
        if "scipy_openblas" in name or ".libs/" in path:
            continue  # the wheels' private copies, not what CHOLMOD calls
        if name.startswith(("libblas.so", "libopenblas", "libmkl_rt", "libblis")):
            found.add(str(Path(path).resolve()))
    return sorted(found)


def time_fn(fn, *args, repeats: int = 7, min_time: float = 0.0):
    """Return (first_call_s, median_s, all_s) of a function returning JAX arrays."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    t_start = time.perf_counter()
    while len(times) < repeats or (time.perf_counter() - t_start) < min_time:
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
        if len(times) > 200:
            break
    return first, statistics.median(times), times


def write_json(path, records, extra=None):
    payload = {"machine": machine(), "records": records}
    if extra:
        payload.update(extra)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    os.replace(tmp, path)


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    out = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        cells = []
        for c in columns:
            v = r.get(c, "")
            cells.append(f"{v:.4g}" if isinstance(v, float) else str(v))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)
