"""Hostile input, round three: the features added since the second round.

102 cases (88 here, 14 in the files named below), each asserting a clear
error (the exact type, with the argument, factor, rows or file named in the
message) or the right answer. By class:

- **Noise heads** (`ConstantNoiseHead`, `HeteroscedasticNoiseHead`, 36): a
  zero, negative, infinite or NaN `sigma` (zero gave σ⁻¹ = inf, a negative
  one σ = 1000, silently), a `sigma` of rank 2, a negative or infinite
  `floor`, a floor of the wrong shape, a floor at or above `1/sigma` (the
  head silently started at the floor), non-positive `in_size`/`width`, a
  bool width, a negative `depth`, a non-positive or NaN `scale`, an
  infinite `shift`, features of another size than `in_size` at the call (a
  raw `dot_general` error), and the largest floor allowed starting at
  `1/sigma`.
- **`KernelChoice` and robust composition** (13): an index out of range set
  with `eqx.tree_at` (clamped by `lax.switch` before), jitted and batched;
  every index in range selecting its kernel; an unknown name; an int for a
  kernel; a zero, negative, NaN or wrongly shaped Huber scale; a kernel that
  is a string; nested kernels; a zero or NaN Student-t dof.
- **Row masks** (3 here; 2 in `test_masked_noise.py`: NaN in a masked row
  reaches no value or derivative): a float mask, a mask of the wrong length,
  a mask around Student-t noise.
- **Training option groups and checkpoints** (13 here; 4 in
  `test_hostile_checkpoint.py`: a checkpoint of another model, of the same
  leaves under other names, of another optimiser, of another batch size):
  a checkpoint or log path below a file (a `FileExistsError` at the first
  write before), at a folder; validation data scored by the training loss
  with another structure or example shape (a `KeyError` in the loss
  before), without examples, ragged; intervals 0, -1 or a bool; a batch
  size of 0.
- **Batched and diverged solves** (6 here; 4 in `test_adjoint.py`: NaN
  gradients of failed solves per adjoint, solo and batched): one values dict
  for a batch (a `vmap` size error before), too few values, no graphs, a
  string among the graphs, two structures; a diverged Gauss-Newton solve
  naming where its first step went.
- **Discovery** (6 here; 2 in `test_discover.py`: `name` and `add` given
  other data than `find`'s): a level of 1.5, 1, 0 or -0.1; a constant
  measurement channel; `name` of a dict.
- **The fixed-lag smoother's per-step API** (6 here; 2 in
  `test_fixed_lag.py`: a state from a smoother of another lag, blamed on
  "factors differ in kind" before, and a float32 step after a float64 init,
  an error inside `lax.dynamic_update_slice` before): a lag of 1.5 or
  `True`, a dict for a state, a covariance of the wrong shape, a robust
  measurement at `init` and at `update`.
- **Loaders and caches of the experiments** (5): a binary file given as
  KITTI poses (a `UnicodeDecodeError` naming no path before), a pendulum
  recording without its keys (a bare `KeyError`) or not a MATLAB file, a
  fold cache whose arrays have other sizes than its name (returned as such
  before), a KITTI sensor cache of another length, first frame or format
  (read without a check before).

A wrong type is named by the run's type checker (jaxtyping's hook) before
eqsmooth's own check; those cases accept either.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises
from jaxtyping import TypeCheckError

import eqsmooth as eqs
from eqsmooth import learn as L


@pytest.mark.parametrize(
    "sigma, fragment",
    [
        (0.0, "[0.0]" if False else "0.0"),
        (-1.0, "-1.0"),
        (np.inf, "inf"),
        (np.nan, "nan"),
        (np.array([0.5, -2.0]), "-2.0"),
    ],
)
@pytest.mark.parametrize("head", ["constant", "heteroscedastic"])
def test_noise_head_sigma_must_be_positive_and_finite(head, sigma, fragment):
    name = {
        "constant": "ConstantNoiseHead",
        "heteroscedastic": "HeteroscedasticNoiseHead",
    }
    with raises(ValueError, name[head], "sigma", "positive and finite", fragment):
        _build(head, sigma)


def _build(head, sigma, **kw):
    if head == "constant":
        return L.ConstantNoiseHead(sigma, **kw)
    kw = {"width": 4, "depth": 1, "key": jax.random.key(0), **kw}
    return L.HeteroscedasticNoiseHead(sigma, kw.pop("in_size", 1), **kw)


@pytest.mark.parametrize("head", ["constant", "heteroscedastic"])
@pytest.mark.parametrize(
    "sigma, kw, exc, fragments",
    [
        (
            np.ones((2, 2)),
            {},
            ValueError,
            ["sigma must have shape () or (m,)", "(2, 2)"],
        ),
        (0.5, {"floor": -0.1}, ValueError, ["floor must be >= 0", "-0.1"]),
        (0.5, {"floor": np.inf}, ValueError, ["floor must be >= 0"]),
        (0.5, {"floor": 2.0}, ValueError, ["floor 2.0 must be below 1/sigma = 2.0"]),
        (0.5, {"floor": 3.0}, ValueError, ["floor 3.0 must be below 1/sigma"]),
        (
            np.array([0.5, 2.0]),
            {"floor": (0.1, 0.6)},
            ValueError,
            ["must be below 1/sigma", "[2.0, 0.5]"],
        ),
        (np.array([0.5, 2.0]), {"floor": (0.1, 0.1, 0.1)}, ValueError, ["(3,)"]),
    ],
)
def test_noise_head_arguments_are_checked(head, sigma, kw, exc, fragments):
    with raises(exc, *fragments):
        _build(head, sigma, **kw)


@pytest.mark.parametrize(
    "kw, exc, fragments",
    [
        ({"in_size": 0}, ValueError, ["in_size must be >= 1", "0"]),
        ({"width": 0}, ValueError, ["width must be >= 1"]),
        ({"width": True}, TypeError, ["width must be an int"]),
        ({"depth": -1}, ValueError, ["depth must be >= 0"]),
        ({"scale": 0.0}, ValueError, ["scale must be positive and finite"]),
        ({"scale": np.nan}, ValueError, ["scale must be positive and finite"]),
        ({"shift": np.inf}, ValueError, ["shift must be finite"]),
    ],
)
def test_heteroscedastic_head_mlp_arguments(kw, exc, fragments):
    with raises(exc, "HeteroscedasticNoiseHead", *fragments):
        _build("heteroscedastic", 0.5, **kw)


@pytest.mark.parametrize("shape", [(5, 3), (5,), (2, 5, 2), ()])
def test_heteroscedastic_head_names_in_size_for_features_of_another_size(shape):
    head = _build("heteroscedastic", 0.5, in_size=1)
    with raises(ValueError, "in_size=1", str(shape)):
        head(jnp.ones(shape))


def test_noise_heads_start_at_one_over_sigma_just_above_the_floor():
    # The largest floor allowed starts where the docs say, at 1/sigma.
    for head in ("constant", "heteroscedastic"):
        h = _build(head, np.array([0.5, 4.0]), floor=(1.99, 0.24))
        np.testing.assert_allclose(h(jnp.ones((3, 1))), [[2.0, 0.25]] * 3, rtol=1e-6)


@pytest.mark.parametrize("index", [9, 12, -1])
def test_kernel_choice_index_out_of_range_is_an_error_not_a_clamp(index):
    choice = eqs.factors.KernelChoice("Huber")
    bad = eqx.tree_at(lambda k: k.index, choice, jnp.int32(index))
    rho = eqx.filter_jit(lambda k, s: k.rho(s, jnp.asarray(1.0)))
    with pytest.raises(
        eqx.EquinoxRuntimeError, match="KernelChoice.index must be in 0..8"
    ):
        rho(bad, jnp.ones(3))
    # Swept as data, one bad element is enough.
    indices = jnp.asarray([0, index], jnp.int32)
    batched = eqx.filter_vmap(
        lambda i: rho(eqx.tree_at(lambda k: k.index, choice, i), jnp.ones(3))
    )
    with pytest.raises(eqx.EquinoxRuntimeError, match="KernelChoice.index"):
        batched(indices)


def test_kernel_choice_in_range_still_selects_its_kernel():
    s = jnp.asarray([0.25, 4.0, 25.0])
    from eqsmooth.factors._robust_kernels import KERNELS

    for i, K in enumerate(KERNELS):
        choice = eqx.tree_at(
            lambda k: k.index, eqs.factors.KernelChoice("Huber"), jnp.int32(i)
        )
        np.testing.assert_allclose(
            eqx.filter_jit(choice.rho)(s, jnp.asarray(1.0))[0],
            K().rho(s, jnp.asarray(1.0))[0],
        )
    with raises(ValueError, "KernelChoice: unknown kernel", "'Hubber'"):
        eqs.factors.KernelChoice("Hubber")


# ---------------------------------------------------------------------------
# Training options, batched solves, diverged solves
# ---------------------------------------------------------------------------


class _Line(eqx.Module):
    w: jax.Array


def _line_loss(model, batch):
    return jnp.mean((model.w * batch["x"] - batch["y"]) ** 2)


_LINE_DATA = {"x": np.linspace(0.0, 1.0, 8), "y": np.linspace(0.0, 2.0, 8)}


@pytest.mark.parametrize("option", ["Checkpoints", "Logging"])
def test_a_file_path_below_a_file_is_refused_when_the_option_is_built(option, tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    path = blocker / "run" / "file.eqx"
    cls = getattr(L, option)
    with raises(ValueError, f"{option}: path {path} cannot be written", "is a file"):
        cls(path)


@pytest.mark.parametrize(
    "valid, fragments",
    [
        ({"x": np.ones(4)}, ["structure differs from train_data's", "'y'"]),
        ({"x": np.ones(4), "y": np.ones(4), "z": np.ones(4)}, ["structure differs"]),
        ({"x": np.ones((4, 2)), "y": np.ones(4)}, ["validation.data['x']", "(2,)"]),
    ],
)
def test_validation_data_must_look_like_the_training_data(valid, fragments):
    import optax

    with raises(ValueError, "train: validation.data", *fragments):
        L.train(
            _Line(jnp.asarray(0.0)),
            _line_loss,
            _LINE_DATA,
            optimizer=optax.sgd(0.1),
            num_steps=1,
            batch_size=4,
            validation=L.Validation(valid),
            logging=L.Logging(progress=False),
        )


def test_one_values_dict_for_a_batch_of_graphs_is_named():
    from helpers import se2_loop

    graphs, values = zip(*[se2_loop(s)[:2] for s in range(3)])
    with raises(ValueError, "least_squares_batch: values['pose']", "3 graphs"):
        eqs.least_squares_batch(list(graphs), values[0], eqs.LevenbergMarquardt())


def _sqrt_residual(x, data, params):
    return jnp.sqrt(x) - data


def test_a_diverged_solve_says_where_its_first_step_went():
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _sqrt_residual,
                (eqs.Var("x", [0, 1]),),
                eqs.IsotropicNoise.from_sigma(1.0),
                data=jnp.asarray([[0.1], [0.1]]),
            )
        ]
    )
    x0 = {"x": jnp.asarray([[4.0], [4.0]])}
    with raises(
        eqx.EquinoxRuntimeError,
        "Nonlinear solve diverged",
        "the first Gauss-Newton step",
        "FunctionFactor (factor stack 0): non-finite residual in rows [0, 1]",
    ):
        eqs.least_squares(graph, x0, eqs.GaussNewton())
    # Levenberg-Marquardt's damping shortens the step: it converges.
    sol = eqs.least_squares(graph, x0, eqs.LevenbergMarquardt())
    np.testing.assert_allclose(sol.value["x"], 0.01, rtol=1e-6)


# ---------------------------------------------------------------------------
# Loaders and caches of the experiments (run from the checkout)
# ---------------------------------------------------------------------------


def test_a_binary_file_given_as_kitti_poses_is_named(tmp_path):
    from experiments.kitti_vo import data as D

    path = tmp_path / "00.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00")
    with raises(ValueError, str(path), "not a KITTI pose file", "offset 0"):
        D.read_poses(path)


@pytest.mark.parametrize("content", ["keys", "not_mat"])
def test_a_pendulum_recording_without_its_keys_is_named(content, tmp_path):
    scipy_io = pytest.importorskip("scipy.io")
    from experiments.pendulum_friction import data as P

    path = tmp_path / "recording.mat"
    if content == "keys":
        scipy_io.savemat(path, {"Y_id": np.ones((1, 3)), "dt": 0.001})
        fragments = ["lacks ['Y_vad']", "MultiArm-Pendulum"]
    else:
        path.write_text("not a MATLAB file")
        fragments = ["not a MATLAB file of the MultiArm-Pendulum recording"]
    with raises(ValueError, str(path), *fragments):
        P.load_segments(path)


def test_a_cache_holding_other_shapes_than_its_name_is_rebuilt(tmp_path):
    from experiments.disk_tracking import data as D

    small = D.load_fold(0, 0, num_sequences=2, num_frames=3, cache_dir=tmp_path)
    # Another fold's arrays under this fold's name (n=2, t=4).
    (cached,) = tmp_path.glob("*.npz")
    cached.rename(tmp_path / cached.name.replace("_t3", "_t4"))
    with pytest.warns(UserWarning, match="damaged cache file.*expected leading"):
        fold = D.load_fold(0, 0, num_sequences=2, num_frames=4, cache_dir=tmp_path)
    assert fold.visible_pixels.shape == (2, 4)
    assert small.visible_pixels.shape == (2, 3)


# ---------------------------------------------------------------------------
# A table of the other new APIs: each case a clear error naming the argument
# ---------------------------------------------------------------------------

_BASE = eqs.IsotropicNoise.from_sigma(1.0)


def _measure(x, data, params):
    return x - data


def _stack(noise, n=4):
    return eqs.FunctionFactor(
        _measure, (eqs.Var("x", np.arange(n)),), noise, data=jnp.zeros((n, 1))
    )


def _solve(noise):
    graph = eqs.FactorGraph([_stack(noise)])
    return eqs.least_squares(graph, {"x": jnp.zeros((4, 1))}, eqs.GaussNewton())


def _batch(graphs, values):
    return eqs.least_squares_batch(graphs, values, eqs.GaussNewton())


def _train(valid=None, batch_size=2):
    import optax

    return L.train(
        _Line(jnp.asarray(0.0)),
        _line_loss,
        _LINE_DATA,
        optimizer=optax.sgd(0.1),
        num_steps=1,
        batch_size=batch_size,
        validation=None if valid is None else L.Validation(valid),
        logging=L.Logging(progress=False),
    )


def _find(alpha=0.05, constant=False):
    import dataclasses

    from test_discover import _model, _simulate

    import eqsmooth.discover as dc

    data = _simulate(2)
    if constant:
        flat = np.full_like(np.asarray(data.measurements), 0.3)
        data = dataclasses.replace(data, measurements=flat)
    return dc.find(_model(), data, alpha=alpha)


def _fixed_lag(case):
    from test_fixed_lag_updates import _se2_initial, _se2_steps

    (_, _, truth), trans, meas = _se2_steps(1.0)
    mean0, cov0 = _se2_initial(truth)
    smoother = eqs.filters.FixedLagSmoother(lag=2)
    robust = eqx.tree_at(lambda f: f.noise, meas[1], eqs.HuberNoise(meas[1].noise, 1.0))
    if case == "covariance shape":
        return smoother.init(mean0, jnp.eye(2), trans[0], meas[0])
    if case == "robust init":
        return smoother.init(mean0, cov0, trans[0], robust)
    state, _ = smoother.init(mean0, cov0, trans[0], meas[0])
    if case == "robust update":
        return smoother.update(state, trans[0], robust)
    return smoother.update({"t": 0}, trans[0], meas[1])


# A wrong type: the runtime type checker of the test run (jaxtyping's hook)
# names the parameter first; without it, eqsmooth's own check does.
_TYPED = (TypeCheckError, TypeError, ValueError)

_TABLE = {
    # robust composition
    "Huber scale 0": (
        lambda: eqs.HuberNoise(_BASE, 0.0),
        ValueError,
        ["HuberNoise.scale must be positive", "0.0"],
    ),
    "Huber scale -1": (
        lambda: eqs.HuberNoise(_BASE, -1.0),
        ValueError,
        ["HuberNoise.scale must be positive", "-1.0"],
    ),
    "Huber scale nan": (
        lambda: eqs.HuberNoise(_BASE, jnp.nan),
        ValueError,
        ["HuberNoise.scale must be finite"],
    ),
    "Huber scale rows": (
        lambda: _solve(eqs.HuberNoise(_BASE, jnp.ones(3))),
        ValueError,
        ["FunctionFactor: HuberNoise.scale has shape (3,)", "(4,)"],
    ),
    "kernel not a kernel": (
        lambda: eqs.RobustNoise(_BASE, "Huber", 1.0),
        _TYPED,
        ["kernel", "Huber"],
    ),
    "kernels nested": (
        lambda: eqs.HuberNoise(eqs.TukeyNoise(_BASE, 1.0), 1.0),
        TypeError,
        ["HuberNoise.base must be a Gaussian", "TukeyNoise", "do not nest"],
    ),
    "Student-t dof 0": (
        lambda: eqs.StudentTNoise(_BASE, 0.0),
        ValueError,
        ["StudentTNoise.dof must be positive"],
    ),
    "Student-t dof nan": (
        lambda: eqs.StudentTNoise(_BASE, jnp.nan),
        ValueError,
        ["StudentTNoise.dof must be finite"],
    ),
    "KernelChoice of an int": (
        lambda: eqs.factors.KernelChoice(3),
        _TYPED,
        ["kernel", "3"],
    ),
    # row masks
    "mask of floats": (
        lambda: eqs.MaskedNoise(_BASE, jnp.ones(4)),
        TypeError,
        ["MaskedNoise.active must be booleans", ".astype(bool)"],
    ),
    "mask rows": (
        lambda: _solve(eqs.MaskedNoise(_BASE, jnp.ones(3, bool))),
        ValueError,
        ["FunctionFactor: MaskedNoise.active has shape (3,)", "(4,)"],
    ),
    "mask of Student-t": (
        lambda: eqs.MaskedNoise(eqs.StudentTNoise(_BASE, 4.0), jnp.ones(4, bool)),
        TypeError,
        ["MaskedNoise.base must be a Gaussian", "StudentTNoise"],
    ),
    # training option groups
    "Validation every 0": (
        lambda: L.Validation({"x": np.ones(3)}, every=0),
        ValueError,
        ["Validation: every must be an int >= 1", "0"],
    ),
    "Validation every True": (
        lambda: L.Validation({"x": np.ones(3)}, every=True),
        _TYPED,
        ["every", "True"],
    ),
    "Checkpoints at a folder": (
        lambda: L.Checkpoints("."),
        ValueError,
        ["Checkpoints: path . is a directory"],
    ),
    "Checkpoints every 0": (
        lambda: L.Checkpoints("ckpt.eqx", every=0),
        ValueError,
        ["Checkpoints: every must be an int >= 1"],
    ),
    "Logging every -1": (
        lambda: L.Logging(every=-1),
        ValueError,
        ["Logging: every must be an int >= 1", "-1"],
    ),
    "batch size 0": (
        lambda: _train(batch_size=0),
        ValueError,
        ["train: need batch_size >= 1", "0"],
    ),
    "validation without examples": (
        lambda: _train({"x": np.ones(0), "y": np.ones(0)}),
        ValueError,
        ["train: validation.data has no examples"],
    ),
    "validation ragged": (
        lambda: _train({"x": np.ones(3), "y": np.ones(2)}),
        ValueError,
        ["validation.data needs the same leading (example) axis", "(3,)", "(2,)"],
    ),
    # batched solves
    "batch of no graphs": (
        lambda: _batch([], []),
        ValueError,
        ["least_squares_batch: no graphs"],
    ),
    "batch with a string": (
        lambda: _batch(
            [eqs.FactorGraph([_stack(_BASE)]), "g"], [{"x": jnp.zeros((4, 1))}] * 2
        ),
        _TYPED,  # beartype checks one random element of a list
        ["graphs"],
    ),
    "batch of two structures": (
        lambda: _batch(
            [eqs.FactorGraph([_stack(_BASE)]), eqs.FactorGraph([_stack(_BASE, 3)])],
            [{"x": jnp.zeros((4, 1))}, {"x": jnp.zeros((3, 1))}],
        ),
        ValueError,
        ["stack_trees: tree 1 differs in structure from tree 0"],
    ),
    "batch with too few values": (
        lambda: _batch(
            [eqs.FactorGraph([_stack(_BASE)])] * 3, [{"x": jnp.zeros((4, 1))}] * 2
        ),
        ValueError,
        ["least_squares_batch: values['x'] has shape (2, 4, 1)", "3 graphs"],
    ),
    # discovery: a level outside (0, 1) (1.5 declared detections, 0 never
    # could); a channel that never changes (its noise scale ran to 1e-21)
    **{
        f"find alpha {a}": (
            lambda a=a: _find(alpha=a),
            ValueError,
            ["find: alpha", "must lie in (0, 1)", str(a)],
        )
        for a in (1.5, 1.0, 0.0, -0.1)
    },
    "find of a constant channel": (
        lambda: _find(constant=True),
        ValueError,
        ["find: data.measurements channel(s) [0]", "[0.3]", "drop the channel"],
    ),
    "name of a dict": (
        lambda: __import__("eqsmooth.discover").discover.name({"detected": True}, None),
        _TYPED,
        ["found"],
    ),
    # the fixed-lag smoother's per-step API
    "lag 1.5": (
        lambda: eqs.filters.FixedLagSmoother(lag=1.5),
        _TYPED,
        ["lag", "1.5"],
    ),
    "lag True": (
        lambda: eqs.filters.FixedLagSmoother(lag=True),
        ValueError,
        ["FixedLagSmoother: lag must be an int >= 1", "True"],
    ),
    "update of a dict": (
        lambda: _fixed_lag("not a state"),
        _TYPED,
        ["state", "FixedLagState"],
    ),
    "init covariance shape": (
        lambda: _fixed_lag("covariance shape"),
        ValueError,
        ["FixedLagSmoother.init: initial_covariance has shape (2, 2)", "(6, 6)"],
    ),
    "robust measurement at init": (
        lambda: _fixed_lag("robust init"),
        TypeError,
        ["FixedLagSmoother.init: factor FunctionFactor", "RobustNoise is robust"],
    ),
    "robust measurement at update": (
        lambda: _fixed_lag("robust update"),
        TypeError,
        ["FixedLagSmoother.update: factor FunctionFactor", "RobustNoise is robust"],
    ),
}


@pytest.mark.parametrize("case", list(_TABLE))
def test_new_apis_name_what_is_wrong(case):
    build, exc, fragments = _TABLE[case]
    if exc is _TYPED:
        with pytest.raises(exc) as info:
            build()
        for fragment in fragments:
            assert fragment in str(info.value), (fragment, str(info.value))
        return
    with raises(exc, *fragments):
        build()


def test_a_sensor_cache_of_another_length_is_rebuilt(tmp_path):
    from experiments.kitti_vo import experiment as E

    path = tmp_path / "seq.npz"
    arrays = {k: np.ones((5, 2)) for k in ("z", "log_sigma", "features")}
    np.savez(path, first=np.asarray(3), **arrays)
    assert E._read_sensor_cache(path, 3, 5)["z"].shape == (5, 2)
    with pytest.warns(UserWarning, match="damaged cache file.*leading axes \\(7,\\)"):
        assert E._read_sensor_cache(path, 3, 7) is None
    with pytest.warns(UserWarning, match="starts at frame 3, not 0"):
        assert E._read_sensor_cache(path, 0, 5) is None
    path.write_bytes(b"not a zip")
    with pytest.warns(UserWarning, match=f"{path}: damaged cache file"):
        assert E._read_sensor_cache(path, 3, 5) is None
