"""When a Gauss-Newton-family solve stops: at its tolerances, or after a fixed
number of steps.

A stopping policy is the half of an [`eqsmooth.solve.AbstractGaussNewton`][]
solver that says how many iterations the loop may run, whether an accepted
step has converged, and what reaching the iteration limit means. The other
half, the descent ([`eqsmooth.solve.UndampedDescent`][],
[`eqsmooth.solve.DampedDescent`][]), says how a step is solved and judged.
"""

import abc
import numbers

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, Int

from .._linearization import gradient, Linearization, Tangent
from .._misc import converged_test, max_abs
from .._solution import RESULTS


class AbstractStopping(eqx.Module):
    """When a Gauss-Newton-family solve stops.

    Subclasses say how many iterations a solve called with `max_steps` may
    run, how many steps are taken after the loop, what reaching the limit
    means, whether the result is a minimiser (which
    [`eqsmooth.solve.ImplicitAdjoint`][] differentiates), and whether a trial
    point has converged.
    """

    @abc.abstractmethod
    def iteration_limit(self, max_steps: int) -> int:
        """The static iteration limit of a solve called with `max_steps`."""

    @abc.abstractmethod
    def steps_after_loop(self) -> int:
        """How many steps the solver takes after its last iteration."""

    @abc.abstractmethod
    def at_max_steps(self) -> RESULTS:
        """The result when the iteration limit is reached before convergence."""

    @abc.abstractmethod
    def reaches_minimum(self) -> bool:
        """Whether the solve runs to a stationary point of the cost."""

    @abc.abstractmethod
    def relative_tolerance(self) -> float:
        """optimistix's `rtol` of the solver (0 where none applies)."""

    @abc.abstractmethod
    def absolute_tolerance(self) -> float:
        """optimistix's `atol` of the solver (0 where none applies)."""

    @abc.abstractmethod
    def out_of_steps(self, step: Int[Array, ""]) -> Bool[Array, ""]:
        """Whether the loop must end after `step` iterations (besides the
        `max_steps` limit of the loop itself)."""

    @abc.abstractmethod
    def converged(
        self,
        first: Bool[Array, ""],
        accepted: Bool[Array, ""],
        old_cost,
        trial: Linearization,
        delta: Tangent,
    ) -> Bool[Array, ""]:
        """Whether the solve has converged at `trial`: the initial values in the
        first iteration (`first`), else the trial point of `delta` (which
        counts only if the descent `accepted` it)."""


class Tolerances(AbstractStopping):
    """Iterate until a tolerance is met, or `max_steps`.

    Converged when, after an accepted step, the relative cost change is at
    most `ftol`, the largest gradient entry at most `gtol`, or the largest
    step entry at most `xtol` (Ceres-like tolerances); the initial values
    count as converged when their largest gradient entry is at most `gtol`.
    The iteration limit is `max_steps + 1`: the first iteration only
    linearises the initial values (and solves for the first step). Reaching
    it before convergence gives `RESULTS.nonlinear_max_steps_reached`.

    **Arguments:**

    - `ftol`, `gtol`, `xtol`: the tolerances (each `>= 0`).
    """

    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)

    def __check_init__(self):
        check_tolerances("Tolerances", self.ftol, self.gtol, self.xtol)

    def relative_tolerance(self) -> float:
        return self.ftol

    def absolute_tolerance(self) -> float:
        return self.xtol

    def iteration_limit(self, max_steps: int) -> int:
        return max_steps + 1

    def steps_after_loop(self) -> int:
        return 0

    def at_max_steps(self) -> RESULTS:
        return RESULTS.nonlinear_max_steps_reached

    def reaches_minimum(self) -> bool:
        return True

    def out_of_steps(self, step):
        return jnp.zeros_like(step, dtype=bool)

    def converged(self, first, accepted, old_cost, trial, delta):
        at_start = max_abs(gradient(trial)) <= self.gtol
        after_step = accepted & converged_test(
            old_cost, trial, delta, self.ftol, self.gtol, self.xtol
        )
        return jnp.where(first, at_start, after_step)


class FixedSteps(AbstractStopping):
    """Exactly `num_steps` steps, whatever they give.

    No tolerance stops the solve early, so the computation (and its gradient
    under [`eqsmooth.solve.UnrolledAdjoint`][]) is the same for every input.
    The loop runs `num_steps` iterations (each one linearisation and one
    solve) and the last step is taken after it, where only the cost of the
    result is evaluated. Reaching `num_steps` is success; the result is not
    a minimiser, so [`eqsmooth.solve.ImplicitAdjoint`][] refuses it unless
    it happens to be stationary.

    **Arguments:**

    - `num_steps`: K, `>= 1`.
    """

    num_steps: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        check_num_steps("FixedSteps", self.num_steps)

    def relative_tolerance(self) -> float:
        return 0.0

    def absolute_tolerance(self) -> float:
        return 0.0

    def iteration_limit(self, max_steps: int) -> int:
        del max_steps
        return self.num_steps

    def steps_after_loop(self) -> int:
        return 1

    def at_max_steps(self) -> RESULTS:
        return RESULTS.successful

    def reaches_minimum(self) -> bool:
        return False

    def out_of_steps(self, step):
        return step >= self.num_steps

    def converged(self, first, accepted, old_cost, trial, delta):
        del accepted, old_cost, trial, delta
        return jnp.zeros_like(first)


def check_tolerances(owner: str, ftol: float, gtol: float, xtol: float) -> None:
    """A `ValueError` naming `owner` for a negative or NaN tolerance."""
    for name, value in (("ftol", ftol), ("gtol", gtol), ("xtol", xtol)):
        if not value >= 0:  # NaN fails every comparison, so it lands here too
            raise ValueError(f"{owner}.{name} must be >= 0, got {value!r}")


def check_num_steps(owner: str, num_steps: int) -> None:
    """A `ValueError` naming `owner` unless `num_steps` is an int >= 1."""
    integral = isinstance(num_steps, numbers.Integral)
    if isinstance(num_steps, bool) or not integral or num_steps < 1:
        raise ValueError(f"{owner}.num_steps must be an int >= 1, got {num_steps!r}")
