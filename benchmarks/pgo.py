"""Pose-graph optimisation on the standard g2o data sets, against GTSAM.

Every file is loaded with `eqsmooth.io.load_g2o` (gauge prior on the first
pose, σ = 1e-6) and solved from its initial values by
`LevenbergMarquardt(linear)`, `--solver`: `sparse` (`SparseLU()`, the
default), `cholmod` (`SparseCholesky()`, needs scikit-sparse), `sparsax`
(`SparsaxCholesky()`, `pip install "eqsmooth[sparse]"`), `pcg` (`PCG()`,
block-Jacobi or `--preconditioner chain`) or `dense`; and by GTSAM's
`LevenbergMarquardtOptimizer` on the same factors (`eqsmooth.io.to_gtsam`;
the initial costs are checked equal). One unit of work is one full solve
(at most `--max-steps` iterations); `median_s` is the median over repeats
after a warm-up call (fewer when a solve exceeds `--budget-s`; `repeats`
says how many), `compile_s` the first call minus the median. Stopping: ours
`ftol = 1e-8`, GTSAM `relativeErrorTol = 1e-8`, `absoluteErrorTol = 0`.

Data: `../shared/data/g2o/` (SE-Sync collection; cubicle's 5021 indefinite
information matrices repaired with `invalid_information="block_diagonal"`);
without it the script times a synthetic 2-D graph.

    python -m benchmarks.pgo --quick                # intel + smallGrid3D
    python -m benchmarks.pgo --json benchmarks/results/pgo.json \\
        --md benchmarks/results/pgo.md
"""

import statistics
import warnings
from importlib.metadata import version
from pathlib import Path

import jax
import numpy as np

from ._common import (
    cli,
    dirty,
    loaded_blas,
    machine,
    markdown_table,
    optional,
    time_host,
    write_json,
    write_text,
)


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402
from eqsmooth.io import load_g2o, synthetic_pose_graph_2d, to_gtsam  # noqa: E402


DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"
FILES = "intel MIT CSAIL manhattan kitti_00 sphere2500 torus3D parking-garage cubicle"
FILES = FILES.split()
QUICK_FILES = ["intel", "smallGrid3D"]


def timed(fn, repeats: int, budget_s: float):
    """(first_s, median_s, repeats, last result) of `fn()`."""
    first, times, out = time_host(fn, repeats, budget_s)
    return first, statistics.median(times), len(times), out


def solve_gtsam(gtsam, pg, max_steps):
    graph, initial = to_gtsam(pg)
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)
    params.setAbsoluteErrorTol(0.0)
    params.setMaxIterations(max_steps)

    def run():
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        return opt, opt.optimize()

    return graph, initial, run


def gtsam_record(gtsam, name, pg, args, rec) -> dict:
    """GTSAM on the same problem, after checking that both costs agree."""
    graph, initial, run = solve_gtsam(gtsam, pg, args.max_steps)
    check = graph.error(initial)
    if not np.isclose(check, rec["initial_cost"], rtol=1e-9):
        raise RuntimeError(
            f"{name}: GTSAM's initial cost {check} differs from ours "
            f"{rec['initial_cost']}: the problems are not the same"
        )
    _, g_median, g_n, (opt, result) = timed(run, args.repeats, args.budget_s)
    return {
        "reference": graph.error(result),
        "reference_name": f"GTSAM {version('gtsam')} LevenbergMarquardtOptimizer",
        "reference_median_s": g_median,
        "reference_repeats": g_n,
        "reference_iterations": int(opt.iterations()),
        "ratio": rec["median_s"] / g_median,
        "cost_ratio": rec["final_cost"] / graph.error(result),
    }


def bench_one(name, pg, args, solver, solver_name, gtsam):
    def run():
        sol = eqs.least_squares(
            pg.graph, pg.values, solver, max_steps=args.max_steps, throw=False
        )
        return jax.block_until_ready(sol)

    first, median, n, sol = timed(run, args.repeats, args.budget_s)
    config = dict(file=name, kind=pg.kind, num_poses=pg.num_poses)
    config |= dict(num_edges=pg.num_edges, solver=solver_name)
    config |= dict(initial_damping=solver.initial_damping, max_steps=args.max_steps)
    config |= dict(dtype="float64", se3_information=pg.se3_information)
    config["anchor_sqrt_information"] = 1e6
    rec = {"benchmark": "pgo", "config": config, "file": name, "median_s": median}
    rec |= {"compile_s": max(first - median, 0.0), "repeats": n}
    rec |= {k: int(sol.stats[k]) for k in ("num_steps", "num_accepted")}
    rec |= {k: float(sol.stats[k]) for k in ("initial_cost", "final_cost")}
    rec["result"] = str(sol.result).split("<", 1)[-1].rstrip(">") or "successful"
    if gtsam:
        rec.update(gtsam_record(gtsam, name, pg, args, rec))
    return rec


def table_of(records: list[dict]) -> str:
    rows = []
    for r in records:
        c, get = r["config"], r.get
        row = {"file": r["file"], "kind": c["kind"], "poses": c["num_poses"]}
        row |= {"edges": c["num_edges"]}
        row["steps (acc.)"] = f"{r['num_steps']} ({r['num_accepted']})"
        row["initial cost"] = f"{r['initial_cost']:.4g}"
        row["final cost"] = f"{r['final_cost']:.8g}"
        row["GTSAM cost"] = f"{r['reference']:.8g}" if "reference" in r else ""
        row |= {"cost ratio": get("cost_ratio", ""), "median s": r["median_s"]}
        row |= {"compile s": r["compile_s"], "GTSAM s": get("reference_median_s", "")}
        row["GTSAM it."] = get("reference_iterations", "")
        row["time ratio"] = get("ratio", "")
        rows.append(row)
    return markdown_table(rows, list(rows[0]) if rows else ["file"])


def write_markdown(path, records, m: dict, solver_name: str, max_steps: int):
    """The report: how it was made, the table, and which rows reached GTSAM."""
    reached = ", ".join(
        r["file"] for r in records if r.get("cost_ratio", 2) <= 1 + 1e-6
    )
    missed = ", ".join(r["file"] for r in records if r.get("cost_ratio", 0) > 1 + 1e-6)
    git = m["git"] + (" (plus uncommitted changes)" if m.get("dirty") else "")
    lines = [
        "# Pose-graph optimisation: eqsmooth vs GTSAM",
        "",
        f"- command: `{m['command']}`",
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
        f"Reached GTSAM's final cost (ratio ≤ 1 + 1e-6): {reached or 'none'}. "
        f"Did not: {missed or 'none'}. The time ratio compares like with like "
        "only where both reached the same cost.",
    ]
    write_text(path, "\n".join(lines))


def make_solver(args):
    """The LevenbergMarquardt solver `--solver` names, and its name."""
    pre = eqs.solve.BlockJacobi()
    if args.preconditioner == "chain":
        pre = eqs.solve.ChainPreconditioner()
    linear = {
        "sparse": eqs.solve.SparseLU,
        "cholmod": eqs.solve.SparseCholesky,
        "sparsax": eqs.solve.SparsaxCholesky,
        "dense": eqs.DenseCholesky,
        "pcg": lambda: eqs.PCG(preconditioner=pre),
    }[args.solver]()
    inner = f"{type(linear).__name__}()"
    if args.solver == "pcg":
        inner = f"PCG(preconditioner={type(pre).__name__}())"
    return eqs.LevenbergMarquardt(linear), f"LevenbergMarquardt({inner})"


def load_problems(args) -> list:
    if not DATA.exists():
        print(f"note: {DATA} not found; timing a synthetic 2-D pose graph instead")
        pg, _ = synthetic_pose_graph_2d(300 if args.quick else 2000, seed=0)
        return [("synthetic_2d", pg)]
    problems = []
    for name in args.files or (QUICK_FILES if args.quick else FILES):
        path = DATA / f"{name}.g2o"
        if not path.exists():
            print(f"note: {path} not found, skipped")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # cubicle's repairs
            problems.append(
                (name, load_g2o(path, invalid_information="block_diagonal"))
            )
    return problems


def main(argv=None):
    parser = cli(__doc__)
    parser.add_argument("--quick", action="store_true", help="intel + smallGrid3D")
    parser.add_argument("--md", default=None, help="write the markdown report here")
    parser.add_argument("--files", nargs="*", default=None, help="subset of files")
    solvers = ["sparse", "cholmod", "sparsax", "pcg", "dense"]
    parser.add_argument("--solver", choices=solvers, default="sparse")
    parser.add_argument("--preconditioner", choices=["jacobi", "chain"])
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget-s", type=float, default=120.0, help="per file")
    parser.add_argument("--no-gtsam", action="store_true")
    args = parser.parse_args(argv)
    if args.max_steps is None:
        args.max_steps = 10 if args.quick else 100
    gtsam = None if args.no_gtsam else optional("gtsam", " (pip install gtsam)")
    solver, solver_name = make_solver(args)
    problems = load_problems(args)
    m = machine()  # git hash and tree state when the run started
    m["dirty"] = bool(dirty())
    if args.solver == "cholmod":
        import sksparse.cholmod  # noqa: F401  (maps CHOLMOD's BLAS)

        m["blas"] = loaded_blas()
    if args.solver == "sparsax":
        m["blas"] = [eqs.solve.sparsax_blas()]  # "mkl" or "bundled" (ATLAS)
    records = []
    for name, pg in problems:
        rec = bench_one(name, pg, args, solver, solver_name, gtsam)
        records.append(rec)
        ref = ""
        if "reference" in rec:
            ref = f"; GTSAM {rec['reference']:.6g} in {rec['reference_iterations']} "
            ref += f"it, {rec['reference_median_s']:.3f} s"
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
    print()
    print(table_of(records))


if __name__ == "__main__":
    main()
