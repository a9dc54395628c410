"""Small things a new user meets first: top-level names, a readable result
code, and a warning when a FunctionFactor's function is re-created."""

import warnings

import jax.numpy as jnp
import pytest


def test_top_level_exports():
    import eqsmooth as eqs

    for name in (
        "SparseLU",
        "SparseCholesky",
        "ChainPreconditioner",
        "PCG",
        "linearize",
        "joint_marginal_covariance",
        "RangeFactor",
        "BearingFactor",
        "BearingRangeFactor",
        "TranslationPriorFactor",
        "PoseToPointFactor",
        "TukeyNoise",
        "GemanMcClureNoise",
        "WelschNoise",
        "DCSNoise",
        "FairNoise",
        "L2WithDeadZoneNoise",
        "TruncatedQuadraticNoise",
    ):
        assert getattr(eqs, name) is not None, name
    assert eqs.SparseLU is eqs.solve.SparseLU
    assert eqs.linearize is eqs.solve.linearize


def test_successful_result_is_readable():
    import eqsmooth as eqs

    text = repr(eqs.RESULTS.successful)
    assert text.endswith("<successful>"), text
    # The other codes keep their messages and optimistix's codes still promote.
    assert "singular" in repr(eqs.RESULTS.linear_solve_failed)
    import optimistix as optx

    promoted = eqs.RESULTS.promote(optx.RESULTS.successful)
    assert bool(promoted == eqs.RESULTS.successful)


def _residual(x, data, params):
    return x - data


def test_function_factor_warns_on_recreated_lambdas():
    import eqsmooth as eqs

    noise = eqs.IsotropicNoise(sqrt_precision=1.0)
    var = eqs.Var("x", [0])
    data = jnp.zeros((1, 2))
    # The same module-level function, many times: no warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(5):
            eqs.FunctionFactor(_residual, (var,), noise, data=data)

    def build():
        return eqs.FunctionFactor(lambda x, d, p: x - d, (var,), noise, data=data)

    build()  # the first object: nothing to say yet
    with pytest.warns(UserWarning, match="new function object"):
        build()  # the second one with the same code warns at once
    # Once per code object: no second warning.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(3):
            build()
