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


def test_stored_program_is_read_back_without_tracing(tmp_path, monkeypatch):
    """With a program folder (`enable_compilation_cache`), a function is
    exported once and a later wrapper (as in a new process) calls the stored
    program without tracing it; under a transformation it runs as before."""
    import jax

    from eqsmooth import _compilation_cache as cc

    monkeypatch.setattr(cc, "_PROGRAM_DIR", tmp_path)
    traces = []

    def fn(x, power):
        traces.append(power)
        return {"y": jnp.sin(x) ** power, "z": (x.sum(),)}

    def fingerprint(arguments):
        return ""

    x = jnp.linspace(0.0, 1.0, 5)
    first = cc.stored_program(fn, jax.jit(fn, static_argnums=1), fingerprint)
    out = first(x, 2)
    assert traces == [2] and len(list(tmp_path.iterdir())) == 1
    later = cc.stored_program(fn, jax.jit(fn, static_argnums=1), fingerprint)
    again = later(x, power=2)
    assert traces == [2]  # read back, not traced
    assert jax.tree.structure(again) == jax.tree.structure(out)
    np.testing.assert_array_equal(np.asarray(again["y"]), np.sin(x) ** 2)
    with compiled_programs() as names:  # placed or not: one program
        later(jax.device_put(x, jax.devices()[0]), 2)
        later(np.asarray(x), 2)
    assert names == [], names
    later(x, 3)  # another static argument: another program
    assert traces == [2, 3] and len(list(tmp_path.iterdir())) == 2
    grad = jax.grad(lambda x: later(x, 2)["z"][0])(x)  # traced: not stored
    np.testing.assert_array_equal(np.asarray(grad), np.ones(5))


def test_model_fingerprint_follows_the_model_functions():
    """The key of a stored discover program changes with what the model's
    functions compute (their constants too), not with the objects."""
    from test_discover import _simulate

    import eqsmooth.discover as dc
    from eqsmooth.discover._model import _fingerprint

    data = _simulate(0)
    library = dc.mechanical_library([0], [1], 2, measured_positions=[0])

    def model(gain):
        def dyn(x, u, params):
            return jnp.asarray(gain) @ x + jnp.stack([0.0, -params * x[0]])

        def meas(x, params):
            return x[:1]

        sigmas = (np.ones(2), np.ones(1), np.ones(2))
        return dc.ChainModel(dyn, meas, jnp.asarray(0.1), *sigmas, library)

    a = np.array([[1.0, 1.0], [0.0, 1.0]])
    key = _fingerprint({"model": model(a), "data": data})
    assert _fingerprint({"model": model(a.copy()), "data": data}) == key
    assert _fingerprint({"model": model(a * 1.01), "data": data}) != key
    other = {"model": model(a), "inputs": np.zeros((2, 3, 4))}
    assert _fingerprint(other) != key  # another input size
