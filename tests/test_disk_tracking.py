"""Visual disk tracking example: data generator, models, a tiny training run."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from experiments.disk_tracking import data as D


@pytest.fixture(scope="module")
def stats_fold():
    # A few hundred sequences: the statistics tests below are about the
    # generator, so they use fresh sequences (seed 123), not the constants'.
    return D.generate_fold(seed=123, fold=3, num_sequences=300)


def test_shapes_and_dtypes():
    f = D.generate_fold(seed=0, fold=0, num_sequences=4, num_frames=6)
    assert f.disk_positions.shape == (4, 6, 26, 2)
    assert f.disk_positions.dtype == np.float32
    assert f.positions.shape == (4, 6, 2) and f.velocities.shape == (4, 6, 2)
    assert f.states.shape == (4, 6, 4)
    assert f.radii.shape == (4, 26) and f.radii.dtype == np.int32
    assert np.all(f.radii[:, 0] == 7)
    assert np.all((f.radii[:, 1:] >= 3) & (f.radii[:, 1:] <= 9))
    assert np.all(f.colours[:, 0] == [255, 0, 0])
    # No distractor is red, so exact red pixels are the visible target.
    assert not np.any(np.all(f.colours[:, 1:] == [255, 0, 0], axis=-1))
    assert f.visible_pixels.shape == (4, 6) and f.visible_pixels.dtype == np.int32
    ims = f.images(np.arange(4))
    assert ims.shape == (4, 6, 120, 120, 3) and ims.dtype == np.uint8
    one = f.images(np.array([2, 3]), np.array([5, 0]))
    assert one.shape == (2, 120, 120, 3)
    np.testing.assert_array_equal(one[0], ims[2, 5])
    np.testing.assert_array_equal(one[1], ims[3, 0])
    np.testing.assert_array_equal(D.count_visible(ims), f.visible_pixels)
    assert np.all(f.visible_pixels <= 149)  # a radius-7 disk has 149 pixels


def test_render_geometry():
    # Target at (x, y) = (10, -20): column 70, row 40 (x right, y down).
    pos = np.zeros((1, 2, 2), dtype=np.float32)
    pos[0, 0] = [10.2, -19.7]
    pos[0, 1] = [200.0, 200.0]  # a distractor outside the image
    radii = np.array([[7, 5]], dtype=np.int32)
    colours = np.array([[[255, 0, 0], [0, 255, 0]]], dtype=np.uint8)
    img = D.render(pos, radii, colours)[0]
    rows, cols = np.nonzero(img[..., 0] == 255)
    assert len(rows) == 149
    assert rows.mean() == 40 and cols.mean() == 70
    assert rows.min() == 33 and rows.max() == 47
    # A distractor drawn over the target occludes it.
    pos[0, 1] = [12.0, -20.0]
    img = D.render(pos, radii, colours)[0]
    assert 0 < D.count_visible(img[None])[0] < 149
    assert np.all(img[40, 72] == [0, 255, 0])


def test_dynamics_from_pre_update_state():
    p = np.array([[10.0, -5.0]])
    v = np.array([[2.0, -3.0]])
    z = np.zeros_like(p)
    p1, v1 = D.dynamics_step(p, v, z, z)
    np.testing.assert_allclose(p1, [[12.0, -8.0]])
    np.testing.assert_allclose(
        v1, [[2.0 - 0.5 - 0.0075 * 4.0, -3.0 + 0.25 + 0.0075 * 9.0]]
    )


def test_determinism_and_prefix_stability():
    a = D.generate_fold(seed=7, fold=2, num_sequences=5, num_frames=8)
    b = D.generate_fold(seed=7, fold=2, num_sequences=3, num_frames=8)
    c = D.generate_fold(seed=8, fold=2, num_sequences=3, num_frames=8)
    d = D.generate_fold(seed=7, fold=3, num_sequences=3, num_frames=8)
    np.testing.assert_array_equal(a.disk_positions[:3], b.disk_positions)
    np.testing.assert_array_equal(a.visible_pixels[:3], b.visible_pixels)
    np.testing.assert_array_equal(a.colours[:3], b.colours)
    np.testing.assert_array_equal(a.images([0, 1]), b.images([0, 1]))
    assert not np.allclose(b.disk_positions, c.disk_positions)
    assert not np.allclose(b.disk_positions, d.disk_positions)


def test_cache_roundtrip(tmp_path):
    a = D.load_fold(seed=1, fold=0, num_sequences=3, num_frames=5, cache_dir=tmp_path)
    files = list(tmp_path.glob("*.npz"))
    assert len(files) == 1
    b = D.load_fold(seed=1, fold=0, num_sequences=3, num_frames=5, cache_dir=tmp_path)
    np.testing.assert_array_equal(a.disk_positions, b.disk_positions)
    np.testing.assert_array_equal(a.visible_pixels, b.visible_pixels)


def test_visible_pixel_statistics(stats_fold):
    # The paper's data: visible pixels 104.9 ± 47.6 over frames. Fold-to-fold
    # variation of the mean is about ±1.5 px at 505 sequences.
    c = stats_fold.visible_pixels.astype(np.float64)
    assert abs(c.mean() - 105.0) < 5.0, c.mean()
    assert abs(c.std() - 48.0) < 4.0, c.std()


def test_image_channel_statistics(stats_fold):
    # The paper's data: channel means [24.3, 29.8, 29.9] on the 0-255 scale.
    ims = stats_fold.images(np.arange(100)).reshape(-1, 3).astype(np.float64)
    mean = ims.mean(axis=0)
    np.testing.assert_allclose(mean, [24.3, 29.8, 29.9], atol=2.0)
    # And the normalisation constants the networks use match the generator.
    np.testing.assert_allclose(mean, D.IMAGE_MEAN, atol=1.5)


def test_dynamics_statistics(stats_fold):
    pos = stats_fold.positions.reshape(-1, 2)
    vel = stats_fold.velocities.reshape(-1, 2)
    assert np.all(np.abs(pos.std(axis=0) - D.POSITION_STD) < 2.5), pos.std(axis=0)
    assert np.all(np.abs(vel.std(axis=0) - 6.6) < 0.6), vel.std(axis=0)


# ---------------------------------------------------------------------------
# Models and a tiny end-to-end run
# ---------------------------------------------------------------------------


def test_model_shapes_and_noise_heads():
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from experiments.disk_tracking import models as M

    @eqx.filter_jit  # one program for the models' set-up and one for their outputs
    def build(key):
        return (
            M.VirtualSensor(key),
            M.heteroscedastic_noise(4.0, key),
            M.HeatmapSensor(key, channels=4),
            M.LstmTracker(key, bidirectional=True, num_features=4, hidden=8),
        )

    @eqx.filter_jit
    def outputs(models, img, counts):
        sensor, het, fast, lstm = models
        big = eqx.tree_at(lambda s: s.background, fast, jnp.array([-50.0, 0.0, 0.0]))
        return {
            "features": sensor.features(img),
            "sensor": sensor(img),
            "const": M.constant_noise(4.0)(counts[:, None]),
            "het": het(counts[:, None]),
            "fast": fast.outputs(img),
            "fast_features": fast.features(img),
            "big": big(img),
            "lstm": lstm(jnp.zeros((3, 4)), jnp.zeros(4)),
        }

    img = jnp.zeros((120, 120, 3), dtype=jnp.uint8)
    counts = jnp.array([0.0, 50.0, 149.0], dtype=jnp.float32)
    out = outputs(build(jax.random.key(0)), img, counts)
    assert out["features"].shape == (240,)
    assert out["sensor"].shape == (2,)
    np.testing.assert_allclose(out["const"], 0.25, rtol=1e-6)
    # Starts constant at 1/sigma (zero last layer), positive everywhere.
    np.testing.assert_allclose(out["het"], 0.25, rtol=1e-5)
    pos, vis = out["fast"]
    assert pos.shape == (2,) and vis.shape == ()
    assert out["fast_features"].shape == (3,)
    # Nothing to see in a black image: the heat map is flat, and the
    # "not visible" outcome starts as heavy as the whole map.
    assert abs(float(vis)) < 1.0
    # Without the "not visible" outcome the read-out is a mean of cell centres,
    # which lie inside the image.
    assert np.all(np.abs(np.asarray(out["big"])) <= 60)
    assert out["lstm"].shape == (3, 2)


def test_smoother_beats_its_measurements():
    import jax
    import jax.numpy as jnp

    import eqsmooth as eqs
    from experiments.disk_tracking import models as M

    f = D.generate_fold(seed=0, fold=0, num_sequences=8, num_frames=20)
    truth = jnp.asarray(f.states, jnp.float64)
    rng = np.random.default_rng(0)
    meas = truth[..., :2] + 5.0 * jnp.asarray(rng.normal(size=(8, 20, 2)))

    def smooth(m):
        graph = M.build_smoother_graph(
            m, jnp.full((20,), 0.2), jnp.asarray(1.0 / M.DYNAMICS_SIGMAS)
        )
        solver = eqs.GaussNewton(eqs.BlockTridiagonal())
        return eqs.least_squares(graph, {"x": M.initial_guess(m)}, solver).value["x"]

    est = jax.vmap(smooth)(meas)
    raw = np.sqrt(np.mean((meas - truth[..., :2]) ** 2))
    smoothed = np.sqrt(np.mean((est[..., :2] - truth[..., :2]) ** 2))
    assert smoothed < 0.75 * raw, (smoothed, raw)


def test_out_of_view_factor():
    import jax
    import jax.numpy as jnp

    from experiments.disk_tracking import models as M, train as T

    # Which factor a method name asks for, and a clear error for others.
    assert T.view_factor("smoother_hetero_surrogate_learndyn") is None
    assert T.view_factor("smoother_hetero_surrogate_learndyn_view") == "hinge"
    assert T.view_factor("smoother_hetero_surrogate_learndyn_robustview") == "robust"
    robust = T.make_smoother_model("const", 5.0, jax.random.key(0), "float32", "robust")
    assert robust.view_robust_scale == T.OUT_OF_VIEW_ROBUST_SCALE
    with pytest.raises(ValueError, match="out-of-view factor 'mixture'"):
        T.make_smoother_model("const", 5.0, jax.random.key(0), "float32", "mixture")

    L = M.VIEW_HALF_WIDTH
    assert L == 67.0  # 60 px half image + radius 7: no target pixel beyond
    x = lambda px, py: jnp.array([px, py, 0.0, 0.0])  # noqa: E731
    r = lambda px, py, hidden: float(M.out_of_view_residual(x(px, py), hidden, None)[0])  # noqa: E731
    assert r(L + 20, 0.0, 1.0) < 1e-3 and r(0.0, -L - 20, 1.0) < 1e-3
    assert abs(r(0.0, 0.0, 1.0) - L) < 1e-3  # the depth inside the window
    assert abs(r(10.0, -30.0, 1.0) - (L - 30)) < 1e-3
    assert r(0.0, 0.0, 0.0) == 0.0  # frames with a visible pixel: inactive
    # In the graph: one factor per frame, weighted by the learned precision.
    T = 5
    meas = jnp.zeros((T, 2))
    hidden = jnp.array([0.0, 0.0, 1.0, 1.0, 0.0])
    graph = M.build_smoother_graph(
        meas,
        jnp.ones(T),
        jnp.asarray(1.0 / M.DYNAMICS_SIGMAS),
        out_of_view=(jnp.asarray(0.5), hidden),
    )
    assert len(graph.factors) == 3
    values = {"x": jnp.zeros((T, 4))}
    plain = M.build_smoother_graph(
        meas, jnp.ones(T), jnp.asarray(1.0 / M.DYNAMICS_SIGMAS)
    )
    extra = float(graph.cost(values)) - float(plain.cost(values))
    np.testing.assert_allclose(extra, 0.5 * 2 * (0.5 * L) ** 2, rtol=1e-4)
    # The robust variant: a Geman-McClure kernel caps each hidden frame's cost
    # at k²/2, so a target the other frames place deep inside stays there.
    k = 1.5
    robust = M.build_smoother_graph(
        meas,
        jnp.ones(T),
        jnp.asarray(1.0 / M.DYNAMICS_SIGMAS),
        out_of_view=(jnp.asarray(0.5), hidden),
        out_of_view_robust_scale=k,
    )
    s = (0.5 * L) ** 2
    extra = float(robust.cost(values)) - float(plain.cost(values))
    np.testing.assert_allclose(extra, 0.5 * 2 * k**2 * s / (k**2 + s), rtol=1e-4)


def _simulate(rng, n: int, frames: int, spread: float) -> np.ndarray:
    """`n` disk trajectories `(n, frames, 4)` from the generator's dynamics,
    started uniformly within `±spread` px."""
    from experiments.disk_tracking import data as D

    states = []
    for _ in range(n):
        x = np.concatenate([rng.uniform(-spread, spread, 2), rng.normal(0, 3, 2)])
        seq = []
        for _ in range(frames):
            seq.append(x)
            p, v = D.dynamics_step(
                x[:2], x[2:], rng.normal(0, 0.1, 2), rng.normal(0, 2, 2)
            )
            x = np.concatenate([p, v])
        states.append(seq)
    return np.asarray(states, np.float32)


def test_out_of_view_smoother_starts_from_the_gaussian_map():
    # Hidden frames report the sensor's "not visible" position (here the image
    # centre). Solved from there in one stage, the hinge pushed some targets
    # out through the wrong edge (hidden-frame RMSE 16 px on these sequences);
    # `smooth_one` first solves without the hinge, then with it (3.4 px).
    import jax
    import jax.numpy as jnp

    import eqsmooth as eqs
    from experiments.disk_tracking import models as M, train as T

    class Gate(eqs.learn.AbstractNoiseHead):
        def __call__(self, features):
            return jnp.where(features[..., 0] > 0, 1.0, 0.01)

    rng = np.random.default_rng(0)
    truth = _simulate(rng, 300, 20, 60)
    hidden = (np.abs(truth[..., :2]) > M.VIEW_HALF_WIDTH).any(-1)
    noise = rng.normal(0, 1, truth[..., :2].shape)
    meas = np.where(hidden[..., None], 0.0, truth[..., :2] + noise).astype("float32")
    counts = np.where(hidden, 0.0, 100.0).astype("float32")
    model = T.SmootherModel(
        Gate(),
        jnp.asarray(-np.log(M.DYNAMICS_SIGMAS), "float32"),
        log_view_sqrt_precision=jnp.asarray(0.0, "float32"),
    )
    batch = dict(meas=meas, counts=counts, truth=truth)
    pos, outcome = jax.tree.map(
        np.asarray, T.smoothed(model, jax.tree.map(jnp.asarray, batch), 10)
    )
    assert 0.01 < hidden.mean() < 0.1
    err = ((pos - truth[..., :2]) ** 2).sum(-1)[hidden]
    assert np.sqrt(err.mean() / 2) < 6.0
    assert outcome.shape == (300,) and set(outcome.tolist()) <= {0, 1}
    # The outcome codes: one step is too few (step limit), and a NaN
    # measurement fails.
    short = T.smoothed(model, jax.tree.map(jnp.asarray, batch), 1)[1]
    assert np.any(np.asarray(short) == 1)
    bad = dict(batch, meas=meas.copy())
    bad["meas"][0, 5] = np.nan
    _, outcome = T.smoothed(model, jax.tree.map(jnp.asarray, bad), 10)
    assert outcome[0] == 2 and set(np.asarray(outcome[1:]).tolist()) <= {0, 1}


def test_method_names_choose_the_surrogate_steps():
    from experiments.disk_tracking import train

    cfg = train.Config()
    assert train.surrogate_steps(cfg, "smoother_hetero_surrogate") == 3
    assert train.surrogate_steps(cfg, "smoother_hetero_surrogate_k5") == 5
    assert train.surrogate_steps(cfg, "smoother_hetero_surrogate_learndyn_k1") == 1
    assert set(train.EXTRA_METHODS) >= {
        "smoother_hetero_surrogate_k1",
        "smoother_hetero_surrogate_k5",
        "smoother_hetero_truncated",
    }


def test_splits_keep_the_test_fold_out():
    from experiments.disk_tracking import train

    cfg = train.Config(sequences_per_fold=10, num_frames=3, num_folds=4)
    tr, va, te = train.make_splits(cfg, test_fold=2, cache_dir=None)
    assert tr.images.shape == (tr.n, 3, 120, 120, 3)
    np.testing.assert_array_equal(tr.images[1], tr.fold.images(np.array([1]))[0])
    assert tr.n + va.n == 30 and va.n == 3 and te.n == 10
    assert te.fold.fold == 2
    np.testing.assert_array_equal(
        te.fold.disk_positions,
        D.generate_fold(0, 2, 10, 3).disk_positions,
    )
    # Training and validation sequences are distinct and none is a test one.
    keys = [{p.tobytes() for p in s.fold.disk_positions[:, 0, 0]} for s in (tr, va, te)]
    assert not (keys[0] & keys[1]) and not (keys[0] & keys[2])
    assert not (keys[1] & keys[2])
    with pytest.raises(ValueError, match="also a training fold"):
        train.make_splits(train.Config(train_folds=(1, 2)), 2, cache_dir=None)


def test_image_cache_is_written_once_and_memory_mapped(tmp_path):
    f = D.generate_fold(seed=0, fold=1, num_sequences=3, num_frames=4)
    mapped = D.fold_images(f, tmp_path)
    assert isinstance(mapped, np.memmap)
    first = np.array(mapped)
    del mapped
    np.testing.assert_array_equal(first, D.fold_images(f, None))
    (path,) = tmp_path.glob("*.u8")
    mtime = path.stat().st_mtime_ns
    np.testing.assert_array_equal(D.fold_images(f, tmp_path), first)
    assert path.stat().st_mtime_ns == mtime  # read back, not rendered again
    # A cache file of the wrong size (a run killed while copying it by hand,
    # say) is rendered again, not trusted.
    path.unlink()  # (truncating in place would break live memory maps)
    path.write_bytes(b"x" * 10)
    np.testing.assert_array_equal(D.fold_images(f, tmp_path), first)


def test_tiny_fold_runs_and_resumes(tmp_path):
    import json

    import equinox as eqx
    import jax

    from experiments.disk_tracking import protocol, report, train

    cfg = train.Config(
        test_folds=(0,),
        train_folds=(1,),
        sequences_per_fold=6,
        num_frames=6,
        max_val_sequences=2,
        max_test_sequences=3,
        sensor_channels=4,
        sensor_steps=2,
        sensor_batch=2,
        sensor_eval_every=1,
        fg_steps=2,
        fg_batch=2,
        lstm_steps=2,
        lstm_batch=2,
        lstm_subsequence=4,
        lstm_hidden=8,
        eval_every=1,
        eval_batch=12,
        fg_lr=1e-2,
        # One of each kind keeps the compile time (most of this test) small.
        methods=(
            "smoother_hetero_surrogate_learndyn_view",
            "ekf_hetero_nll",
            "lstm_uni",
            "smoother_hetero_finetune",
        ),
        finetune_steps=1,
        finetune_batch=1,
        finetune_eval_every=1,
        quick=True,
    )
    work, cache = tmp_path / "work", tmp_path / "cache"
    # optax's Adam mixes int and float scalars, which strict promotion rejects.
    with jax.numpy_dtype_promotion("standard"):
        res = protocol.run_fold(cfg, 0, work, cache, log=lambda *a: None)
    recs = res["records"]
    assert set(recs) == {"virtual_sensor", *cfg.methods}
    for name, r in recs.items():
        assert np.isfinite(r["test_rmse"]), name
        if name.startswith("smoother"):  # how each test-time solve ended
            assert set(r["test_solves"]) == set(train.SOLVE_OUTCOMES), name
            assert sum(r["test_solves"].values()) == 3, name
    # Every training loss gives a finite, non-zero gradient for the noise MLP.
    test = res["test"]
    meas = jax.numpy.asarray(test.sensor[0], "float32")
    counts = jax.numpy.asarray(test.fold.visible_pixels[0], "float32")
    truth = jax.numpy.asarray(test.fold.states[0], "float32")
    learned = res["models"]["smoother_hetero_surrogate_learndyn_view"]
    assert learned.log_view_sqrt_precision is not None
    g = eqx.filter_jit(
        eqx.filter_grad(lambda m: train.surrogate_loss_one(m, meas, counts, truth, 3))
    )(learned)
    assert np.any(np.asarray(g.log_dynamics_sqrt_precision) != 0)
    het = dataclasses.replace(learned, learn_dynamics=False)
    # The paper's graph (no first-state prior) solves from the measurements.
    seqs = {k: jax.numpy.asarray(v) for k, v in test.sequences("float32").items()}
    free = train.smoothed_without_first_state(het, seqs, 5)
    assert free.shape == seqs["truth"].shape[:2] + (2,)
    assert np.all(np.isfinite(np.asarray(free)))
    for loss in (
        lambda m: train.surrogate_loss_one(m, meas, counts, truth, 3),
        lambda m: train.joint_nll_one(m, meas, counts, truth),
        lambda m: train.truncated_loss_one(m, meas, counts, truth, 10),
        lambda m: train.ekf_mse_one(m, meas, counts, truth),
        lambda m: train.ekf_nll_one(m, meas, counts, truth),
    ):
        g = eqx.filter_jit(eqx.filter_grad(loss))(het)
        w = np.asarray(g.noise.mlp.layers[-1].weight)
        assert np.all(np.isfinite(w)) and np.any(w != 0)
        # The dynamics noise is fixed (the paper's setting): no gradient.
        assert np.all(np.asarray(g.log_dynamics_sqrt_precision) == 0)

    # Resume: the same call again finds every stage finished (checkpoints and
    # the cached sensor outputs) and gives the same numbers.
    cached = work / "fold_0" / "sensor_test.npz"
    mtime = cached.stat().st_mtime_ns
    before = json.loads((work / "fold_0" / "timings.json").read_text())
    with jax.numpy_dtype_promotion("standard"):
        again = protocol.run_fold(cfg, 0, work, cache, log=lambda *a: None)
    assert cached.stat().st_mtime_ns == mtime
    for name, r in recs.items():
        assert again["records"][name]["test_rmse"] == r["test_rmse"], name
        assert again["records"][name]["best_step"] == r["best_step"], name
    after = json.loads((work / "fold_0" / "timings.json").read_text())
    assert all(after[k] >= before[k] for k in before)  # time accumulates

    # The committed files and the summary built from them.
    out = tmp_path / "out"
    path = protocol.write_fold(out, dataclasses.asdict(cfg), res)
    assert path.exists() and (out / "sensor_fold0.eqx").exists()
    record, table = report.write_summary(out, num_folds=1)
    assert "QUICK" in table and "smoother, heteroscedastic" in table
    assert record["folds"] == [0] and (out / "summary.json").exists()

    # Fresh-data confirmation from the committed sensor: the finished heads
    # are reloaded from `work` (no retraining here), evaluated on fold 10.
    from experiments.disk_tracking import fresh

    with jax.numpy_dtype_promotion("standard"):
        path = fresh.run(cfg, 0, out, work, cache, log=lambda *a: None)
    rows = json.loads(path.read_text())["records"]
    assert set(rows) == {"virtual_sensor", *cfg.methods}
    for name in cfg.methods:
        assert np.isfinite(rows[name]["fresh_rmse"]), name
        assert rows[name]["test_rmse"] == recs[name]["test_rmse"], name
        assert (out / "heads" / "fold_0" / f"{name}.eqx").exists()
    record, table = fresh.summarise(out)
    assert (out / "fresh.json").exists() and "fold 10" in table
    assert record["rows"]["lstm_uni"]["max_abs_retrain_drift"] == 0.0


def test_docs_table_is_the_committed_results(tmp_path):
    import shutil

    from experiments.disk_tracking import report

    root = Path(__file__).resolve().parents[1]
    results = root / "results" / "disk"
    page = root / "docs" / "tutorial" / "disk-tracking.md"
    if not list(results.glob("fold_*.json")):
        pytest.skip(f"no committed fold results under {results}")
    for f in results.glob("fold_*.json"):
        shutil.copy(f, tmp_path)
    _, table = report.write_summary(tmp_path)
    assert report.docs_table(page) == table


def test_damaged_fold_cache_is_reported_and_rebuilt(tmp_path):
    # A cache cut short by a kill raised zipfile.BadZipFile with no path.
    kw = dict(seed=0, fold=1, num_sequences=3, num_frames=5, cache_dir=tmp_path)
    fresh = D.load_fold(**kw)
    (path,) = tmp_path.glob("*.npz")
    path.write_bytes(path.read_bytes()[:40])
    with pytest.warns(UserWarning, match=f"{path.name}: damaged cache file"):
        again = D.load_fold(**kw)
    np.testing.assert_array_equal(again.disk_positions, fresh.disk_positions)
    assert D.load_cache(path, ("radii",)) is not None  # rewritten whole


def test_online_methods_run_the_fixed_lag_smoother():
    # The online rows (issue 38): `online_<kind>_lag<L>` trains the heads
    # through eqs.filters.fixed_lag_smoother and scores its online estimate.
    # On the disk model (quadratic drag) with unit noise, the lag-1 window
    # (an iterated EKF) stays within a fraction of a pixel of the EKF, and a
    # longer window, which relinearises each state over more frames, does too.
    import jax
    import jax.numpy as jnp

    from experiments.disk_tracking import train as T

    assert T.online_lag("online_hetero_lag10") == 10
    with pytest.raises(ValueError, match="not an online method"):
        T.online_lag("online_hetero_nll")
    assert {"online_hetero_lag1", "online_hetero_lag5"} <= set(T.EXTRA_METHODS)
    rng = np.random.default_rng(1)
    truth = _simulate(rng, 4, 8, 30)
    meas = (truth[..., :2] + rng.normal(0, 1, truth[..., :2].shape)).astype("float32")
    batch = jax.tree.map(
        jnp.asarray,
        dict(meas=meas, counts=np.full((4, 8), 100.0, "float32"), truth=truth),
    )
    model = T.make_smoother_model("const", 1.0, jax.random.key(0), "float32")
    ekf = np.asarray(T.ekf_positions(model, batch))
    for lag in (1, 4):
        online = np.asarray(T.online_positions(model, batch, lag))
        assert online.shape == (4, 8, 2) and np.isfinite(online).all()
        np.testing.assert_allclose(online[:, 0], truth[:, 0, :2], atol=0.1)
        assert np.abs(online - ekf).max() < 0.5
        lagged = np.asarray(T.lagged_positions(model, batch, lag))
        if lag == 1:  # a one-state window: the delayed estimate is the online one
            np.testing.assert_allclose(lagged, online, atol=1e-5)
        else:  # the newest frame's delayed estimate is the last window's
            np.testing.assert_allclose(lagged[:, -1], online[:, -1], atol=1e-5)
            assert np.abs(lagged[:, :-1] - online[:, :-1]).max() > 1e-3
    loss = T.online_mse_one(
        model, batch["meas"][0], batch["counts"][0], batch["truth"][0], 2
    )
    assert np.isfinite(float(loss))


def test_online_summary_pairs_folds(tmp_path):
    import json

    from experiments.disk_tracking import online

    rmse = {  # per fold: EKF, batch smoother, lag 1, lag 10
        0: (3.0, 1.9, 3.1, 2.5),
        1: (3.2, 2.0, 3.1, 2.6),
    }
    for k, (e, s, l1, l10) in rmse.items():
        rec = lambda v, ms: dict(test_rmse=v, latency_ms_per_step=ms, seconds=60.0)  # noqa: E731
        records = dict(
            ekf_hetero_mse=rec(e, 0.1),
            smoother_hetero_surrogate=rec(s, 0.4),
            online_hetero_lag1=rec(l1, 0.2),
            online_hetero_lag10=rec(l10, 2.0),
        )
        fold = dict(fold=k, quick=False, git_hash="abc", records=records)
        (tmp_path / f"fold_{k}.json").write_text(json.dumps(fold))
    record, table = online.summarise(tmp_path)
    d = record["paired"]["online_hetero_lag10 - ekf_hetero_mse"]
    np.testing.assert_allclose(d["folds"], [-0.5, -0.6])
    assert d["better_folds"] == 2
    d = record["paired"]["online_hetero_lag1 - ekf_hetero_mse"]
    assert d["better_folds"] == 1
    assert record["rows"]["online_hetero_lag10"]["latency_ms_per_step"] == 2.0
    assert "lag 10, online" in table and (tmp_path / "online.json").exists()
    # lag order: 1 before 10 (not string order)
    keys = list(record["paired"])
    assert keys.index("online_hetero_lag1 - ekf_hetero_mse") < keys.index(
        "online_hetero_lag10 - ekf_hetero_mse"
    )


def test_ablation_pairs_are_reported():
    from experiments.disk_tracking import report

    summary = {
        "smoother_hetero_surrogate": report.mean_se([2.0, 2.2]),
        "smoother_hetero_surrogate_k1": report.mean_se([2.1, 2.0]),
    }
    paired, table = report.paired_table(summary, report.ABLATION_PAIRS)
    (key,) = paired
    assert key == "smoother_hetero_surrogate_k1 - smoother_hetero_surrogate"
    assert paired[key]["mean"] == pytest.approx(-0.05)
    assert paired[key]["better_folds"] == 1
    assert "surrogate loss (K=1) − " in table and "1/2" in table
    assert report.paired_table({}, report.ABLATION_PAIRS) == ({}, "")
    # A row scored without the first-state prior, against itself with it.
    folds = [
        {"records": {"smoother_hetero_surrogate": {report.FREE_START: v}}}
        for v in (2.5, 2.1)
    ]
    paired, table = report.paired_table(summary, (), folds)
    (key,) = paired
    assert paired[key]["mean"] == pytest.approx(0.2)
    assert "heads trained with the first-state prior, scored without it" in table


def test_seed_summary_pools_within_fold_spread(tmp_path):
    import json

    from experiments.disk_tracking import seeds

    base, root = tmp_path / "disk", tmp_path / "seeds"
    # (smoother, LSTM) test RMSE per run and fold; fold 2 only in seed 0.
    runs = {
        base: {0: (2.0, 1.8), 1: (2.2, 1.9), 2: (2.1, 1.7)},
        base / "fresh": {0: (2.1, 1.8), 1: (2.2, 1.9)},
        root / "seed1": {0: (1.9, 1.8), 1: (2.3, 1.9)},
    }
    for d, folds in runs.items():
        d.mkdir(parents=True)
        for k, (s, lstm) in folds.items():
            rec = dict(smoother_hetero_surrogate=s, lstm_bi=lstm)
            rec = {m: {"test_rmse": v} for m, v in rec.items()}
            (d / f"fold_{k}.json").write_text(json.dumps({"fold": k, "records": rec}))
    record, table = seeds.summarise(base, root)
    assert record["runs"] == ["seed 0", "seed 0 again", "seed 1"]
    assert record["folds"] == [0, 1]
    row = record["rows"]["smoother_hetero_surrogate"]
    np.testing.assert_allclose(row["mean_per_run"], [2.1, 2.15, 2.1])
    # fold 0: std of (2.0, 2.1, 1.9) = 0.1; fold 1: of (2.2, 2.2, 2.3) ≈ 0.0577
    np.testing.assert_allclose(
        row["within_fold_seed_std"], np.sqrt((0.01 + 0.01 / 3) / 2)
    )
    assert record["rows"]["lstm_bi"]["within_fold_seed_std"] == pytest.approx(0.0)
    pair = record["paired"]["smoother_hetero_surrogate - lstm_bi"]
    assert pair["negative_cells"] == 0 and pair["same_sign_everywhere"]
    assert (root / "seeds.md").read_text() == table
    assert "seed std within a fold" in table
    with pytest.raises(FileNotFoundError, match="seedS"):
        seeds.summarise(base, tmp_path / "nothing")
