"""A chain's factorisation + solve against loop variants (issue 60 item 3).

Times, in one process and interleaved (one call of each variant per round;
medians, `compile_s` = first call minus median), `x = A⁻¹ b` for a random SPD
block-tridiagonal `A` (`D = 5`): `cr`, the library's cyclic reduction (batched
LAPACK per level, a 32-block sequential tail); `cr_unrolled`, the same without
LAPACK (`unrolled_factor`); `seq`, a sequential block Cholesky, one `lax.scan`
over all `T` blocks (the library's tail code), `seq_packed` with the scanned
inputs and outputs packed into one array each, `seq_unrollK` with
`lax.scan(unroll=K)`, `seq_chunkK` scanning `T / K` chunks with the chunk's
steps unrolled. Modes: `fwd`, and `jax.grad` of `w · x` by `adjoint` (the rule
of `lineax.linear_solve`, how `BlockTridiagonal` is differentiated: one more
solve) and `autodiff` (reverse mode through the loops). Then a 10-step
`FixedStepGaussNewton` solve of `benchmarks.chain`'s problems with
`BlockTridiagonal(tail_size=S)` (the tail is the library's one scan).

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.chain_carries \\
        --json benchmarks/results/chain_carries.json
"""

import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs
from eqsmooth.solve._linear import _block_tridiagonal as bt

from ._common import cli, print_and_save, record
from .chain import make_solve, se2vel_problem, vehicle_problem


jax.config.update("jax_enable_x64", True)
mm, mT = bt.mm, bt._mT


def unrolled_factor(A, B, tail_size=bt.DEFAULT_TAIL_SIZE):
    """`cyclic_reduction_factor` with each level's Cholesky factor and `L⁻¹`
    unrolled (`_small_blocks`) and `A_o⁻¹ B` as two products with `L⁻¹`: no
    LAPACK call (pivot checks left out)."""
    D, levels = A.shape[-1], []
    while A.shape[0] > tail_size:
        n = A.shape[0]
        m, k = n // 2, n - n // 2
        Bp = bt._pad_end(B, n)
        odd, even = A[1::2], A[0::2]
        b_left, b_right = Bp[0 : 2 * m : 2], Bp[1 : 2 * m : 2]
        eye = jnp.broadcast_to(jnp.eye(D, dtype=A.dtype), (m, D, D))
        li = bt.block_solve_lower(bt.block_cholesky(odd), eye)
        both = mm(mT(li), mm(li, jnp.concatenate([mT(b_left), b_right], 2)))
        prod = mm(b_left, both)
        A = even - bt._pad_end(prod[..., :D], k)
        A = A - bt._shift_down(mm(mT(b_right), both[..., D:]), k)
        B = -prod[: k - 1, :, D:]
        levels.append(bt._Level(li, both[..., :D], both[..., D:]))
    tail, _ = bt._tail_factor(A, B)
    return bt.CyclicReductionState(tuple(levels), tail, jnp.asarray(True), tail_size)


def seq_solve(A, B, b, unroll=1, packed=False, chunk=0):
    """Sequential block Cholesky `A = M Mᵀ` and the two substitutions."""
    T, D = A.shape[0], A.shape[-1]
    if chunk:  # pad with decoupled identity blocks to whole chunks
        extra = -(T - 1) % chunk
        eye = jnp.broadcast_to(jnp.eye(D, dtype=A.dtype), (extra, D, D))
        A, B = jnp.concatenate([A, eye]), bt._pad_end(B, T - 1 + extra)
        b = bt._pad_end(b, T + extra)
    eye = jnp.eye(D, dtype=A.dtype)

    def inverse_factor(s):
        return bt.block_solve_lower(bt.block_cholesky(0.5 * (s + mT(s))), eye)

    def factor_step(inv_prev, a, b_):
        w = mm(inv_prev, b_)
        inv = inverse_factor(a - mm(mT(w), w))
        return inv, (inv, w)

    def fwd_step(y_prev, li, w, rhs):
        y = mm(li, rhs - mm(mT(w), y_prev))
        return y, (y,)

    def bwd_step(x_next, li, w, yt):
        x = mm(mT(li), yt - mm(w, x_next))
        return x, (x,)

    def run(step, init, xs, reverse=False):
        """`lax.scan` of `step(carry, *x) -> (carry, outputs)`, per variant."""
        cuts = np.cumsum([x.shape[-1] for x in xs])[:-1]

        def body(c, x):
            c, out = step(c, *(jnp.split(x, cuts, axis=-1) if packed else x))
            return c, (jnp.concatenate(out, -1) if packed else out)

        xs = jnp.concatenate(xs, -1) if packed else xs
        if chunk:
            one = body

            def body(c, xk):  # noqa: F811
                outs = [None] * chunk
                for i in reversed(range(chunk)) if reverse else range(chunk):
                    c, outs[i] = one(c, jax.tree.map(lambda x: x[i], xk))
                return c, jax.tree.map(lambda *o: jnp.stack(o), *outs)

            xs = jax.tree.map(lambda x: x.reshape((-1, chunk) + x.shape[1:]), xs)
        _, out = jax.lax.scan(body, init, xs, reverse=reverse, unroll=unroll)
        if chunk:
            out = jax.tree.map(lambda o: o.reshape((-1,) + o.shape[2:]), out)
        if not packed:
            return out
        return jnp.split(out, [D], axis=-1) if out.shape[-1] == 2 * D else (out,)

    inv0 = inverse_factor(A[0])
    Li, W = run(factor_step, inv0, (A[1:], B))
    Li = jnp.concatenate([inv0[None], Li])
    b = b[:, :, None]
    y0 = mm(Li[0], b[0])
    (y,) = run(fwd_step, y0, (Li[1:], W, b[1:]))
    y = jnp.concatenate([y0[None], y])
    x_last = mm(mT(Li[-1]), y[-1])
    (x,) = run(bwd_step, x_last, (Li[:-1], W, y[:-1]), reverse=True)
    return jnp.concatenate([x, x_last[None]])[:T, :, 0]


VARIANTS = {
    "cr": lambda A, B, b: bt.cyclic_reduction_solve(
        bt.cyclic_reduction_factor(A, B), b
    ),
    "cr_unrolled": lambda A, B, b: bt.cyclic_reduction_solve(unrolled_factor(A, B), b),
    "seq": seq_solve,
    "seq_packed": lambda A, B, b: seq_solve(A, B, b, packed=True),
}
for _k in (4, 16):
    VARIANTS[f"seq_unroll{_k}"] = lambda A, B, b, k=_k: seq_solve(A, B, b, unroll=k)
    VARIANTS[f"seq_chunk{_k}"] = lambda A, B, b, k=_k: seq_solve(A, B, b, chunk=k)


def programs(solve, w):
    """`fwd`, and the gradient of `w · x` by `adjoint` (`b̄ = A⁻¹ x̄`, `Ā = −b̄ xᵀ`
    on the block-tridiagonal pattern) and by `autodiff`."""

    @jax.custom_vjp
    def adjoint(A, B, b):
        return solve(A, B, b)

    def forward(A, B, b):
        x = solve(A, B, b)
        return x, (A, B, x)

    def backward(res, x_bar):
        x, g = res[2], solve(res[0], res[1], x_bar)
        dB = g[:-1, :, None] * x[1:, None, :] + x[:-1, :, None] * g[1:, None, :]
        return -g[:, :, None] * x[:, None, :], -dB, g

    adjoint.defvjp(forward, backward)

    def grad(f):
        return jax.jit(jax.grad(lambda *a: jnp.sum(w * f(*a)), argnums=(0, 1, 2)))

    return {"fwd": jax.jit(solve), "adjoint": grad(adjoint), "autodiff": grad(solve)}


def random_chain(T, D=5, seed=0):
    """A random SPD block-tridiagonal matrix (a chain's `JᵀJ`) and a right side:
    per step a measurement block J0 on x_t, dynamics [J1, -I] on x_t, x_t+1."""
    rng = np.random.default_rng(seed)
    J0, J1 = rng.normal(size=(T, D, D)), rng.normal(size=(T - 1, D, D))
    A = np.einsum("tji,tjk->tik", J0, J0)
    A[:-1] += np.einsum("tji,tjk->tik", J1, J1)
    A[1:] += np.eye(D)
    B = -np.swapaxes(J1, 1, 2)
    return jnp.asarray(A), jnp.asarray(B), jnp.asarray(rng.normal(size=(T, D)))


def interleaved(fns: dict, args: tuple, repeats: int) -> dict:
    """Per name: (first call s, median s), one call of each per round."""
    times = {k: [] for k in fns}
    for _ in range(repeats + 1):
        for k, f in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            times[k].append(time.perf_counter() - t0)
    return {k: (t[0], statistics.median(t[1:])) for k, t in times.items()}


def kernels(T: int, names: list[str], repeats: int) -> list[dict]:
    """Every variant forward and under both gradients at one `T`."""
    A, B, b = random_chain(T)
    w = jnp.asarray(np.random.default_rng(1).normal(size=b.shape))
    fns = {(n, mode): f for n in names for mode, f in programs(VARIANTS[n], w).items()}
    # Reverse mode through LAPACK levels runs independent batched LAPACK calls,
    # which can hang jaxlib 0.10's CPU runtime (`eqsmooth/_xla_flags.py`); it did.
    fns.pop(("cr", "autodiff"), None)
    timed = interleaved(fns, (A, B, b), repeats)
    ref = fns["cr", "fwd"](A, B, b) if ("cr", "fwd") in fns else None
    records = []
    for (name, mode), (first, median) in timed.items():
        config = {"T": T, "variant": name, "mode": mode, "D": 5}
        rec = record("chain_carries", config, median_ms=median * 1e3)
        rec["compile_s"] = first - median
        if mode == "fwd" and ref is not None:
            x = fns[name, mode](A, B, b)
            rec["max_rel_diff"] = float(jnp.max(jnp.abs(x - ref)) / jnp.max(abs(ref)))
        print(
            f"T={T} {name} {mode} {median * 1e3:.2f} ms compile {first - median:.2f} s"
        )
        records.append(rec)
    return records


def solves(sizes, problems, tails, steps: int, repeats: int) -> list[dict]:
    """A `steps`-step Gauss-Newton solve with `BlockTridiagonal(tail_size=S)`."""
    build = {"se2vel": se2vel_problem, "vehicle": vehicle_problem}
    records = []
    for T, problem in [(T, p) for T in sizes for p in problems]:
        graph, values = build[problem](T)
        fns = {S: make_solve(eqs.BlockTridiagonal(tail_size=S), steps) for S in tails}
        for S, (first, median) in interleaved(fns, (graph, values), repeats).items():
            config = {"T": T, "variant": f"tail{S}", "problem": problem}
            rec = record("chain_carries", config | {"mode": "solve"})
            rec |= {"median_ms": median * 1e3, "ms_per_step": median / steps * 1e3}
            rec |= {"compile_s": first - median, "solve_steps": steps}
            rec["final_cost"] = float(fns[S](graph, values)[1])
            print(f"{problem} T={T} tail {S} {rec['ms_per_step']:.2f} ms/step")
            records.append(rec)
    return records


COLUMNS = ["T", "problem", "variant", "mode", "median_ms", "ms_per_step"]
COLUMNS += ["compile_s", "max_rel_diff"]


def main(argv=None):
    parser = cli(__doc__)
    add = parser.add_argument
    add("--sizes", type=int, nargs="*", default=[10_000])
    add("--variants", nargs="*", default=[v for v in VARIANTS if "16" not in v])
    add("--large", type=int, nargs="*", default=[100_000])
    add("--large-variants", nargs="*", default=["cr", "seq_packed"])
    add("--solve-sizes", type=int, nargs="*", default=[10_000, 100_000])
    add("--problems", nargs="*", default=["se2vel", "vehicle"])
    add("--tails", type=int, nargs="*", default=[8, 32])
    add("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    eqs.set_xla_cpu_flags()  # as in benchmarks/results/chain.md
    records = []
    for T in args.sizes:
        records += kernels(T, args.variants, args.repeats)
    for T in args.large:
        records += kernels(T, args.large_variants, args.repeats)
    records += solves(args.solve_sizes, args.problems, args.tails, 10, args.repeats)
    print_and_save(records, COLUMNS, args.json)


if __name__ == "__main__":
    main()
