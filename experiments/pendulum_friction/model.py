"""The nominal model, the ideal pendulum, and its candidate effects."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth.discover as dc


COULOMB_EPS = 0.05  # rad/s, smoothing velocity of the Coulomb term
SIGMA_A = 0.05  # rad s^-1.5, starting density of the random acceleration
PRIOR_SIGMA = np.array([1.0, 8.0])  # first state (φ, φ̇) ~ N(0, diag²): swing size


def _field(x, omega0_sq):
    return jnp.stack([x[1], -omega0_sq * jnp.sin(x[0])])


def pendulum_step(x, u, params):
    """Nominal model: one RK4 step of the frictionless pendulum, x = (φ, φ̇)."""
    dt, w2 = params["dt"], params["omega0_sq"]
    k1 = _field(x, w2)
    k2 = _field(x + 0.5 * dt * k1, w2)
    k3 = _field(x + 0.5 * dt * k2, w2)
    k4 = _field(x + dt * k3, w2)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def measure_angle(x, params):
    return x[:1]


@dataclasses.dataclass(frozen=True)
class PendulumField:
    """The ideal pendulum's vector field `(φ̇, −ω₀² sin φ)`: hashable, so that
    candidates built with it share compiled code."""

    omega0_sq: float

    def __call__(self, x, u):
        return _field(x, self.omega0_sq)


# The library's names, and the pendulum's own names and units for them.
_DYNAMICS = {
    "constant force": ("constant torque", "rad/s^2", "φ̈ += c"),
    "viscous damping": ("viscous damping", "1/s", "φ̈ -= c φ̇"),
    "quadratic drag": ("quadratic drag", "1/rad", "φ̈ -= c φ̇|φ̇|"),
    "Coulomb friction": ("Coulomb friction", "rad/s^2", "φ̈ -= c tanh(φ̇/ε)"),
    "cubic damping": ("cubic damping", "s/rad^2", "φ̈ -= c φ̇³"),
    "spring error": ("spring error", "1/s^2", "φ̈ -= c φ"),
    "cubic stiffness": ("cubic stiffness", "1/(rad^2 s^2)", "φ̈ -= c φ³"),
}


def pendulum_library(dt: float, omega0_sq: float) -> tuple[dc.Candidate, ...]:
    """Friction laws, stiffness errors and a constant torque, plus the angle
    sensor's bias, scale and delay, from
    [`mechanical_library`][eqsmooth.discover.mechanical_library].

    Each acceleration is a continuous-time term: its kick over one step is
    evaluated at the nominal half-step state (`vector_field=`, a midpoint
    kick), so a fitted coefficient is a continuous-time quantity (for
    viscous damping the rate γ of φ̈ = … − γ φ̇, in s^-1). Against a 1 ms RK4
    simulation of the damped pendulum over 9 s, this kick dissipates the
    right energy within 0.5 % at 50 Hz (viscous, Coulomb, quadratic drag;
    amplitudes 0.4 and 1.6 rad), where a kick at the start of the step
    dissipates 0.5-1.1 % too little. (The exact derivative of the RK4 step
    with respect to `c` is as accurate and triples the compile time.)
    """
    library = dc.mechanical_library(
        [0],
        [1],
        2,
        dt=dt,
        coulomb_eps=COULOMB_EPS,
        measured_positions=[0],
        vector_field=PendulumField(float(omega0_sq)),
    )
    missing = set(_DYNAMICS) - {c.name for c in library}
    assert not missing, f"mechanical_library has no {sorted(missing)}"
    out = []
    for c in library:
        if c.name in _DYNAMICS:
            name, unit, description = _DYNAMICS[c.name]
            c = dataclasses.replace(c, name=name, unit=unit, description=description)
        out.append(c)
    return tuple(out)


def build_model(dt: float, omega0_sq: float, angle_sigma: float) -> dc.ChainModel:
    """The ideal pendulum with the candidate library and starting noise levels.

    Process noise: a white random acceleration of density `SIGMA_A`, whose
    exact discretisation has standard deviations `σ_a (√(dt³/3), √dt)` on
    angle and velocity (the chain model keeps the diagonal). Measurement
    noise: the angle noise measured at 1 kHz. First state: `PRIOR_SIGMA`
    around zero. The workflow refits one multiplier for each of the three.
    """
    q = SIGMA_A * np.array([np.sqrt(dt**3 / 3), np.sqrt(dt)])
    params = {"dt": jnp.asarray(dt), "omega0_sq": jnp.asarray(omega0_sq)}
    return dc.ChainModel(
        pendulum_step,
        measure_angle,
        params,
        q,
        np.array([angle_sigma]),
        PRIOR_SIGMA,
        pendulum_library(dt, omega0_sq),
    )


def viscous_only(model: dc.ChainModel) -> dc.ChainModel:
    """The authors' model: the same nominal pendulum and noise levels with
    viscous friction as its only candidate."""
    viscous = model.candidates[model.index("viscous damping")]
    return dc.ChainModel(
        pendulum_step,
        measure_angle,
        model.params,
        model.process_sigma,
        model.measurement_sigma,
        model.prior_sigma,
        (viscous,),
    )


@eqx.filter_jit
def open_loop(model: dc.ChainModel, x0, steps: int):
    """Noise-free simulations `(B, steps, 2)` of the model's mean dynamics."""

    def one(x):
        def step(x, _):
            return model.transition(x, jnp.zeros(1, x.dtype)), x

        return jax.lax.scan(step, x, None, length=steps)[1]

    return jax.vmap(one)(x0)
