"""Shared by the posterior routes (marginals, joint marginals): the
linearisation a `Solution` keeps, and the error for a matrix that cannot be
factorised."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._linearization import Linearization
from .._solution import Solution


def as_linearization(
    lin_or_solution: Linearization | Solution, who: str
) -> Linearization:
    """The linearisation held by a solve's final state, or `lin` itself."""
    if isinstance(lin_or_solution, Linearization):
        return lin_or_solution
    if isinstance(lin_or_solution, Solution):
        lin = getattr(lin_or_solution.state, "lin", None)
        if isinstance(lin, Linearization):
            return lin
        raise TypeError(
            f"{who}: this Solution's state ({type(lin_or_solution.state).__name__}) "
            "keeps no linearisation; pass eqsmooth.linearize(graph, sol.value)"
        )
    raise TypeError(
        f"{who}: expected a Linearization or a Solution, got "
        f"{type(lin_or_solution).__name__}"
    )


def real_counts(lin_or_solution: Linearization | Solution) -> dict[str, int] | None:
    """`{group: real variables}` of a `Solution` solved on a padded copy of
    its graph (its linearisation's groups hold them first), else `None`."""
    if isinstance(lin_or_solution, Solution) and lin_or_solution.padding:
        return dict(lin_or_solution.padding)
    return None


def take_real(blocks: dict, counts: dict[str, int] | None) -> dict:
    """The real variables' rows of per-variable `blocks` (host slicing of
    concrete arrays: compiles nothing)."""
    if counts is None:
        return blocks
    out = {}
    for name, a in blocks.items():
        if isinstance(a, jax.core.Tracer):
            out[name] = a[: counts[name]]
        else:
            out[name] = jax.device_put(np.asarray(a)[: counts[name]])
    return out


def singular_message(who: str, dtype) -> str:
    """What a failed factorisation of `JᵀJ` means, for the marginal routes."""
    message = (
        f"{who}: the normal matrix JᵀJ could not be factorised: it is singular "
        "(a gauge freedom not fixed by a prior: every variable group needs one, "
        "e.g. a PriorFactor on the first pose), so some marginal covariance is "
        "infinite"
    )
    if jnp.dtype(dtype) == jnp.float32:
        message += (
            ", or too ill-conditioned for float32 (noise scales that differ by "
            "several orders of magnitude, e.g. sigma 1e-3 against 10, exceed its "
            "precision: enable float64 with "
            "jax.config.update('jax_enable_x64', True) and float64 values)"
        )
    return message


def raise_unless_ok(ok, out, message: str):
    """`out`, after raising `EquinoxRuntimeError(message)` where `ok` is false.

    Concrete (called outside `jit`): checked on the host, so the error is
    the message alone. Traced: an `eqx.error_if` joins the caller's program.
    """
    try:
        ok = np.asarray(ok)
    except jax.errors.TracerArrayConversionError:
        return eqx.error_if(out, ~ok, message)
    if not np.all(ok):
        raise eqx.EquinoxRuntimeError(message)
    return out
