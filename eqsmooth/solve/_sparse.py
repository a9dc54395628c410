"""Sparse direct solves of the normal equations on the host (SuperLU or CHOLMOD)."""

import functools as ft
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ..factors import GroupLayout
from ._linear_solver import (
    AbstractNormalSolver,
    flat_damping,
    normal_operator_of,
    NormalOperator,
)
from ._linearization import flatten_layout, unflatten_layout


class _Pattern:
    """The static sparsity pattern of `JᵀJ + diag(damping)` in CSC form.

    `slot[e]` says which stored entry the `e`-th block-product entry (all
    stacks' `(n, K, K)` products flattened, then the `N` diagonal entries)
    is added to; duplicates are summed. Built once per graph structure.
    """

    def __init__(self, layout, variables):
        N = sum(g.count * g.dim for g in layout)
        offsets, start = {}, 0
        for g in layout:
            offsets[g.name] = start
            start += g.count * g.dim
        dims = {g.name: g.dim for g in layout}
        rows, cols = [], []
        for vars_ in variables:
            if not vars_ or len(np.asarray(vars_[0].ids)) == 0:
                continue
            c = np.concatenate(
                [
                    offsets[v.group]
                    + np.asarray(v.ids)[:, None] * dims[v.group]
                    + np.arange(dims[v.group])[None]
                    for v in vars_
                ],
                axis=1,
            )
            K = c.shape[1]
            rows.append(np.broadcast_to(c[:, :, None], (c.shape[0], K, K)).ravel())
            cols.append(np.broadcast_to(c[:, None, :], (c.shape[0], K, K)).ravel())
        rows.append(np.arange(N))
        cols.append(np.arange(N))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        key = cols.astype(np.int64) * N + rows
        unique, slot = np.unique(key, return_inverse=True)
        self.size = N
        self.nnz = len(unique)
        self.slot = slot.astype(np.int32)
        self.indices = (unique % N).astype(np.int32)
        self.indptr = np.searchsorted(unique // N, np.arange(N + 1)).astype(np.int32)
        # Host-side state reused across solves of this pattern (e.g. CHOLMOD's
        # symbolic analysis).
        self.cache: dict = {}


@ft.lru_cache(maxsize=16)
def _pattern(layout, variables) -> _Pattern:
    return _Pattern(layout, variables)


def _host_csc(pattern: _Pattern, data):
    import scipy.sparse as sp

    n = pattern.size
    return sp.csc_matrix(
        (np.asarray(data), pattern.indices, pattern.indptr), shape=(n, n)
    )


def _pivots_ok(pivots, reference, dtype) -> bool:
    # Pivots of a symmetric elimination are all positive for a positive definite
    # matrix; one at rounding level relative to its original diagonal entry means
    # singular to working precision.
    tol = pivots.shape[0] * np.finfo(dtype).eps
    return bool(np.all(np.isfinite(pivots)) and np.all(pivots > tol * reference))


def _superlu_solve(pattern: _Pattern, data, b):
    """Factorise and solve on the host; NaNs and `ok = False` if singular."""
    import scipy.sparse.linalg as spla

    b = np.asarray(b)
    A = _host_csc(pattern, data)
    diag = A.diagonal()
    try:
        lu = spla.splu(
            A,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True, "Equil": False},
        )
    except RuntimeError:  # exactly singular
        return np.full_like(b, np.nan), np.asarray(False)
    # With symmetric mode and diagonal pivots, U's diagonal holds the pivots of
    # a symmetric elimination in the order `perm_c`.
    ok = np.array_equal(lu.perm_c, lu.perm_r) and _pivots_ok(
        lu.U.diagonal(), diag[np.argsort(lu.perm_c)], A.dtype
    )
    x = lu.solve(b)
    ok = ok and bool(np.all(np.isfinite(x)))
    return x.astype(b.dtype), np.asarray(ok)


def _cholmod_solve(pattern: _Pattern, data, b):
    """Supernodal Cholesky (CHOLMOD), the symbolic analysis done once per pattern."""
    from sksparse.cholmod import analyze, CholmodError

    b = np.asarray(b)
    A = _host_csc(pattern, data)
    symbolic = pattern.cache.get("cholmod")
    if symbolic is None:
        symbolic = pattern.cache["cholmod"] = analyze(A)
    try:
        factor = symbolic.cholesky(A)
    except CholmodError:  # not positive definite
        return np.full_like(b, np.nan), np.asarray(False)
    # D of the equivalent LDLᵀ holds the pivots, in the order P.
    ok = _pivots_ok(factor.D(), A.diagonal()[factor.P()], A.dtype)
    x = factor(b)
    ok = ok and bool(np.all(np.isfinite(x)))
    return x.astype(b.dtype), np.asarray(ok)


class SparseNormalState(eqx.Module):
    """The assembled normal matrix (CSC values) and its static pattern."""

    data: Float[Array, " nnz"]
    pattern: _Pattern = eqx.field(static=True)
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)


def assemble_sparse(op: NormalOperator) -> SparseNormalState:
    """`JᵀJ + diag(damping)` in CSC form: the pattern is computed once per graph
    structure, the values with one segment sum."""
    lin = op.lin
    pattern = _pattern(lin.layout, tuple(fl.variables for fl in lin.factors))
    values = []
    for fl in lin.factors:
        if fl.residual.shape[0] == 0:
            continue
        jac = jnp.concatenate(fl.jacobians, axis=2)
        values.append(jnp.einsum("nmi,nmj->nij", jac, jac).reshape(-1))
    damp = flat_damping(lin, op.damping)
    values.append(jnp.zeros((pattern.size,), lin.dtype) if damp is None else damp)
    data = jax.ops.segment_sum(
        jnp.concatenate(values), pattern.slot, num_segments=pattern.nnz
    )
    return SparseNormalState(data, pattern, lin.layout)


def _host_compute(host_solve, state: SparseNormalState, vector):
    b = flatten_layout(state.layout, vector)
    out = (
        jax.ShapeDtypeStruct(b.shape, b.dtype),
        jax.ShapeDtypeStruct((), jnp.bool_),
    )
    x, ok = jax.pure_callback(
        ft.partial(host_solve, state.pattern),
        out,
        state.data,
        b,
        vmap_method="sequential",
    )
    x = jnp.where(ok, x, jnp.zeros_like(x))
    result = lx.RESULTS.where(ok, lx.RESULTS.successful, lx.RESULTS.singular)
    return unflatten_layout(state.layout, x), result, {}


class SparseLU(AbstractNormalSolver):
    """Sparse direct solve of `JᵀJ + diag(damping)` on the host CPU (SciPy).

    A lineax solver of the [`eqsmooth.solve.NormalOperator`][]. Assembles
    the normal matrix in compressed-column form (the sparsity pattern is
    computed once per graph structure, the values with one segment sum in
    JAX) and factorises it with SciPy's SuperLU through `jax.pure_callback`,
    with a minimum-degree ordering of `Aᵀ + A` and diagonal pivoting
    (symmetric mode). Exact for any graph shape; for large graphs with many
    loop closures it is far faster than [`eqsmooth.solve.PCG`][] on CPU.

    Through `lineax.linear_solve` it can be differentiated (the backward pass
    is one more host solve) and `vmap`ped (the batch is solved one graph
    after another). It needs SciPy, always runs on the host CPU (data on an
    accelerator is copied), and cannot be used under `jax.jit` on backends
    without host callbacks. A singular or indefinite system gives
    `RESULTS.singular` and a zero step.
    """

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        try:
            import scipy.sparse  # noqa: F401
        except ImportError as e:  # pragma: no cover
            raise ImportError("SparseLU needs SciPy: pip install scipy") from e
        return assemble_sparse(normal_operator_of(operator, "SparseLU"))

    def compute(self, state: SparseNormalState, vector, options: dict[str, Any]):
        del options
        return _host_compute(_superlu_solve, state, vector)


class SparseCholesky(AbstractNormalSolver):
    """Sparse supernodal Cholesky of `JᵀJ + diag(damping)` on the host (CHOLMOD).

    The same assembly and host callback as [`eqsmooth.solve.SparseLU`][], but
    the factorisation is SuiteSparse's CHOLMOD (through the optional
    `scikit-sparse` package): the fill-reducing ordering and symbolic
    analysis are computed once per graph structure and reused by every
    later solve, and the numeric factorisation is supernodal (dense BLAS
    blocks), so its speed is that of the BLAS SuiteSparse is linked against
    (measurements: `benchmarks/results/pgo_cholmod_openblas.md`). A matrix
    that is not positive definite (or singular to working precision) gives
    `RESULTS.singular` and a zero step.

    Needs `scikit-sparse`, which builds against the system SuiteSparse
    (Debian/Ubuntu: `apt-get install libsuitesparse-dev`, then
    `pip install cython && pip install --no-build-isolation scikit-sparse`;
    with SuiteSparse 5.x use `scikit-sparse==0.4.16`). Constructing it
    without the package raises an `ImportError` saying so.
    """

    def __check_init__(self):
        try:
            import sksparse.cholmod  # noqa: F401
        except ImportError as e:
            raise ImportError(
                "SparseCholesky needs scikit-sparse (CHOLMOD): apt-get install "
                "libsuitesparse-dev; pip install cython; pip install "
                "--no-build-isolation scikit-sparse. Or use SparseLU() (SciPy only)."
            ) from e

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        return assemble_sparse(normal_operator_of(operator, "SparseCholesky"))

    def compute(self, state: SparseNormalState, vector, options: dict[str, Any]):
        del options
        return _host_compute(_cholmod_solve, state, vector)
