"""KITTI visual odometry example: loader, renderer, folds, metrics (tiny and quick)."""

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from experiments.kitti_vo import data as D


def _write_png(path: Path, image: np.ndarray) -> None:
    """A minimal RGB8 PNG writer (zlib only), to build the layout without Pillow."""
    h, w, _ = image.shape
    raw = b"".join(b"\x00" + image[i].tobytes() for i in range(h))

    def chunk(kind, body):
        out = struct.pack(">I", len(body)) + kind + body
        return out + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw))
    png += chunk(b"IEND", b"")
    path.write_bytes(png)


def _yaw_pose(x_cam, z_cam, yaw):
    # Camera turned left by `yaw` (about its down-pointing y axis).
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    return np.concatenate([R, [[x_cam], [0.0], [z_cam]]], axis=1)


def test_poses_to_2d_convention():
    poses = np.stack([_yaw_pose(0.0, 0.0, 0.0), _yaw_pose(-2.0, 5.0, 0.3)])
    xyt = D.poses_to_2d(poses)
    np.testing.assert_allclose(xyt[0], [0.0, 0.0, 0.0], atol=1e-12)
    # x = forward z, y = -x_cam (left), θ = the yaw to the left.
    np.testing.assert_allclose(xyt[1], [5.0, 2.0, 0.3], atol=1e-12)


def test_loader_reads_generated_layout(tmp_path):
    rng = np.random.default_rng(0)
    N, seq = 5, 4
    images = {}
    for cam, pose_file in (("image_2", "image1"), ("image_3", "image2")):
        folder = tmp_path / f"{seq:02d}" / cam
        folder.mkdir(parents=True)
        imgs = rng.integers(0, 256, (N,) + D.IMAGE_SHAPE, dtype=np.uint8)
        images[cam] = imgs
        for f in reversed(range(N)):  # written out of order: sorted by frame
            _write_png(folder / f"kitti_{seq:02d}_{f:06d}.png", imgs[f])
        lines = [
            " ".join(f"{v:.9e}" for v in _yaw_pose(-0.1 * f, 1.0 * f, 0.05 * f).ravel())
            for f in range(N)
        ]
        (tmp_path / f"{seq:02d}_{pose_file}.txt").write_text("\n".join(lines) + "\n")
    trajs = D.load_kitti10_sequence(tmp_path, seq)
    assert [t.camera for t in trajs] == ["image_2", "image_3"]
    for t in trajs:
        assert t.num_frames == N
        np.testing.assert_array_equal(t.images(np.arange(N)), images[t.camera])
        np.testing.assert_allclose(t.poses[:, 0], np.arange(N), atol=1e-8)
        np.testing.assert_allclose(t.poses[:, 2], 0.05 * np.arange(N), atol=1e-8)
    mirrored = D.with_mirrors(trajs)
    assert len(mirrored) == 4 and mirrored[1].mirrored
    np.testing.assert_array_equal(
        mirrored[1].images([2]), images["image_2"][[2]][:, :, ::-1]
    )
    np.testing.assert_allclose(mirrored[1].poses[:, 2], -trajs[0].poses[:, 2])


def _toy_path(N=40):
    t = np.arange(N) * D.DT
    theta = 0.2 * np.sin(t)
    x = np.cumsum(10.0 * np.cos(theta) * D.DT)
    y = np.cumsum(10.0 * np.sin(theta) * D.DT)
    return np.stack([x, y, theta], 1)


def test_renderer_is_deterministic_and_nuisances_vary():
    xyt = _toy_path()
    a = D.Renderer(xyt, seed=3, seq=4).images("image_2", [0, 7, 20])
    b = D.Renderer(xyt, seed=3, seq=4).images("image_2", [0, 7, 20])
    c = D.Renderer(xyt, seed=4, seq=4).images("image_2", [0, 7, 20])
    d = D.Renderer(xyt, seed=3, seq=4).images("image_3", [0, 7, 20])
    assert a.shape == (3,) + D.IMAGE_SHAPE and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert np.any(a != c) and np.any(a != d)
    assert a.std() > 10  # not a blank image
    r = D.Renderer(_toy_path(600), seed=0, seq=0)
    nz = r.nuisances(np.arange(600))
    assert nz["gain"].min() < 0.5 < nz["gain"].max()
    assert 0 < np.mean(nz["blur"] > 0) < 0.5
    assert np.any(nz["occluded"]) and np.any(nz["low_texture"])


def test_reliability_variant_is_deterministic_and_differs_from_default():
    xyt = _toy_path(200)
    frames = np.arange(0, 200, 3)
    a = D.Renderer(xyt, seed=33, seq=4, variant="reliability")
    b = D.Renderer(xyt, seed=33, seq=4, variant="reliability")
    default = D.Renderer(xyt, seed=33, seq=4).images("image_2", frames)
    np.testing.assert_array_equal(
        a.images("image_2", frames), b.images("image_2", frames)
    )
    assert np.any(a.images("image_2", frames) != default)
    nz, nz0 = (
        a.nuisances(np.arange(200)),
        D.Renderer(xyt, 33, 4).nuisances(np.arange(200)),
    )
    assert np.any(nz["misframed"]) and not np.any(nz0["misframed"])
    assert np.all(nz["blur"] >= nz0["blur"]) and np.any(nz["gain"] != nz0["gain"])
    # A repeated frame slot shows the previous capture: the pair sees no motion.
    f = int(np.nonzero(a.world.source == np.arange(200) - 1)[0][0])
    pair = a.images("image_3", [f - 1, f])
    np.testing.assert_array_equal(pair[0], pair[1])
    with pytest.raises(ValueError, match="unknown variant"):
        D.Renderer(xyt, seed=33, seq=4, variant="nope")


def test_folds_and_splits():
    seen = set()
    for f in range(D.NUM_FOLDS):
        spec = D.fold_spec(f)
        assert spec.test == D.SEQUENCES[f]
        assert spec.valid != spec.test and 1 not in (spec.test, spec.valid)
        assert spec.test not in spec.train and spec.valid not in spec.train
        assert 1 not in spec.train and len(spec.train) == 8
        seen.add(spec.test)
    assert seen == set(D.SEQUENCES)
    pre, smo = D.pretrain_frames(1000), D.smoother_frames(1000)
    assert pre[-1] == 794 and smo[0] == 800 and smo[-1] == 999 and smo.size == 200
    # Windows of 100 states need 101 frames; sequence 04 has 271 frames.
    np.testing.assert_array_equal(D.windows(np.arange(271), 100), [0, 100])
    np.testing.assert_array_equal(D.windows(smo, 50, 25), np.arange(800, 950, 25))


def test_metric_on_known_trajectory():
    truth = np.zeros((101, 3))
    truth[:, 0] = np.linspace(0.0, 100.0, 101)
    est = truth.copy()
    est[-1, 1] += 1.0
    est[-1, 2] += np.radians(2.0)
    trans, rot = D.window_metrics(est, truth)
    assert trans == pytest.approx(0.01)
    assert rot == pytest.approx(0.02)
    # Whole-window: the same errors averaged over the 101 states (one is off).
    trans, rot = D.whole_window_metrics(est, truth)
    assert trans == pytest.approx(0.01 / 101) and rot == pytest.approx(0.02 / 101)


def test_velocities_match_the_library_state():
    import jax.numpy as jnp

    import eqsmooth as eqs

    xyt = _toy_path(10)
    v = D.velocities(xyt)
    poses = eqs.SE2.from_xy_theta(
        jnp.asarray(xyt[:, 0]), jnp.asarray(xyt[:, 1]), jnp.asarray(xyt[:, 2])
    )
    state = eqs.factors.VehicleState.from_poses(poses, D.DT)
    np.testing.assert_allclose(np.asarray(state.velocity), v, atol=1e-9)


def test_real_kitti_poses():
    if not (D.DEFAULT_POSES_DIR / "04.txt").exists():
        pytest.skip(
            f"KITTI ground-truth poses not found at {D.DEFAULT_POSES_DIR} "
            "(../shared/data/kitti_poses; see its README)"
        )
    for seq, count in D.FRAME_COUNTS.items():
        lines = (D.DEFAULT_POSES_DIR / f"{seq:02d}.txt").read_text().splitlines()
        assert len(lines) == count
    trajs = D.rendered_sequence(4, seed=0)
    assert [t.num_frames for t in trajs] == [271, 271]
    v = D.velocities(trajs[0].poses)
    assert 5.0 < np.median(v[:, 0]) < 20.0  # a car on a road, m/s
    lateral = trajs[0].poses[:, :2] - trajs[1].poses[:, :2]
    np.testing.assert_allclose(np.linalg.norm(lateral, axis=1), 0.54, atol=1e-6)


def _tiny_windows(B=2, T=5):
    from experiments.kitti_vo import experiment as E, models as M

    rng = np.random.default_rng(0)
    xyt = _toy_path(T + 1)
    vel = D.velocities(xyt)[:T]
    return {
        "z": (vel[None] + 0.1 * rng.normal(size=(B, T, 2))).astype(np.float32),
        "log_sigma": np.zeros((B, T, 2), np.float32),
        "features": rng.normal(size=(B, T, M.FEATURES)).astype(np.float32),
        "pose": np.broadcast_to(E._relative_params(xyt[:T]), (B, T, 4)).astype(
            np.float32
        ),
        "velocity": np.broadcast_to(vel, (B, T, 2)).astype(np.float32),
    }


def test_summary_and_docs_table_come_from_fold_json(tmp_path):
    import json

    from experiments.kitti_vo import report

    def fold(k, trans, rot):
        rows = {
            "smoother_hetero_e2e": {"trans_m_per_m": trans, "rot_deg_per_m": rot},
            "ekf_hetero": {"trans_m_per_m": 2 * trans, "rot_deg_per_m": 2 * rot},
        }
        methods = list(rows)
        return {"fold": k, "rows": rows, "config": {"quick": False, "methods": methods}}

    for k, (t, r) in enumerate([(0.1, 0.01), (0.3, 0.03)]):
        (tmp_path / f"fold_{k}.json").write_text(json.dumps(fold(k, t, r)))
    # A fold still running (a row missing) is left out of the summary.
    running = fold(2, 9.0, 9.0)
    del running["rows"]["ekf_hetero"]
    (tmp_path / "fold_2.json").write_text(json.dumps(running))
    table = report.write_summary(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    e2e = summary["methods"]["smoother_hetero_e2e"]
    assert e2e["num_folds"] == 2
    np.testing.assert_allclose(e2e["trans_m_per_m"], 0.2)
    np.testing.assert_allclose(e2e["trans_m_per_m_sem"], 0.1)  # std 0.1414 / √2
    assert "| smoother_hetero_e2e | 0.2000 ± 0.1000 |" in table
    # The per-fold criterion, ours from these folds, the paper's from its release.
    assert "| ekf_hetero | 2/2 | 8/10 (not 5, 8) |" in table
    assert "| smoother_const_e2e | — | 10/10 |" in table
    page = tmp_path / "page.md"
    page.write_text(f"intro\n{report.DOCS_START}\nSTALE\n{report.DOCS_END}\ntail\n")
    report.update_docs(page, table)
    text = page.read_text()
    assert "STALE" not in text and table in text and text.endswith("tail\n")
    with pytest.raises(ValueError, match="kitti-results"):
        report.update_docs(tmp_path / "fold_0.json", table)


def test_derived_rows_are_paired_per_fold(tmp_path):
    import json

    from experiments.kitti_vo import report

    methods = ["smoother_hetero_e2e", "ekf_hetero"]
    for k, late in enumerate([0.02, 0.04, 0.03]):
        rows = {m: {"trans_m_per_m": 0.2, "rot_deg_per_m": 0.1} for m in methods}
        rows["ekf_hetero_one_frame_late"] = {
            "trans_m_per_m": 0.2 + late,
            "rot_deg_per_m": 0.1,
        }
        config = {"quick": False, "methods": methods}
        fold = {"fold": k, "rows": rows, "config": config}
        (tmp_path / f"fold_{k}.json").write_text(json.dumps(fold))
    # A derived row from a retrained source model counts as its source row
    # shifted by the difference to the retrained model's own score in that
    # run (source_now): here +0.03 again.
    fold2 = json.loads((tmp_path / "fold_2.json").read_text())
    late = fold2["rows"]["ekf_hetero_one_frame_late"]
    late.update(derived_from="ekf_hetero", source_now={"trans_m_per_m": 0.5})
    late["trans_m_per_m"] = 0.53  # still +0.03 against its own source
    (tmp_path / "fold_2.json").write_text(json.dumps(fold2))
    table = report.write_summary(tmp_path)
    # mean +0.03, std 0.01 / √3; the smoother is below the late EKF on 3/3.
    assert "| ekf_hetero_one_frame_late − ekf_hetero | +0.0300 ± 0.0058" in table
    assert "| smoother_hetero_e2e − ekf_hetero_one_frame_late | -0.0300" in table
    assert "(3/3 folds below 0) | -0.0227 ± 0.0064 (8/10 folds below 0) |" in table


def test_rescore_rule_and_method_key():
    """A row scored before the whole-window metric existed keeps its
    final-step fields of record and takes the whole-window fields of the
    retrained model, whose own final-step score is kept beside them; a
    method's initialisation key does not depend on the run's method list."""
    import jax

    from experiments.kitti_vo import experiment as E

    old = {"trans_m_per_m": 0.2, "rot_deg_per_m": 0.1, "best_step": 100}
    old["trans_m_per_m_windows"] = [0.2]
    metrics = np.array([[0.3, 0.2, 0.05, 0.04]])
    new = E._row(metrics, 12.0, 1.0, 300)
    row = E._rescored(old, new, {"git": "abc"})
    assert row["trans_m_per_m"] == 0.2 and row["trans_m_per_m_windows"] == [0.2]
    assert row["best_step"] == 100
    assert row["trans_m_per_m_whole"] == 0.05
    assert row["rot_deg_per_m_whole_windows"] == [0.04]
    assert row["whole_window_from"] == {
        "git": "abc",
        "best_step": 300,
        "train_s": 12.0,
        "trans_m_per_m": 0.3,
        "rot_deg_per_m": 0.2,
    }
    assert "trans_m_per_m_whole" not in old  # the earlier record is not mutated
    from experiments.kitti_vo import report

    (line,) = report.rescored_lines([{"rows": {"ekf_hetero": row}}])
    assert "ekf_hetero (1 folds; largest |Δ| 0.1000 m/m, 0.1000 deg/m)" in line
    assert report.rescored_lines([{"rows": {"ekf_hetero": old}}]) == []
    key = jax.random.key(3)
    a, b = (E.method_key(key, m) for m in ("ekf_hetero", "lstm_bi"))
    assert not np.array_equal(jax.random.key_data(a), jax.random.key_data(b))
    # The full protocol's keys are those it always had (place in METHODS).
    assert np.array_equal(
        jax.random.key_data(E.method_key(key, "ekf_hetero")),
        jax.random.key_data(jax.random.fold_in(key, 10 + 4)),
    )


def test_declared_criterion_of_a_variant(tmp_path):
    import json

    from experiments.kitti_vo import report

    keys = ("trans_m_per_m", "rot_deg_per_m", "trans_m_per_m_whole")
    keys += ("rot_deg_per_m_whole",)
    config = {"methods": ["smoother_hetero_e2e", "ekf_hetero"], "variant": "x"}
    config.update(cameras=["image_2"], mirror=True, validate=True)
    for k in range(10):
        d = -0.01 if k < 8 else 0.005  # the smoother below the EKF on 8 folds
        rows = {}
        for m, v in (("smoother_hetero_e2e", 0.1 + d), ("ekf_hetero", 0.1)):
            rows[m] = {key: v for key in keys}
            rows[m].update({key + "_windows": [v] * 4 for key in keys})
        fold = {"fold": k, "rows": rows, "config": config, "label": "variant x"}
        (tmp_path / f"fold_{k}.json").write_text(json.dumps(fold))
    table = report.write_summary(tmp_path)
    c = json.loads((tmp_path / "summary.json").read_text())["declared_criterion"]
    assert c["complete"] and c["target_1_met"] and c["target_2_met"]
    assert c["trans_m_per_m"]["folds_below_0"] == 8
    np.testing.assert_allclose(c["trans_m_per_m"]["mean"], -0.007)
    assert "variant x" in table and "Target 1" in table and "**met**" in table


@pytest.mark.slow
def test_losses_have_finite_gradients():
    import jax

    # The example runs in float32 with JAX's default promotion rules, not the
    # strict ones the library's tests use.
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        _check_losses()


def _check_losses():
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from experiments.kitti_vo import models as M

    w = jax.tree_util.tree_map(jnp.asarray, _tiny_windows())
    sig = np.array([1.0, 0.1])
    hetero = M.Estimator(M.heteroscedastic_noise(sig, jax.random.key(0)))

    def velocity_loss(model, batch):
        return M.surrogate_loss(model, batch, target="velocity")

    for loss in (M.surrogate_loss, velocity_loss, M.nll_loss, M.ekf_loss):
        value, grads = eqx.filter_value_and_grad(loss)(hetero, w)
        assert np.isfinite(float(value))
        leaves = jax.tree_util.tree_leaves(grads)
        assert all(np.all(np.isfinite(np.asarray(g))) for g in leaves)
        assert any(np.any(np.asarray(g) != 0) for g in leaves)
    # The smoother recovers the true start and stays close to the truth.
    est = M.smooth(hetero, jax.tree_util.tree_map(lambda a: a[0], w))
    p = np.asarray(est.pose.unit_complex_xy)
    np.testing.assert_allclose(p[0], np.asarray(w["pose"][0, 0]), atol=1e-3)
    assert np.max(np.abs(p[:, 2:] - np.asarray(w["pose"][0, :, 2:]))) < 0.5


def test_late_ekf_velocity_loss_and_bilstm_rows():
    """The rows added for issue 33: the code release's one-frame-late EKF
    scoring, the velocity surrogate loss and the bidirectional LSTM."""
    import jax

    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        _check_late_ekf_velocity_loss_and_bilstm_rows()


def _check_late_ekf_velocity_loss_and_bilstm_rows():
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from eqsmooth.factors import vehicle_motion
    from experiments.kitti_vo import experiment as E, models as M

    w = jax.tree_util.tree_map(jnp.asarray, _tiny_windows())
    one = jax.tree_util.tree_map(lambda a: a[0], w)
    model = M.Estimator(M.constant_noise(np.array([1.0, 0.1])))
    # One frame late: every mean moved one step by the motion model, so the
    # pose scored at t is the filter's prediction of t + 1.
    mean = M.run_ekf(model, one).mean
    late = M.ekf_one_frame_late(model, one)
    nxt = vehicle_motion(mean[2], D.DT)
    np.testing.assert_allclose(
        np.asarray(late[2].pose.unit_complex_xy),
        np.asarray(nxt.pose.unit_complex_xy),
        rtol=1e-6,
    )
    step = np.linalg.norm(np.diff(np.asarray(mean.pose.unit_complex_xy)[:, 2:], axis=0))
    assert step > 0  # the toy path moves, so the late scoring differs
    # The velocity loss scores velocities only: a position-only change of the
    # truth leaves it unchanged, a velocity change does not. The change moves
    # the last position only: a shift of every position is a symmetry of the
    # problem (the solve starts from dead reckoning from the first pose) and
    # leaves both losses unchanged up to rounding.
    vel = E.losses("smoother_const_e2e_vel", E.Config())[0]
    pos = E.losses("smoother_const_e2e", E.Config())[0]
    moved = {**w, "pose": w["pose"].at[..., -1, 2:].add(0.5)}
    faster = {**w, "velocity": w["velocity"] + 0.5}
    base = float(vel(model, w))
    np.testing.assert_allclose(float(vel(model, moved)), base, rtol=1e-5)
    assert float(vel(model, faster)) > base + 1e-3
    assert float(pos(model, moved)) > float(pos(model, w)) + 1e-3
    assert E.losses("smoother_hetero_nll", E.Config())[0] is M.nll_loss
    with pytest.raises(ValueError, match="target must be one of"):
        M.surrogate_loss(model, w, target="pose")
    # The bidirectional LSTM: a change at the last step reaches the first
    # velocity (the unidirectional one cannot see it).
    bi = E.build_model("lstm_bi", None, jax.random.key(0))
    uni = E.build_model("lstm", None, jax.random.key(0))
    bi = eqx.tree_at(lambda m: m.head.weight, bi, jnp.ones_like(bi.head.weight))
    uni = eqx.tree_at(lambda m: m.head.weight, uni, jnp.ones_like(uni.head.weight))
    late_change = {**one, "features": one["features"].at[-1].add(3.0)}
    for m, reaches in ((bi, True), (uni, False)):
        v0, v1 = m.velocities(one), m.velocities(late_change)
        assert bool(jnp.any(v0[0] != v1[0])) == reaches
    assert E.estimator_kind("lstm_bi") == "lstm"
    assert E.estimator_kind("ekf_one_frame_late") == "ekf_one_frame_late"
    assert E.estimator_kind("smoother_hetero_e2e_vel") == "smoother"
    assert set(s for _, s in E.DERIVED.values()) <= set(E.METHODS)


@pytest.mark.slow
def test_sensor_shapes():
    import jax
    import jax.numpy as jnp

    from experiments.kitti_vo import models as M

    sensor = M.VelocitySensor(jax.random.key(0))
    pair = jnp.zeros((2,) + D.IMAGE_SHAPE, jnp.uint8)
    with jax.numpy_dtype_promotion("standard"):
        v, ls, h = sensor(pair)
    assert v.shape == (2,) and ls.shape == (2,) and h.shape == (M.FEATURES,)


@pytest.mark.parametrize("token", ["nan", "inf", "-inf"])
def test_read_poses_refuses_non_finite_lines(tmp_path, token):
    # A "nan" in a pose file used to come back as NaN poses.
    path = tmp_path / "05.txt"
    good = " ".join(["1", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0"])
    bad = good.replace("0", token, 1)
    path.write_text("\n".join([good, good, bad, good]) + "\n")
    with pytest.raises(ValueError, match=r"05\.txt: lines \[3\] hold non-finite"):
        D.read_poses(path)


def _fake_release(root: Path, num_frames: int) -> None:
    """A tree laid out like the preprocessed KITTI-10 release (issue 33): for
    each of the 11 sequences, `NN/image_2/*.png`, `NN/image_3/*.png`,
    `NN_image1.txt` and `NN_image2.txt`, with the first `num_frames` frames of
    the real trajectory and rendered views of them."""
    for seq in range(11):
        lines = (D.DEFAULT_POSES_DIR / f"{seq:02d}.txt").read_text().splitlines()
        trajs = D.rendered_sequence(seq)
        for traj, pose_file in zip(trajs, ("image1", "image2")):
            folder = root / f"{seq:02d}" / traj.camera
            folder.mkdir(parents=True)
            images = traj.images(np.arange(num_frames))
            for f in range(num_frames):
                _write_png(folder / f"{seq:02d}_{f:06d}.png", images[f])
            text = "\n".join(lines[:num_frames]) + "\n"
            (root / f"{seq:02d}_{pose_file}.txt").write_text(text)


@pytest.mark.slow
def test_real_data_dir_runs_end_to_end(tmp_path):
    """`python -m experiments.kitti_vo --quick --real-data-dir` on a generated
    release tree:
    the protocol as shipped, from the loader to the fold's JSON. Slow (a
    whole quick run in a child process, about 4 minutes on 2 cores); CI runs
    the quick experiment itself, and the loader's tests here run by default."""
    import json
    import subprocess
    import sys

    from helpers import child_env

    pytest.importorskip("matplotlib", reason="the run draws figures (examples extra)")
    if not (D.DEFAULT_POSES_DIR / "00.txt").exists():
        pytest.skip(f"KITTI ground-truth poses not found in {D.DEFAULT_POSES_DIR}")
    release, out = tmp_path / "release", tmp_path / "out"
    _fake_release(release, num_frames=260)  # sequence 04 has 271
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "experiments.kitti_vo",
            "--quick",
            "--real-data-dir",
            str(release),
            "--out",
            str(out),
        ],
        env=child_env(),
        cwd=Path(__file__).resolve().parents[1],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads((out / "fold_3.json").read_text())
    assert result["config"]["real_data_dir"] == str(release)
    for method in result["config"]["methods"]:
        row = result["rows"][method]
        assert np.isfinite(row["trans_m_per_m"]), method
        assert np.isfinite(row["rot_deg_per_m"]), method


@pytest.mark.slow
def test_uncertainty_covariances_and_scores():
    """Issue 58: the KITTI estimators' planar covariances (smoother Laplace
    marginal, EKF filtered covariance, bi-LSTM variance head) and their
    scores. Slow (three estimators and a gradient compiled: about 50 s on
    2 cores); the frame and wrap rules below run by default."""
    import jax

    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        _check_uncertainty_covariances_and_scores()


def _check_uncertainty_covariances_and_scores():
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from experiments.kitti_vo import models as M, uncertainty as U

    w = _tiny_windows(B=2, T=6)
    sig = np.array([1.0, 0.1])
    key = jax.random.key(0)
    for method in ("smoother_hetero_e2e", "ekf_const", U.LSTM_VARIANCE):
        model = U.build_model(method, sig, key)
        est, cov, ok = U.estimate_with_covariance(method, model, w, batch=2)
        assert est.shape == (2, 6, 3) and cov.shape == (2, 6, 3, 3) and ok.all()
        eig = np.linalg.eigvalsh(0.5 * (cov + np.swapaxes(cov, -1, -2)))
        assert np.all(eig[:, 1:] > 0), method  # frame 0 is the given start
        # The position covariance grows along the window (dead reckoning
        # between velocity readings).
        assert np.trace(cov[0, -1, :2, :2]) > np.trace(cov[0, 1, :2, :2]), method
        s = U.score(est, cov, U.truth_planar(w))
        assert set(s) == {"position", "heading"}
        assert s["position"]["scored_frames_per_sequence"] == 5
        assert np.isfinite(s["position"]["nll"]) and np.isfinite(s["heading"]["nees"])
    # The variance head leaves the mean alone: the loss's gradient on the
    # LSTM is the bi-LSTM's own (position MSE), and it trains the head.
    model = U.build_model(U.LSTM_VARIANCE, sig, key)
    model = eqx.tree_at(
        lambda m: m.sigma_head.bias, model, jnp.array([0.3, -0.2], jnp.float32)
    )
    batch = jax.tree_util.tree_map(jnp.asarray, w)
    g = eqx.filter_grad(M.lstm_variance_loss)(model, batch)
    g_mean = eqx.filter_grad(M.lstm_loss)(model.lstm, batch)
    for a, b in zip(
        jax.tree_util.tree_leaves(g.lstm), jax.tree_util.tree_leaves(g_mean)
    ):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)
    assert np.any(np.asarray(g.sigma_head.bias) != 0)
    assert np.all(np.isfinite(np.asarray(g.log_walk_sigma)))
    # The variance row's mean network starts where lstm_bi's does.
    from experiments.kitti_vo import experiment as E

    bi = E.build_model("lstm_bi", None, E.method_key(key, "lstm_bi"))
    assert bool(eqx.tree_equal(model.lstm, bi))


def test_uncertainty_window_frame_and_heading_wrap():
    import jax.numpy as jnp

    from experiments.kitti_vo import uncertainty as U

    # The tangent's position block is rotated into the window frame.
    est = jnp.array([[0.0, 0.0, np.pi / 2]])
    pose_cov = jnp.diag(jnp.array([4.0, 1.0, 0.5]))[None]
    np.testing.assert_allclose(
        np.asarray(U._to_window_frame(est, pose_cov))[0],
        np.diag([1.0, 4.0, 0.5]),
        atol=1e-6,
    )
    # Heading errors are wrapped: -π + 0.01 is 0.02 rad past π - 0.01.
    truth = np.zeros((1, 2, 3))
    truth[0, 1] = [1.0, 0.0, np.pi - 0.01]
    guess = truth.copy()
    guess[0, 1, 2] = -np.pi + 0.01
    cov = np.broadcast_to(np.eye(3) * 1e-4, (1, 2, 3, 3))
    np.testing.assert_allclose(U.score(guess, cov, truth)["heading"]["nees"], 4.0)


def test_uncertainty_reproduction_record():
    from experiments.kitti_vo import uncertainty as U

    now = {"trans_m_per_m": 0.21, "rot_deg_per_m": 0.17}
    committed = {
        "rows": {
            "ekf_hetero": {"trans_m_per_m": 0.20, "rot_deg_per_m": 0.17},
            "smoother_hetero_e2e": {
                "trans_m_per_m": 0.25,
                "rot_deg_per_m": 0.18,
                "whole_window_from": {
                    "trans_m_per_m": 0.2105,
                    "rot_deg_per_m": 0.17,
                    "git": "abc",
                    "best_step": 100,
                },
            },
        }
    }
    r = U.reproduction("ekf_hetero", now, committed)
    np.testing.assert_allclose(r["difference"]["trans_m_per_m"], 0.01)
    r = U.reproduction("smoother_hetero_e2e", now, committed)
    np.testing.assert_allclose(r["difference_retrain"]["trans_m_per_m"], -0.0005)
    assert U.reproduction(U.LSTM_VARIANCE, now, committed)["committed"] is None


@pytest.mark.slow
def test_uncertainty_mode_quick_run(tmp_path, monkeypatch):
    """`--uncertainty` (`uncertainty.run_fold`) on the quick configuration
    with a stand-in sensor, tiny windows in place of the rendered fold (the
    rendering and the sensor cache are `experiment.prepare_fold`'s, run by
    the quick experiment) and two steps: rows, heads, the check against
    `fold_K.json`, resume (a finished fold is skipped) and the pooled
    uncertainty.json with its figure. Slow (two estimators compiled for
    training and scoring)."""
    import dataclasses
    import json

    import equinox as eqx
    import jax

    pytest.importorskip("matplotlib", reason="the summary draws a figure")
    from experiments.kitti_vo import experiment as E, models as M, uncertainty as U

    cfg = dataclasses.replace(
        E.quick_config(), methods=("ekf_const",), steps=2, eval_every=1
    )
    with pytest.raises(FileNotFoundError, match="no sensor"):
        U.run_fold(cfg, 3, tmp_path)
    eqx.tree_serialise_leaves(
        tmp_path / "sensor_fold3.eqx", M.VelocitySensor(jax.random.key(0))
    )
    windows = _tiny_windows(B=4, T=8)

    def prepare(cfg, fold, out, timings, save=None, train_sensor=True):
        assert not train_sensor and (out / f"sensor_fold{fold}.eqx").exists()
        timings["load_s"] = 0.0
        return {
            "train": windows,
            "valid": windows,
            "test": windows,
            "sigmas": np.array([1.0, 0.1]),
        }

    monkeypatch.setattr(E, "prepare_fold", prepare)
    committed = {"rows": {"ekf_const": {"trans_m_per_m": 1.0, "rot_deg_per_m": 1.0}}}
    (tmp_path / "fold_3.json").write_text(json.dumps(committed))
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        rec = U.run_fold(cfg, 3, tmp_path)
        assert set(rec["rows"]) == {"ekf_const", U.LSTM_VARIANCE}
        for m, row in rec["rows"].items():
            assert (tmp_path / row["head"]).exists(), m
            assert row["head_bytes"] < 1_000_000
            assert row["windows_with_covariance"] == 4
            assert np.isfinite(row["position"]["nll"]), m
            assert set(row["position"]["coverage"]) == {str(q) for q in U.LEVELS}
        ekf = rec["rows"]["ekf_const"]["test_scores"]
        assert ekf["difference"]["trans_m_per_m"] == pytest.approx(
            ekf["now"]["trans_m_per_m"] - 1.0
        )
        assert U.run_fold(cfg, 3, tmp_path) is None  # finished: skipped
        # A lost row is scored again from its saved head, not trained.
        nll = rec["rows"]["ekf_const"]["position"]["nll"]
        del rec["rows"]["ekf_const"]
        (tmp_path / "uncertainty_fold_3.json").write_text(json.dumps(rec))
        again = U.run_fold(cfg, 3, tmp_path)
        assert again["rows"]["ekf_const"]["train_s"] is None
        np.testing.assert_allclose(
            again["rows"]["ekf_const"]["position"]["nll"], nll, rtol=1e-6
        )
    summary = U.summarise(tmp_path)
    assert summary["folds"] == [3]
    assert set(summary["position"]["rows"]) == {"ekf_const", U.LSTM_VARIANCE}
    assert (tmp_path / "uncertainty.json").exists()
    assert (tmp_path / "fig_calibration.png").stat().st_size > 10_000
    assert "Finished folds: [3]" in U.markdown(summary)
