"""Block cyclic reduction solves: unrolled XLA block kernels vs jaxlib's LAPACK.

Factor a random symmetric positive definite block-tridiagonal system (`T`
blocks of `D x D`, float64) with `cyclic_reduction_factor` (LAPACK in both
arms) and time `cyclic_reduction_solve` with it, once with eqsmooth's
unrolled element-wise block triangular solves (`eqsmooth/solve/_small_blocks.py`,
the default for `D <= 8`) and once with jaxlib's batched LAPACK kernels (the
limit set to 0), in the same process, alternating the two arms per size.
`compile_s` is the solve's compile time.

    cd benchmarks && OPENBLAS_NUM_THREADS=1 \
        python small_blocks.py --json results/small_blocks.json
"""

import argparse
import time

import jax
import jax.numpy as jnp
from _common import markdown_table, time_fn, write_json

from eqsmooth.solve import _small_blocks
from eqsmooth.solve._block_tridiagonal import (
    cyclic_reduction_factor,
    cyclic_reduction_solve,
)


jax.config.update("jax_enable_x64", True)


def system(T: int, D: int):
    k = jax.random.split(jax.random.key(0), 3)
    A = jax.random.normal(k[0], (T, D, D))
    A = A @ jnp.swapaxes(A, 1, 2) + 2 * D * jnp.eye(D)
    B = 0.3 * jax.random.normal(k[1], (T - 1, D, D))
    b = jax.random.normal(k[2], (T, D))
    return A, B, b


def measure(T: int, D: int, arm: str, repeats: int) -> dict:
    default = _small_blocks.SMALL_BLOCK_LIMIT
    _small_blocks.SMALL_BLOCK_LIMIT = 0 if arm == "lapack" else default
    try:
        A, B, b = system(T, D)
        # Fresh jit wrappers per arm: the limit is read at trace time.
        factor = jax.jit(lambda A, B: cyclic_reduction_factor(A, B))
        solve = jax.jit(lambda s, b: cyclic_reduction_solve(s, b))
        factor_c = factor.lower(A, B).compile()
        state = factor_c(A, B)
        t0 = time.perf_counter()
        solve_c = solve.lower(state, b).compile()
        compile_s = time.perf_counter() - t0
        _, factor_s, _ = time_fn(factor_c, A, B, repeats=repeats)
        _, solve_s, _ = time_fn(solve_c, state, b, repeats=repeats)
        x = solve_c(state, b)
        op = jnp.einsum("tde,te->td", A, x)
        op = op.at[:-1].add(jnp.einsum("tde,te->td", B, x[1:]))
        op = op.at[1:].add(jnp.einsum("ted,te->td", B, x[:-1]))
        residual = float(jnp.max(jnp.abs(op - b)) / jnp.max(jnp.abs(b)))
    finally:
        _small_blocks.SMALL_BLOCK_LIMIT = default
    return {
        "T": T,
        "D": D,
        "arm": arm,
        "factor_ms": 1e3 * factor_s,
        "solve_ms": 1e3 * solve_s,
        "compile_s": compile_s,
        "rel_residual": residual,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[1000, 10_000, 100_000])
    parser.add_argument("--dims", type=int, nargs="*", default=[4, 5, 8])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    rows = []
    for D in args.dims:
        for T in args.sizes:
            pair = {}
            for arm in ("lapack", "unrolled"):
                pair[arm] = measure(T, D, arm, args.repeats)
                rows.append(pair[arm])
            r = pair["unrolled"]
            r["solve_speedup"] = pair["lapack"]["solve_ms"] / r["solve_ms"]
            print(
                f"T={T:<7} D={D}  factor {r['factor_ms']:8.2f} ms  solve "
                f"{pair['lapack']['solve_ms']:7.2f} -> {r['solve_ms']:7.2f} ms "
                f"(x{r['solve_speedup']:.2f})  solve compile "
                f"{pair['lapack']['compile_s']:.2f} -> {r['compile_s']:.2f} s",
                flush=True,
            )
    columns = [
        "T",
        "D",
        "arm",
        "factor_ms",
        "solve_ms",
        "compile_s",
        "solve_speedup",
        "rel_residual",
    ]
    print(markdown_table(rows, columns))
    if args.json:
        write_json(args.json, rows, {"argv": argv or []})


if __name__ == "__main__":
    main()
