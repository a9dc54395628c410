"""Unrolled element-wise block kernels vs jaxlib's batched LAPACK, in one process.

For `--count` random `D x D` SPD blocks (float64): a Cholesky factorisation
plus a triangular solve `L⁻¹ R` with `2D` right-hand sides, once through
`jnp.linalg.cholesky` + `lax.linalg.triangular_solve` (LAPACK) and once
through `eqsmooth/solve/_small_blocks.py` (unrolled XLA operations), jitted,
median of repeats. This is the figure quoted in `_small_blocks`' docstring.

    cd benchmarks && OPENBLAS_NUM_THREADS=1 \\
        python small_blocks.py --json results/small_blocks.json
"""

import argparse

import jax
import jax.numpy as jnp
from _common import markdown_table, time_fn, write_json

from eqsmooth.solve._linear._small_blocks import block_cholesky, block_solve_lower


jax.config.update("jax_enable_x64", True)


def lapack(A, R):
    L = jnp.linalg.cholesky(A)
    return jax.lax.linalg.triangular_solve(L, R, left_side=True, lower=True)


def unrolled(A, R):
    return block_solve_lower(block_cholesky(A), R)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--count", type=int, default=32_000)
    parser.add_argument("--dims", type=int, nargs="*", default=[4, 5, 8])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    rows = []
    for D in args.dims:
        k = jax.random.split(jax.random.key(D), 2)
        A = jax.random.normal(k[0], (args.count, D, D))
        A = A @ jnp.swapaxes(A, 1, 2) + D * jnp.eye(D)
        R = jax.random.normal(k[1], (args.count, D, 2 * D))
        ref = jax.jit(lapack)(A, R)
        row = {"count": args.count, "D": D}
        for name, fn in (("lapack", lapack), ("unrolled", unrolled)):
            f = jax.jit(fn)
            _, med, _ = time_fn(f, A, R, repeats=args.repeats)
            row[f"{name}_ms"] = 1e3 * med
            row[f"{name}_max_abs_diff"] = float(jnp.max(jnp.abs(f(A, R) - ref)))
        row["speedup"] = row["lapack_ms"] / row["unrolled_ms"]
        rows.append(row)
        print(
            f"D={D}: LAPACK {row['lapack_ms']:.2f} ms, unrolled "
            f"{row['unrolled_ms']:.2f} ms (x{row['speedup']:.2f})",
            flush=True,
        )
    cols = ["count", "D", "lapack_ms", "unrolled_ms", "speedup"]
    cols += ["unrolled_max_abs_diff"]
    print(markdown_table(rows, cols))
    if args.json:
        write_json(args.json, rows, {"argv": argv or []})


if __name__ == "__main__":
    main()
