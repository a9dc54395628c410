"""The pose graphs GTSAM ships: TORO's 3-D lines (`VERTEX3`/`EDGE3`), `EDGE2`
lines in g2o's information order, and, with gtsam installed, the same cost as
GTSAM's own reader (`load2D`/`readG2o`/`load3D`) at the same values.

The timing of every file against GTSAM is `python -m benchmarks.pgo
--gtsam-files` (results in `benchmarks/results/pgo_gtsam_files.json`).
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation


GTSAM_REASON = "GTSAM not installed (pip install gtsam)"


def _write(tmp_path, text, name="graph.graph"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _rotations(values):
    wxyz = np.asarray(values["pose"].wxyz_xyz)[:, :4]
    return Rotation.from_quat(wxyz[:, [1, 2, 3, 0]]).as_matrix()


def _information(pg):
    R = np.asarray(pg.between.noise.sqrt_information)
    return np.swapaxes(R, -1, -2) @ R


def _upper(m):
    return " ".join(repr(float(v)) for v in m[np.triu_indices(m.shape[0])])


# ------------------------------------------------------------- TORO's 3-D lines

RPY = [(0.3, -0.2, 1.1), (-2.9, 1.2, -0.4)]


def test_vertex3_edge3_rotations_are_yaw_pitch_roll(tmp_path):
    from eqsmooth.io import load_g2o

    (r0, p0, y0), (r1, p1, y1) = RPY
    text = (
        f"VERTEX3 0 1 2 3 {r0} {p0} {y0}\nVERTEX3 1 -1 0.5 2 {r1} {p1} {y1}\n"
        f"EDGE3 0 1 0.1 0.2 0.3 {r1} {p1} {y1}\n"
    )
    pg = load_g2o(_write(tmp_path, text))
    # R = Rz(yaw) Ry(pitch) Rx(roll): intrinsic z-y'-x'' angles (yaw, pitch, roll).
    expected = Rotation.from_euler("ZYX", [(y, p, r) for r, p, y in RPY]).as_matrix()
    np.testing.assert_allclose(_rotations(pg.values), expected, atol=1e-14)
    np.testing.assert_allclose(
        _rotations({"pose": pg.between.measurement}), expected[1:], atol=1e-14
    )
    t = np.asarray(pg.values["pose"].wxyz_xyz)[:, 4:]
    np.testing.assert_array_equal(t, [[1, 2, 3], [-1, 0.5, 2]])
    assert pg.kind == "se3" and pg.se3_information == "gtsam"
    # Without information entries an EDGE3 line gets unit information.
    np.testing.assert_allclose(_information(pg)[0], np.eye(6), atol=1e-12)


def test_edge3_information_is_rotation_first(tmp_path):
    from eqsmooth.io import load_g2o

    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    info = a @ a.T + 6 * np.eye(6)  # GTSAM's tangent order (ω, v)
    text = "VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 0 0 0 0 0\n"
    text += f"EDGE3 0 1 1 0 0 0 0 0 {_upper(info)}\n"
    pg = load_g2o(_write(tmp_path, text))
    swap = [3, 4, 5, 0, 1, 2]  # to eqsmooth's (v, ω)
    np.testing.assert_allclose(_information(pg)[0], info[swap][:, swap], rtol=1e-12)


def test_edge3_round_trip_through_edge_se3_quat(tmp_path):
    from eqsmooth.io import load_g2o, save_g2o

    info = np.diag([10.0, 10, 10, 100, 100, 25])
    text = "VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 0 0 0.1 0.2 0.3\n"
    text += f"EDGE3 0 1 1 0 0 0.1 0.2 0.3 {_upper(info)}\n"
    pg = load_g2o(_write(tmp_path, text))
    save_g2o(tmp_path / "out.g2o", pg)
    back = load_g2o(tmp_path / "out.g2o", se3_information="gtsam")
    np.testing.assert_allclose(_information(back), _information(pg), rtol=1e-12)
    np.testing.assert_allclose(
        _rotations(back.values), _rotations(pg.values), atol=1e-14
    )


def test_edge2_information_in_either_order(tmp_path):
    from eqsmooth.io import load_g2o

    vertices = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\n"
    # g2o's order xx xy xt yy yt tt (GTSAM's w100_30.g2o, w20000.txt) and
    # TORO's xx xy yy tt xt yt give the same diagonal matrix.
    g2o = load_g2o(_write(tmp_path, vertices + "EDGE2 0 1 1 0 0 4 0 0 9 0 25\n"))
    toro = load_g2o(_write(tmp_path, vertices + "EDGE2 0 1 1 0 0 4 0 9 25 0 0\n"))
    np.testing.assert_allclose(_information(g2o)[0], np.diag([4.0, 9, 25]))
    np.testing.assert_allclose(_information(toro)[0], np.diag([4.0, 9, 25]))


@pytest.mark.parametrize(
    "text, line, match",
    [
        ("VERTEX3 0 0 0 0 0 0\n", 1, r"VERTEX3 needs 7 fields .*got 6"),
        ("EDGE3 0 1 0 0 0 0 0 0 1 2\n", 1, r"EDGE3 needs 8 or 29 fields .*got 10"),
        (
            "EDGE3 0 1 0 0 0 0 0 0\nEDGE3 1 2 0 0 0 0 0 0" + " 1" * 21 + "\n",
            2,
            "either every EDGE3 line has information entries or none",
        ),
        (
            "EDGE3 0 1 0 0 0 0 0 0\nEDGE_SE3:QUAT 1 2 0 0 0 0 0 0 1"
            + " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n",
            1,
            "pass se3_information='gtsam'",
        ),
        ("VERTEX2 0 0 0 0\nEDGE3 0 1 0 0 0 0 0 0\n", 2, "mixes 2-D and 3-D"),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, line, match):
    from eqsmooth.io import load_g2o

    path = _write(tmp_path, text)
    with pytest.raises(ValueError, match=match) as info:
        load_g2o(path)
    assert f"{path}:{line}:" in str(info.value)


# ---------------------------------------------------- GTSAM's files and readers

# (file, GTSAM's reader of it). load2D reads the diagonal g2o matrices of
# pose2example.txt as covariances (its NoiseFormatAUTO), readG2o and we as
# information; costs of ~1e-28 (nothing to optimise) compare absolutely.
SMALL = [
    ("w100.graph", "load2D"),
    ("w100_30.g2o", "readG2o"),
    ("pose2example.txt", "readG2o"),
    ("noisyToyGraph.txt", "load2D"),
    ("cityTrees_reduced_1k.g2o", "load2D"),  # LANDMARK2 lines: GTSAM skips them
    ("Klaus3.g2o", "load3D"),
    ("pose3example-grid.txt", "load3D"),
    ("pose3example-offdiagonal.txt", "load3D"),
    ("sphere2500.txt", "load3D"),  # EDGE3 only: GTSAM's load3D makes no values
]


def _gtsam_values(gtsam, pg):
    """Our initial poses as `gtsam.Values` keyed by the file's vertex ids."""
    from eqsmooth.io import to_gtsam

    _, values = to_gtsam(pg)
    at = values.atPose2 if pg.kind == "se2" else values.atPose3
    keyed = gtsam.Values()
    for k, i in enumerate(pg.vertex_ids.tolist()):
        keyed.insert(i, at(k))
    return keyed


@pytest.mark.parametrize("name, reader", SMALL)
def test_initial_cost_matches_gtsams_reader(name, reader):
    gtsam = pytest.importorskip("gtsam", reason=GTSAM_REASON)
    from eqsmooth.io import load_g2o

    path = gtsam.findExampleDataFile(name)
    pg = load_g2o(path, skip_unsupported=True, se3_information="gtsam")
    graph, their_values = getattr(gtsam, reader)(path)
    assert graph.size() == pg.num_edges
    ours = float(pg.graph.cost(pg.values))
    theirs = graph.error(_gtsam_values(gtsam, pg))
    np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-20)
    if their_values.size():  # their initial values are ours too
        assert their_values.size() == pg.num_poses
        np.testing.assert_allclose(
            graph.error(their_values), ours, rtol=1e-9, atol=1e-20
        )


def test_sphere_smallnoise_vertices_and_first_edge_match_gtsam():
    # Its EDGE3 lines have no information entries; GTSAM's load3D stops after
    # the first one, so only the poses and that edge can be compared.
    gtsam = pytest.importorskip("gtsam", reason=GTSAM_REASON)
    from eqsmooth.io import load_g2o

    path = gtsam.findExampleDataFile("sphere_smallnoise.graph")
    pg = load_g2o(path)
    graph, values = gtsam.load3D(path)
    assert (pg.num_poses, pg.num_edges, values.size(), graph.size()) == (
        2200,
        8647,
        2200,
        1,
    )
    theirs = np.stack([values.atPose3(int(i)).matrix() for i in pg.vertex_ids])
    np.testing.assert_allclose(_rotations(pg.values), theirs[:, :3, :3], atol=1e-12)
    t = np.asarray(pg.values["pose"].wxyz_xyz)[:, 4:]
    np.testing.assert_allclose(t, theirs[:, :3, 3], atol=1e-12)
    z = graph.at(0).measured().matrix()
    np.testing.assert_allclose(
        _rotations({"pose": pg.between.measurement})[0], z[:3, :3], atol=1e-12
    )
