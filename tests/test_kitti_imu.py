"""The KITTI IMU + GPS outage protocol (experiments/kitti_imu): folds,
outages and intervals (fast), and the quick configuration end to end
(slow). The data comes from the gtsam wheel, so those tests skip without it."""

import json

import numpy as np
import pytest

from experiments.kitti_imu import data as D


def test_folds_are_disjoint_and_cover_every_segment():
    cfg = D.Config()
    tests = []
    for fold in range(cfg.num_segments):
        s = D.fold_split(fold, cfg)
        parts = s["train"] + s["valid"] + s["test"]
        assert sorted(parts) == list(range(cfg.num_segments))
        assert len(set(parts)) == len(parts)
        assert s["valid"] == [(fold + 1) % cfg.num_segments]
        tests += s["test"]
    assert sorted(tests) == list(range(cfg.num_segments))
    with pytest.raises(ValueError, match="fold must be in 0..4"):
        D.fold_split(5, cfg)


def test_declared_outages():
    mask = D.outage_mask(D.Config())
    assert mask.shape == (93,) and mask.sum() == 60
    assert np.flatnonzero(mask).tolist() == list(range(10, 40)) + list(range(55, 85))


def test_initial_guess_never_reads_a_withheld_fix():
    rng = np.random.default_rng(0)
    xyz = np.cumsum(rng.normal(size=(20, 3)), axis=0)
    withheld = np.zeros(20, bool)
    withheld[5:12] = True
    a = D.initial_guess(xyz, withheld)
    xyz2 = xyz.copy()
    xyz2[withheld] = 1e6
    b = D.initial_guess(xyz2, withheld)
    for u, v in zip(a, b):
        np.testing.assert_array_equal(u, v)
    # Interpolated in the outage, the fixes elsewhere.
    np.testing.assert_allclose(a[0][~withheld], xyz[~withheld])
    np.testing.assert_allclose(a[0][8], xyz[4] + (xyz[12] - xyz[4]) * 4 / 8)


def test_intervals_follow_the_example_rule():
    # GTSAM's example walks the samples once: a sample on a keyframe time
    # ends that interval and is not taken again by the next.
    imu_t = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.2, 3.0, 3.5])
    key_t = np.array([0.5, 2.0, 3.0])
    rows = D.interval_rows(imu_t, key_t)
    assert [r.tolist() for r in rows] == [[1, 2, 3, 4], [5, 6]]


def test_segments_of_the_drive():
    pytest.importorskip("gtsam", reason="the KITTI files come from the gtsam wheel")
    meta, imu, gps = D.load()
    cfg = D.Config()
    data = D.segments(meta, imu, gps, cfg)
    assert data["samples"].shape[:2] == (5, 92)
    assert data["gps"].shape == (5, 93, 3)
    # Contiguous, in time order, no keyframe in two segments.
    t = data["time"]
    assert np.all(np.diff(t, axis=1) > 0) and np.all(t[1:, 0] > t[:-1, -1])
    np.testing.assert_allclose(t[:, 0], [0.0, 93.0, 186.0, 279.0, 372.0], atol=0.05)
    # Every interval's masked samples lie between its keyframes.
    s, m = data["samples"], data["mask"]
    assert m.sum() == data["count"].sum() and data["count"].min() >= 100
    np.testing.assert_allclose(
        np.where(m, s[..., 0], 0).sum(-1), np.diff(t, axis=1), atol=0.02
    )
    with pytest.raises(ValueError, match="need 931 GPS rows"):
        D.segments(meta, imu, gps, D.Config(num_segments=10))


@pytest.mark.slow
def test_quick_run(tmp_path):
    """The quick configuration end to end (61 s on 2 shared cores with a warm
    compilation cache, about 4 minutes cold, nearly all compilation): a fold
    file with both rows scored, the learned sigmas moved by training, and the
    summary refuses quick files."""
    pytest.importorskip("gtsam", reason="the KITTI files come from the gtsam wheel")
    from experiments.kitti_imu.__main__ import main

    main(["--quick", "--out", str(tmp_path)])
    out = json.loads((tmp_path / "fold_0.json").read_text())
    assert out["config"]["quick"] and out["split"]["test"] == [0]
    rows = out["rows"]
    for row in ("metadata", "learned_constant"):
        r = rows[row]
        assert r["withheld_fixes"] == 8 and r["valid_covariances"] == 8
        assert np.isfinite([r["rms_horizontal_m"], r["nll"]]).all()
        assert r["max_horizontal_m"] >= r["rms_horizontal_m"] > 0
    assert np.isclose(rows["metadata"]["sigmas"]["accelerometer"], 0.01)
    steps = [h["step"] for h in out["training"]["history"]]
    assert max(steps) == 2
    if out["training"]["best_step"] > 0:
        a = rows["metadata"]["sigmas"]
        b = rows["learned_constant"]["sigmas"]
        assert any(abs(np.log(a[k] / b[k])) > 1e-4 for k in a)
    with pytest.raises(SystemExit, match="no fold files of the declared protocol"):
        main(["--summary", "--out", str(tmp_path)])
