"""Continuous-time nominal dynamics, integrated with the model's own scheme."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
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
    The stages of all substeps run in one `lax.scan`, so the vector field
    and the candidates are traced once per program, whatever the scheme
    and the number of substeps (on `benchmarks/discover_speed.py`'s
    pendulum this cut the first `find → name → add` call from 220 s to
    61 s). `u` is held constant over a step (zero-order hold).

    **Arguments:**

    - `vector_field`: `f(x, u, params) -> ẋ` `(n,)`, with `x` ONE state and
        `u` one input. Must be hashable (a module-level function or a frozen
        dataclass).
    - `dt`: the time step of the discrete model (the sequences' sample time).
    - `method`: `"rk4"` (classical Runge-Kutta, default), `"midpoint"` or
        `"euler"`.
    - `substeps`: integration steps per sample (`≥ 1`).
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

        # Every scheme here is explicit with stages k_i = f(x + h a_i k_{i-1})
        # and x' = x + h Σ b_i k_i. The stages of all substeps run in one
        # `lax.scan`, so the vector field (and the candidates' features) is
        # traced once, not once per stage: the programs that differentiate
        # it twice compile several times faster than the unrolled scheme.
        a, b = _TABLEAUX[self.method]
        s = len(a)
        h = self.dt / self.substeps
        num = s * self.substeps
        coef_a = jnp.asarray(np.tile(a, self.substeps), x.dtype)
        coef_b = jnp.asarray(np.tile(b, self.substeps), x.dtype)
        last = jnp.asarray(np.arange(num) % s == s - 1)

        def stage(carry, inputs):
            start, k_prev, acc = carry
            ai, bi, is_last = inputs
            k = field(start + (h * ai) * k_prev)
            acc = acc + bi * k
            end = start + h * acc
            start = jnp.where(is_last, end, start)
            acc = jnp.where(is_last, jnp.zeros_like(acc), acc)
            return (start, k, acc), None

        zero = jnp.zeros_like(x)
        (x, _, _), _ = jax.lax.scan(stage, (x, zero, zero), (coef_a, coef_b, last))
        return x


# (a, b) of each scheme: stage i evaluates f at x + h a_i k_{i-1}.
_TABLEAUX = {
    "euler": ((0.0,), (1.0,)),
    "midpoint": ((0.0, 0.5), (0.0, 1.0)),
    "rk4": ((0.0, 0.5, 0.5, 1.0), (1 / 6, 1 / 3, 1 / 3, 1 / 6)),
}
