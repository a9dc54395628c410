"""Hostile input, round three: the features added since the second round.

Each case asserts a clear error (the exact type, and the argument, field,
shape or file named in the message) or the right answer. By class:

- **Noise heads** (`ConstantNoiseHead`, `HeteroscedasticNoiseHead`): a zero,
  negative, infinite or NaN `sigma` (a zero one gave σ⁻¹ = inf, a negative
  one σ = 1000 silently), a `sigma` of rank 2, a negative or non-finite
  `floor`, a floor of the wrong shape, a floor at or above `1/sigma` (the
  head silently started at the floor, not at `1/sigma`), non-integer or
  non-positive `in_size`/`width`, a negative `depth`, a non-positive or
  non-finite `scale`, a non-finite `shift`, features of another size than
  `in_size` at the call (a raw `dot_general` shape error before).
- **`KernelChoice`**: an index out of range set with `eqx.tree_at`
  (`lax.switch` clamped it to the last kernel), above and below, jitted and
  batched; an unknown kernel name.
- Elsewhere (their own files): a checkpoint of another run
  (`test_hostile_checkpoint.py`); NaN gradients of failed solves under every
  adjoint, solo and batched (`test_adjoint.py`); masked rows that no value
  in them reaches (`test_masked_noise.py`); discovery's level, constant
  channels and `name`/`add` given other data than `find`'s
  (`test_discover.py::test_discovery_refuses_what_it_cannot_use`).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises

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


@pytest.mark.parametrize("shape", [(5, 3), (5,), (2, 5, 2)])
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
