"""How a Gauss-Newton-family solver solves and judges its steps: undamped
(Gauss-Newton) or damped (Levenberg-Marquardt).

A descent is the half of an [`eqsmooth.solve.AbstractGaussNewton`][] solver
that gives the damping of the normal equations `(JᵀJ + λD) δ = −Jᵀr` and
decides, once the trial point `x ⊕ δ` is linearised, whether the step is
taken, how λ moves, and whether the solve must stop. The other half, the
stopping policy ([`eqsmooth.solve.Tolerances`][],
[`eqsmooth.solve.FixedSteps`][]), says when it has converged.
"""

import abc
import math
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .._linearization import (
    apply_jacobian,
    block_diagonal,
    gradient,
    Linearization,
    Tangent,
)
from .._misc import sq_norm
from .._solution import RESULTS


class Verdict(NamedTuple):
    """A descent's judgement of a trial point.

    - `accept`: the step is taken (never in the first iteration, which only
        linearises the initial values).
    - `stop`: the solve ends here (before any convergence test).
    - `result`: the result code if it ends.
    - `diverged`: the step failed in a way that ends the solve: nothing is
        differentiable through the values it returns.
    - `damping`, `nu`: λ for the next solve and its growth factor.
    """

    accept: Bool[Array, ""]
    stop: Bool[Array, ""]
    result: RESULTS
    diverged: Bool[Array, ""]
    damping: Float[Array, ""]
    nu: Float[Array, ""]


class AbstractDescent(eqx.Module):
    """How a Gauss-Newton-family solver solves and judges its steps.

    `judge` receives the solver state (`state.lin` at the current values,
    `state.delta` the step just tried, `state.solved` whether it came from a
    successful linear solve, `state.damping`, `state.nu`) and the
    linearisation of the trial point.
    """

    @abc.abstractmethod
    def initial_damping_value(self) -> float:
        """λ₀ (0 for an undamped descent)."""

    @abc.abstractmethod
    def damping(self, lin: Linearization, lam) -> Tangent | None:
        """`λD` per group for the next solve, or None (undamped)."""

    @abc.abstractmethod
    def judge(
        self,
        state,
        trial: Linearization,
        finite: Bool[Array, ""],
        first: Bool[Array, ""],
    ) -> Verdict:
        """Whether the trial point is taken, and what follows."""

    @abc.abstractmethod
    def recovers_from_failed_solve(self) -> bool:
        """Whether a failed linear solve is a rejected step (the damping can
        grow and the solve go on) rather than the end of the solve."""


class UndampedDescent(AbstractDescent):
    """Gauss-Newton: solve `JᵀJ δ = −Jᵀr` and take every finite step.

    A trial point whose linearisation is not finite ends the solve with
    `RESULTS.nonlinear_divergence` (`RESULTS.nonfinite_problem` for the
    initial values), returning the values before it; a failed linear solve
    ends it with `RESULTS.linear_solve_failed`. Nothing is differentiable
    through a failed step (its derivative is NaN).
    """

    def initial_damping_value(self) -> float:
        return 0.0

    def damping(self, lin, lam):
        del lin, lam
        return None

    def judge(self, state, trial, finite, first):
        del trial
        result = RESULTS.where(
            finite,
            RESULTS.successful,
            RESULTS.where(
                first, RESULTS.nonfinite_problem, RESULTS.nonlinear_divergence
            ),
        )
        return Verdict(
            accept=finite & ~first,
            stop=~finite,
            result=result,
            diverged=~finite & ~first,
            damping=state.damping,
            nu=state.nu,
        )

    def recovers_from_failed_solve(self) -> bool:
        return False


def marquardt_damping(lin: Linearization, lam, min_diag: float, max_diag: float):
    """`λ clip(diag(JᵀJ), min_diag, max_diag)` per group."""
    blocks = block_diagonal(lin)
    return {
        name: lam * jnp.clip(jnp.diagonal(b, axis1=1, axis2=2), min_diag, max_diag)
        for name, b in blocks.items()
    }


def predicted_decrease(lin: Linearization, delta: Tangent) -> Float[Array, ""]:
    """Decrease of the Gauss-Newton model: `−gᵀδ − ½‖Jδ‖²`."""
    g = gradient(lin)
    gd = sum(jnp.sum(g[k] * delta[k]) for k in g)
    jd = sq_norm(apply_jacobian(lin, delta))
    return -gd - 0.5 * jd


class DampedDescent(AbstractDescent):
    """Levenberg-Marquardt: `(JᵀJ + λD) δ = −Jᵀr` with a gain-ratio test.

    `D = clip(diag(JᵀJ), min_diagonal, max_diagonal)` (Marquardt scaling with
    a floor, so the damped system is positive definite even where `JᵀJ` is
    singular). A step is accepted when the gain ratio (actual / predicted
    cost decrease) exceeds `min_gain`; λ then moves by the `damping_update`
    rule: `"nielsen"` multiplies it by `max(1/3, 1 − (2ρ − 1)³)` for gain
    ratio ρ and by a factor that doubles on every consecutive rejection,
    `"fixed"` divides it by `damping_factor` on every accepted step and
    multiplies it by `damping_factor` on every rejection. A non-finite trial
    point or a failed linear solve counts as a rejection. The solve ends when
    λ exceeds `max_damping` (`RESULTS.linear_solve_failed`) or when the
    predicted decrease is at the level of rounding in the cost (convergence).

    **Arguments:** as [`eqsmooth.solve.LevenbergMarquardt`][].
    """

    initial_damping: float = eqx.field(static=True, default=1e-8)
    min_diagonal: float = eqx.field(static=True, default=1e-6)
    max_diagonal: float = eqx.field(static=True, default=1e32)
    max_damping: float = eqx.field(static=True, default=1e16)
    min_gain: float = eqx.field(static=True, default=1e-3)
    damping_update: str = eqx.field(static=True, default="nielsen")
    damping_factor: float = eqx.field(static=True, default=10.0)

    def __check_init__(self):
        check_damping("DampedDescent", self)

    def initial_damping_value(self) -> float:
        return self.initial_damping

    def damping(self, lin, lam):
        return marquardt_damping(lin, lam, self.min_diagonal, self.max_diagonal)

    def judge(self, state, trial, finite, first):
        lin, delta, lam = state.lin, state.delta, state.damping
        predicted = predicted_decrease(lin, delta)
        actual = lin.cost - trial.cost
        gain = actual / jnp.where(predicted > 0, predicted, 1.0)
        accept = (
            state.solved & finite & (predicted > 0) & (gain > self.min_gain) & ~first
        )
        if self.damping_update == "nielsen":
            # Nielsen (1999): λ shrinks smoothly with the gain ratio (and grows
            # when it is below 1/2); on rejections it grows by ν, which doubles.
            shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
            new_lam = jnp.where(accept, lam * shrink, lam * state.nu)
            new_nu = jnp.where(accept, 2.0, 2.0 * state.nu)
        else:
            # A fixed factor down on every accepted step and up on every
            # rejection, whatever the gain ratio (GTSAM's default).
            factor = self.damping_factor
            new_lam = jnp.where(accept, lam / factor, lam * factor)
            new_nu = state.nu
        new_lam = jnp.maximum(new_lam, jnp.finfo(lam.dtype).tiny)
        # Nothing left to gain: the model's predicted decrease is at the level
        # of floating-point noise in the cost (or not positive), so no
        # accepted step can be told apart from rounding. This is convergence.
        eps = jnp.finfo(lam.dtype).eps
        stalled = state.solved & (predicted <= 16 * eps * jnp.maximum(lin.cost, 1.0))
        stalled = stalled & ~first
        gave_up = (new_lam > self.max_damping) & ~first
        result = RESULTS.where(
            gave_up & ~stalled, RESULTS.linear_solve_failed, RESULTS.successful
        )
        # The first iteration: the initial values, stopped at once if they
        # are not finite.
        result = RESULTS.where(first & ~finite, RESULTS.nonfinite_problem, result)
        return Verdict(
            accept=accept,
            stop=jnp.where(first, ~finite, stalled | gave_up),
            result=result,
            diverged=jnp.zeros_like(first),
            damping=jnp.where(first, lam, new_lam).astype(lam.dtype),
            nu=jnp.where(first, state.nu, new_nu).astype(lam.dtype),
        )

    def recovers_from_failed_solve(self) -> bool:
        return True


DAMPING_UPDATES = ("nielsen", "fixed")


def check_damping(owner: str, d) -> None:
    """A `ValueError` naming `owner` for a damping parameter out of range."""
    checks = (
        ("initial_damping", 0 <= d.initial_damping < math.inf, ">= 0 and finite"),
        ("min_diagonal", 0 < d.min_diagonal < math.inf, "> 0 and finite"),
        ("max_diagonal", d.max_diagonal >= d.min_diagonal, ">= min_diagonal"),
        ("max_damping", d.max_damping > d.initial_damping, "> initial_damping"),
        ("min_gain", 0 <= d.min_gain < 1, "in [0, 1)"),
        ("damping_update", d.damping_update in DAMPING_UPDATES, "'nielsen' or 'fixed'"),
        ("damping_factor", 1 < d.damping_factor < math.inf, "> 1 and finite"),
    )
    for field, ok, need in checks:
        if not ok:  # NaN fails every comparison, so it lands here too
            raise ValueError(
                f"{owner}.{field} must be {need}, got {getattr(d, field)!r}"
            )
