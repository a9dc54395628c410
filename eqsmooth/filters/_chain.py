"""A chain of factor stacks as the sequential estimators read it.

The extended Kalman filter and the fixed-lag smoother take the same
arguments: a transition stack whose rows link `x_t` to `x_{t+1}` and
measurement stacks touching one state each. This module holds what both
need of them: the checks (a chain, measurements on its group, the initial
covariance's shape), the time order of the transition rows, the measurement
rows as layers over time, the residual size of a row, and the forward-mode
Jacobian both linearise with.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, PyTree

from ..factors import AbstractFactor
from ..manifold import is_group
from ._rows import check_gaussian, check_rows, with_rows


def value_and_jacobian(fn, dim: int, dtype):
    """`fn(0)` and its Jacobian at `0` for `fn` of a `dim`-vector."""
    # One primal evaluation, then the identity pushed through the JVP
    # (forward mode, as the smoother's linearisation does).
    zero = jnp.zeros((dim,), dtype=dtype)
    r, jvp = jax.linearize(fn, zero)
    J = jax.vmap(jvp, in_axes=1, out_axes=1)(jnp.eye(dim, dtype=dtype))
    return r, J


def chain_order(transition: AbstractFactor) -> tuple[str, np.ndarray]:
    """The chain's variable group and the transition's rows in time order,
    or a `ValueError` if its rows do not link `t` to `t + 1` once each."""
    name = type(transition).__name__
    if len(transition.variables) != 2:
        raise ValueError(
            f"ekf: the transition factor {name} must touch two variables "
            f"(x_t, x_t+1); it touches {len(transition.variables)}"
        )
    va, vb = transition.variables
    if va.group != vb.group:
        raise ValueError(
            f"ekf: the transition factor {name} links groups {va.group!r} and "
            f"{vb.group!r}; both variables must be in one group"
        )
    ia, ib = va.ids, vb.ids
    n = ia.shape[0]
    if n == 0:
        raise ValueError(f"ekf: the transition factor {name} has no rows")
    perm = np.argsort(ia, kind="stable")
    if not (np.array_equal(ia[perm], np.arange(n)) and np.array_equal(ib, ia + 1)):
        raise ValueError(
            f"ekf: the transition factor {name} must form a chain: each row touches "
            f"({va.group}[t], {va.group}[t+1]) and every t = 0..{n - 1} appears "
            f"exactly once; got rows {ia[:4].tolist()} -> {ib[:4].tolist()}"
            + (" ..." if n > 4 else "")
        )
    return va.group, perm


def time_layers(ids: np.ndarray, T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-row layer (occurrence number of its time step), table and mask.

    `table[t, k]` is the row holding the k-th measurement of time `t` (0 where
    there is none) and `mask[t, k]` whether it exists.
    """
    n = ids.shape[0]
    order = np.argsort(ids, kind="stable")
    sorted_ids = ids[order]
    first = np.searchsorted(sorted_ids, sorted_ids, side="left")
    layer = np.empty(n, dtype=np.int64)
    layer[order] = np.arange(n) - first
    L = int(layer.max()) + 1
    table = np.zeros((T, L), dtype=np.int64)
    mask = np.zeros((T, L), dtype=bool)
    table[ids, layer] = np.arange(n)
    mask[ids, layer] = True
    return layer, table, mask


def residual_dim(factor: AbstractFactor, rows, *states) -> int:
    """The residual size of one row of `factor` at `states`, or a
    `ValueError` saying the initial mean is the likely cause."""
    row0 = jax.tree_util.tree_map(lambda a: a[0] if eqx.is_array(a) else a, rows)

    def fn(rows0, *xs):
        return with_rows(factor, rows0).residual(*xs)

    name = type(factor).__name__
    try:
        out = eqx.filter_eval_shape(fn, row0, *states)
    except (TypeError, ValueError, IndexError) as e:
        # A mean of the wrong size or type fails deep inside the user's
        # residual; say that the initial mean is the likely cause.
        raise ValueError(
            f"ekf: factor {name} cannot be evaluated at initial_mean "
            f"({_describe(states[0])}); initial_mean must be one state of the "
            f"chain's group, of the type and size the factor's residual expects. "
            f"The residual raised {type(e).__name__}: {e}"
        ) from e
    if not isinstance(out, jax.ShapeDtypeStruct) or len(out.shape) != 1:
        shape = getattr(out, "shape", type(out).__name__)
        raise ValueError(
            f"ekf: {name}.residual must return a 1-D array, got {shape} at "
            f"initial_mean ({_describe(states[0])}); initial_mean is one state, "
            "without a time axis"
        )
    return out.shape[0]


def _describe(state: PyTree) -> str:
    leaves = jax.tree_util.tree_leaves(state, is_leaf=is_group)
    parts = [
        f"{type(x).__name__} of shape {tuple(x.parameters().shape)}"
        if is_group(x)
        else f"array of shape {tuple(jnp.shape(x))}"
        for x in leaves
    ]
    if len(leaves) == 1 and (is_group(state) or eqx.is_array(state)):
        return parts[0]
    return f"{type(state).__name__} of " + ", ".join(parts) if parts else "empty"


def checked_covariance(who: str, cov: ArrayLike, d: int) -> Array:
    """`cov` as an array of shape `(d, d)`, else a `ValueError` naming `who`."""
    cov = jnp.asarray(cov)
    if cov.shape != (d, d):
        raise ValueError(
            f"{who}: initial_covariance has shape {cov.shape}; the state has "
            f"tangent dimension {d}, so it must be ({d}, {d})"
        )
    return cov


def check_smoother_noise(noise, where: str, *, maskable: bool) -> None:
    """Gaussian noise for the fixed-lag smoother; a row mask
    ([`eqsmooth.factors.MaskedNoise`][]) where `maskable` (measurements and
    closures). A masked row whitens to a zero square-root information, so its
    residual and Jacobian are zero in every window and marginal: it adds
    exactly what a dropped row adds, nothing."""
    if noise.is_gaussian and noise.active_rows() is not None:
        if maskable:
            return  # MaskedNoise checks that its base is Gaussian
        raise TypeError(
            f"{where}: the transition's rows cannot be masked (MaskedNoise): each "
            "step's transition predicts the new state, so every step needs one. "
            "Mask a missing measurement or closure instead"
        )
    check_gaussian(noise, where)


def checked_measurements(
    transition, measurements, *, maskable: bool = False
) -> tuple[AbstractFactor, ...]:
    """The measurement stacks as a tuple, each checked against the chain
    (masked rows allowed in the measurements where `maskable`: the
    fixed-lag smoother)."""
    if isinstance(measurements, AbstractFactor):
        measurements = (measurements,)
    measurements = tuple(measurements)
    for f in measurements:
        if not isinstance(f, AbstractFactor):
            raise TypeError(
                f"ekf: measurements must be AbstractFactor stacks, got "
                f"{type(f).__name__}"
            )
    group, _ = chain_order(transition)
    T = transition.num_rows + 1
    for f in measurements:
        name = type(f).__name__
        if len(f.variables) != 1:
            raise ValueError(
                f"ekf: measurement factor {name} must touch one variable (x_t); it "
                f"touches {len(f.variables)}"
            )
        var = f.variables[0]
        if len(var) == 0:
            raise ValueError(f"ekf: measurement factor {name} has no rows")
        if var.group != group:
            raise ValueError(
                f"ekf: measurement factor {name} touches group {var.group!r} but the "
                f"transition factor {type(transition).__name__} is on group "
                f"{group!r}"
            )
        if len(var) and var.ids.max() >= T:
            raise ValueError(
                f"ekf: measurement factor {name} has time indices up to "
                f"{int(var.ids.max())}, but the transition defines only {T} states"
            )
    for f in (transition,) + measurements:
        check_rows(f)
        where = f"ekf: factor {type(f).__name__}"
        if maskable:
            check_smoother_noise(f.noise, where, maskable=f is not transition)
        else:
            check_gaussian(f.noise, where)
    return measurements
