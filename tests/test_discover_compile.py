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
