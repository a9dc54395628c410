"""What a first call of the discrepancy workflow compiles."""

import jax.numpy as jnp
import numpy as np
from helpers import compiled_programs
from test_discover import _model


def test_workflow_helpers_compile_no_eager_operations():
    """The host-side steps of `find` compile only their own programs: applied
    eagerly to JAX arrays, each operation compiled a program of its own on a
    first call (about forty, a tenth of its compile time)."""
    import eqsmooth.discover as dc
    from eqsmooth.discover._diagnostics import (
        localisation_table,
        open_loop,
        residual_summary,
    )
    from eqsmooth.discover._fit import feature_scales, fitted_model
    from eqsmooth.discover._model import apply_z, Offsets, z_of

    rng = np.random.default_rng(0)
    y = rng.normal(size=(3, 7, 1))  # shapes no other test uses
    data = dc.Sequences(y, np.zeros((3, 2)))
    x = rng.normal(size=(3, 7, 2))
    model = _model()
    z = z_of(model) + rng.normal(size=len(model.candidates) + 3) * 0.1
    with compiled_programs() as names:
        fitted = fitted_model(model, z)
        feature_scales(model, data, x)
        Offsets.zeros(data, 2)
        for check in (open_loop, residual_summary, localisation_table):
            check(fitted, data, x)
    assert set(names) <= {"jit(trajectory_checks)", "jit(_eval_features)"}, names
    reference = apply_z(model, jnp.asarray(z))
    for field in ("coefficients", "process_sigma", "measurement_sigma", "prior_sigma"):
        a, b = getattr(fitted, field), getattr(reference, field)
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-14)


def test_every_find_program_can_be_cached():
    """JAX's persistent cache stores no program with a host callback (an
    `eqx.error_if` under `jit`): the diagnostic filter's initial-belief check
    kept it out, and a process with a warm cache compiled it again (about a
    fifth of such a first call)."""
    import jax
    from test_discover import _simulate

    from eqsmooth.discover import _model as M

    data, model = _simulate(0), _model()
    x = data.initial_states
    for fn, args in (
        (M.diagnostic_innovations, (model, data, x)),
        (M.trajectory_checks, (model, x, data.inputs)),
    ):
        text = str(jax.make_jaxpr(fn.__wrapped__)(*args))
        assert "callback" not in text, fn.__name__


def test_ekf_checks_a_traced_initial_belief_only_when_asked_to_throw():
    import equinox as eqx
    import jax
    import pytest
    from test_hostile_io import _ekf_factors

    import eqsmooth as eqs

    tr, me = _ekf_factors()

    def run(cov, throw):
        return eqs.ekf(tr, me, jnp.zeros(2), cov, throw=throw).mean

    bad = jnp.array([[1.0, 2.0], [2.0, 1.0]])  # symmetric, not definite
    with pytest.raises(eqx.EquinoxRuntimeError, match="initial belief"):
        eqx.filter_jit(run)(bad, True)
    assert "callback" not in str(jax.make_jaxpr(run, static_argnums=1)(bad, False))
    with pytest.raises(ValueError, match="positive definite"):
        run(bad, False)  # concrete: checked either way
