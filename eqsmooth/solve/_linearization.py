"""The whitened, block-sparse linearisation every linear solver consumes."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from .._precision import einsum
from ..factors import FactorGraph, GroupLayout, Var
from ..factors._factor import linearize_rows
from ..manifold import retract
from ._linear._small_blocks import block_gram


Tangent = dict[str, Float[Array, "_N _d"]]


class FactorLinearization(eqx.Module):
    """One factor stack linearised: whitened residual and Jacobian blocks.

    `residual` has shape `(n, m)`; `jacobians[k]` has shape `(n, m, d_k)` and
    multiplies the tangent of variable `variables[k].ids[i]` for row `i`. Both
    include the noise whitening and the IRLS weight `√ρ'` of robust models.
    """

    residual: Float[Array, "n m"]
    jacobians: tuple[Float[Array, "n m _d"], ...]
    variables: tuple[Var, ...]
    name: str = eqx.field(static=True, default="")  # the factor type, for messages


class Linearization(eqx.Module):
    """The Gauss-Newton model of a graph at a linearisation point.

    The linear least-squares problem is `min_δ ½‖J δ + r‖²` with `δ` a
    tangent dict `{group: (N_g, d_g)}`; `cost` is the true (robust) cost at
    the linearisation point.
    """

    factors: tuple[FactorLinearization, ...]
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)
    cost: Float[Array, ""]

    @property
    def dtype(self):
        return self.factors[0].residual.dtype

    @property
    def num_tangent(self) -> int:
        return sum(g.count * g.dim for g in self.layout)


@eqx.filter_jit
def linearize(graph: FactorGraph, values: dict[str, PyTree]) -> Linearization:
    """Linearise `graph` at `values` (whitened, robust-weighted Jacobian blocks).

    Compiled as one program (`eqx.filter_jit`), so an eager call costs one
    compilation per graph structure rather than one per JAX operation.
    Inside `jit`, it is traced into the caller's program.
    """
    return linearize_graph(graph, values)


def linearize_graph(graph: FactorGraph, values: dict[str, PyTree]) -> Linearization:
    """[`eqsmooth.solve.linearize`][] without its own `jit`: what the solvers
    trace inside their programs."""
    layout = graph.validate(values)
    out = []
    cost = jnp.zeros((), dtype=_values_dtype(values))
    for f in graph.factors:
        states = graph.states_of(f, values)
        r, jacs = linearize_rows(f, states)
        n, m = r.shape
        f.noise.check_shapes(type(f).__name__, n, m)
        rw = f.noise.whiten(r)
        jw = _whiten_jacobians(f.noise, jacs)
        s = jnp.sum(rw * rw, axis=1)
        rho, drho = f.noise.rho(s)
        cost = cost + 0.5 * jnp.sum(rho).astype(cost.dtype)
        # √ρ' with a finite derivative where ρ' = 0 (Tukey and Welsch
        # outliers): the plain square root's derivative there is infinite,
        # and forward mode turned it into NaN.
        positive = drho > 0
        w = jnp.where(positive, jnp.sqrt(jnp.where(positive, drho, 1.0)), 0.0)
        rw = rw * w[:, None]
        jw = tuple(j * w[:, None, None] for j in jw)
        out.append(FactorLinearization(rw, jw, f.variables, type(f).__name__))
    return Linearization(tuple(out), layout, cost)


def _whiten_jacobians(noise, jacs: tuple[Array, ...]) -> tuple[Array, ...]:
    """Whiten a factor's Jacobian blocks as one `(n, m, Σd)` array: one batched
    product instead of one per variable, which XLA on CPU runs several times
    faster (the performance page has the figures)."""
    if len(jacs) == 1:
        return (noise.whiten(jacs[0]),)
    whole = noise.whiten(jnp.concatenate(jacs, axis=2))
    return tuple(jnp.split(whole, np.cumsum([j.shape[2] for j in jacs])[:-1], axis=2))


def placeholder_linearization(
    graph: FactorGraph,
    values: dict[str, PyTree],
    residuals: PyTree[jax.ShapeDtypeStruct] | None = None,
) -> Linearization:
    """Zeros shaped like `linearize(graph, values)`.

    A solver's initial state holds it until its first iteration linearises,
    so that the compiled solve contains one copy of the linearisation (in the
    loop) instead of two (before the loop and in it). `residuals`, the
    shapes of the graph's whitened residuals (one `(n, m)` per factor
    stack), saves tracing the linearisation for its shapes: block `k` of a
    stack is `(n, m, d)` with `d` the tangent dimension of its variable's
    group, and every block has its stack's residual dtype.
    """
    if residuals is None:
        shapes = eqx.filter_eval_shape(linearize_graph, graph, values)
        return jax.tree_util.tree_map(
            lambda x: (
                jnp.zeros(x.shape, x.dtype)
                if isinstance(x, jax.ShapeDtypeStruct)
                else x
            ),
            shapes,
            is_leaf=lambda x: isinstance(x, jax.ShapeDtypeStruct),
        )
    layout = graph.validate(values)
    dims = {g.name: g.dim for g in layout}
    residuals = jax.tree_util.tree_leaves(residuals)
    if len(residuals) != len(graph.factors) or any(r.ndim != 2 for r in residuals):
        raise ValueError(
            "the residual function returned shapes "
            f"{[tuple(r.shape) for r in residuals]}; the graph has "
            f"{len(graph.factors)} factor stacks, each with (n, m) residuals"
        )
    out = []
    for f, r in zip(graph.factors, residuals):
        n, m = r.shape
        jacobians = tuple(
            jnp.zeros((n, m, dims[v.group]), r.dtype) for v in f.variables
        )
        out.append(
            FactorLinearization(
                jnp.zeros((n, m), r.dtype), jacobians, f.variables, type(f).__name__
            )
        )
    return Linearization(tuple(out), layout, jnp.zeros((), _values_dtype(values)))


def _values_dtype(values):
    leaves = jax.tree_util.tree_leaves(values)
    return jnp.result_type(*[leaf.dtype for leaf in leaves])


def zeros_tangent(lin: Linearization) -> Tangent:
    return {g.name: jnp.zeros((g.count, g.dim), lin.dtype) for g in lin.layout}


def apply_jacobian(lin: Linearization, delta: Tangent) -> tuple[Array, ...]:
    """`J δ`, one `(n, m)` array per factor stack."""
    out = []
    for fl in lin.factors:
        acc = jnp.zeros_like(fl.residual)
        for j, var in zip(fl.jacobians, fl.variables):
            acc = acc + einsum("nmd,nd->nm", j, delta[var.group][var.index])
        out.append(acc)
    return tuple(out)


def apply_transpose(lin: Linearization, rows: tuple[Array, ...]) -> Tangent:
    """`Jᵀ y` for per-stack row vectors `y` of shape `(n, m)`."""
    out = zeros_tangent(lin)
    for fl, y in zip(lin.factors, rows):
        for j, var in zip(fl.jacobians, fl.variables):
            contrib = einsum("nmd,nm->nd", j, y)
            out[var.group] = out[var.group].at[var.index].add(contrib)
    return out


def gradient(lin: Linearization) -> Tangent:
    """`Jᵀ r`: the gradient of the cost in tangent coordinates."""
    return apply_transpose(lin, tuple(fl.residual for fl in lin.factors))


def normal_matvec(lin: Linearization, delta: Tangent) -> Tangent:
    """`JᵀJ δ` without forming `JᵀJ`."""
    return apply_transpose(lin, apply_jacobian(lin, delta))


def block_diagonal(lin: Linearization) -> dict[str, Float[Array, "_N _d _d"]]:
    """Diagonal blocks of `JᵀJ`: `{group: (N_g, d_g, d_g)}`."""
    out = {g.name: jnp.zeros((g.count, g.dim, g.dim), lin.dtype) for g in lin.layout}
    for fl in lin.factors:
        for j, var in zip(fl.jacobians, fl.variables):
            out[var.group] = out[var.group].at[var.index].add(block_gram(j, j))
    return out


def flatten_tangent(lin: Linearization, delta: Tangent) -> Float[Array, " N"]:
    """Group-major flat vector (groups in sorted order, variables, coordinates)."""
    return flatten_layout(lin.layout, delta)


def unflatten_tangent(lin: Linearization, flat: Float[Array, " N"]) -> Tangent:
    return unflatten_layout(lin.layout, flat)


def flatten_layout(layout: tuple[GroupLayout, ...], delta: Tangent) -> Array:
    """`flatten_tangent` given only the (static) layout."""
    return jnp.concatenate([delta[g.name].reshape(-1) for g in layout])


def unflatten_layout(layout: tuple[GroupLayout, ...], flat: Array) -> Tangent:
    """The inverse of `flatten_layout`."""
    out, start = {}, 0
    for g in layout:
        size = g.count * g.dim
        out[g.name] = flat[start : start + size].reshape(g.count, g.dim)
        start += size
    return out


def group_offsets(lin: Linearization) -> dict[str, int]:
    offsets, start = {}, 0
    for g in lin.layout:
        offsets[g.name] = start
        start += g.count * g.dim
    return offsets


def dense_jacobian(
    lin: Linearization,
) -> tuple[Float[Array, "M N"], Float[Array, " M"]]:
    """Materialise `J` (group-major columns) and `r`: for small graphs and tests."""
    offsets = group_offsets(lin)
    dims = {g.name: g.dim for g in lin.layout}
    blocks, rs = [], []
    for fl in lin.factors:
        n, m = fl.residual.shape
        rows = jnp.zeros((n, m, lin.num_tangent), lin.dtype)
        for j, var in zip(fl.jacobians, fl.variables):
            cols = _columns(var, offsets, dims)
            rows = _scatter_cols(rows, j, cols)
        blocks.append(rows.reshape(n * m, lin.num_tangent))
        rs.append(fl.residual.reshape(-1))
    return jnp.concatenate(blocks), jnp.concatenate(rs)


def dense_normal_matrix(
    lin: Linearization, damping: Tangent | None = None
) -> Float[Array, "N N"]:
    """`JᵀJ + diag(damping)` as a dense group-major matrix.

    Every factor stack contributes one `(n, K, K)` batch of products of its
    concatenated row Jacobian `[J_1 … J_k]` (`K = Σ d_i`); all entries of all
    stacks are added into the flat `N²` matrix by a single scatter whose
    indices are computed once, at trace time (no `M × N` Jacobian, no
    per-block scatter).
    """
    N = lin.num_tangent
    offsets = group_offsets(lin)
    dims = {g.name: g.dim for g in lin.layout}
    values, indices = [], []
    for fl in lin.factors:
        n = fl.residual.shape[0]
        if n == 0:
            continue
        dynamic = any(v.is_dynamic for v in fl.variables)
        xnp = jnp if dynamic else np
        cols = xnp.concatenate(
            [_columns(v, offsets, dims) for v in fl.variables], axis=1
        )  # (n, K) absolute coordinates touched by each row
        jac = jnp.concatenate(fl.jacobians, axis=2)  # (n, m, K)
        values.append(block_gram(jac, jac).reshape(-1))
        indices.append((cols[:, :, None] * N + cols[:, None, :]).reshape(-1))
    flat = jnp.zeros((N * N,), lin.dtype)
    if values:
        # Static indices are one constant; dynamic ones ride in the program.
        xnp = np if all(isinstance(i, np.ndarray) for i in indices) else jnp
        flat = flat.at[xnp.concatenate(indices)].add(jnp.concatenate(values))
    H = flat.reshape(N, N)
    if damping is not None:
        d = flatten_tangent(lin, {k: v.astype(lin.dtype) for k, v in damping.items()})
        H = H + jnp.diag(d)
    return H


def _columns(var: Var, offsets: dict[str, int], dims: dict[str, int]):
    """`(n, d)` absolute coordinates of each row's variable: numpy for static
    indices, JAX for dynamic ones ([`eqsmooth.factors.Var.dynamic`][])."""
    d = dims[var.group]
    xnp = jnp if var.is_dynamic else np
    return offsets[var.group] + var.index[:, None] * d + xnp.arange(d)[None]


def _scatter_cols(rows, j, cols):
    # rows: (n, m, N); j: (n, m, d); cols: (n, d) absolute column indices.
    n = rows.shape[0]
    return rows.at[jnp.arange(n)[:, None], :, cols].add(jnp.swapaxes(j, 1, 2))


def retract_values(values: dict[str, PyTree], delta: Tangent) -> dict[str, PyTree]:
    """Apply `x ⊕ δ` to every variable of every group."""
    return {
        name: retract(group, delta[name].astype(_values_dtype(group)))
        for name, group in values.items()
    }
