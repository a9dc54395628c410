"""One sparse factorisation + solve of a pose graph's normal matrix: SuperLU vs CHOLMOD.

For each g2o file: linearise at the file's initial values, assemble
`JᵀJ + 1e-3·I` exactly as [`eqsmooth.solve.SparseLU`] does, and time the
host work of one linear solve with each backend, in the same process:
SuperLU as `SparseLU` calls it (minimum-degree ordering of `Aᵀ + A`,
symmetric mode), CHOLMOD from scratch (ordering + symbolic + numeric), and
CHOLMOD numeric only (what `SparseCholesky` does after its first solve,
reusing the symbolic analysis). `median_s` is the median over `--repeats`
runs; `residual` is `‖Ax − b‖ / ‖b‖`; `factor_nnz` is the fill of the
factorisation (`nnz(L) + nnz(U)` for SuperLU, `nnz(L)` for CHOLMOD).
`--superlu-orderings` also times SuperLU with other column orderings (SciPy's
`permc_spec`). CHOLMOD needs `scikit-sparse`
(see `eqsmooth.solve.SparseCholesky`); without it only SuperLU is timed.

    python benchmarks/sparse_factor.py                       # every file
    python benchmarks/sparse_factor.py --files torus3D intel
    python benchmarks/sparse_factor.py --files torus3D \
        --superlu-orderings MMD_AT_PLUS_A COLAMD MMD_ATA
    python benchmarks/sparse_factor.py --json benchmarks/results/sparse_factor.json \\
        --markdown benchmarks/results/sparse_factor.md
"""

import argparse
import functools as ft
import statistics
import time
import warnings
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import loaded_blas, machine, markdown_table, write_json  # noqa: E402

from eqsmooth.io import load_g2o  # noqa: E402
from eqsmooth.solve._linear._linear_solver import NormalOperator  # noqa: E402
from eqsmooth.solve._linear._sparse import _host_csc, assemble_sparse  # noqa: E402
from eqsmooth.solve._linearization import linearize  # noqa: E402


DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"
FILES = ["intel", "manhattan", "kitti_00", "sphere2500", "torus3D", "cubicle"]


def normal_matrix(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # cubicle's repairs
        pg = load_g2o(path, invalid_information="block_diagonal")
    lin = jax.jit(linearize)(pg.graph, pg.values)
    damping = {g.name: jnp.full((g.count, g.dim), 1e-3) for g in lin.layout}
    state = assemble_sparse(NormalOperator(lin, damping))
    pattern, data = state.pattern, state.data
    return _host_csc(pattern, data)


def _time(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--files", nargs="*", default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    parser.add_argument(
        "--superlu-orderings",
        nargs="+",
        default=["MMD_AT_PLUS_A"],
        choices=["MMD_AT_PLUS_A", "COLAMD", "MMD_ATA", "NATURAL"],
        help="SuperLU column orderings to time; the first is SparseLU's",
    )
    args = parser.parse_args(argv)
    import scipy.sparse.linalg as spla

    blas = []
    try:
        from sksparse.cholmod import analyze, cholesky

        blas = loaded_blas()
        print("BLAS used by CHOLMOD:", ", ".join(blas) or "unknown")
    except ImportError:
        analyze = cholesky = None
        print("note: scikit-sparse not installed: CHOLMOD not timed")
    try:
        import sparsax
    except ImportError:
        sparsax = None
        print("note: sparsax not installed: not timed")
    try:
        import cholespy
    except ImportError:
        cholespy = None
        print("note: cholespy not installed: not timed")
    if not DATA.exists():
        raise SystemExit(f"{DATA} not found: the g2o files are needed")
    records = []
    for name in args.files or FILES:
        A = normal_matrix(DATA / f"{name}.g2o")
        b = np.random.default_rng(0).normal(size=A.shape[0])

        def superlu(permc_spec):
            lu = spla.splu(
                A,
                permc_spec=permc_spec,
                diag_pivot_thresh=0.0,
                options={"SymmetricMode": True, "Equil": False},
            )
            return lu.solve(b), lu.L.nnz + lu.U.nnz

        def cholmod(factor):
            return factor(b), factor.L().nnz

        methods = {}
        for i, order in enumerate(args.superlu_orderings):
            label = "SuperLU (SparseLU)" if order == "MMD_AT_PLUS_A" else "SuperLU"
            methods[f"{label}, {order}" if i else label] = ft.partial(superlu, order)
        if cholesky is not None:
            symbolic = analyze(A)
            methods["CHOLMOD, from scratch"] = lambda: cholmod(cholesky(A))
            methods["CHOLMOD, numeric only (SparseCholesky)"] = lambda: cholmod(
                symbolic.cholesky(A)
            )
        if sparsax is not None:
            coo = A.tocoo()
            upper = coo.row <= coo.col
            Ai = jnp.asarray(coo.row[upper], jnp.int32)
            Aj = jnp.asarray(coo.col[upper], jnp.int32)
            Ax0 = jnp.asarray(coo.data[upper])
            sx_solve = jax.jit(lambda Ax, b: sparsax.solve(Ai, Aj, Ax, b))
            sx_count = [0]

            def sparsax_numeric():
                # sparsax skips the refactorisation when the values repeat, so
                # every call gets (slightly) different values, as a solver's
                # iterations do; its symbolic analysis is cached per pattern.
                sx_count[0] += 1
                Ax = Ax0 * (1.0 + 1e-9 * sx_count[0])
                x = np.asarray(jax.block_until_ready(sx_solve(Ax, jnp.asarray(b))))
                return x * (1.0 + 1e-9 * sx_count[0]), -1

            sparsax_numeric()  # compile, and the cached symbolic analysis
            methods["sparsax (CHOLMOD in jit), numeric only"] = sparsax_numeric
        if cholespy is not None:
            coo = A.tocoo()

            def cholespy_solve():
                solver = cholespy.CholeskySolverD(
                    A.shape[0],
                    coo.row.astype(np.int32),
                    coo.col.astype(np.int32),
                    coo.data,
                    cholespy.MatrixType.COO,
                )
                x = np.zeros_like(b)
                solver.solve(b, x)
                return x, -1

            methods["cholespy, from scratch"] = cholespy_solve
        base = None
        for method, fn in methods.items():
            median, (x, fill) = _time(fn, args.repeats)
            base = base or median
            rec = {
                "benchmark": "sparse_factor",
                "config": {"file": name, "method": method},
                "file": name,
                "n": A.shape[0],
                "nnz": A.nnz,
                "method": method,
                "factor_nnz": int(fill),
                "median_s": median,
                "compile_s": 0.0,
                "speedup_vs_superlu": base / median,
                "residual": float(np.linalg.norm(A @ x - b) / np.linalg.norm(b)),
            }
            records.append(rec)
            print(
                f"{name:10s} n={A.shape[0]:6d} {method:40s} {median:8.3f} s  "
                f"x{rec['speedup_vs_superlu']:.2f}  res {rec['residual']:.1e}",
                flush=True,
            )
    cols = [
        "file",
        "n",
        "nnz",
        "method",
        "factor_nnz",
        "median_s",
        "speedup_vs_superlu",
        "residual",
    ]
    table = markdown_table(records, cols)
    print()
    print(table)
    if args.json:
        write_json(args.json, records, extra={"cholmod_blas": blas})
    if args.markdown:
        m = machine()
        Path(args.markdown).write_text(
            "\n".join(
                [
                    "# One sparse factorisation + solve: SuperLU vs CHOLMOD",
                    "",
                    f"- command: `{m['command']}` (in `benchmarks/`)",
                    f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}; "
                    "load average at the end "
                    + ", ".join(f"{x:.1f}" for x in m["load_average"])
                    + " (compare within a file)",
                    f"- jax {m['jax']}, python {m['python']}, git {m['git']}",
                    f"- BLAS used by CHOLMOD: {', '.join(blas) or 'unknown'}",
                    "",
                    table,
                    "",
                ]
            )
        )


if __name__ == "__main__":
    main()
