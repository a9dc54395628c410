"""Continuous-time nominal dynamics, integrated with the model's own scheme."""

from collections.abc import Callable

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float, PyTree


_METHODS = ("euler", "midpoint", "rk4")


class Integrator(eqx.Module):
    """Discrete dynamics `x_{t+1} = Φ_dt(x_t)` from a continuous-time vector field.

    Use it as the `dynamics` of a [`eqsmooth.discover.ChainModel`][]. Then
    candidates with `target="rate"` are terms of the vector field itself,
    `ẋ = f(x, u, params) + Σ_k c_k φ_k(x, u)`, integrated by the same scheme
    as the nominal model. A fitted coefficient is then exactly a
    continuous-time quantity (a damping rate in 1/s, a torque in rad/s²),
    with no discretisation bias, and an effect acting inside the dynamics
    cannot leak into a stiffness-like term through the scheme's own error.
    The price is compile time: the candidates' derivatives pass through
    every stage of the scheme. `u` is held constant over a step
    (zero-order hold).

    **Arguments:**

    - `vector_field`: `f(x, u, params) -> ẋ` `(n,)`, with `x` ONE state and
        `u` one input. Must be hashable (a module-level function or a frozen
        dataclass).
    - `dt`: the time step of the discrete model (the sequences' sample time).
    - `method`: `"rk4"` (classical Runge-Kutta, default), `"midpoint"` or
        `"euler"`.
    - `substeps`: integration steps per sample (`≥ 1`), unrolled.
    """

    vector_field: Callable = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    method: str = eqx.field(static=True, default="rk4")
    substeps: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if not callable(self.vector_field):
            raise TypeError(
                "Integrator.vector_field must be a callable f(x, u, params) -> ẋ, "
                f"got {type(self.vector_field).__name__}"
            )
        try:
            hash(self.vector_field)
        except TypeError:
            raise TypeError(
                "Integrator.vector_field must be hashable (a module-level function "
                "or a frozen dataclass), so that compiled code is reused"
            ) from None
        if self.method not in _METHODS:
            raise ValueError(
                f"Integrator.method must be one of {_METHODS}, got {self.method!r}"
            )
        if isinstance(self.dt, bool) or not (
            isinstance(self.dt, (int, float, np.floating)) and self.dt > 0
        ):
            raise ValueError(
                f"Integrator.dt must be a positive number, got {self.dt!r}"
            )
        if (
            isinstance(self.substeps, bool)
            or not isinstance(self.substeps, int)
            or self.substeps < 1
        ):
            raise ValueError(
                f"Integrator.substeps must be an int >= 1, got {self.substeps!r}"
            )

    def __call__(
        self, x: Float[Array, " n"], u: Float[Array, " k"], params: PyTree
    ) -> Float[Array, " n"]:
        """One sample step of the nominal vector field."""
        return self.step(x, u, params, None)

    def step(
        self,
        x: Float[Array, " n"],
        u: Float[Array, " k"],
        params: PyTree,
        extra: Callable | None,
    ) -> Float[Array, " n"]:
        """One sample step of `f(x, u, params) + extra(x, u)` (`extra` may be None)."""

        def field(z):
            out = self.vector_field(z, u, params)
            return out if extra is None else out + extra(z, u)

        h = self.dt / self.substeps
        for _ in range(self.substeps):
            if self.method == "euler":
                x = x + h * field(x)
            elif self.method == "midpoint":
                x = x + h * field(x + 0.5 * h * field(x))
            else:
                k1 = field(x)
                k2 = field(x + 0.5 * h * k1)
                k3 = field(x + 0.5 * h * k2)
                k4 = field(x + h * k3)
                x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return x
