"""The check that the `fn` handed to an eqsmooth solver is the graph's residuals.

eqsmooth's solvers linearise the factor graph passed as optimistix's `args`,
not `fn`, so another `fn` would be silently ignored. `fn_mismatch` proves the
common case at trace time (optimistix's closure-converted copy of
`graph_residuals` is the same program, so the graph route pays nothing at run
time) and otherwise compares `fn` with the graph's residuals at two points.
"""

import equinox as eqx
import jax
import jax.extend.core as jex
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool

from ...factors import FactorGraph
from .._derivatives import stop_arrays
from .._linearization import Linearization, retract_values, Tangent
from ._residuals import graph_residuals, manifold_residuals, residual_rows


def fn_mismatch(
    fn, y, graph: FactorGraph, lin: Linearization, who: str
) -> Bool[Array, ""] | None:
    """Whether `fn(y, graph)` differs from the graph's residuals; None when it
    is proven at trace time to be them.

    Proven when `fn` is `graph_residuals` (or the chart's
    `manifold_residuals`) itself, or optimistix's closure-converted copy of
    one: the same program with the same captured constants, up to optimistix's
    identity casts of the outputs. Otherwise its shapes are checked at trace
    time and its values at run time at two points, the initial values `y` and
    `y ⊕ u` with `u` a fixed pseudo-random tangent perturbation (entries up
    to 0.15), so that a function that agrees with the graph at `y` only is
    caught. No option skips the check.
    """
    if fn is graph_residuals or fn is manifold_residuals:
        return None
    if _same_program(fn, y, graph):
        return None
    y, graph = stop_arrays((y, graph))
    hint = (
        f"{who} solves the factor graph passed as args, so its fn must be "
        "eqsmooth.solve.graph_residuals (the graph's own residuals); for another "
        "residual function use optimistix's solvers, or "
        "eqsmooth.solve.tangent_least_squares for Lie-group values"
    )
    bad = jnp.array(False)
    for point in (y, retract_values(y, _probe_tangent(lin))):
        got, want = _fn_output(fn, point, graph), residual_rows(point, graph)
        if len(got) != len(want) or any(
            jnp.shape(a) != jnp.shape(b) for a, b in zip(got, want)
        ):
            raise ValueError(
                f"{hint}; fn returned shapes {[jnp.shape(a) for a in got]}, the "
                f"graph's residuals have shapes {[jnp.shape(b) for b in want]}"
            )
        bad = bad | _differ(got, want)
    return bad


def _same_program(fn, y, graph: FactorGraph) -> bool:
    """Whether the closure-converted `fn` (`(y, args) ↦ (residuals, aux)`) is
    `graph_residuals` or `manifold_residuals`, read off its jaxpr."""
    jaxpr = getattr(fn, "jaxpr", None)
    if not isinstance(jaxpr, jex.Jaxpr):
        return False
    consts = jax.tree_util.tree_leaves(getattr(fn, "consts", None))
    for reference in (graph_residuals, manifold_residuals):
        want, _, _ = eqx.filter_make_jaxpr(lambda v, a: (reference(v, a), None))(
            y, graph
        )
        if _same_constants(consts, want.consts) and _passes_through(jaxpr, want.jaxpr):
            return True
    return False


def _same_constants(got: list, want: list) -> bool:
    """Whether two jaxprs' captured constants are the same concrete arrays
    (the library's own constants, e.g. an identity matrix; a captured
    tracer, such as a closed-over traced value, never is)."""
    if len(got) != len(want):
        return False
    for a, b in zip(got, want):
        if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
            return False
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape or a.dtype != b.dtype:
            return False
        if not np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"):
            return False
    return True


def _passes_through(got: jex.Jaxpr, want: jex.Jaxpr) -> bool:
    """Whether `got` is `want` followed only by identity calls on its
    outputs (optimistix casts every output with a `custom_jvp` whose primal is
    the identity when the dtype is already inexact)."""
    n = len(want.eqns)
    if len(got.eqns) < n:
        return False
    source = {}
    for eqn in got.eqns[n:]:
        inner = eqn.params.get("call_jaxpr")
        inner = getattr(inner, "jaxpr", inner)
        identity = (
            isinstance(inner, jex.Jaxpr)
            and not inner.eqns
            and len(eqn.invars) == len(eqn.outvars) == 1
            and list(inner.outvars) == list(inner.invars)
        )
        if not identity:
            return False
        source[eqn.outvars[0]] = eqn.invars[0]
    outvars = [source.get(v, v) for v in got.outvars]
    trimmed = got.replace(eqns=got.eqns[:n], outvars=outvars)
    return str(trimmed) == str(want)


def _probe_tangent(lin: Linearization) -> Tangent:
    """A fixed, deterministic tangent perturbation with entries in
    [-0.15, 0.15] (a low-discrepancy sequence: no PRNG in the program)."""
    out, offset = {}, 0
    for g in lin.layout:
        n = g.count * g.dim
        k = jnp.arange(offset, offset + n, dtype=lin.dtype) + 1.0
        out[g.name] = (0.15 * jnp.sin(2.399963 * k)).reshape(g.count, g.dim)
        offset += n
    return out


def _fn_output(fn, y, graph) -> list:
    out = fn(y, graph)
    want = eqx.filter_eval_shape(residual_rows, y, graph)
    # optimistix wraps `fn` so that it returns `(residuals, aux)`.
    wrapped = isinstance(out, tuple) and len(out) == 2
    if wrapped and jax.tree_util.tree_structure(out) != jax.tree_util.tree_structure(
        want
    ):
        out = out[0]
    return jax.tree_util.tree_leaves(out)


def _differ(got: list, want: tuple) -> Bool[Array, ""]:
    """Whether two lists of residual arrays differ beyond `√ε` (relative to the
    largest finite entry); entries non-finite in both the same way agree."""
    dtype = jnp.result_type(*want)
    tol = float(np.sqrt(np.finfo(dtype).eps))
    bad = jnp.array(False)
    for a, b in zip(got, want):
        same = (a == b) | (jnp.isnan(a) & jnp.isnan(b))
        gap = jnp.where(same, 0.0, jnp.abs(a - b))
        finite_b = jnp.where(jnp.isfinite(b), jnp.abs(b), 0.0)
        scale = 1.0 + jnp.max(finite_b, initial=0.0)
        bad = bad | ~(jnp.max(gap, initial=0.0) <= tol * scale)
    return bad
