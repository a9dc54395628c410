"""Real pendulum recording: what `python -m experiments.pendulum_friction` relies on
(its stages are in experiments/pendulum_friction/).

The data (../shared/data/pendulum, MultiArm-Pendulum benchmark, Kaheman et
al. 2022) is not part of the repository; the tests that read it skip when it
is absent.
"""

import numpy as np
import pytest

from experiments.pendulum_friction import data as D, energy as EN, model as M


@pytest.fixture(scope="module")
def data():
    if not D.DEFAULT_DATA.is_file():
        pytest.skip(
            f"pendulum data not found at {D.DEFAULT_DATA} (download "
            f"single_pendulum_freeswing_1khz.mat from {D.SOURCE})"
        )
    return D.load_segments(D.DEFAULT_DATA)


def test_loader_and_calibration(data):
    assert data["dt"] == 0.001
    assert data["identification"].shape == (4, 2, 9166)
    assert data["validation"].shape == (2, 2, 9166)
    theta = data["identification"][:, 0]
    assert np.all(np.abs(np.mean(theta, axis=1) - np.pi) < 0.05)
    cal = D.calibrate(data["identification"], data["dt"])
    # The rest angle is about 1 mrad off pi; the period gives ω0² a little
    # below the published 64.2 s^-2.
    assert 0.0 < cal["offset"] < 3e-3
    assert 63.9 < cal["omega0_sq"] < 64.2 and cal["omega0_sq_spread"] < 0.05
    assert 1e-5 < D.angle_noise_std(theta) < 1e-4


def test_energy_balance_needs_more_than_viscous_friction(data):
    cal = D.calibrate(data["identification"], data["dt"])
    rates = {}
    for part in ("identification", "validation"):
        rows = EN.energy_balance(
            data[part], cal["offset"], cal["omega0_sq"], data["dt"]
        )
        assert np.all(rows[:, 1] > 0)  # every swing loses energy
        fit = EN.fit_dissipation(rows, ("viscous damping",))
        rates[part] = fit["viscous damping"]
    # The viscous rate that explains the large swings is below the published
    # 0.067 s^-1, the one that explains the small swings above it: a single
    # viscous rate does not describe both (a Coulomb-like component).
    ident, valid = rates["identification"], rates["validation"]
    assert 0.045 < ident["value"] < 0.065
    assert valid["value"] > ident["value"] + 5 * np.hypot(
        ident["std_error"], valid["std_error"]
    )


def test_midpoint_kick_is_a_continuous_time_rate():
    import jax
    import jax.numpy as jnp

    # A damped pendulum simulated with the nominal RK4 step plus c times the
    # viscous candidate at 100 Hz loses the energy of the continuous damped
    # pendulum at rate c (reference: RK4 at 1 ms).
    w2, c, dt, amp = 64.0, 0.067, 0.01, 1.2
    library = M.pendulum_library(dt, w2)
    feature = next(c for c in library if c.name == "viscous damping").feature
    params = {"dt": jnp.asarray(dt), "omega0_sq": jnp.asarray(w2)}
    zero = jnp.zeros(1)

    def coarse(x, _):
        return M.pendulum_step(x, zero, params) + c * feature(x, zero), None

    def fine(x, _):
        h = 1e-3
        f = lambda s: jnp.stack([s[1], -w2 * jnp.sin(s[0]) - c * s[1]])  # noqa: E731
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + f(x + h * k3)), None

    x0 = jnp.array([amp, 0.0])
    xc, _ = jax.lax.scan(coarse, x0, None, length=500)
    xf, _ = jax.lax.scan(fine, x0, None, length=5000)

    def energy(x):
        return 0.5 * x[1] ** 2 + w2 * (1 - jnp.cos(x[0]))

    lost_coarse = energy(x0) - energy(xc)
    lost_fine = energy(x0) - energy(xf)
    assert abs(float(lost_coarse / lost_fine) - 1) < 0.01


def test_ideal_pendulum_disagrees_with_the_recording(data):
    import eqsmooth.discover as dc

    # 1 s of each identification segment at 100 Hz, one candidate (viscous
    # friction) to keep compilation short: the score test must fire.
    cal = D.calibrate(data["identification"], data["dt"])
    dt = 10 * data["dt"]
    raw = D.windows(data["identification"], 1000, 1)
    seqs = D.make_sequences(raw, 10, cal["offset"])
    assert seqs.measurements.shape == (4, 100, 1)
    full = M.build_model(dt, cal["omega0_sq"], 4e-5)
    viscous = full.candidates[full.index("viscous damping")]
    model = dc.ChainModel(
        full.dynamics,
        full.measurement,
        full.params,
        full.process_sigma,
        full.measurement_sigma,
        full.prior_sigma,
        (viscous,),
    )
    found = dc.find(model, seqs)
    assert found["detected"]
    assert found["score_test"]["p_value"] < 1e-6
    (cand,) = found["candidates"]
    assert cand["score_z"] > 0  # the data want positive (dissipative) friction
