"""Small helpers shared by the solvers: tangent-dict arithmetic and one PCG."""

from collections.abc import Callable

import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PyTree

from ._linearization import gradient, Linearization, Tangent


def all_arrays(tree) -> bool:
    """Whether every leaf is an array (JAX or numpy): arguments that a
    `jax.jit` entry point takes as they are (it traces both kinds and
    transfers numpy ones in C++), where `eqx.filter_jit` would be needed for
    Python scalars and other non-array leaves."""
    return all(
        isinstance(x, (jax.Array, np.ndarray)) for x in jax.tree_util.tree_leaves(tree)
    )


def tree_where(pred, a, b):
    """`jnp.where(pred, a, b)` leaf by leaf."""
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


@jax.custom_jvp
def _nan_derivative_leaf(failed, x, witness):
    return x


@_nan_derivative_leaf.defjvp
def _nan_derivative_leaf_jvp(primals, tangents):
    failed, x, witness = primals
    _, t_x, t_witness = tangents
    # Linear in the tangents: NaN times each of them where `failed`.
    scale = jnp.where(failed, jnp.nan, 1.0).astype(x.dtype)
    poison = jnp.where(failed, jnp.nan, 0.0).astype(x.dtype)
    return x, scale * t_x + poison * t_witness.astype(x.dtype)


def nan_derivative_if(failed, tree, witness):
    """`tree` unchanged, with NaN derivatives (forward and reverse) where
    `failed` is true: a step that was rejected because a solve failed has no
    meaningful derivative, and a zero or stale one would look plausible.

    `witness` is a scalar that depends on whatever is being differentiated
    (e.g. the cost of the linearisation), so that the derivative is NaN even
    where `tree` itself does not depend on it (a rejected first step leaves
    the initial values, which are constants).
    """
    return jax.tree_util.tree_map(
        lambda x: _nan_derivative_leaf(failed, x, witness), tree
    )


def max_abs(tree) -> Float[Array, ""]:
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.max(jnp.stack([jnp.max(jnp.abs(x)) for x in leaves]))


def sq_norm(tree) -> Float[Array, ""]:
    return sum(jnp.sum(x * x) for x in jax.tree_util.tree_leaves(tree))  # pyright: ignore[reportReturnType]


def dot(a: Tangent, b: Tangent) -> Float[Array, ""]:
    return sum(jnp.sum(a[k] * b[k]) for k in a)  # pyright: ignore[reportReturnType]


def axpy(alpha, x: Tangent, y: Tangent) -> Tangent:
    """`alpha x + y`."""
    return {k: y[k] + alpha * x[k] for k in y}


def tree_dot(a: PyTree[Array], b: PyTree[Array]) -> Float[Array, ""]:
    """`Σ aᵢ bᵢ` over every leaf of two pytrees of the same structure (real)."""
    products = jax.tree_util.tree_map(lambda x, y: jnp.sum(x * y), a, b)
    return sum(jax.tree_util.tree_leaves(products))  # pyright: ignore[reportReturnType]


def tree_axpy(alpha, x: PyTree[Array], y: PyTree[Array]) -> PyTree[Array]:
    """`alpha x + y` leaf by leaf."""
    return jax.tree_util.tree_map(lambda u, v: v + alpha * u, x, y)


def finite_lin(lin: Linearization) -> Bool[Array, ""]:
    """Whether the cost, every residual and every Jacobian block are finite."""
    ok = jnp.isfinite(lin.cost)
    for fl in lin.factors:
        ok = ok & jnp.all(jnp.isfinite(fl.residual))
        for j in fl.jacobians:
            ok = ok & jnp.all(jnp.isfinite(j))
    return ok


def preconditioned_cg(
    matvec: Callable[[PyTree[Array]], PyTree[Array]],
    precondition: Callable[[PyTree[Array]], PyTree[Array]],
    b: PyTree[Array],
    rtol,
    atol,
    max_steps: int,
    flexible: bool = False,
):
    """Solve `A x = b` for symmetric positive (semi)definite `A` by PCG.

    `b` and `x` are any pytrees of arrays (a tangent dict, one array, a dict
    of arrays): vector operations are tree-mapped, so `A` may be any lineax
    operator's `mv`.

    Stops when `‖b − A x‖₂ ≤ max(rtol‖b‖₂, atol)` (the Euclidean norm, the
    usual inexact-Newton criterion, rather than lineax's per-component test),
    after `max_steps` iterations, or on breakdown (a search direction of
    non-positive or non-finite curvature: `A` singular or indefinite along
    it), keeping the last iterate. `flexible=True` uses the Polak-Ribière
    form of `β`, which tolerates a preconditioner that varies slightly from
    call to call (an inner iterative solve).

    Returns `(x, converged, breakdown, num_steps)`.
    """
    x0 = jax.tree_util.tree_map(jnp.zeros_like, b)
    bnorm = jnp.sqrt(tree_dot(b, b))
    dtype = bnorm.dtype
    tol = jnp.maximum(jnp.asarray(rtol, dtype) * bnorm, jnp.asarray(atol, dtype))
    z0 = precondition(b)
    rz0 = tree_dot(b, z0)

    def cond(carry):
        _, r, _, _, _, k, breakdown = carry
        rnorm = jnp.sqrt(tree_dot(r, r))
        return (rnorm > tol) & (k < max_steps) & ~breakdown

    def body(carry):
        x, r, z, p, rz, k, _ = carry
        ap = matvec(p)
        pap = tree_dot(p, ap)
        breakdown = ~(jnp.isfinite(pap) & (pap > 0) & jnp.isfinite(rz))
        alpha = jnp.where(breakdown, 0.0, rz / jnp.where(breakdown, 1.0, pap))
        x = tree_axpy(alpha, p, x)
        r_new = tree_axpy(-alpha, ap, r)
        z_new = precondition(r_new)
        rz_new = tree_dot(r_new, z_new)
        if flexible:
            num = tree_dot(z_new, jax.tree_util.tree_map(jnp.subtract, r_new, r))
        else:
            num = rz_new
        beta = num / jnp.where(rz == 0, 1.0, rz)
        p = tree_axpy(beta, p, z_new)
        return x, r_new, z_new, p, rz_new, k + 1, breakdown

    init = (x0, b, z0, z0, rz0, jnp.asarray(0), jnp.asarray(False))
    x, r, _, _, _, k, breakdown = lax.while_loop(cond, body, init)
    converged = jnp.sqrt(tree_dot(r, r)) <= tol
    return x, converged, breakdown, k


def converged_test(old_cost, new_lin: Linearization, delta: Tangent, ftol, gtol, xtol):
    """Ceres-like convergence: relative cost change, largest gradient or step entry."""
    finfo = jnp.finfo(new_lin.dtype)
    rel = jnp.abs(old_cost - new_lin.cost) / jnp.maximum(old_cost, finfo.tiny)
    # A relative change below a few ulps is rounding: never ask for less.
    ftol = jnp.where(ftol > 0, jnp.maximum(ftol, 4 * finfo.eps), ftol)
    gnorm = max_abs(gradient(new_lin))
    xnorm = max_abs(delta)
    return (rel <= ftol) | (gnorm <= gtol) | (xnorm <= xtol)


def stationary(lin: Linearization) -> Bool[Array, ""]:
    """Whether the gradient `Jᵀr` of a linearisation vanishes to rounding level
    (`max |Jᵀr| ≤ √ε · max(1, 2 cost)`): where an implicit derivative holds."""
    eps = jnp.finfo(lin.dtype).eps
    tol = jnp.sqrt(eps) * jnp.maximum(1.0, 2.0 * lin.cost)
    return max_abs(gradient(lin)) <= tol
