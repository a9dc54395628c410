"""Pose-graph optimisation on the standard g2o data sets, against GTSAM.

For every file: load it with `eqsmooth.io.load_g2o` (gauge prior on the first
pose, σ = 1e-6), solve with `LevenbergMarquardt(SparseLU())` (host sparse
direct solves; or `--solver cholmod` for `SparseCholesky()`, CHOLMOD through
the optional scikit-sparse; or `--solver pcg` for `PCG()` with block-Jacobi, plus
`--preconditioner chain` for `ChainPreconditioner()`; or `--solver sparsax`
for `SparsaxCholesky()`, CHOLMOD inside jit through the optional sparsax
wheel, `pip install "eqsmooth[sparse]"`; or `--solver dense`)
from the file's initial values, and solve the same problem with GTSAM's
`LevenbergMarquardtOptimizer` in the same run. GTSAM gets exactly the same
factors (`eqsmooth.io.to_gtsam`: same measurements, same information
matrices reordered to its (ω, v) tangent, same prior), so both report the
same cost, `½ Σ ‖R r‖²` (checked at the initial values).

One unit of work is one full solve from the initial values (at most
`--max-steps` iterations). `median_s` is the median over repeats after a
warm-up call (fewer repeats than asked when one solve exceeds the per-file
time budget; `repeats` says how many), `compile_s` is first call minus
median. GTSAM is timed the same way (optimizer construction + optimize).
Stopping rules: ours `ftol = 1e-8` (relative cost decrease), GTSAM
`relativeErrorTol = 1e-8`, `absoluteErrorTol = 0`, `maxIterations =
--max-steps`.

Data: `../shared/data/g2o/` (SE-Sync collection). cubicle.g2o has 5021
indefinite information matrices; they are repaired with
`invalid_information="block_diagonal"` for both solvers. Without the data
folder the script times a synthetic 2-D graph instead.

    python benchmarks/pgo.py                        # all files (many minutes)
    python benchmarks/pgo.py --quick                # intel + smallGrid3D (CI)
    python benchmarks/pgo.py --json benchmarks/results/pgo.json \\
        --md benchmarks/results/pgo.md
"""

import argparse
import statistics
import subprocess
import time
import warnings
from pathlib import Path

import jax
import numpy as np
from _common import loaded_blas, machine, markdown_table, write_json


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402
from eqsmooth.io import load_g2o, synthetic_pose_graph_2d, to_gtsam  # noqa: E402


DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"
FILES = [
    "intel",
    "MIT",
    "CSAIL",
    "manhattan",
    "kitti_00",
    "sphere2500",
    "torus3D",
    "parking-garage",
    "cubicle",
]
QUICK_FILES = ["intel", "smallGrid3D"]


def timed(fn, repeats: int, budget_s: float):
    """(first_s, median_s, repeats, last result) of `fn()`."""
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
    return first, statistics.median(times), len(times), out


def solve_ours(pg, solver, max_steps):
    def run():
        sol = eqs.least_squares(
            pg.graph, pg.values, solver, max_steps=max_steps, throw=False
        )
        return jax.block_until_ready(sol)

    return run


def solve_gtsam(pg, max_steps):
    import gtsam

    graph, initial = to_gtsam(pg)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(max_steps)

    def run():
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = opt.optimize()
        return opt, result

    return graph, initial, run


def _gtsam_version() -> str:
    from importlib.metadata import version

    try:
        return version("gtsam")
    except Exception:
        return "?"


def bench_one(name, pg, args, solver, solver_name, have_gtsam):
    first, median, n, sol = timed(
        solve_ours(pg, solver, args.max_steps), args.repeats, args.budget_s
    )
    rec = {
        "benchmark": "pgo",
        "config": {
            "file": name,
            "kind": pg.kind,
            "num_poses": pg.num_poses,
            "num_edges": pg.num_edges,
            "solver": solver_name,
            "initial_damping": solver.initial_damping,
            "max_steps": args.max_steps,
            "dtype": "float64",
            "se3_information": pg.se3_information,
            "anchor_sqrt_information": 1e6,
        },
        "file": name,
        "median_s": median,
        "compile_s": max(first - median, 0.0),
        "repeats": n,
        "num_steps": int(sol.stats["num_steps"]),
        "num_accepted": int(sol.stats["num_accepted"]),
        "initial_cost": float(sol.stats["initial_cost"]),
        "final_cost": float(sol.stats["final_cost"]),
        "result": str(sol.result).split("<", 1)[-1].rstrip(">") or "successful",
    }
    if have_gtsam:
        graph, initial, run = solve_gtsam(pg, args.max_steps)
        check = graph.error(initial)
        if not np.isclose(check, rec["initial_cost"], rtol=1e-9):
            raise RuntimeError(
                f"{name}: GTSAM's initial cost {check} differs from ours "
                f"{rec['initial_cost']}: the problems are not the same"
            )
        g_first, g_median, g_n, (opt, result) = timed(run, args.repeats, args.budget_s)
        rec.update(
            reference=graph.error(result),
            reference_name=f"GTSAM {_gtsam_version()} LevenbergMarquardtOptimizer",
            reference_median_s=g_median,
            reference_repeats=g_n,
            reference_iterations=int(opt.iterations()),
        )
        rec["ratio"] = median / g_median
        rec["cost_ratio"] = rec["final_cost"] / rec["reference"]
    return rec


def table_of(records: list[dict]) -> str:
    rows = []
    for r in records:
        c = r["config"]
        rows.append(
            {
                "file": r["file"],
                "kind": c["kind"],
                "poses": c["num_poses"],
                "edges": c["num_edges"],
                "steps (acc.)": f"{r['num_steps']} ({r['num_accepted']})",
                "initial cost": f"{r['initial_cost']:.4g}",
                "final cost": f"{r['final_cost']:.8g}",
                "GTSAM cost": f"{r['reference']:.8g}" if "reference" in r else "",
                "cost ratio": r.get("cost_ratio", ""),
                "median s": r["median_s"],
                "compile s": r["compile_s"],
                "GTSAM s": r.get("reference_median_s", ""),
                "GTSAM it.": r.get("reference_iterations", ""),
                "time ratio": r.get("ratio", ""),
            }
        )
    return markdown_table(rows, list(rows[0]) if rows else ["file"])


def _dirty() -> bool:
    try:
        out = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
        ).stdout
    except OSError:
        return False
    return bool(out.strip())


def write_markdown(path, records, m: dict, solver_name: str, max_steps: int):
    """The report: how it was made, the table, and which rows reached GTSAM."""
    reached = [r["file"] for r in records if r.get("cost_ratio", 2.0) <= 1 + 1e-6]
    missed = [r["file"] for r in records if r.get("cost_ratio", 0.0) > 1 + 1e-6]
    git = m["git"] + (" (plus uncommitted changes)" if m.get("dirty") else "")
    lines = [
        "# Pose-graph optimisation: eqsmooth vs GTSAM",
        "",
        f"- command: `{m['command']}` (in `benchmarks/`)",
        f"- solver: `{solver_name}`, max_steps {max_steps}; GTSAM "
        "LevenbergMarquardtOptimizer with relativeErrorTol 1e-8, "
        "absoluteErrorTol 0, same factors and initial values",
        f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}; "
        f"JAX {m['jax']} ({m['backend']}), Python {m['python']}",
        f"- git: {git}",
        "- times: median of `repeats` full solves after a warm-up call, seconds",
    ]
    if m.get("blas"):
        lines.append(f"- BLAS used by CHOLMOD: {', '.join(m['blas'])}")
    lines += [
        "",
        table_of(records),
        "",
        "Reached GTSAM's final cost (ratio ≤ 1 + 1e-6): "
        + (", ".join(reached) or "none")
        + ". Did not: "
        + (", ".join(missed) or "none")
        + ". The time ratio compares like with like only where both reached "
        "the same cost.",
    ]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="intel + smallGrid3D")
    parser.add_argument("--json", default=None, help="write records here")
    parser.add_argument("--md", default=None, help="write the markdown report here")
    parser.add_argument("--files", nargs="*", default=None, help="subset of files")
    parser.add_argument(
        "--solver",
        choices=["sparse", "cholmod", "sparsax", "pcg", "dense"],
        default="sparse",
        help="sparse: SparseLU() (SciPy); cholmod: SparseCholesky() (needs "
        "scikit-sparse); sparsax: SparsaxCholesky() (needs sparsax); pcg: PCG(); "
        "dense: DenseCholesky()",
    )
    parser.add_argument(
        "--preconditioner",
        choices=["jacobi", "chain"],
        default="jacobi",
        help="PCG preconditioner: BlockJacobi() or ChainPreconditioner()",
    )
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget-s", type=float, default=120.0, help="per file")
    parser.add_argument("--no-gtsam", action="store_true")
    args = parser.parse_args(argv)
    if args.max_steps is None:
        args.max_steps = 10 if args.quick else 100

    try:
        import gtsam  # noqa: F401

        have_gtsam = not args.no_gtsam
    except ImportError:
        have_gtsam = False
        print("note: gtsam not installed (pip install gtsam); no reference timings")

    if args.solver == "pcg":
        pre = (
            eqs.solve.ChainPreconditioner()
            if args.preconditioner == "chain"
            else eqs.solve.BlockJacobi()
        )
        linear = eqs.PCG(preconditioner=pre)
        solver_name = f"LevenbergMarquardt(PCG(preconditioner={type(pre).__name__}()))"
    elif args.solver == "sparse":
        linear = eqs.solve.SparseLU()
        solver_name = "LevenbergMarquardt(SparseLU())"
    elif args.solver == "cholmod":
        linear = eqs.solve.SparseCholesky()
        solver_name = "LevenbergMarquardt(SparseCholesky())"
    elif args.solver == "sparsax":
        linear = eqs.solve.SparsaxCholesky()
        solver_name = "LevenbergMarquardt(SparsaxCholesky())"
    else:
        linear = eqs.DenseCholesky()
        solver_name = "LevenbergMarquardt(DenseCholesky())"
    solver = eqs.LevenbergMarquardt(linear)

    problems = []
    if DATA.exists():
        for name in args.files or (QUICK_FILES if args.quick else FILES):
            path = DATA / f"{name}.g2o"
            if not path.exists():
                print(f"note: {path} not found, skipped")
                continue
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # cubicle's repairs
                pg = load_g2o(path, invalid_information="block_diagonal")
            problems.append((name, pg))
    else:
        print(f"note: {DATA} not found; timing a synthetic 2-D pose graph instead")
        pg, _ = synthetic_pose_graph_2d(300 if args.quick else 2000, seed=0)
        problems.append(("synthetic_2d", pg))

    m = machine()  # git hash and tree state when the run started
    m["dirty"] = _dirty()
    if args.solver == "cholmod":
        import sksparse.cholmod  # noqa: F401  (maps CHOLMOD's BLAS)

        m["blas"] = loaded_blas()
    if args.solver == "sparsax":
        m["blas"] = [eqs.solve.sparsax_blas()]  # "mkl" or "bundled" (ATLAS)
    records = []
    for name, pg in problems:
        rec = bench_one(name, pg, args, solver, solver_name, have_gtsam)
        records.append(rec)
        ref = (
            f"; GTSAM {rec['reference']:.6g} in {rec['reference_iterations']} it, "
            f"{rec['reference_median_s']:.3f} s"
            if "reference" in rec
            else ""
        )
        print(
            f"{name:15s} {rec['initial_cost']:.4g} -> {rec['final_cost']:.6g} in "
            f"{rec['num_steps']} steps ({rec['num_accepted']} accepted), "
            f"{rec['median_s']:.3f} s (compile {rec['compile_s']:.1f} s){ref}",
            flush=True,
        )
        # Written after every file, so a long run that is cut off keeps its rows.
        if args.md:
            write_markdown(args.md, records, m, solver_name, args.max_steps)
        if args.json:
            write_json(args.json, records, extra={"machine": m})

    table = table_of(records)
    print()
    print(table)


if __name__ == "__main__":
    main()
