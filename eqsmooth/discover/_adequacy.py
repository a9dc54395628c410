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

The hats are not added to the model as candidates (that was a new,
larger program to compile for every model structure, about half of a
first call's compile time). Each enters the nominal model's score program
through `Offsets`, its value and slope at the MAP, which give its exact
score and, by central differences, its observed information (equal to the
augmented model's: `tests/test_discover_adequacy.py`).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._stats import normal_quantile
from ._fit import Evaluation, EVALUATION_ERRORS, feature_values
from ._model import batch_scores, ChainModel, Offsets, Sequences
from ._score import score_test


# Knots of the hat functions: quantiles of the variable over the smoothed
# states (inputs), inner ones at the quartiles, outer ones just inside the
# range so that a few outlying states do not stretch the first and last hat.
_KNOT_QUANTILES = (0.02, 0.25, 0.5, 0.75, 0.98)
_NUM_KNOTS = len(_KNOT_QUANTILES)


def hat(s: np.ndarray, knots, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Value and slope at `s` of hat `b` over `knots`: 1 at its knot, falling
    linearly to 0 at the neighbouring knots; the first and last hats stay at
    1 beyond the outer knots (so the hats sum to 1 everywhere). The slope is
    that of the piece `s` lies in (0 on a flat piece; exactly at a knot, the
    piece to its right)."""
    k = np.asarray(knots, float)
    s = np.asarray(s, float)
    last = len(k) - 1
    if b == 0:
        w = np.clip((k[1] - s) / (k[1] - k[0]), 0.0, 1.0)
        dw = np.where((s >= k[0]) & (s < k[1]), -1.0 / (k[1] - k[0]), 0.0)
    elif b == last:
        w = np.clip((s - k[-2]) / (k[-1] - k[-2]), 0.0, 1.0)
        dw = np.where((s >= k[-2]) & (s < k[-1]), 1.0 / (k[-1] - k[-2]), 0.0)
    else:
        up = (s - k[b - 1]) / (k[b] - k[b - 1])
        down = (k[b + 1] - s) / (k[b + 1] - k[b])
        w = np.maximum(np.minimum(up, down), 0.0)
        dw = np.where((s >= k[b - 1]) & (s < k[b]), 1.0 / (k[b] - k[b - 1]), 0.0)
        dw = np.where((s >= k[b]) & (s < k[b + 1]), -1.0 / (k[b + 1] - k[b]), dw)
    return w, dw


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
    values = feature_values(model, x, u)
    for j in acting:
        c, f = model.candidates[j], values[j]
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


@dataclasses.dataclass(frozen=True)
class _HatTerm:
    """One hat term: hat `b` of variable `source[index]` on row `row` of the
    dynamics or measurement equations, with its values and slopes (in that
    variable) at the MAP states, `(B, T)` each."""

    target: str  # "dynamics" or "measurement"
    row: int
    source: str  # "x" or "u"
    index: int
    value: np.ndarray
    slope: np.ndarray

    def offsets(self, zero: Offsets, c: float) -> Offsets:
        """`zero` with this term at coefficient `c` added (built in NumPy:
        eager `.at[]` updates each compiled a small program on first use)."""
        w, dw = c * self.value, c * self.slope
        if self.target == "dynamics":
            d = np.array(zero.dynamics)
            d[:, :, self.row] += w[:, :-1]
            changed = {"dynamics": d}
            if self.source == "x":
                jac = np.array(zero.dynamics_jacobian)
                jac[:, :, self.row, self.index] += dw[:, :-1]
                changed["dynamics_jacobian"] = jac
        else:
            d = np.array(zero.measurement)
            d[:, :, self.row] += w
            changed = {"measurement": d}
            if self.source == "x":
                jac = np.array(zero.measurement_jacobian)
                jac[:, :, self.row, self.index] += dw
                changed["measurement_jacobian"] = jac
        changed = {k: jnp.asarray(v) for k, v in changed.items()}
        return dataclasses.replace(zero, **changed)

    def score(self, g: Offsets) -> np.ndarray:
        """Per-sequence score `(B,)` of this term's coefficient at 0, from the
        gradients `g` (NumPy arrays) of the evidences with respect to the
        offsets."""
        if self.target == "dynamics":
            d, jac, w, dw = g.dynamics, g.dynamics_jacobian, self.value, self.slope
            w, dw = w[:, :-1], dw[:, :-1]
        else:
            d, jac = g.measurement, g.measurement_jacobian
            w, dw = self.value, self.slope
        out = np.sum(d[:, :, self.row] * w, axis=1)
        if self.source == "x":
            out = out + np.sum(jac[:, :, self.row, self.index] * dw, axis=1)
        return out


def _hat_terms(model, data, xhat, acting):
    """The hat library on the equations where the candidates `acting` act:
    its terms and where each sits."""
    inputs = np.asarray(data.inputs)
    n, k = xhat.shape[-1], inputs.shape[-1]
    variables = [("x", i, xhat[..., i]) for i in range(n)]
    variables += [("u", j, inputs[..., j]) for j in range(k)]
    equations = _named_equations(model, data, xhat, acting)
    terms, where = [], []
    for source, index, values in variables:
        knots = _knots(values.ravel())
        if knots is None:
            continue
        for target, row, _ in equations:
            block = f"{source}{index} on " + (
                f"x{row}'" if target == "dynamics" else f"y{row}"
            )
            for b, knot in enumerate(knots):
                w, dw = hat(values, knots, b)
                terms.append(_HatTerm(target, row, source, index, w, dw))
                where.append(
                    {
                        "block": block,
                        "equation": block.split(" on ")[1],
                        "variable": f"{source}{index}",
                        "near": knot,
                        "knots": list(knots),
                    }
                )
    return terms, where


def _hat_evaluation(model, data, z, xhat, terms) -> Evaluation:
    """Scores `(B, H)` of the hat terms at coefficient 0 and their observed
    information (central differences of the exact scores, the MAP held at
    `xhat`, as `evaluate` does for candidates), from the nominal model's
    one score program."""
    zj, xj = jnp.asarray(z), jnp.asarray(xhat)
    zero = Offsets.zeros(data, xhat.shape[-1])

    def hat_scores(offsets):
        vals, _, g = batch_scores(model, zj, data, xj, offsets)
        g = jax.tree_util.tree_map(np.asarray, g)  # once, not once per hat
        return np.asarray(vals), np.stack([t.score(g) for t in terms], axis=1)

    vals, scores = hat_scores(zero)
    H = len(terms)
    hessian = np.zeros((H, H))
    for i, t in enumerate(terms):
        # A perturbation of 1e-4 state units per step (as `_step_sizes`).
        scale = float(np.sqrt(np.mean(t.value**2)))
        h = 1e-4 / (scale if scale > 0 else 1.0)
        _, gp = hat_scores(t.offsets(zero, h))
        _, gm = hat_scores(t.offsets(zero, -h))
        hessian[:, i] = (gp.sum(0) - gm.sum(0)) / (2 * h)
    hessian = 0.5 * (hessian + hessian.T)
    return Evaluation(
        z=np.zeros(H),
        log_marginal=float(np.sum(vals)),
        per_sequence=vals,
        scores=scores,
        hessian=hessian,
        xhat=np.asarray(xhat).copy(),
    )


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
    terms, where = _hat_terms(model, data, xhat, acting)
    if not terms:
        return {"tested": False, "significant": False, "p_value": float("nan")}
    H = len(terms)
    test = np.arange(H)
    try:
        ev = _hat_evaluation(model, data, z, xhat, terms)
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
        result = score_test(ev, test[idx], np.zeros(0, int), "hessian")
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
