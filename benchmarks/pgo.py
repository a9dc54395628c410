"""Pose-graph optimisation on the standard g2o data sets, against GTSAM.

Each file is read by `eqsmooth.io.load_g2o` (gauge prior on the first pose,
σ = 1e-6) and solved from its initial values by `LevenbergMarquardt(linear)`,
`--solver` `sparse` (`SparseLU()`, the default), `cholmod` (`SparseCholesky()`,
scikit-sparse), `sparsax` (`SparsaxCholesky()`), `pcg` (`PCG()`, block-Jacobi,
`--preconditioner chain` or `twolevel`) or `dense`, and by GTSAM's
`LevenbergMarquardtOptimizer` on the same factors (`eqsmooth.io.to_gtsam`;
initial costs checked equal), both stopping at a relative cost decrease of
1e-8 (GTSAM's absoluteErrorTol 0). `median_s`: median of `repeats` full
solves (at most `--max-steps` iterations; fewer repeats past `--budget-s`)
after a warm-up call `first_s`; `compile_s = first_s - median_s`. Data:
`../shared/data/g2o/` (SE-Sync; cubicle's 5021 indefinite information
matrices repaired with `invalid_information="block_diagonal"`), else a
synthetic 2-D graph. `--gtsam-files`: every pose graph in the gtsam wheel,
`--solver default` (`LevenbergMarquardt()`) against GTSAM's default
`LevenbergMarquardtParams()`. `--damping-update`: LM's rule for λ.

    python -m benchmarks.pgo --quick                # intel + smallGrid3D
    python -m benchmarks.pgo --json benchmarks/results/pgo.json \\
        --md benchmarks/results/pgo.md
"""

import os
import statistics
import warnings
from importlib.metadata import version
from pathlib import Path

import jax
import numpy as np

from . import _common as common


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402
from eqsmooth.io import load_g2o, synthetic_pose_graph_2d, to_gtsam  # noqa: E402


DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"
FILES = "intel MIT CSAIL manhattan kitti_00 sphere2500 torus3D parking-garage cubicle"
FILES = FILES.split()


def timed(fn, repeats: int, budget_s: float):
    """(first_s, median_s, repeats, last result) of `fn()`."""
    first, times, out = common.time_host(fn, repeats, budget_s)
    return first, statistics.median(times), len(times), out


# Every pose graph the gtsam wheel ships, read by GTSAM's load2D, load3D, or
# readG2o where load2D reads diagonal g2o matrices as covariances. Not pose
# graphs: example.graph, victoria_park.txt (2-D landmarks), *trackxyz*,
# known_landmark_localization_*, example_with_vertices (3-D points);
# T1_city10000_04.txt (no GTSAM reader reads it).
GTSAM_FILES = """w100.graph w10000.graph w100_30.g2o w20000.txt pose2example.txt
    noisyToyGraph.txt optimizedNoisyToyGraph.txt orientationsNoisyToyGraph.txt
    cityTrees_reduced_1k.g2o victoriaPark_reduced_1k.g2o sphere_smallnoise.graph
    sphere2500.txt sphere2500_groundtruth.txt Klaus3.g2o toyExample.g2o
    pose3example.txt pose3example-grid.txt pose3example-offdiagonal.txt
    pose3example-offdiagonal-rewritten.txt pose3Localizationexample.txt
    simpleGraph10gradIter.txt""".split()
READ_G2O = ("w20000.txt", "pose2example.txt")


def gtsam_record(gtsam, name, pg, args, rec) -> dict:
    """GTSAM on the same problem, after checking that both costs agree; with
    `--gtsam-files`, its defaults on its own reader's graph of the file (plus
    our gauge prior) where that is our problem (same cost at the same values)."""
    graph, initial = to_gtsam(pg)
    params, out = gtsam.LevenbergMarquardtParams(), {}
    if args.gtsam_files:
        out["gtsam_reader"] = "readG2o" if name in READ_G2O else f"load{pg.kind[-1]}D"
        path = Path(gtsam.__file__).parent / "Data" / name
        their, _ = getattr(gtsam, out["gtsam_reader"])(str(path))
        keyed, at = gtsam.Values(), getattr(initial, f"atPose{pg.kind[-1]}")
        for k, i in enumerate(pg.vertex_ids.tolist()):
            keyed.insert(i, at(k))
        out["reader_cost"] = cost = their.error(keyed)
        same = abs(cost - rec["initial_cost"]) <= 1e-9 * cost + 1e-20
        prior = getattr(gtsam, f"PriorFactorPose{pg.kind[-1]}")
        sigma = gtsam.noiseModel.Isotropic.Sigma(3 * int(pg.kind[-1]) - 3, 1e-6)
        for k in pg.anchored.tolist() if same else []:
            their.add(prior(int(pg.vertex_ids[k]), at(k), sigma))
        graph, initial = (their, keyed) if same else (graph, initial)
        out["same_problem"] = same
    else:
        params.setRelativeErrorTol(1e-8)
        params.setAbsoluteErrorTol(0.0)
        params.setMaxIterations(args.max_steps)

    def run():
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        return opt, opt.optimize()

    check = graph.error(initial)
    if not np.isclose(check, rec["initial_cost"], rtol=1e-9):
        raise RuntimeError(
            f"{name}: GTSAM's initial cost {check} differs from ours "
            f"{rec['initial_cost']}: the problems are not the same"
        )
    _, g_median, g_n, (opt, result) = timed(run, args.repeats, args.budget_s)
    return out | {
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
    config |= dict(damping_update=solver.damping_update, dtype="float64")
    config |= dict(se3_information=pg.se3_information, anchor_sqrt_information=1e6)
    rec = {"benchmark": "pgo", "config": config, "file": name, "median_s": median}
    rec |= {"first_s": first, "compile_s": max(first - median, 0.0), "repeats": n}
    rec["load_average"] = os.getloadavg()
    rec |= {k: int(sol.stats[k]) for k in ("num_steps", "num_accepted")}
    rec |= {k: float(sol.stats[k]) for k in ("initial_cost", "final_cost")}
    rec["result"] = str(sol.result).split("<", 1)[-1].rstrip(">") or "successful"
    if gtsam:
        rec.update(gtsam_record(gtsam, name, pg, args, rec))
        # The first step whose cost is GTSAM's final cost or lower (-1: none).
        hist = np.asarray(sol.stats["cost_history"])[: rec["num_steps"] + 1]
        ok = np.flatnonzero(hist <= rec["reference"] * (1 + 1e-6))
        rec["steps_to_reference"] = int(ok[0]) if len(ok) else -1
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
    return common.markdown_table(rows, list(rows[0]) if rows else ["file"])


def write_markdown(path, records, m: dict, solver_name: str, args):
    """The report: how it was made, the table, and which rows reached GTSAM."""
    ok = {r["file"]: r["cost_ratio"] <= 1 + 1e-6 for r in records if "reference" in r}
    reached, missed = (", ".join(f for f in ok if ok[f] == v) for v in (True, False))
    git = m["git"] + (" (plus uncommitted changes)" if m.get("dirty") else "")
    gtsam = "default LevenbergMarquardtParams(), its reader's graph + our prior"
    if not args.gtsam_files:
        gtsam = "relativeErrorTol 1e-8, absoluteErrorTol 0, same factors"
    lines = [
        "# Pose-graph optimisation: eqsmooth vs GTSAM",
        "",
        f"- command: `{m['command']}`",
        f"- solver: `{solver_name}`, max_steps {args.max_steps}; GTSAM "
        f"LevenbergMarquardtOptimizer with {gtsam} and initial values",
        f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}; "
        f"JAX {m['jax']} ({m['backend']}), Python {m['python']}",
        f"- git: {git}",
        "- times: median of `repeats` full solves after a warm-up call, seconds",
        *[f"- BLAS used by CHOLMOD: {', '.join(b)}" for b in [m.get("blas")] if b],
    ]
    lines += [
        "",
        table_of(records),
        "",
        f"Reached GTSAM's final cost (ratio ≤ 1 + 1e-6): {reached or 'none'}. "
        f"Did not: {missed or 'none'}. The time ratio compares like with like "
        "only where both reached the same cost.",
    ]
    common.write_text(path, "\n".join(lines))


def make_solver(args):
    """The LevenbergMarquardt solver `--solver` names, and its name."""
    pre = eqs.solve.BlockJacobi()
    if args.preconditioner in ("chain", "twolevel"):
        pre = {"chain": eqs.ChainPreconditioner, "twolevel": eqs.TwoLevelPreconditioner}
        pre = pre[args.preconditioner]()
    linear = {
        "sparse": eqs.solve.SparseLU,
        "cholmod": eqs.solve.SparseCholesky,
        "sparsax": eqs.solve.SparsaxCholesky,
        "dense": eqs.DenseCholesky,
        "pcg": lambda: eqs.PCG(preconditioner=pre),
        "default": lambda: None,
    }[args.solver]()
    inner = f"{type(linear).__name__}()" if linear else ""
    if args.solver == "pcg":
        inner = f"PCG(preconditioner={type(pre).__name__}())"
    lm = eqs.LevenbergMarquardt(linear, damping_update=args.damping_update)
    return lm, f"LevenbergMarquardt({inner}), {lm.damping_update!r} damping update"


def load_problems(args) -> list:
    if args.gtsam_files:
        data = Path(__import__("gtsam").__file__).parent / "Data"
        kw = dict(skip_unsupported=True, se3_information="gtsam")
        return [(f, load_g2o(data / f, **kw)) for f in args.files or GTSAM_FILES]
    if not DATA.exists():
        print(f"note: {DATA} not found; timing a synthetic 2-D pose graph instead")
        pg, _ = synthetic_pose_graph_2d(300 if args.quick else 2000, seed=0)
        return [("synthetic_2d", pg)]
    problems = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # cubicle's repairs
        for name in args.files or (["intel", "smallGrid3D"] if args.quick else FILES):
            if not (path := DATA / f"{name}.g2o").exists():
                print(f"note: {path} not found, skipped")
                continue
            pg = load_g2o(path, invalid_information="block_diagonal")
            problems.append((name, pg))
    return problems


def main(argv=None):
    parser = common.cli(__doc__)
    parser.add_argument("--quick", action="store_true", help="intel + smallGrid3D")
    parser.add_argument("--md", default=None, help="write the markdown report here")
    parser.add_argument("--files", nargs="*", default=None, help="subset of files")
    solvers = "sparse cholmod sparsax pcg dense default".split()
    parser.add_argument("--solver", choices=solvers)
    parser.add_argument("--gtsam-files", action="store_true", help="see above")
    parser.add_argument("--preconditioner", choices=["jacobi", "chain", "twolevel"])
    parser.add_argument("--damping-update", choices=["nielsen", "fixed"])
    parser.add_argument("--max-steps", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--budget-s", type=float, default=120.0, help="per file")
    parser.add_argument("--no-gtsam", action="store_true")
    args = parser.parse_args(argv)
    args.max_steps = args.max_steps or (10 if args.quick else 100)
    args.solver = args.solver or ("default" if args.gtsam_files else "sparse")
    args.damping_update = args.damping_update or eqs.LevenbergMarquardt.damping_update
    gtsam = None if args.no_gtsam else common.optional("gtsam", " (pip install gtsam)")
    solver, solver_name = make_solver(args)
    problems = load_problems(args)
    m = common.machine() | {"dirty": bool(common.dirty())}  # tree at the start
    if args.solver == "cholmod":
        import sksparse.cholmod  # noqa: F401  (maps CHOLMOD's BLAS)

        m["blas"] = common.loaded_blas()
    if args.solver == "sparsax":
        m["blas"] = [eqs.solve.sparsax_blas()]  # "mkl" or "bundled" (ATLAS)
    records = []
    for name, pg in problems:
        records.append(rec := bench_one(name, pg, args, solver, solver_name, gtsam))
        print(table_of([rec]).splitlines()[-1], flush=True)  # the table's row
        # Written after every file, so a long run that is cut off keeps its rows.
        if args.md:
            write_markdown(args.md, records, m, solver_name, args)
        if args.json:
            common.write_json(args.json, records, extra={"machine": m})
    print("\n" + table_of(records))


if __name__ == "__main__":
    main()
