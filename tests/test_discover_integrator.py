"""Candidates inside the model's own integrator (`target="rate"`)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


W2 = 4.0  # ω₀² of the test pendulum (rad²/s²)
GAMMA = 0.3  # true viscous damping rate (1/s)
DT = 0.25  # coarse sample time, so that discretisation errors show


def _pendulum_field(x, u, params):
    return jnp.stack([x[1], -params * jnp.sin(x[0])])


def _measure(x, params):
    return x[:1]


@dataclasses.dataclass(frozen=True)
class _Field:
    """The nominal vector field without params (for midpoint kicks)."""

    w2: float

    def __call__(self, x, u):
        return _pendulum_field(x, u, self.w2)


@dataclasses.dataclass  # eq=True without frozen: not hashable
class _Unhashable:
    def __call__(self, x, u, params):
        return x


def _unit_noise_model(integrator, library, coefficients):
    """The test pendulum with unit noise sigmas and the given coefficients."""
    import eqsmooth.discover as dc

    ones = np.ones(2), np.ones(1), np.ones(2)
    return dc.ChainModel(
        integrator, _measure, jnp.asarray(W2), *ones, library, np.asarray(coefficients)
    )


def _true_states(num=6, steps=40):
    """Sampled states of the damped pendulum, integrated with 1 ms RK4 steps."""

    def field(x):
        return jnp.stack([x[1], -W2 * jnp.sin(x[0]) - GAMMA * x[1]])

    def rk4(x, _):
        h = 1e-3
        k1 = field(x)
        k2 = field(x + 0.5 * h * k1)
        k3 = field(x + 0.5 * h * k2)
        k4 = field(x + h * k3)
        return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

    def sample(x, _):
        x, _ = jax.lax.scan(rk4, x, None, length=round(DT / 1e-3))
        return x, x

    x0 = jnp.stack([jnp.linspace(0.3, 1.8, num), jnp.zeros(num)], 1)
    _, xs = jax.vmap(lambda x: jax.lax.scan(sample, x, None, length=steps))(x0)
    return np.asarray(jnp.concatenate([x0[:, None], xs], 1))


def _fit_one_step(model, xs):
    """Least-squares coefficients of one-step predictions on the true states
    (the transition is linear in the coefficients only for kicks, so solve
    Gauss-Newton on its Jacobian, three steps)."""
    K = len(model.candidates)
    u = jnp.zeros(1)

    @eqx.filter_jit
    def residual(c):
        m = model.with_coefficients(c)
        pred = jax.vmap(jax.vmap(lambda x: m.transition(x, u)))(xs[:, :-1])
        return (xs[:, 1:] - pred).ravel()

    c = jnp.zeros(K)
    for _ in range(3):
        J = jax.jacfwd(residual)(c)
        c = c - jnp.linalg.lstsq(J, residual(c))[0]
    return dict(zip(model.names, np.asarray(c)))


def test_rate_candidates_fit_the_continuous_coefficients_without_leakage():
    """Viscous damping and a spring error fitted together on a coarsely
    sampled damped pendulum: inside the RK4 integrator the damping rate is
    exact and the spring error ~0 (measured: γ 0.3002, spring error 0.0013
    against ω₀² = 4); as kicks both are biased (start of step: γ 0.268,
    spring error −0.119; midpoint: 0.268, −0.006), the damping leaking into
    a stiffness-like term."""
    import eqsmooth.discover as dc

    xs = jnp.asarray(_true_states())
    include = ("viscous damping", "spring error")
    common = dict(positions=[0], velocities=[1], state_dim=2, dt=DT, include=include)
    args = (jnp.asarray(W2), np.ones(2), np.ones(1), np.ones(2))
    integrator = dc.Integrator(_pendulum_field, DT)
    inside = dc.ChainModel(
        integrator, _measure, *args, dc.mechanical_library(rate=True, **common)
    )
    fit = _fit_one_step(inside, xs)
    assert abs(fit["viscous damping"] - GAMMA) < 1e-3 * GAMMA, fit
    assert abs(fit["spring error"]) < 1e-3 * W2, fit
    for kick in (
        dc.mechanical_library(**common),
        dc.mechanical_library(vector_field=_Field(W2), **common),
    ):
        fit = _fit_one_step(dc.ChainModel(integrator, _measure, *args, kick), xs)
        assert abs(fit["viscous damping"] - GAMMA) > 5e-3 * GAMMA, fit
        assert abs(fit["spring error"]) > 1e-3 * W2, fit


def test_integrator_schemes_and_a_rate_term():
    """RK4 / midpoint / Euler steps of f + c φ match the schemes written out."""
    import eqsmooth.discover as dc

    lib = dc.mechanical_library(
        [0], [1], 2, dt=DT, include=("viscous damping",), rate=True
    )
    x, u = jnp.asarray([0.7, -0.4]), jnp.zeros(1)

    def f(z):
        return jnp.stack([z[1], -W2 * jnp.sin(z[0]) - GAMMA * z[1]])

    for method, substeps in (("rk4", 1), ("midpoint", 2), ("euler", 3)):
        model = _unit_noise_model(
            dc.Integrator(_pendulum_field, DT, method, substeps), lib, [GAMMA]
        )
        z, h = x, DT / substeps
        for _ in range(substeps):
            if method == "rk4":
                k1 = f(z)
                k2 = f(z + h / 2 * k1)
                k3 = f(z + h / 2 * k2)
                k4 = f(z + h * k3)
                z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
            elif method == "midpoint":
                z = z + h * f(z + h / 2 * f(z))
            else:
                z = z + h * f(z)
        np.testing.assert_allclose(model.transition(x, u), z, rtol=1e-12)


def test_integrator_and_rate_errors():
    import eqsmooth.discover as dc

    with pytest.raises(ValueError, match=r"Integrator\.method must be one of"):
        dc.Integrator(_pendulum_field, DT, "rk45")
    with pytest.raises(ValueError, match=r"Integrator\.dt must be a positive"):
        dc.Integrator(_pendulum_field, 0.0)
    with pytest.raises(ValueError, match=r"Integrator\.substeps must be an int"):
        dc.Integrator(_pendulum_field, DT, substeps=0)
    with pytest.raises(TypeError, match=r"Integrator\.vector_field must be hashable"):
        dc.Integrator(_Unhashable(), DT)
    lib = dc.mechanical_library([0], [1], 2, include=("viscous damping",), rate=True)
    assert lib[0].target == "rate" and lib[0].description == "v̇ -= c v"
    with pytest.raises(ValueError, match=r"target 'rate' .* needs dynamics given"):
        dc.ChainModel(
            _pendulum_field, _measure, 1.0, np.ones(2), np.ones(1), np.ones(2), lib
        )
    with pytest.raises(ValueError, match="vector_field .* or rate=True"):
        dc.mechanical_library([0], [1], 2, vector_field=_Field(W2), rate=True)


def test_library_for_the_models_dynamics():
    """Given the model's dynamics, the library fits it: rate terms and the
    integrator's dt for an Integrator, kicks for a discrete map."""
    import eqsmooth.discover as dc

    integrator = dc.Integrator(_pendulum_field, DT)
    lib = dc.mechanical_library(
        [0], [1], 2, measured_positions=[0], dynamics=integrator
    )
    dyn = [c for c in lib if c.target != "measurement"]
    assert dyn and all(c.target == "rate" for c in dyn)
    assert all(c.feature.dt == DT for c in dyn)
    # The same candidates as asking for them by hand (same compiled code).
    assert lib == dc.mechanical_library(
        [0], [1], 2, dt=DT, measured_positions=[0], rate=True
    )
    kicks = dc.mechanical_library([0], [1], 2, dynamics=integrator, rate=False)
    assert all(c.target == "dynamics" and c.feature.dt == DT for c in kicks)
    midpoint = dc.mechanical_library(
        [0], [1], 2, dynamics=integrator, vector_field=_Field(W2)
    )
    assert all(c.target == "dynamics" for c in midpoint)
    discrete = dc.mechanical_library([0], [1], 2, dt=DT, dynamics=_pendulum_field)
    assert all(c.target == "dynamics" for c in discrete)
    with pytest.raises(ValueError, match=r"dt=0\.5 differs from the integrator's"):
        dc.mechanical_library([0], [1], 2, dt=0.5, dynamics=integrator)
    # Under runtime type checks the annotation refuses it first.
    with pytest.raises(TypeError, match="dynamics"):
        dc.mechanical_library([0], [1], 2, dynamics=3.0)


def test_integrator_step_derivatives_match_central_differences():
    """The scanned scheme differentiates like the formula: first derivatives
    in the state and a rate coefficient, and the second derivative in the
    state (the Laplace evidence's gradient uses it), against float64
    central differences."""
    import eqsmooth.discover as dc

    lib = dc.mechanical_library(
        [0], [1], 2, include=("viscous damping", "cubic stiffness"), rate=True
    )
    model = _unit_noise_model(
        dc.Integrator(_pendulum_field, DT, "rk4", 2), lib, [GAMMA, 0.2]
    )
    x, u, w = jnp.asarray([0.7, -0.4]), jnp.zeros(1), jnp.asarray([0.3, -1.1])

    def out(x, c):
        return w @ model.with_coefficients(c).transition(x, u)

    c = model.coefficients
    eps = 1e-5
    grad_x, grad_c = jax.grad(out, argnums=(0, 1))(x, c)
    hess_x = jax.hessian(out)(x, c)
    for i in range(2):
        e = jnp.zeros(2).at[i].set(eps)
        fd_x = (out(x + e, c) - out(x - e, c)) / (2 * eps)
        fd_c = (out(x, c + e) - out(x, c - e)) / (2 * eps)
        fd_h = (jax.grad(out)(x + e, c) - jax.grad(out)(x - e, c)) / (2 * eps)
        np.testing.assert_allclose(grad_x[i], fd_x, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(grad_c[i], fd_c, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(hess_x[:, i], fd_h, rtol=1e-6, atol=1e-9)
