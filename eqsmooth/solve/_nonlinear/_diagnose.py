"""The detail of a failed solve's error, found on the host after the solve:
which factor rows are not finite (`RESULTS.nonfinite_problem`), whether a
singular system is a missing prior or float32 ill-conditioning
(`RESULTS.linear_solve_failed`), and where a diverged solve's first step led
(`RESULTS.nonlinear_divergence`)."""

import jax
import numpy as np
from jaxtyping import PyTree

from ...factors import FactorGraph
from .._linearization import (
    dense_jacobian,
    group_offsets,
    linearize,
    retract_values,
    unflatten_tangent,
)
from .._solution import result_index, RESULTS


def _rows(mask: np.ndarray) -> str:
    rows = np.flatnonzero(mask)
    more = f" and {rows.size - 8} more" if rows.size > 8 else ""
    return f"{rows[:8].tolist()}{more}"


def nonfinite_rows(graph: FactorGraph, values: dict[str, PyTree]) -> str:
    """The initial values and factor rows that are not finite, in words.

    Called only after a solve failed with `RESULTS.nonfinite_problem`, on
    concrete values: it linearises once more (one compilation, on the
    failure path only) and names each factor stack's rows with a non-finite
    residual or Jacobian, with the factor's
    `nonfinite_hint` (a class attribute of the factor).
    """
    parts = []
    for name, group in values.items():
        for leaf in jax.tree_util.tree_leaves(group):
            leaf = np.asarray(leaf)
            bad = ~np.isfinite(leaf.reshape(leaf.shape[0], -1)).all(axis=1)
            if bad.any():
                parts.append(f"values[{name!r}] rows {_rows(bad)} are not finite")
                break
    lin = linearize(graph, values)
    for k, (f, fl) in enumerate(zip(graph.factors, lin.factors)):
        residual = ~np.isfinite(np.asarray(fl.residual)).all(axis=1)
        jacobian = np.zeros_like(residual)
        for j in fl.jacobians:
            jacobian |= ~np.isfinite(np.asarray(j)).all(axis=(1, 2))
        jacobian &= ~residual
        where = f"{type(f).__name__} (factor stack {k})"
        for what, bad in (("residual", residual), ("Jacobian", jacobian)):
            if bad.any():
                variables = ", ".join(
                    f"{v.group}[{int(np.asarray(v.index)[np.flatnonzero(bad)[0]])}]"
                    for v in f.variables
                )
                hint = f.nonfinite_hint
                parts.append(
                    f"{where}: non-finite {what} in rows {_rows(bad)} (first row "
                    f"touches {variables})" + (f"; {hint}" if hint else "")
                )
    return "; ".join(parts)


# Dense eigenvalues of the normal matrix only for small problems.
_MAX_DENSE = 3000


def singular_detail(graph: FactorGraph, values: dict[str, PyTree]) -> str:
    """Whether the normal matrix at the initial values is singular (a gauge
    freedom: which variables the null direction moves) or only ill-conditioned
    for the values' dtype, from its eigenvalues computed in float64 on the host
    (problems of up to 3000 tangent dimensions)."""
    lin = linearize(graph, values)
    if lin.num_tangent > _MAX_DENSE or not np.all(np.isfinite(np.asarray(lin.cost))):
        return ""
    J, _ = dense_jacobian(lin)
    J = np.asarray(J, np.float64)
    if not np.isfinite(J).all():
        return ""
    w, v = np.linalg.eigh(J.T @ J)
    top = max(float(w[-1]), 1e-300)
    if w[0] <= 1e-12 * top:
        # The null direction's largest entries: the variables it moves.
        names = []
        offsets = group_offsets(lin)
        for g in lin.layout:
            start = offsets[g.name]
            block = np.abs(v[start : start + g.count * g.dim, 0]).reshape(
                g.count, g.dim
            )
            for i in np.flatnonzero(block.max(axis=1) > 0.5 * np.abs(v[:, 0]).max()):
                names.append(f"{g.name}[{int(i)}]")
        count = int(np.sum(w <= 1e-12 * top))
        return (
            f"At the initial values the normal matrix is singular in float64 too "
            f"({count} unconstrained direction(s), moving {', '.join(names[:6])}"
            f"{' ...' if len(names) > 6 else ''}): a gauge freedom or a variable "
            "without enough factors; add a prior or the missing measurements."
        )
    condition = top / float(w[0])
    eps = float(np.finfo(lin.dtype).eps)
    if condition * eps > 1e-2:
        return (
            f"At the initial values the normal matrix is positive definite in "
            f"float64 but its condition number is {condition:.1e}, too large for "
            f"{np.dtype(lin.dtype).name} (precision {eps:.1e}): not a missing "
            "prior but ill-conditioning (noise scales several orders of magnitude "
            "apart); solve in float64 (jax.config.update('jax_enable_x64', True) "
            "and values and noise in float64)."
        )
    return ""


def divergence_detail(graph: FactorGraph, values: dict[str, PyTree]) -> str:
    """Where a diverged solve went: the first Gauss-Newton step from the
    (finite) initial values, computed densely in float64 on the host
    (problems of up to 3000 tangent dimensions), and the factor rows that are
    not finite there."""
    lin = linearize(graph, values)
    if lin.num_tangent > _MAX_DENSE or not np.all(np.isfinite(np.asarray(lin.cost))):
        return ""
    J, r = (np.asarray(a, np.float64) for a in dense_jacobian(lin))
    if not (np.isfinite(J).all() and np.isfinite(r).all()):
        return ""
    step = -np.linalg.lstsq(J, r, rcond=None)[0]
    moved = retract_values(values, unflatten_tangent(lin, jax.numpy.asarray(step)))
    where = nonfinite_rows(graph, moved)
    if not where:
        return ""
    return (
        "The initial values are finite, but the first Gauss-Newton step from them "
        f"leads where {where}. A residual undefined there (a square root or "
        "logarithm of a negative number, a division by zero) or a step too long "
        "for the model: start closer, use LevenbergMarquardt (its damping "
        "shortens such steps), or make the residual defined everywhere."
    )


def failure_detail(
    graph: FactorGraph, values: dict[str, PyTree], result: RESULTS
) -> str:
    """The detail of a failed solve's error (empty when there is nothing to add)."""
    code = np.asarray(result_index(result))
    for kind, detail in (
        (RESULTS.nonfinite_problem, nonfinite_rows),
        (RESULTS.linear_solve_failed, singular_detail),
        (RESULTS.nonlinear_divergence, divergence_detail),
    ):
        if np.all(code == np.asarray(result_index(kind))):
            return detail(graph, values)
    return ""
