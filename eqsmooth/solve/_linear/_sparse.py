"""Sparse direct solves of the normal equations on the host (SuperLU or CHOLMOD)."""

import functools as ft
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ...factors import GroupLayout
from .._linearization import flatten_layout, unflatten_layout
from ._linear_solver import (
    AbstractNormalSolver,
    flat_damping,
    normal_operator_of,
    NormalOperator,
)
from ._small_blocks import block_gram


class _Term(NamedTuple):
    """One block product of a factor stack, added to a class of canonical blocks.

    Rows `rows` of stack `stack` add their `J_kᵀ J_l` block (rows and columns
    `rsl`, `csl` of the stack's `(n, K, K)` product) to block `segments[i]`
    of shape class `shape`.
    """

    stack: int
    rows: np.ndarray | None  # None: every row
    rsl: tuple[int, int]
    csl: tuple[int, int]
    shape: tuple[int, int]
    segments: np.ndarray


def _block_products(layout, variables, offsets, dims) -> list:
    """The block products of the normal matrix: one entry per (stack, pair
    of variables, triangle): `(stack, rows, row slice, column slice, shape,
    first scalar row and column of the canonical block, per row)`; `stack`
    None for the diagonal block of every variable, touched or not."""
    raw: list = []
    for g in layout:  # every variable's diagonal block, touched or not
        starts = offsets[g.name] + np.arange(g.count) * g.dim
        raw.append((None, None, None, None, (g.dim, g.dim), starts, starts))
    for stack, vars_ in enumerate(variables):
        if not vars_ or len(np.asarray(vars_[0].ids)) == 0:
            continue
        starts = [offsets[v.group] + np.asarray(v.ids) * dims[v.group] for v in vars_]
        vdims = [dims[v.group] for v in vars_]
        col0 = np.concatenate([[0], np.cumsum(vdims)]).astype(int)
        sl = [(int(col0[k]), int(col0[k + 1])) for k in range(len(vars_))]
        for k in range(len(vars_)):
            for j in range(k, len(vars_)):
                if k == j:
                    shape = (vdims[k], vdims[k])
                    raw.append((stack, None, sl[k], sl[k], shape, starts[k], starts[k]))
                    continue
                # Rows where k's block comes first add J_kᵀJ_j to (k, j);
                # the others add J_jᵀJ_k to (j, k). Both when k and j are
                # the same variable (its diagonal block gets both).
                for a, b, mask in (
                    (k, j, starts[k] <= starts[j]),
                    (j, k, starts[j] <= starts[k]),
                ):
                    rows = np.nonzero(mask)[0]
                    if len(rows) == 0:
                        continue
                    every = len(rows) == len(mask)
                    raw.append(
                        (
                            stack,
                            None if every else rows,
                            sl[a],
                            sl[b],
                            (vdims[a], vdims[b]),
                            starts[a][rows],
                            starts[b][rows],
                        )
                    )
    return raw


class SparsityPattern:
    """The static sparsity pattern of `JᵀJ + diag(damping)` in CSC form, and
    how its values are assembled.

    The values are summed block by block: every factor row adds its `J_kᵀ J_l`
    products to canonical blocks, one per pair of touched variables (the
    block whose first scalar row is not after its first column; the other
    triangle is read from it transposed), plus a diagonal block for every
    variable. A block sum is one windowed segment sum per block shape, which
    XLA runs far faster than a scalar scatter of every product entry. The
    stored CSC entries are then gathered from the blocks (`gather`), and the
    damping added on the diagonal (`diagonal`). Built once per graph
    structure.
    """

    def __init__(self, layout, variables):
        N = sum(g.count * g.dim for g in layout)
        offsets, start = {}, 0
        for g in layout:
            offsets[g.name] = start
            start += g.count * g.dim
        dims = {g.name: g.dim for g in layout}
        raw = _block_products(layout, variables, offsets, dims)
        # Number the distinct blocks of each shape.
        shapes = list(dict.fromkeys(t[4] for t in raw))
        tables, segments = [], {}
        for shape in shapes:
            idx = [i for i, t in enumerate(raw) if t[4] == shape]
            keys = np.concatenate(
                [raw[i][5].astype(np.int64) * N + raw[i][6] for i in idx]
            )
            unique, inverse = np.unique(keys, return_inverse=True)
            tables.append((shape, unique // N, unique % N))
            for i, part in zip(
                idx, np.split(inverse, np.cumsum([len(raw[i][5]) for i in idx])[:-1])
            ):
                segments[i] = part.astype(np.int32)
        terms = [
            _Term(t[0], t[1], t[2], t[3], t[4], segments[i])
            for i, t in enumerate(raw)
            if t[0] is not None
        ]
        self.shapes: tuple[tuple[tuple[int, int], int], ...] = tuple(
            (shape, len(r0)) for shape, r0, _ in tables
        )
        # Every scalar entry of every block, in both triangles: its key
        # (column * N + row) and its position in the concatenated blocks.
        keys, positions, base = [], [], 0
        for (dr, dc), r0, c0 in tables:
            r = r0[:, None, None] + np.arange(dr)[None, :, None]
            c = c0[:, None, None] + np.arange(dc)[None, None, :]
            r, c = np.broadcast_arrays(r, c)
            pos = base + np.arange(r.size).reshape(r.shape)
            keys.append((c * N + r).ravel())
            positions.append(pos.ravel())
            off = r0 != c0  # the other triangle, read transposed
            keys.append((r[off] * N + c[off]).ravel())
            positions.append(pos[off].ravel())
            base += r.size
        keys, positions = np.concatenate(keys), np.concatenate(positions)
        unique, first = np.unique(keys, return_index=True)
        self.size = N
        self.nnz = len(unique)
        self.terms = tuple(terms)
        self.gather = positions[first].astype(np.int32)
        self.indices = (unique % N).astype(np.int32)  # row of each stored entry
        self.columns = (unique // N).astype(np.int32)  # its column
        self.indptr = np.searchsorted(self.columns, np.arange(N + 1)).astype(np.int32)
        self.diagonal = np.searchsorted(unique, np.arange(N) * (N + 1)).astype(np.int32)
        # Host-side state reused across solves of this pattern (e.g. CHOLMOD's
        # symbolic analysis).
        self.cache: dict = {}


@ft.lru_cache(maxsize=16)
def _pattern(layout, variables) -> SparsityPattern:
    return SparsityPattern(layout, variables)


def _host_csc(pattern: SparsityPattern, data):
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


def _superlu_solve(pattern: SparsityPattern, data, b):
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


def _cholmod_solve(pattern: SparsityPattern, data, b):
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
    pattern: SparsityPattern = eqx.field(static=True)
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)


def assemble_sparse(op: NormalOperator) -> SparseNormalState:
    """`JᵀJ + diag(damping)` in CSC form: the pattern is computed once per graph
    structure; the values are summed block by block (one segment sum per
    block shape), gathered into the stored entries, and damped."""
    lin = op.lin
    pattern = _pattern(lin.layout, tuple(fl.variables for fl in lin.factors))
    products = {}
    for i, fl in enumerate(lin.factors):
        if fl.residual.shape[0] == 0:
            continue
        jac = jnp.concatenate(fl.jacobians, axis=2)
        products[i] = block_gram(jac, jac)
    parts: dict[tuple[int, int], list] = {shape: [] for shape, _ in pattern.shapes}
    for t in pattern.terms:
        prod = products[t.stack]
        if t.rows is not None:
            prod = prod[t.rows]
        block = prod[:, t.rsl[0] : t.rsl[1], t.csl[0] : t.csl[1]]
        parts[t.shape].append((block.reshape(block.shape[0], -1), t.segments))
    stored = []
    for shape, count in pattern.shapes:
        if parts[shape]:
            values = jnp.concatenate([v for v, _ in parts[shape]])
            segments = np.concatenate([seg for _, seg in parts[shape]])
            sums = jax.ops.segment_sum(values, segments, num_segments=count)
        else:
            sums = jnp.zeros((count, shape[0] * shape[1]), lin.dtype)
        stored.append(sums.reshape(-1))
    data = jnp.concatenate(stored)[pattern.gather]
    damp = flat_damping(lin, op.damping)
    if damp is not None:
        data = data.at[pattern.diagonal].add(damp, unique_indices=True)
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
    (the linear solvers page has measurements). A matrix
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
