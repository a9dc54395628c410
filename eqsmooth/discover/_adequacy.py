"""Adequacy of a named model: does a flexible alternative still find structure?

After `name` has fitted its candidates, a wrong smooth candidate can absorb
much of an effect the library does not contain (an input saturation fitted
as a sensor scale, a dead zone as an actuator gain) and leave innovations
clean enough for the residual diagnostics. The test here asks the data
directly: add a nonparametric term (piecewise-linear "hat" functions of
one state or input, on one equation) for every variable and every equation
the named candidates act on, and score-test them at zero, at the named
model's fit. A significant score means the named term does not have the
shape the data ask for there, and says where the difference sits.
"""

import dataclasses
import math
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._candidates import Candidate
from ._fit import _eval_feature, evaluate, EVALUATION_ERRORS, feature_scales
from ._integrator import Integrator
from ._model import ChainModel, Sequences
from ._score import score_test
from ._stats import normal_quantile


# Knots of the hat functions: quantiles of the variable over the smoothed
# states (inputs), inner ones at the quartiles, outer ones just inside the
# range so that a few outlying states do not stretch the first and last hat.
_KNOT_QUANTILES = (0.02, 0.25, 0.5, 0.75, 0.98)
_NUM_KNOTS = len(_KNOT_QUANTILES)


@dataclasses.dataclass(frozen=True)
class _Hat:
    """Hat function `b` of a variable, on one equation (a unit vector of
    length `dim`). The knots are not constants of the feature (that would make
    every data set a new program): they arrive as input channels
    `u[knot_at : knot_at + NUM_KNOTS]`, constant over time. The first and last
    hats stay at 1 beyond the outer knots."""

    dim: int
    equation: int
    source: str  # "x" or "u"
    index: int
    knot_at: int
    b: int

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " k"]) -> Array:
        s = (x if self.source == "x" else u)[self.index]
        k = [u[self.knot_at + i] for i in range(_NUM_KNOTS)]
        b = self.b
        if b == 0:
            w = jnp.clip((k[1] - s) / (k[1] - k[0]), 0.0, 1.0)
        elif b == _NUM_KNOTS - 1:
            w = jnp.clip((s - k[-2]) / (k[-1] - k[-2]), 0.0, 1.0)
        else:
            up = (s - k[b - 1]) / (k[b] - k[b - 1])
            down = (k[b + 1] - s) / (k[b + 1] - k[b])
            w = jnp.maximum(jnp.minimum(up, down), 0.0)
        unit = np.zeros(self.dim)
        unit[self.equation] = 1.0
        return w * jnp.asarray(unit, x.dtype)


@dataclasses.dataclass(frozen=True)
class _FirstInputs:
    """`fn(x, u[:k], *rest)`: a model function or feature that sees only the
    model's own inputs, not the knot channels appended after them."""

    fn: Callable
    k: int

    def __call__(self, x, u, *rest):
        return self.fn(x, u[: self.k], *rest)


def _knots(values: np.ndarray) -> tuple[float, ...] | None:
    """Quantile knots of `values`, or None when the variable hardly varies."""
    q = np.quantile(values, _KNOT_QUANTILES)
    spread = q[-1] - q[0]
    if not np.isfinite(spread) or spread <= 1e-9 * max(1.0, float(np.max(np.abs(q)))):
        return None
    if np.any(np.diff(q) <= 1e-6 * spread):
        # A variable with a few discrete values (a switched input): evenly
        # spaced knots over its range instead.
        q = np.linspace(q[0], q[-1], len(_KNOT_QUANTILES))
    return tuple(float(v) for v in q)


def _named_equations(model, data, xhat, acting) -> list[tuple[str, int, int]]:
    """The equations (target, row, length) on which the candidates `acting`
    act: the rows where their features are not zero at the MAP states."""
    n, m = xhat.shape[-1], int(data.measurements.shape[-1])
    x = np.asarray(xhat).reshape(-1, n)
    u = np.asarray(data.inputs).reshape(-1, data.inputs.shape[-1])
    rows = set()
    for j in acting:
        c = model.candidates[j]
        f = np.asarray(_eval_feature(c.feature, x, u))
        nonzero = np.flatnonzero(np.any(f != 0, axis=0))
        target = "measurement" if c.target == "measurement" else "dynamics"
        rows.update((target, int(r)) for r in nonzero)
    return [(t, r, m if t == "measurement" else n) for t, r in sorted(rows)]


def _region(knots, z, z_crit) -> list[list[float | None]]:
    """Intervals of the variable nearest to the knots of the hats with
    `|z| ≥ z_crit` (from half-way to the previous knot to half-way to the
    next, the outer ones open-ended), merged; the largest hat's interval when
    none passes."""
    z = np.asarray(z)
    flagged = np.flatnonzero(np.abs(z) >= z_crit)
    if not len(flagged) and np.all(np.isfinite(z)):
        flagged = [int(np.argmax(np.abs(z)))]
    last = len(knots) - 1
    spans = sorted(
        (
            -math.inf if b == 0 else 0.5 * (knots[b - 1] + knots[b]),
            math.inf if b == last else 0.5 * (knots[b] + knots[b + 1]),
        )
        for b in flagged
    )
    merged: list[list[float]] = []
    for lo, hi in spans:
        if merged and lo <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], hi)
        else:
            merged.append([lo, hi])
    # Open ends as None (JSON has no infinity).
    return [[v if math.isfinite(v) else None for v in span] for span in merged]


def describe_region(variable: str, region: list[list[float | None]]) -> str:
    """`"x0 ≤ -3.1 or x0 ≥ 4.2"` for the intervals of `_region`."""
    parts = []
    for lo, hi in region:
        if lo is None and hi is None:
            parts.append(f"all {variable}")
        elif lo is None:
            parts.append(f"{variable} ≤ {hi:.3g}")
        elif hi is None:
            parts.append(f"{variable} ≥ {lo:.3g}")
        else:
            parts.append(f"{lo:.3g} ≤ {variable} ≤ {hi:.3g}")
    return " or ".join(parts)


def _augmented(model, data, xhat, acting):
    """The model with the hat library appended to its candidates, the data
    with the knots appended to its inputs, and where each hat sits."""
    inputs = np.asarray(data.inputs)
    n, k = xhat.shape[-1], inputs.shape[-1]
    variables = [("x", i, xhat[..., i].ravel()) for i in range(n)]
    variables += [("u", j, inputs[..., j].ravel()) for j in range(k)]
    equations = _named_equations(model, data, xhat, acting)
    hats, where, knot_channels = [], [], []
    for source, index, values in variables:
        knots = _knots(values)
        if knots is None:
            continue
        knot_at = k + len(knot_channels)
        knot_channels.extend(knots)
        for target, eq, dim in equations:
            block = f"{source}{index} on " + (
                f"x{eq}'" if target == "dynamics" else f"y{eq}"
            )
            for b, knot in enumerate(knots):
                hats.append(
                    Candidate(
                        f"[hat {b} of {block}]",
                        _Hat(dim, eq, source, index, knot_at, b),
                        target=target,
                    )
                )
                where.append(
                    {
                        "block": block,
                        "equation": block.split(" on ")[1],
                        "variable": f"{source}{index}",
                        "near": knot,
                        "knots": list(knots),
                    }
                )
    if not hats:
        return None
    dynamics = model.dynamics
    if isinstance(dynamics, Integrator):
        dynamics = dataclasses.replace(
            dynamics, vector_field=_FirstInputs(dynamics.vector_field, k)
        )
    else:
        dynamics = _FirstInputs(dynamics, k)
    own = tuple(
        dataclasses.replace(c, feature=_FirstInputs(c.feature, k))
        for c in model.candidates
    )
    augmented = dataclasses.replace(
        model,
        dynamics=dynamics,
        candidates=own + tuple(hats),
        coefficients=np.concatenate([model.coefficients, np.zeros(len(hats))]),
    )
    B, T = inputs.shape[:2]
    knot_inputs = np.broadcast_to(np.asarray(knot_channels), (B, T, len(knot_channels)))
    augmented_data = Sequences(
        data.measurements,
        data.x0_mean,
        np.concatenate([inputs, knot_inputs], axis=-1),
        data.initial_states,
    )
    return augmented, augmented_data, where


def adequacy_test(
    model: ChainModel,
    data: Sequences,
    z: np.ndarray,
    xhat: np.ndarray,
    nuisance: np.ndarray,
    alpha: float,
    acting: list[int],
) -> dict:
    """Score test of the hat library at the fit `z` of `model` (candidate
    coefficients, then the noise scales), on the equations where the
    candidates `acting` (the named ones and those in a set with them) act.

    Only those equations: the test asks whether the named terms have the
    right shape where they act. Hats of the latent states on other equations
    scored with a bias (the Laplace evidence's log-determinant term, taken
    at the MAP instead of averaged over the posterior, is large on an
    equation with small process noise): a correctly named constant force
    scored z = -9 on the hats of the velocity in the position equation.

    One test per block (the hats of one variable on one equation), with the
    candidates' own observed information (see
    [`eqsmooth.discover.score_test`][]); the named model is inadequate when
    the smallest block p-value, Bonferroni-corrected over the blocks, is
    below `alpha`. The report names that block and the knot where its
    largest single score sits.
    """
    xhat = np.asarray(xhat)
    built = _augmented(model, data, xhat, acting)
    if built is None:
        return {"tested": False, "significant": False, "p_value": float("nan")}
    augmented, augmented_data, where = built
    K, H = len(model.candidates), len(where)
    za = np.concatenate([z[:K], np.zeros(H), z[K:]])
    test = K + np.arange(H)
    nuis = np.asarray(nuisance, int)
    nuis = np.where(nuis >= K, nuis + H, nuis)
    try:
        scales = feature_scales(augmented, augmented_data, xhat)
        ev = evaluate(augmented, augmented_data, za, xhat, scales, test, at_map=True)
    except (*EVALUATION_ERRORS, ValueError) as e:
        return {
            "tested": False,
            "significant": False,
            "p_value": float("nan"),
            "error": f"{type(e).__name__}: {e}",
        }
    # Each hat's own standardised score; the hats beyond a Bonferroni bound
    # over all of them mark where the structure sits.
    g = np.sum(ev.scores, axis=0)[test]
    info = np.abs(np.diag(ev.hessian)[test])
    zs = g / np.sqrt(np.maximum(info, 1e-300))
    z_crit = normal_quantile(1.0 - alpha / (2 * H))
    names = list(dict.fromkeys(w["block"] for w in where))
    blocks = []
    for block in names:
        idx = np.asarray([i for i, w in enumerate(where) if w["block"] == block])
        result = score_test(ev, test[idx], nuis, "hessian")
        zj = result.get("largest_z", {"index": 0, "z": float("nan")})
        at = where[int(idx[zj["index"]])]
        blocks.append(
            {
                "block": block,
                "equation": at["equation"],
                "variable": at["variable"],
                "p_value": float(result["p_value"]),
                "statistic": float(result["statistic"]),
                "df": int(result["df"]),
                "near": at["near"],
                "z": float(zj["z"]),
                "hat_z": [float(v) for v in zs[idx]],
                "knots": at["knots"],
                "region": _region(at["knots"], zs[idx], z_crit),
            }
        )
    pvals = np.asarray([b["p_value"] for b in blocks])
    finite = np.isfinite(pvals)
    if not finite.any():
        return {"tested": False, "significant": False, "p_value": float("nan")}
    worst = int(np.nanargmin(np.where(finite, pvals, np.inf)))
    p = min(1.0, float(pvals[worst]) * len(blocks))
    return {
        "tested": True,
        "significant": bool(p < alpha),
        "p_value": p,
        "where": blocks[worst],
        "blocks": blocks,
    }
