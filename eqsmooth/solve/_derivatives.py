"""Derivatives attached to quantities a solve computes with gradients stopped."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp


def stop_arrays(tree):
    """`tree` with gradients stopped at its array leaves (other leaves kept)."""
    return jax.tree_util.tree_map(
        lambda x: jax.lax.stop_gradient(x) if eqx.is_array(x) else x, tree
    )


def _float_leaves(tree) -> list:
    return [
        x
        for x in jax.tree_util.tree_leaves(tree)
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.inexact)
    ]


def recomputed(problem, value, fn: Callable):
    """`value`, which equals `fn(*problem)`, with the reverse-mode derivative of
    `fn` at `problem` (whatever derivative `value` carried is replaced).

    The forward pass costs nothing; the backward pass differentiates `fn`
    (one more evaluation). Used for what a solver's state keeps, e.g. the
    linearisation at the solution under the implicit adjoint, whose loop
    runs with gradients stopped.
    """
    value = stop_arrays(value)
    return _recomputed(problem, value, fn)


@eqx.filter_custom_vjp
def _recomputed(problem, value, fn):
    del problem, fn
    return value


@_recomputed.def_fwd
def _recomputed_fwd(perturbed, problem, value, fn):
    del perturbed, problem, fn
    return value, None


@_recomputed.def_bwd
def _recomputed_bwd(residuals, grad_value, perturbed, problem, value, fn):
    del residuals
    # Only the inexact array leaves carry derivatives; the output's other
    # leaves (index arrays, static parts) are not differentiated.
    cts = [
        jnp.zeros_like(v) if g is None else g
        for g, v in zip(
            jax.tree_util.tree_leaves(grad_value, is_leaf=lambda x: x is None),
            jax.tree_util.tree_leaves(value, is_leaf=lambda x: x is None),
        )
        if eqx.is_array(v) and jnp.issubdtype(v.dtype, jnp.inexact)
    ]
    _, vjp_fn = eqx.filter_vjp(lambda p: _float_leaves(fn(*p)), problem)
    (grad,) = vjp_fn(cts)
    return jax.tree_util.tree_map(
        lambda g, p: g if p else None, grad, perturbed, is_leaf=lambda x: x is None
    )


def refuse_derivative(witness, x, message: str):
    """`x`, whose reverse-mode derivative raises a `ValueError(message)`.

    For what a solve hands out but cannot differentiate correctly (e.g. the
    costs of intermediate iterates under the implicit adjoint, which only
    knows the solution). `witness` must depend on what is being
    differentiated (so that JAX asks for this derivative at all); the error
    is raised only when a gradient actually reaches `x`.
    """

    def refuse(*_):
        raise ValueError(message)

    return recomputed((witness,), x, refuse)


def checked_derivative(x, aux, fails: Callable, message: str):
    """`x`, whose reverse-mode derivative raises an `EquinoxRuntimeError(message)`
    at run time where `fails(aux)` is true (e.g. an implicit gradient taken
    at a point that is not stationary). The derivative itself is unchanged,
    and `fails` is evaluated in the backward pass only (the forward pass
    costs nothing)."""
    aux = stop_arrays(aux)
    return _checked(x, aux, fails, message)


@eqx.filter_custom_vjp
def _checked(x, aux, fails, message):
    del aux, fails, message
    return x


@_checked.def_fwd
def _checked_fwd(perturbed, x, aux, fails, message):
    del perturbed, aux, fails, message
    return x, None


@_checked.def_bwd
def _checked_bwd(residuals, grad_x, perturbed, x, aux, fails, message):
    del residuals, x
    grad_x = jax.tree_util.tree_map(
        lambda g, p: g if p else None, grad_x, perturbed, is_leaf=lambda y: y is None
    )
    return eqx.error_if(grad_x, fails(aux), message)
