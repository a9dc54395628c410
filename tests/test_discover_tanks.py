"""Cascaded Tanks benchmark: what examples/10_discover_cascaded_tanks.py
relies on.

The data (../shared/data/cascaded_tanks/dataBenchmark.csv, Schoukens et al.
2016) is not part of the repository; the tests that read it skip when it is
absent.
"""

import importlib.util
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


EXAMPLE = (
    Path(__file__).resolve().parents[1] / "examples" / "10_discover_cascaded_tanks.py"
)


@pytest.fixture(scope="module")
def ex():
    spec = importlib.util.spec_from_file_location("discover_tanks", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def data(ex):
    if not ex.DEFAULT_DATA.is_file():
        pytest.skip(
            f"Cascaded Tanks data not found at {ex.DEFAULT_DATA} (dataBenchmark.csv "
            "of the benchmark, www.nonlinearbenchmark.org; see "
            "shared/data/README.md)"
        )
    return ex.load(ex.DEFAULT_DATA)


def test_loader(ex, data):
    assert data["ts"] == 4.0
    for key in ("u_est", "y_est", "u_val", "y_val"):
        assert data[key].shape == (1024,) and np.all(np.isfinite(data[key]))
    # The level reading stops at 10 V in both records (the hard limit).
    assert data["y_est"].max() == ex.SENSOR_LIMIT == data["y_val"].max()


def test_user_candidates_have_the_right_shapes(ex):
    import jax.numpy as jnp

    from eqsmooth.discover._candidates import check_features

    library = ex.tank_library((0.05, 0.09), (5.0, 7.5))
    check_features(library, jnp.zeros(2), jnp.zeros(1), 1)
    names = [c.name for c in library]
    assert len(set(names)) == len(names)
    # The upper tank's overflow level is profiled: two families over it.
    families = {c.profiled.family for c in library if c.profiled is not None}
    assert families == {"upper overflow (lost)", "upper overflow (to lower)"}
    # Rate candidates act inside the integrator the model is built on.
    assert {c.target for c in library} == {"rate", "measurement"}


def test_fit_output_error_drops_a_non_finite_start(ex, data):
    """A start whose simulation is not finite (here k₁ = e⁸⁰⁰ overflows)
    comes back as a failed fit with an infinite RMSE and the reason, for the
    multi-start refit to drop; scipy stopped the whole example on one."""
    model = ex.tank_model(data["ts"])
    y0 = float(data["y_est"][0])
    theta0 = np.array([800.0, np.log(0.05), np.log(0.05), y0, y0])
    fit = ex.fit_output_error(data["u_est"], data["y_est"], model, theta0)
    assert fit["rmse"] == math.inf
    assert fit["failed"].startswith("not finite: the simulation at")
    np.testing.assert_array_equal(fit["theta"], theta0)


@pytest.mark.slow
def test_quick_example_runs(data, tmp_path):
    out = subprocess.run(
        [sys.executable, str(EXAMPLE), "--quick", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=1800,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["workflow"]["find"]["status"] == "ok"
    assert report["workflow"]["find"]["detected"]
    assert report["nominal"]["validation_rmse"] > 0
    # The workflow names the upper tank's overflow, and adding what it named
    # lowers the validation RMSE (0.669 -> 0.284 V at the commit that added
    # this check).
    named = report["workflow"]["name"]["named"]
    assert any(nm.startswith("upper overflow") for nm in named), named
    stages = report["after"]["stages"]
    assert stages[-1]["validation_rmse"] < 0.8 * report["nominal"]["validation_rmse"]
    # A coefficient without a standard error is explained by a flag, never a
    # bare NaN (the sensor clip's information matrix is indefinite).
    added = report["workflow"]["add"]
    for c in added["coefficients"]:
        if not math.isfinite(c["std_error"]):
            assert any(c["name"] in f for f in added["flags"]), added["flags"]
