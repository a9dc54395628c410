"""Optimise a pose graph read from a g2o file (2-D or 3-D).

What it shows: how to load a standard pose-graph benchmark with
`eqsmooth.io.load_g2o` (one stacked between-factor for all edges, full
information matrices, a prior fixing the gauge), solve it with
Levenberg-Marquardt on the manifold and a sparse linear solver (conjugate
gradients with a block-Jacobi preconditioner by default; `--solver pcg-chain`
for the odometry-chain preconditioner, `--solver sparse` for SciPy's sparse
LU on the host, much faster on large graphs; `--solver cholmod` for
CHOLMOD's sparse Cholesky, the fastest on large 3-D graphs, which needs
scikit-sparse and an optimised system BLAS; `--solver dense` for small
graphs), write the result with `eqsmooth.io.save_g2o`, and plot the initial
and optimised trajectories. It steps the solver by hand (`init` / `step` /
`terminate`, each jitted) to print a table of cost, damping and time per
iteration; `eqsmooth.least_squares` runs the same loop in one call.

Data: the g2o files of the SE-Sync collection, looked for in
`../shared/data/g2o/` next to the repository (see the README for where to get
them). When the default file is absent, the script makes a synthetic 2-D pose
graph with `eqsmooth.io.synthetic_pose_graph_2d` instead, so it always runs.

Runtime on 2 CPU cores: about 20 s with `--quick` (intel.g2o, 10 iterations,
mostly compilation); about 20 s by default on intel.g2o; larger and 3-D
files take longer (see benchmarks/results/pgo.md for measured solve times).

    python examples/02_pose_graph.py --quick --out results/pgo
    python examples/02_pose_graph.py --file ../shared/data/g2o/sphere2500.g2o
"""

import argparse
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402


# Compiled programs are kept on disk: a second run answers sooner.
eqs.enable_compilation_cache()
from eqsmooth.io import load_g2o, save_g2o, synthetic_pose_graph_2d  # noqa: E402


REPO = Path(__file__).resolve().parents[1]
DEFAULT_FILE = REPO / ".." / "shared" / "data" / "g2o" / "intel.g2o"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--file",
        type=Path,
        default=None,
        help=f"g2o file (default: {DEFAULT_FILE}, or a synthetic graph if absent)",
    )
    p.add_argument("--out", type=Path, default=Path("results/02_pose_graph"))
    p.add_argument("--quick", action="store_true", help="few iterations (CI)")
    p.add_argument(
        "--solver",
        choices=["pcg", "pcg-chain", "sparse", "cholmod", "dense"],
        default="pcg",
    )
    p.add_argument("--max-steps", type=int, default=None, help="LM iterations")
    p.add_argument(
        "--invalid-information",
        choices=["raise", "clip", "block_diagonal"],
        default="block_diagonal",
        help="repair of non-positive-definite information matrices (cubicle.g2o)",
    )
    return p.parse_args(argv)


def load(args):
    if args.file is not None:
        if not args.file.exists():
            sys.exit(f"error: g2o file {args.file} not found")
        return load_g2o(args.file, invalid_information=args.invalid_information), str(
            args.file
        )
    if DEFAULT_FILE.exists():
        return load_g2o(DEFAULT_FILE), str(DEFAULT_FILE.resolve())
    print(f"note: {DEFAULT_FILE} not found; using a synthetic 2-D pose graph")
    pg, _ = synthetic_pose_graph_2d(300 if args.quick else 1000, seed=0)
    return pg, "synthetic_pose_graph_2d(seed=0)"


def solve_with_table(pg, solver, max_steps):
    """Run the solver step by step (optimistix's init / step / terminate, the
    graph as `args`), printing one table row per iteration."""
    fn, opts, tags = eqs.solve.graph_residuals, {}, frozenset()
    init = eqx.filter_jit(
        lambda graph, values: solver.init(fn, values, graph, opts, None, None, tags)
    )
    step = eqx.filter_jit(
        lambda graph, values, state: solver.step(fn, values, graph, opts, state, tags)
    )

    t0 = time.perf_counter()
    state = jax.block_until_ready(init(pg.graph, pg.values))
    initial_cost = float(state.lin.cost)
    values = pg.values
    print("\n| iter | cost | damping | accepted | time [s] |\n|---|---|---|---|---|")
    print(f"| 0 | {float(state.lin.cost):.6e} | | | {time.perf_counter() - t0:.3f} |")
    times = []
    for _ in range(max_steps):
        t0 = time.perf_counter()
        values, state, _ = step(pg.graph, values, state)
        jax.block_until_ready(state.lin.cost)
        times.append(time.perf_counter() - t0)
        print(
            f"| {int(state.step)} | {float(state.lin.cost):.6e} | "
            f"{float(state.damping):.1e} | {int(state.num_accepted)} | "
            f"{times[-1]:.3f} |"
        )
        if bool(state.done):
            break
    result = state.result
    if not bool(state.done) and bool(result == eqs.RESULTS.successful):
        result = eqs.RESULTS.nonlinear_max_steps_reached
    return values, state, times, result, initial_cost


def _describe(result) -> str:
    if bool(result == eqs.RESULTS.successful):
        return "converged"
    return str(result).split("<", 1)[-1].rstrip(">")


def plot(pg, values, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def xy(v):
        p = np.asarray(v["pose"].parameters())
        return (p[:, 2:4] if pg.kind == "se2" else p[:, 4:6]).T

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, v, name in [
        (axes[0], pg.values, "initial"),
        (axes[1], values, "optimised"),
    ]:
        x, y = xy(v)
        edges = pg.edges
        closures = edges[np.abs(edges[:, 1] - edges[:, 0]) > 1]
        for i, j in closures[:2000]:
            ax.plot([x[i], x[j]], [y[i], y[j]], color="tab:red", lw=0.3, alpha=0.3)
        ax.plot(x, y, color="tab:blue", lw=0.8)
        ax.set_title(f"{name} ({len(closures)} loop closures in red)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None):
    args = parse_args(argv)
    pg, source = load(args)
    max_steps = args.max_steps or (10 if args.quick else 100)
    if args.solver == "dense":
        linear, name = eqs.DenseCholesky(), "DenseCholesky()"
    elif args.solver == "sparse":
        linear, name = eqs.solve.SparseLU(), "SparseLU()"
    elif args.solver == "cholmod":
        linear, name = eqs.solve.SparseCholesky(), "SparseCholesky()"
    elif args.solver == "pcg-chain":
        linear = eqs.PCG(preconditioner=eqs.solve.ChainPreconditioner())
        name = "PCG(preconditioner=ChainPreconditioner())"
    else:
        linear, name = eqs.PCG(), "PCG()"
    solver = eqs.LevenbergMarquardt(linear)
    print(
        f"{source}: {pg.kind}, {pg.num_poses} poses, {pg.num_edges} edges; "
        f"LevenbergMarquardt({name}), at most {max_steps} steps"
    )
    t0 = time.perf_counter()
    values, state, times, result, initial_cost = solve_with_table(pg, solver, max_steps)
    total = time.perf_counter() - t0
    first, rest = times[0], times[1:]
    steady = float(np.median(rest)) if rest else first
    print(
        f"\n{int(state.step)} iterations ({int(state.num_accepted)} accepted), "
        f"result: {_describe(result)}; total {total:.1f} s, first iteration "
        f"{first:.2f} s (with compilation), then {steady:.3f} s per iteration "
        "(median)"
    )

    args.out.mkdir(parents=True, exist_ok=True)
    save_g2o(args.out / "optimized.g2o", pg, values=values)
    plot(
        pg,
        values,
        args.out / "pose_graph.png",
        f"{Path(source).name}: cost {float(state.lin.cost):.4g} "
        f"(initial {initial_cost:.4g})",
    )
    print(f"wrote {args.out / 'optimized.g2o'} and {args.out / 'pose_graph.png'}")


if __name__ == "__main__":
    main()
