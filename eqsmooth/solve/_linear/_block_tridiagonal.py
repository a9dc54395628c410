"""Exact solves of chain-structured graphs: block-tridiagonal normal equations.

A graph is a *chain* when every variable group has the same count `T` and every
factor row touches variables of at most two consecutive time steps `t, t+1`.
Stacking the `t`-th variable of every group (in layout order) into one block of
size `D = Σ_g d_g`, the normal matrix `JᵀJ` is then block tridiagonal with `T`
diagonal and `T − 1` super-diagonal `D × D` blocks.

The system is solved by block cyclic reduction (odd-even reduction; Heller
1976, "Some aspects of the cyclic reduction algorithm for block tridiagonal
linear systems", SIAM J. Numer. Anal. 13(4)). Eliminating the odd-indexed
blocks leaves a block-tridiagonal Schur complement on the even blocks, half the
size; once at most `tail_size` blocks remain (a static field of
[`eqsmooth.solve.BlockTridiagonal`][], 32 by default), a sequential block Cholesky
(one `lax.scan`) factors them. Every level is a handful of batched `D × D`
Cholesky factorisations, triangular solves and products, so the cost is
`O(T D³)` like a sequential block Cholesky, but the depth is
`O(log T + tail_size)` instead of `O(T)`: no per-time-step loop over a long
chain on CPU, and parallel on GPU.
It is the Cholesky factorisation of the odd-even permuted matrix, hence
backward stable for symmetric positive definite systems.

The same factorisation gives the diagonal blocks of the inverse (marginal
covariances) by a selected inversion that walks the levels back up.
"""

import dataclasses
import functools as ft
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from ..._precision import einsum, matmul as mm
from ...factors import GroupLayout, Var
from .._linearization import Linearization, Tangent
from ._linear_solver import (
    AbstractFactorization,
    AbstractNormalSolver,
    normal_operator_of,
    pivot_tolerance,
    register_symmetric_psd,
    UnsupportedOperatorError,
)
from ._small_blocks import block_cholesky, block_gram, block_solve_lower


# ---------------------------------------------------------------------------
# Chain detection and the static assembly plan (numpy, trace time)
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Placement:
    """Where selected rows of a stack go along the time axis of a block array."""

    rows: np.ndarray | None  # rows of the stack to take; None means all rows
    times: np.ndarray  # target block index of each selected row
    start: int | None  # set when `times` is `arange(start, start + len)`
    is_sorted: bool

    @classmethod
    def make(cls, rows: np.ndarray | None, times: np.ndarray) -> "_Placement":
        times = np.asarray(times, dtype=np.int64)
        n = times.shape[0]
        start = None
        if n and np.array_equal(times, np.arange(times[0], times[0] + n)):
            start = int(times[0])
        is_sorted = bool(n == 0 or np.all(times[1:] >= times[:-1]))
        return cls(rows, times, start, is_sorted)

    def place(self, values: Array, length: int) -> Array:
        """Sum the selected rows of `values` into an array of `length` blocks."""
        if self.rows is not None:
            values = values[self.rows]
        if self.start is not None:
            n = values.shape[0]
            pad = [(self.start, length - self.start - n)] + [(0, 0)] * (values.ndim - 1)
            return jnp.pad(values, pad)
        return jax.ops.segment_sum(
            values, self.times, num_segments=length, indices_are_sorted=self.is_sorted
        )


@dataclasses.dataclass(frozen=True)
class _Term:
    """One `J_kᵀ J_l` product of a stack and where (and how) it is added."""

    first: int  # index of J_k among the stack's variables
    second: int  # index of J_l
    target: str  # "diag" or "upper"
    transpose: bool  # add (J_kᵀ J_l)ᵀ = J_lᵀ J_k instead
    row_group: int  # layout index of the block row (after any transpose)
    col_group: int
    placement: _Placement


@dataclasses.dataclass(frozen=True)
class ChainPlan:
    """Static description of a chain: sizes and how to assemble its blocks."""

    length: int  # T
    block_size: int  # D
    dims: tuple[int, ...]  # d_g per group, layout order
    offsets: tuple[int, ...]  # offset of each group inside a block
    group_index: dict[str, int]
    # Per factor stack: gradient placements per variable and Hessian terms.
    gradient_terms: tuple[tuple[tuple[int, int, _Placement], ...], ...]
    hessian_terms: tuple[tuple[_Term, ...], ...]

    def to_tangent(self, blocks: Array, layout: tuple[GroupLayout, ...]) -> Tangent:
        """`(T, D)` to `{group: (T, d_g)}`."""
        return {
            g.name: blocks[:, off : off + g.dim] for g, off in zip(layout, self.offsets)
        }

    def from_tangent(
        self, tangent: Tangent, layout: tuple[GroupLayout, ...], dtype
    ) -> Array:
        """`{group: (T, d_g)}` to `(T, D)` (the inverse of `to_tangent`)."""
        return jnp.concatenate([tangent[g.name].astype(dtype) for g in layout], axis=1)


def _stack_name(lin: Linearization, index: int) -> str:
    name = getattr(lin.factors[index], "name", "")
    return f"{name} (factor stack {index})" if name else f"factor stack {index}"


def chain_plan(lin: Linearization) -> ChainPlan:
    """The chain structure of `lin`, or a `ValueError` if it is not a chain."""
    variables = tuple(fl.variables for fl in lin.factors)
    names = tuple(_stack_name(lin, i) for i in range(len(lin.factors)))
    return _chain_plan(lin.layout, variables, names)


def chain_violation(
    layout: tuple[GroupLayout, ...],
    variables: tuple[tuple[Var, ...], ...],
    names: tuple[str, ...],
) -> str | None:
    """Why a graph's structure is not a chain, in words, or `None` if it is.

    A chain has one variable per time step in every group, and every factor
    row touches time steps `t` and `t + 1` only: the structure
    [`eqsmooth.solve.BlockTridiagonal`][] solves (a static query, from the
    variable indices).
    """
    dynamic = [n for n, vs in zip(names, variables) if any(v.is_dynamic for v in vs)]
    if dynamic:  # checked before the cache, whose keys would hold the arrays
        return (
            f"BlockTridiagonal needs static variable indices (its plan is built at "
            f"trace time), but {dynamic[0]} has Var.dynamic indices. Use "
            "DenseCholesky() or a lineax solver for graphs with dynamic indices."
        )
    return _static_chain_violation(layout, variables, names)


@ft.lru_cache(maxsize=64)
def _static_chain_violation(
    layout: tuple[GroupLayout, ...],
    variables: tuple[tuple[Var, ...], ...],
    names: tuple[str, ...],
) -> str | None:
    counts = {g.name: g.count for g in layout}
    if len(set(counts.values())) != 1:
        return (
            "BlockTridiagonal needs a chain: every variable group must have the same "
            f"number of variables (one per time step), got counts {counts}. Use "
            "PCG() or DenseCholesky() for general graphs."
        )
    for name, vars_ in zip(names, variables):
        ids = np.stack([v.ids for v in vars_])  # (k, n)
        if ids.shape[1] == 0:
            continue
        bad = ids.max(axis=0) - ids.min(axis=0) > 1
        if bad.any():
            row = int(np.argmax(bad))
            touched = ", ".join(f"{v.group}[{int(v.ids[row])}]" for v in vars_)
            return (
                f"BlockTridiagonal needs a chain (every factor row touches time steps "
                f"t and t+1 only), but {name} row {row} touches {touched}. Use PCG() "
                "or DenseCholesky() for graphs with loop closures or long-range "
                "factors."
            )
    return None


def _chain_plan(
    layout: tuple[GroupLayout, ...],
    variables: tuple[tuple[Var, ...], ...],
    names: tuple[str, ...],
) -> ChainPlan:
    violation = chain_violation(layout, variables, names)
    if violation is not None:
        raise ValueError(violation)
    length = layout[0].count
    dims = tuple(g.dim for g in layout)
    offsets = tuple(int(o) for o in np.cumsum((0,) + dims[:-1]))
    group_index = {g.name: i for i, g in enumerate(layout)}

    gradient_terms, hessian_terms = [], []
    for name, vars_ in zip(names, variables):
        if len(vars_[0]) == 0:
            gradient_terms.append(())
            hessian_terms.append(())
            continue
        grads = tuple(
            (k, group_index[v.group], _Placement.make(None, v.ids))
            for k, v in enumerate(vars_)
        )
        terms = []
        for k, vk in enumerate(vars_):
            gk = group_index[vk.group]
            for j in range(k, len(vars_)):
                vl = vars_[j]
                gl = group_index[vl.group]
                tk, tl = vk.ids, vl.ids
                if j == k:
                    terms.append(_Term(k, j, "diag", False, gk, gk, _full(tk)))
                    continue
                same, up, down = tl == tk, tl == tk + 1, tk == tl + 1
                if same.any():
                    placement = _subset(same, tk)
                    terms.append(_Term(k, j, "diag", False, gk, gl, placement))
                    terms.append(_Term(k, j, "diag", True, gl, gk, placement))
                if up.any():
                    terms.append(_Term(k, j, "upper", False, gk, gl, _subset(up, tk)))
                if down.any():
                    terms.append(_Term(k, j, "upper", True, gl, gk, _subset(down, tl)))
        gradient_terms.append(grads)
        hessian_terms.append(tuple(terms))
    return ChainPlan(
        length,
        sum(dims),
        dims,
        offsets,
        group_index,
        tuple(gradient_terms),
        tuple(hessian_terms),
    )


def _full(times: np.ndarray) -> _Placement:
    return _Placement.make(None, times)


def _subset(mask: np.ndarray, times: np.ndarray) -> _Placement:
    if mask.all():
        return _Placement.make(None, times)
    rows = np.nonzero(mask)[0]
    return _Placement.make(rows, times[rows])


def assemble_chain(
    lin: Linearization, plan: ChainPlan, damping: Tangent | None
) -> tuple[Float[Array, "T D D"], Float[Array, "T-1 D D"], Float[Array, "T D"]]:
    """Blocks of `JᵀJ + diag(damping)` and the gradient `Jᵀr` of a chain.

    Every product is formed once per factor stack and variable pair, batched
    over rows, and summed into place with static pads or sorted segment sums.
    """
    T, ng = plan.length, len(plan.dims)
    dtype = lin.dtype
    diag_acc: dict[tuple[int, int], Array] = {}
    upper_acc: dict[tuple[int, int], Array] = {}
    grad_acc: dict[int, Array] = {}

    def add(acc, key, value):
        acc[key] = value if key not in acc else acc[key] + value

    for fl, grads, terms in zip(lin.factors, plan.gradient_terms, plan.hessian_terms):
        r, jacs = fl.residual, fl.jacobians
        for k, g, placement in grads:
            add(grad_acc, g, placement.place(einsum("nmd,nm->nd", jacs[k], r), T))
        products: dict[tuple[int, int], Array] = {}
        for term in terms:
            key = (term.first, term.second)
            if key not in products:
                # Jᵢᵀ Jⱼ per row.
                products[key] = block_gram(jacs[term.first], jacs[term.second])
            p = products[key]
            if term.transpose:
                p = jnp.swapaxes(p, 1, 2)
            if term.target == "diag":
                add(
                    diag_acc,
                    (term.row_group, term.col_group),
                    term.placement.place(p, T),
                )
            else:
                add(
                    upper_acc,
                    (term.row_group, term.col_group),
                    term.placement.place(p, T - 1),
                )

    def block_matrix(acc, length):
        rows = []
        for i in range(ng):
            cols = []
            for j in range(ng):
                shape = (length, plan.dims[i], plan.dims[j])
                cols.append(acc.get((i, j), jnp.zeros(shape, dtype)).astype(dtype))
            rows.append(jnp.concatenate(cols, axis=2))
        return jnp.concatenate(rows, axis=1)

    diag = block_matrix(diag_acc, T)
    upper = block_matrix(upper_acc, T - 1)
    grad = jnp.concatenate(
        [
            grad_acc.get(i, jnp.zeros((T, d), dtype)).astype(dtype)
            for i, d in enumerate(plan.dims)
        ],
        axis=1,
    )
    if damping is not None:
        damp = jnp.concatenate(
            [damping[name].astype(dtype) for name in plan.group_index], axis=1
        )
        eye = jnp.eye(plan.block_size, dtype=dtype)
        diag = diag + damp[:, :, None] * eye[None]
    return diag, upper, grad


# ---------------------------------------------------------------------------
# The lineax operator
# ---------------------------------------------------------------------------


class BlockTridiagonalOperator(lx.AbstractLinearOperator):
    """A symmetric positive semidefinite block-tridiagonal matrix.

    Acts on vectors of shape `(T, D)`; row block `t` is
    `upper[t-1]ᵀ x[t-1] + diagonal[t] x[t] + upper[t] x[t+1]`.

    **Arguments:**

    - `diagonal`: the `(T, D, D)` diagonal blocks (each symmetric).
    - `upper`: the `(T − 1, D, D)` super-diagonal blocks; the sub-diagonal
        blocks are their transposes.
    """

    diagonal: Float[Array, "T D D"]
    upper: Float[Array, "T-1 D D"]

    def mv(self, vector):
        out = einsum("tde,te->td", self.diagonal, vector)
        if self.upper.shape[0]:
            zero = jnp.zeros_like(vector[:1])
            above = einsum("tde,te->td", self.upper, vector[1:])
            below = einsum("ted,te->td", self.upper, vector[:-1])
            out = (
                out
                + jnp.concatenate([above, zero], axis=0)
                + jnp.concatenate([zero, below], axis=0)
            )
        return out

    def as_matrix(self):
        T, D, _ = self.diagonal.shape
        t = np.arange(T)
        dense = jnp.zeros((T, D, T, D), self.diagonal.dtype)
        dense = dense.at[t, :, t, :].set(self.diagonal)
        if T > 1:
            s = t[:-1]
            dense = dense.at[s, :, s + 1, :].set(self.upper)
            dense = dense.at[s + 1, :, s, :].set(jnp.swapaxes(self.upper, 1, 2))
        return dense.reshape(T * D, T * D)

    def transpose(self):
        return self

    def in_structure(self):
        return jax.ShapeDtypeStruct(self.diagonal.shape[:2], self.diagonal.dtype)

    def out_structure(self):
        return self.in_structure()


register_symmetric_psd(
    BlockTridiagonalOperator,
    diagonal=lambda op: jnp.diagonal(op.diagonal, axis1=1, axis2=2).reshape(-1),
    is_diagonal=lambda op: op.diagonal.shape[0] == 1 and op.diagonal.shape[1] == 1,
    is_tridiagonal=lambda op: op.diagonal.shape[1] == 1,
)


# ---------------------------------------------------------------------------
# Block cyclic reduction
# ---------------------------------------------------------------------------


def _mT(x):
    return jnp.swapaxes(x, -1, -2)


def _lapack_cho_solve(chol, b):
    """`A⁻¹ b` by jaxlib's batched LAPACK triangular solves (see `_small_blocks`)."""
    y = jax.lax.linalg.triangular_solve(chol, b, left_side=True, lower=True)
    return jax.lax.linalg.triangular_solve(
        chol, y, left_side=True, lower=True, transpose_a=True
    )


def _pad_end(x, length):
    extra = length - x.shape[0]
    if extra == 0:
        return x
    return jnp.concatenate([x, jnp.zeros((extra,) + x.shape[1:], x.dtype)])


def _shift_down(x, length):
    """`[0, x[0], x[1], ...]` cut or padded to `length` entries."""
    zero = jnp.zeros((1,) + x.shape[1:], x.dtype)
    return _pad_end(jnp.concatenate([zero, x])[:length], length)


class _Level(eqx.Module):
    """One reduction level: the odd blocks' inverse Cholesky factors and couplings.

    For odd block `o = 2j + 1` with `A_o = L Lᵀ`: `chol_inv[j] = L⁻¹`,
    `left[j] = A_o⁻¹ B_{2j}ᵀ` and `right[j] = A_o⁻¹ B_{2j+1}` (zero when block
    `o` is the last one). Keeping `L⁻¹` turns every later solve into
    products: no triangular solves, no LAPACK calls, a small program to
    compile.
    """

    chol_inv: Float[Array, "m D D"]
    left: Float[Array, "m D D"]
    right: Float[Array, "m D D"]


class _Tail(eqx.Module):
    """The last `S` blocks, factorised sequentially (block Cholesky).

    With `L_t` the Cholesky factor of the Schur complement
    `A_t − W_{t−1}ᵀ W_{t−1}` and `W_t = L_t⁻¹ B_t`, the matrix is `M Mᵀ` for
    the block lower bidiagonal `M` with `L_t` on its diagonal and `W_tᵀ`
    below it. Stored: `chol_inv[t] = L_t⁻¹` and `coupling[t] = W_t`.
    """

    chol_inv: Float[Array, "S D D"]
    coupling: Float[Array, "S-1 D D"]


class CyclicReductionState(eqx.Module):
    """The factorisation computed by [`eqsmooth.solve.BlockCyclicReduction`][]."""

    levels: tuple[_Level, ...]
    tail: _Tail
    ok: Bool[Array, ""]
    tail_size: int = eqx.field(static=True, default=32)

    def log_det(self) -> Float[Array, ""]:
        """`log det` of the factorised matrix: the pivots of every level and the tail.

        The matrix is the Cholesky factorisation of its odd-even permutation,
        so its determinant is the product of the squared pivots, `−2 Σ log
        diag(L⁻¹)` over the stored inverse factors. Differentiable by
        ordinary autodiff; NaN when a pivot is not positive.
        """
        total = -2.0 * jnp.sum(
            jnp.log(jnp.diagonal(self.tail.chol_inv, axis1=-2, axis2=-1))
        )
        for level in self.levels:
            total = total - 2.0 * jnp.sum(
                jnp.log(jnp.diagonal(level.chol_inv, axis1=-2, axis2=-1))
            )
        return total


DEFAULT_TAIL_SIZE = 32
"""Default of `BlockTridiagonal.tail_size`: cyclic reduction stops once at most
this many blocks are left and a sequential block Cholesky (one `lax.scan`)
factors the rest. Every reduction level compiles to a dozen XLA kernels of its
own while the scan body compiles once, so a larger tail cuts the compile time
of long chains."""


def _tail_factor(A, B) -> tuple[_Tail, Array]:
    """The sequential factorisation and the pivots (diagonals of the `L_t`)."""
    eye = jnp.eye(A.shape[-1], dtype=A.dtype)

    def factor(s):
        chol = block_cholesky(0.5 * (s + _mT(s)))
        return block_solve_lower(chol, eye), jnp.diagonal(chol)

    inv0, piv0 = factor(A[0])
    if A.shape[0] == 1:
        return _Tail(inv0[None], B), piv0[None]

    def step(inv_prev, blocks):
        a, b = blocks
        w = mm(inv_prev, b)
        inv, piv = factor(a - mm(_mT(w), w))
        return inv, (inv, w, piv)

    _, (inv, coupling, piv) = jax.lax.scan(step, inv0, (A[1:], B))
    tail = _Tail(jnp.concatenate([inv0[None], inv]), coupling)
    return tail, jnp.concatenate([piv0[None], piv])


def _tail_solve(tail: _Tail, b):
    Li, W = tail.chol_inv, tail.coupling
    y0 = mm(Li[0], b[0])
    if b.shape[0] == 1:
        return mm(_mT(Li[0]), y0)[None]

    def forward(y_prev, blocks):
        li, w, rhs = blocks
        y = mm(li, rhs - mm(_mT(w), y_prev))
        return y, y

    _, y = jax.lax.scan(forward, y0, (Li[1:], W, b[1:]))
    x_last = mm(_mT(Li[-1]), y[-1])

    def backward(x_next, blocks):
        li, w, yt = blocks
        x = mm(_mT(li), yt - mm(w, x_next))
        return x, x

    ys = jnp.concatenate([y0[None], y[:-1]])
    _, x = jax.lax.scan(backward, x_last, (Li[:-1], W, ys), reverse=True)
    return jnp.concatenate([x, x_last[None]])


def _tail_inverse_blocks(tail: _Tail):
    """Diagonal and super-diagonal blocks of `(M Mᵀ)⁻¹`, from the last block up:
    `Σ_{t,t+1} = −G_t Σ_{t+1,t+1}` and `Σ_tt = L_t⁻ᵀ L_t⁻¹ + G_t Σ_{t+1,t+1} G_tᵀ`
    with `G_t = L_t⁻ᵀ W_t`."""
    Li, W = tail.chol_inv, tail.coupling
    last = mm(_mT(Li[-1]), Li[-1])
    if Li.shape[0] == 1:
        return last[None], W

    def step(s_next, blocks):
        li, w = blocks
        G = mm(_mT(li), w)
        cross = -mm(G, s_next)
        s = mm(_mT(li), li) - mm(cross, _mT(G))
        s = 0.5 * (s + _mT(s))
        return s, (s, cross)

    _, (diag, upper) = jax.lax.scan(step, last, (Li[:-1], W), reverse=True)
    return jnp.concatenate([diag, last[None]]), upper


def cyclic_reduction_factor(
    diagonal: Float[Array, "T D D"],
    upper: Float[Array, "T-1 D D"],
    tail_size: int = DEFAULT_TAIL_SIZE,
) -> CyclicReductionState:
    """Factorise a symmetric positive definite block-tridiagonal matrix.

    `ok` is false when a pivot is non-finite or below rounding level relative to
    the original diagonal entry of its coordinate (singular or indefinite).

    The reduction levels call jaxlib's batched LAPACK kernels: each level's
    Cholesky and triangular solve depend on the previous level's, so these
    calls run one after another (see `_small_blocks` for why that matters).
    The last `tail_size` blocks (or fewer) are factorised by a sequential
    block Cholesky, and the solves that use the factorisation call no LAPACK.
    """
    dtype = diagonal.dtype
    T, D, _ = diagonal.shape
    num_levels = int(np.ceil(np.log2(T))) if T > 1 else 0
    rel_tol = pivot_tolerance(dtype, D * (num_levels + 1), jnp.asarray(1.0, dtype))
    # Relative-pivot test: each squared pivot against the original diagonal entry
    # of its coordinate, so that badly scaled but regular problems pass.
    scale = jnp.diagonal(diagonal, axis1=1, axis2=2)
    A, B = diagonal, upper
    levels = []
    ok = jnp.asarray(True)

    def check(piv, ref):
        return jnp.all(piv * piv > rel_tol * ref)

    if tail_size < 1:
        raise ValueError(f"tail_size must be >= 1, got {tail_size}")
    while A.shape[0] > tail_size:
        n = A.shape[0]
        m, k = n // 2, n - n // 2
        Bp = _pad_end(B, n)
        odd, even = A[1::2], A[0::2]
        b_left, b_right = Bp[0 : 2 * m : 2], Bp[1 : 2 * m : 2]
        chol = jnp.linalg.cholesky(odd)
        # One solve with both couplings side by side: batched tiny-matrix
        # calls are dominated by per-call overhead on CPU.
        both = _lapack_cho_solve(chol, jnp.concatenate([_mT(b_left), b_right], axis=2))
        left, right = both[..., :D], both[..., D:]
        eye = jnp.broadcast_to(jnp.eye(D, dtype=dtype), (m, D, D))
        chol_inv = block_solve_lower(chol, eye)
        ok = ok & check(jnp.diagonal(chol, axis1=1, axis2=2), scale[1::2])
        scale = scale[0::2]
        prod = mm(b_left, both)  # [B_{2j} A_o⁻¹ B_{2j}ᵀ, B_{2j} A_o⁻¹ B_{2j+1}]
        A = even - _pad_end(prod[..., :D], k) - _shift_down(mm(_mT(b_right), right), k)
        B = -prod[: k - 1, :, D:]
        levels.append(_Level(chol_inv, left, right))
    tail, pivots = _tail_factor(A, B)
    ok = ok & check(pivots, scale)
    return CyclicReductionState(tuple(levels), tail, ok, tail_size)


def _level_sizes(T: int, tail_size: int) -> list[int]:
    sizes = []
    while T > tail_size:
        sizes.append(T)
        T = T - T // 2
    return sizes


def cyclic_reduction_solve(
    state: CyclicReductionState, rhs: Float[Array, "T D"]
) -> Float[Array, "T D"]:
    """Solve with a factorisation from `cyclic_reduction_factor`."""
    sizes = _level_sizes(rhs.shape[0], state.tail_size)
    b = rhs
    partial = []
    for n, level in zip(sizes, state.levels):
        m, k = n // 2, n - n // 2
        odd, even = b[1::2], b[0::2]
        y = einsum("jde,je->jd", level.chol_inv, odd)
        partial.append(einsum("jed,je->jd", level.chol_inv, y))
        b = (
            even
            - _pad_end(einsum("jde,jd->je", level.left, odd), k)
            - _shift_down(einsum("jde,jd->je", level.right, odd), k)
        )
    x = _tail_solve(state.tail, b)
    for n, level, u in zip(reversed(sizes), reversed(state.levels), reversed(partial)):
        m, k = n // 2, n - n // 2
        xe = _pad_end(x, m + 1)
        xo = (
            u
            - einsum("jde,je->jd", level.left, xe[:m])
            - einsum("jde,je->jd", level.right, xe[1 : m + 1])
        )
        pairs = jnp.stack([xe[:m], xo], axis=1).reshape((2 * m,) + x.shape[1:])
        x = jnp.concatenate([pairs, x[m:]])
    return x


def cyclic_reduction_inverse_blocks(
    state: CyclicReductionState, T: int
) -> tuple[Float[Array, "T D D"], Float[Array, "T-1 D D"]]:
    """Diagonal and super-diagonal blocks of the inverse (selected inversion).

    With the odd blocks eliminated, `Σ_ee = S⁻¹` (the reduced system's inverse),
    `Σ_oe = −W Σ_ee` and `Σ_oo = A_oo⁻¹ + W Σ_ee Wᵀ` with `W = A_oo⁻¹ A_oe`;
    `A_oo` is block diagonal and `W` has two blocks per row (`left`, `right`),
    so only the tridiagonal part of `Σ_ee` is ever needed.
    """
    sizes = _level_sizes(T, state.tail_size)
    D = state.tail.chol_inv.shape[-1]
    diag, upper = _tail_inverse_blocks(state.tail)
    for n, level in zip(reversed(sizes), reversed(state.levels)):
        m = n // 2
        Wl, Wr = level.left, level.right
        se = _pad_end(diag, m + 1)
        s0, s1 = se[:m], se[1 : m + 1]
        c = _pad_end(upper, m)  # Σ_{2j, 2j+2} of the reduced system
        a_inv = mm(_mT(level.chol_inv), level.chol_inv)
        odd = (
            a_inv
            + mm(mm(Wl, s0), _mT(Wl))
            + mm(mm(Wl, c), _mT(Wr))
            + mm(mm(Wr, _mT(c)), _mT(Wl))
            + mm(mm(Wr, s1), _mT(Wr))
        )
        odd = 0.5 * (odd + _mT(odd))
        cross_left = -(mm(s0, _mT(Wl)) + mm(c, _mT(Wr)))  # Σ_{2j, 2j+1}
        cross_right = -(mm(Wl, c) + mm(Wr, s1))  # Σ_{2j+1, 2j+2}
        diag = jnp.concatenate(
            [jnp.stack([s0, odd], axis=1).reshape(2 * m, D, D), diag[m:]]
        )
        upper = jnp.stack([cross_left, cross_right], axis=1).reshape(2 * m, D, D)
        upper = upper[: n - 1]
    return diag, upper


class BlockCyclicReduction(lx.AbstractLinearSolver):
    """A lineax solver for [`eqsmooth.solve.BlockTridiagonalOperator`][].

    Exact block cyclic reduction, `O(T D³)` work and `O(log T)` depth. Through
    `lineax.linear_solve` it gets lineax's derivative rules: the backward pass
    of a solve is one more solve with the same factorisation. Singular or
    indefinite operators give `lineax.RESULTS.singular` and a zero solution.
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if not isinstance(operator, BlockTridiagonalOperator):
            raise UnsupportedOperatorError(
                "BlockCyclicReduction needs an eqsmooth.solve."
                f"BlockTridiagonalOperator, got {type(operator).__name__}"
            )
        return cyclic_reduction_factor(operator.diagonal, operator.upper)

    def compute(self, state: CyclicReductionState, vector, options: dict[str, Any]):
        del options
        x = cyclic_reduction_solve(state, vector)
        x = jnp.where(state.ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(state.ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return x, result, {}

    def transpose(self, state: CyclicReductionState, options: dict[str, Any]):
        return state, options

    def conj(self, state: CyclicReductionState, options: dict[str, Any]):
        return state, options

    def assume_full_rank(self):
        return True


# ---------------------------------------------------------------------------
# The eqsmooth linear solver
# ---------------------------------------------------------------------------


class ChainFactorization(AbstractFactorization):
    """The state of [`eqsmooth.solve.BlockTridiagonal`][]: a chain's block cyclic
    reduction, with the static layout that maps blocks to tangent groups."""

    factor: CyclicReductionState
    ok: Bool[Array, ""]
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)
    offsets: tuple[int, ...] = eqx.field(static=True)

    def to_tangent(self, blocks: Array) -> Tangent:
        return {
            g.name: blocks[:, off : off + g.dim]
            for g, off in zip(self.layout, self.offsets)
        }

    def from_tangent(self, tangent: Tangent, dtype) -> Array:
        return jnp.concatenate(
            [tangent[g.name].astype(dtype) for g in self.layout], axis=1
        )

    def log_det(self) -> Float[Array, ""]:
        return self.factor.log_det()

    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        cov, _ = cyclic_reduction_inverse_blocks(self.factor, self.layout[0].count)
        return {
            g.name: cov[:, off : off + g.dim, off : off + g.dim]
            for g, off in zip(self.layout, self.offsets)
        }


class BlockTridiagonal(AbstractNormalSolver):
    """Exact solver for chains (smoothing problems): block cyclic reduction.

    Use it when every variable group has one variable per time step and every
    factor touches time steps `t` and `t + 1` only (priors, odometry, dynamics,
    measurements): the normal matrix is then block tridiagonal and this solver
    is exact in `O(T D³)` time, `D` being the summed tangent dimension of one
    time step. The structure is checked once, at trace time; a graph that is
    not a chain raises a `ValueError` naming the first offending factor row.

    A lineax solver of a [`eqsmooth.solve.NormalOperator`][]: derivatives go
    through `lineax.linear_solve`, so reverse mode costs one more
    block-tridiagonal solve with the same factorisation, and the solver
    `vmap`s over batches of graphs. (lineax raises at run time when a
    derivative of a failed solve is requested: there is no result code to
    carry it.) Its state is a [`eqsmooth.solve.ChainFactorization`][]
    (log-determinant, marginal covariances).

    **Arguments:**

    - `tail_size`: cyclic reduction stops once at most this many blocks are
        left; a sequential block Cholesky factors the rest. Changes compile
        time, not results.
    """

    tail_size: int = eqx.field(static=True, default=DEFAULT_TAIL_SIZE)

    def __check_init__(self):
        if not isinstance(self.tail_size, int) or self.tail_size < 1:
            raise ValueError(
                "BlockTridiagonal.tail_size must be an int >= 1, got "
                f"{self.tail_size!r}"
            )

    def init(
        self, operator: lx.AbstractLinearOperator, options: dict[str, Any]
    ) -> ChainFactorization:
        del options
        op = normal_operator_of(operator, "BlockTridiagonal")
        plan = chain_plan(op.lin)
        diag, upper, _ = assemble_chain(op.lin, plan, op.damping)
        factor = cyclic_reduction_factor(diag, upper, self.tail_size)
        return ChainFactorization(factor, factor.ok, op.lin.layout, plan.offsets)

    def compute(self, state: ChainFactorization, vector, options: dict[str, Any]):
        del options
        dtype = state.factor.tail.chol_inv.dtype
        x = cyclic_reduction_solve(state.factor, state.from_tangent(vector, dtype))
        x = jnp.where(state.ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(state.ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return state.to_tangent(x), result, {}


def block_tridiagonal_log_det(
    diagonal: Float[Array, "T D D"], upper: Float[Array, "T-1 D D"]
) -> Float[Array, ""]:
    """`log det` of a symmetric positive definite block-tridiagonal matrix.

    From the block cyclic reduction of [`eqsmooth.solve.BlockTridiagonal`][]
    (the same factorisation the solves use): `O(T D³)` work, differentiable
    by ordinary reverse- or forward-mode autodiff.

    **Arguments:**

    - `diagonal`: the `(T, D, D)` diagonal blocks.
    - `upper`: the `(T − 1, D, D)` super-diagonal blocks.

    **Returns:**

    The scalar log-determinant; NaN when the matrix is not positive definite
    (a non-positive pivot).
    """
    if diagonal.ndim != 3 or diagonal.shape[1] != diagonal.shape[2]:
        raise ValueError(
            f"block_tridiagonal_log_det: diagonal must be (T, D, D), got "
            f"{diagonal.shape}"
        )
    T, D, _ = diagonal.shape
    if upper.shape != (T - 1, D, D):
        raise ValueError(
            f"block_tridiagonal_log_det: upper must be ({T - 1}, {D}, {D}), got "
            f"{upper.shape}"
        )
    return cyclic_reduction_factor(diagonal, upper).log_det()
