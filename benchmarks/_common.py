"""Shared scaffolding of the benchmark scripts: timing, machine record, output,
child processes, optional imports and the 5-pose SE(2) graph several workloads
use."""

import argparse
import importlib
import importlib.util
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def git(*args: str, where: Path = ROOT) -> str:
    """Output of `git ARGS` in the checkout holding `where` ("" if unavailable)."""
    try:
        out = subprocess.run(["git", *args], capture_output=True, text=True, cwd=where)
    except OSError:
        return ""
    return out.stdout.strip()


def dirty(*paths: str) -> list[str]:
    """Paths (relative to the repository root) with uncommitted changes."""
    out = git("status", "--porcelain", "--untracked-files=no", "--", *paths)
    # `git` strips the output, and with it the first line's leading status
    # column: split on whitespace instead of slicing fixed columns.
    return [line.split(maxsplit=1)[1] for line in out.splitlines() if line.strip()]


def cli_command() -> str:
    """The command line of this process, as `python -m MODULE ARGS` when it was
    started with `-m`."""
    spec = getattr(sys.modules["__main__"], "__spec__", None)
    head = ["-m", spec.name] if spec else sys.argv[:1]
    return " ".join([Path(sys.executable).name, *head, *sys.argv[1:]])


def _proc_field(path: str, key: str) -> str | None:
    try:
        lines = Path(path).read_text().splitlines()
    except OSError:
        return None
    return next((x.split(":", 1)[1].strip() for x in lines if x.startswith(key)), None)


def machine() -> dict:
    """What a timing depends on: hardware, versions, tree, threads, load."""
    mem = _proc_field("/proc/meminfo", "MemTotal")
    # The eqsmooth actually imported (PYTHONPATH may point at another checkout
    # than the one holding this script, e.g. for a before/after comparison).
    lib = sys.modules.get("eqsmooth")
    lib_dir = Path(lib.__file__).parent if lib is not None else None
    # Thread settings and load change timings by large factors on a shared
    # 2-core machine (an oversubscribed OpenBLAS made a 400 x 400 Cholesky
    # 10-100x slower), so they are part of the record.
    env_keys = "OPENBLAS_NUM_THREADS OMP_NUM_THREADS XLA_FLAGS GLIBC_TUNABLES".split()
    lib_git = git("rev-parse", "--short", "HEAD", where=lib_dir) if lib_dir else None
    return {
        "cores": os.cpu_count(),
        "memory": f"{int(mem.split()[0]) / 2**20:.1f} GiB" if mem else None,
        "cpu": _proc_field("/proc/cpuinfo", "model name") or "unknown",
        "python": platform.python_version(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": sorted({d.device_kind for d in jax.devices()}),
        "git": git("rev-parse", "--short", "HEAD") or "unknown",
        "eqsmooth": str(lib_dir),
        "eqsmooth_git": lib_git or "not imported",
        "command": cli_command(),
        "env": {k: os.environ[k] for k in env_keys if k in os.environ},
        "load_average": os.getloadavg(),
    }


def optional(module: str, note: str = ""):
    """The module, or None after printing that it is not installed."""
    try:
        return importlib.import_module(module)
    except ImportError:
        print(f"note: {module} not installed{note}; not timed")


def time_host(fn, repeats: int, budget_s: float = float("inf")):
    """(first_s, times, last result) of `fn()` (which blocks itself); stops
    early when another call would exceed `budget_s` (at least one repeat)."""
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < repeats:
        if times and time.perf_counter() - start + times[-1] > budget_s:
            break
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return first, times, out


def time_fn(fn, *args, repeats: int = 7):
    """(first_call_s, median_s, all_s) of a function returning JAX arrays."""
    first, times, _ = time_host(lambda: jax.block_until_ready(fn(*args)), repeats)
    return first, statistics.median(times), times


def compile_log() -> list[tuple[str, float]]:
    """A list to which every XLA compilation from now on appends its
    `(program name, seconds)` (JAX's monitoring events)."""
    log = []

    def on_duration(event, secs, **kw):
        if event.endswith("backend_compile_duration"):
            log.append((kw.get("fun_name"), secs))

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    return log


def xla_cost(compiled) -> dict:
    """XLA's cost analysis (flops, bytes accessed) of a compiled program."""
    c = compiled.cost_analysis()
    c = c[0] if isinstance(c, list) else c
    return {k: c.get(k, 0.0) for k in ("flops", "bytes accessed")}


def run_child(module: str, args: list[str], tree=None, env=None) -> dict:
    """Run `python -P -m benchmarks.MODULE ARGS` in a fresh process; the JSON
    object its last line of output prints.

    The child imports eqsmooth from `tree` (a checkout, for before/after runs
    in one command; by default the one this process would import) and the
    benchmark code from this checkout: with `-P` the working directory is not
    searched for modules, and a temporary folder linking this checkout's
    `benchmarks/` and `experiments/` comes first on `PYTHONPATH`, then
    `tree`, then what `PYTHONPATH` held. `env` adds environment variables.
    """
    env = {**os.environ, **(env or {})}
    tree = tree or Path(importlib.util.find_spec("eqsmooth").origin).parents[1]
    with tempfile.TemporaryDirectory(prefix="eqs_bench_") as tmp:
        for name in ("benchmarks", "experiments"):
            (Path(tmp) / name).symlink_to(ROOT / name)
        path = [tmp, str(Path(tree).resolve()), env.get("PYTHONPATH", "")]
        env["PYTHONPATH"] = os.pathsep.join(p for p in path if p)
        cmd = [sys.executable, "-P", "-m", f"benchmarks.{module}", *args]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"{' '.join(cmd[2:])} failed:\n{out.stderr[-4000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def record(benchmark: str, config: dict, **fields) -> dict:
    """One result: the workload's name, its configuration (also spread at the
    top level, for tables) and the measured fields."""
    return {"benchmark": benchmark, "config": config, **config, **fields}


def cli(doc: str) -> argparse.ArgumentParser:
    """A parser described by the first line of `doc`, with `--json PATH`."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--json", default=None, help="write the records here")
    return parser


def print_and_save(records, columns, path=None, extra=None) -> None:
    """Print `records` as a table; write them to `path` (JSON) if given."""
    print("\n" + markdown_table(records, columns))
    if path:
        write_json(path, records, extra)


def write_json(path, records, extra=None):
    payload = {"machine": machine(), "records": records, **(extra or {})}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    os.replace(tmp, path)


def write_text(path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text if text.endswith("\n") else text + "\n")


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    out = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        cells = (r.get(c, "") for c in columns)
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in cells]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def loaded_blas() -> list[str]:
    """The BLAS libraries mapped into this process, other than NumPy's own.

    CHOLMOD's supernodal factorisation spends its time in the system BLAS that
    SuiteSparse was linked against, so the report says which one was used.
    """
    try:
        maps = Path("/proc/self/maps").read_text().splitlines()
    except OSError:
        return []
    blas = ("libblas.so", "libopenblas", "libmkl_rt", "libblis")
    # Not the wheels' private copies (scipy_openblas, */.libs/): CHOLMOD calls none.
    paths = {x.split()[-1] for x in maps}
    paths = {p for p in paths if Path(p).name.startswith(blas) and ".libs/" not in p}
    return sorted({str(Path(p).resolve()) for p in paths if "scipy_openblas" not in p})


def disk_step(x):
    """The paper's disk dynamics with drag, state `[px, py, vx, vy]`:
    `p' = p + v`, `v' = v − 0.05 p − 0.0075 sign(v) v²`."""
    p, v = x[..., :2], x[..., 2:]
    v_next = v - 0.05 * p - 0.0075 * jnp.sign(v) * v * v
    return jnp.concatenate([p + v, v_next], axis=-1)


def disk_dynamics(a, b, data, params):
    """The disk's dynamics residual (a `FunctionFactor` function)."""
    return b - disk_step(a)


def disk_position(x, data, params):
    """The disk's position measurement residual."""
    return x[:2] - data


def se2(xyt):
    """SE(2) poses of the rows `(x, y, θ)` of `xyt`, in float64."""
    import eqsmooth as eqs

    return eqs.SE2.from_xy_theta(*jnp.asarray(np.asarray(xyt, np.float64).T))


def pose2_problem():
    """GTSAM's Pose2SLAM example shape: 5 SE(2) poses, a prior, 4 odometry
    factors and a loop closure 4 -> 1. Returns `(graph, values)`."""
    import eqsmooth as eqs

    def diag(*sigmas):
        return eqs.DiagonalNoise.from_sigmas(jnp.array(sigmas))

    h = np.pi / 2
    odo = [[2.0, 0, 0], [2.1, 0.05, h], [1.9, -0.03, h + 0.02]]
    odo += [[2.05, 0, h - 0.03], [2.1, 0.1, h + 0.05]]
    init = [[0.4, 0.1, 0.15], [2.3, 0.1, -0.2], [4.1, 0.2, h]]
    init += [[4.0, 2.1, np.pi], [2.1, 2.2, -h]]
    prior = eqs.PriorFactor(eqs.Var("x", [0]), se2([[0.0] * 3]), diag(0.3, 0.3, 0.1))
    a, b = eqs.Var("x", [0, 1, 2, 3, 4]), eqs.Var("x", [1, 2, 3, 4, 1])
    odometry = eqs.BetweenFactor(a, b, se2(odo), diag(0.2, 0.2, 0.1))
    return eqs.FactorGraph([prior, odometry]), {"x": se2(init)}
