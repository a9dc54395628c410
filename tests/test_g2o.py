"""g2o input/output: parsing, information conversion, round trips, errors, data."""

import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation


DATA = Path(__file__).parents[1] / ".." / "shared" / "data" / "g2o"


# ------------------------------------------------------------ numpy references


def _se2_matrix(x, y, theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0, 0, 1.0]])


def _se3_matrix(t, q_xyzw):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
    m[:3, 3] = t
    return m


def _g2o_error_se2(za, a, b):
    """g2o's EDGE_SE2 error: (x, y, θ) of z⁻¹ a⁻¹ b."""
    d = np.linalg.inv(za) @ np.linalg.inv(a) @ b
    return np.array([d[0, 2], d[1, 2], np.arctan2(d[1, 0], d[0, 0])])


def _g2o_error_se3(z, a, b):
    """g2o's EDGE_SE3:QUAT error: translation and quaternion vector part (w ≥ 0)."""
    d = np.linalg.inv(z) @ np.linalg.inv(a) @ b
    q = Rotation.from_matrix(d[:3, :3]).as_quat()  # x y z w
    q = q if q[3] >= 0 else -q
    return np.concatenate([d[:3, 3], q[:3]])


def _upper(m):
    return " ".join(repr(float(v)) for v in m[np.triu_indices(m.shape[0])])


def _spd(rng, d):
    a = rng.normal(size=(d, d))
    return a @ a.T + d * np.eye(d)


def _write(tmp_path, text, name="graph.g2o"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _params(values):
    return np.asarray(values["pose"].parameters())


def _cost(pose_graph, values) -> float:
    # Jitted: an eager first call costs seconds of per-operation compilation.
    import equinox as eqx

    return float(eqx.filter_jit(_graph_cost)(pose_graph.graph, values))


def _graph_cost(graph, values):
    return graph.cost(values)


# -------------------------------------------------------------------- parsing

SE2_TEXT = """\
# a comment, then a blank line

VERTEX_SE2 10 1.0 2.0 0.5
VERTEX_SE2 5 0.0 0.0 0.0
VERTEX_SE2 7 0.5 0.25 -0.3
EDGE_SE2 5 7 0.5 0.2 -0.25 100 1 2 200 3 300
EDGE_SE2 7 10 0.6 1.7 0.8 50 0 0 50 0 20
"""


def test_load_se2_values_ids_and_information(tmp_path):
    from eqsmooth.io import load_g2o

    pg = load_g2o(_write(tmp_path, SE2_TEXT))
    assert pg.kind == "se2" and pg.num_poses == 3 and pg.num_edges == 2
    np.testing.assert_array_equal(pg.vertex_ids, [5, 7, 10])
    np.testing.assert_array_equal(pg.edges, [[0, 1], [1, 2]])
    np.testing.assert_array_equal(pg.anchored, [0])
    p = _params(pg.values)
    np.testing.assert_allclose(
        p[2], [np.cos(0.5), np.sin(0.5), 1.0, 2.0], rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(
        p[1], [np.cos(-0.3), np.sin(-0.3), 0.5, 0.25], rtol=0, atol=1e-15
    )
    R = np.asarray(pg.between.noise.sqrt_information)
    info0 = np.array([[100, 1, 2], [1, 200, 3], [2, 3, 300.0]])
    np.testing.assert_allclose(R[0].T @ R[0], info0, rtol=1e-12)
    np.testing.assert_allclose(R[1].T @ R[1], np.diag([50, 50, 20.0]), rtol=1e-12)
    np.testing.assert_array_equal(R, np.tril(R))
    # The anchor prior sits at the initial value: it adds nothing to the cost.
    free = load_g2o(_write(tmp_path, SE2_TEXT), anchor=False)
    assert len(free.graph.factors) == 1 and len(free.anchored) == 0
    np.testing.assert_allclose(
        _cost(pg, pg.values), _cost(free, free.values), rtol=1e-12
    )


def test_older_se2_tags_read_as_the_current_ones(tmp_path):
    # TORO's VERTEX2 / EDGE2 (GTSAM's w10000.graph) have the fields of
    # VERTEX_SE2 / EDGE_SE2, EDGE2's information listed as xx xy yy tt xt yt.
    from eqsmooth.io import load_g2o

    def toro(line):
        t = line.split()
        if t and t[0] == "EDGE_SE2":
            xx, xy, xt, yy, yt, tt = t[6:]
            t = ["EDGE2", *t[1:6], xx, xy, yy, tt, xt, yt]
        return " ".join(t).replace("VERTEX_SE2", "VERTEX2")

    old = "\n".join(toro(line) for line in SE2_TEXT.splitlines())
    a = load_g2o(_write(tmp_path, SE2_TEXT, "new.g2o"))
    b = load_g2o(_write(tmp_path, old, "old.graph"))
    np.testing.assert_array_equal(_params(a.values), _params(b.values))
    np.testing.assert_array_equal(a.edges, b.edges)
    np.testing.assert_array_equal(
        np.asarray(a.between.noise.sqrt_information),
        np.asarray(b.between.noise.sqrt_information),
    )


def test_se2_cost_matches_g2o_by_hand(tmp_path):
    from eqsmooth.io import load_g2o
    from eqsmooth.lie import SE2

    info = _spd(np.random.default_rng(0), 3)
    z = (0.8, -0.3, 0.4)
    text = (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0.8 -0.3 0.4\n"
        f"EDGE_SE2 0 1 {z[0]} {z[1]} {z[2]} {_upper(info)}\n"
    )
    pg = load_g2o(_write(tmp_path, text), anchor=False)
    a = _se2_matrix(0, 0, 0)
    # Pure translation or pure rotation of the relative pose: g2o's error and
    # the SE(2) logarithm coincide, so the costs agree exactly.
    for dx, dy, dth in [(0.05, -0.02, 0.0), (0.0, 0.0, 0.1), (1e-4, -2e-4, 3e-4)]:
        b = _se2_matrix(*z) @ _se2_matrix(dx, dy, 0) @ _se2_matrix(0, 0, dth)
        e = _g2o_error_se2(_se2_matrix(*z), a, b)
        expected = 0.5 * e @ info @ e
        values = {
            "pose": SE2.from_xy_theta(
                np.array([0.0, b[0, 2]]),
                np.array([0.0, b[1, 2]]),
                np.array([0.0, np.arctan2(b[1, 0], b[0, 0])]),
            )
        }
        got = _cost(pg, values)
        exact = dx == 0 or dth == 0
        np.testing.assert_allclose(got, expected, rtol=1e-9 if exact else 1e-3)


def _se3_graph_text(info, t, q, header=""):
    return (
        header
        + "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
        + f"VERTEX_SE3:QUAT 1 {t[0]} {t[1]} {t[2]} {q[0]} {q[1]} {q[2]} {q[3]}\n"
        + f"EDGE_SE3:QUAT 0 1 {t[0]} {t[1]} {t[2]} {q[0]} {q[1]} {q[2]} {q[3]} "
        + _upper(info)
        + "\n"
    )


def test_se3_information_conversion(tmp_path):
    """Default: the file's Λ is for (t, q_vec ≈ ω/2), so the cost equals g2o's;
    "gtsam": Λ is used for (v, ω) directly, rotation weights 4 times larger."""
    from eqsmooth.io import load_g2o
    from eqsmooth.lie import SE3

    rng = np.random.default_rng(1)
    info = _spd(rng, 6)
    t = np.array([1.0, -0.5, 0.25])
    q = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_quat()
    path = _write(tmp_path, _se3_graph_text(info, t, q))
    pg = load_g2o(path, anchor=False)
    pg_gtsam = load_g2o(path, anchor=False, se3_information="gtsam")
    z = _se3_matrix(t, q)
    half = np.diag([1, 1, 1, 0.5, 0.5, 0.5])
    R = np.asarray(pg.between.noise.sqrt_information)[0]
    np.testing.assert_allclose(R.T @ R, half @ info @ half, rtol=1e-12)

    def cost_at(graph, b):
        qb = Rotation.from_matrix(b[:3, :3]).as_quat()
        params = np.stack(
            [[1.0, 0, 0, 0, 0, 0, 0], np.concatenate([qb[3:], qb[:3], b[:3, 3]])]
        )
        return _cost(graph, {"pose": SE3(params)})

    a = np.eye(4)
    cases = [  # (perturbation, rtol against g2o's cost)
        (_se3_matrix([0.03, -0.01, 0.02], [0, 0, 0, 1]), 1e-9),  # translation: exact
        (
            _se3_matrix([0, 0, 0], Rotation.from_rotvec([3e-3, -1e-3, 2e-3]).as_quat()),
            1e-5,
        ),
        (
            _se3_matrix(
                [2e-4, 1e-4, -1e-4], Rotation.from_rotvec([1e-4, 2e-4, -3e-4]).as_quat()
            ),
            2e-3,
        ),
    ]
    for delta, rtol in cases:
        b = z @ delta
        e = _g2o_error_se3(z, a, b)
        np.testing.assert_allclose(cost_at(pg, b), 0.5 * e @ info @ e, rtol=rtol)
    # Pure rotation: GTSAM's convention weighs the angle, g2o's the half angle.
    rot = cases[1][0]
    w = Rotation.from_matrix(rot[:3, :3]).as_rotvec()
    r = np.concatenate([np.zeros(3), w])
    np.testing.assert_allclose(
        cost_at(pg_gtsam, z @ rot), 0.5 * r @ info @ r, rtol=1e-9
    )
    np.testing.assert_allclose(
        cost_at(pg_gtsam, z @ rot), 4 * cost_at(pg, z @ rot), rtol=1e-5
    )


# ---------------------------------------------------------------- round trips


def test_round_trip_se2_and_se3(tmp_path):
    from eqsmooth.io import load_g2o, save_g2o

    rng = np.random.default_rng(2)
    lines = ["FIX 7"]
    for vid in [3, 7, 11, 12]:
        q = Rotation.random(random_state=rng).as_quat()
        lines.append(
            f"VERTEX_SE3:QUAT {vid} "
            + " ".join(repr(float(v)) for v in [*rng.normal(size=3), *q])
        )
    for i, j in [(3, 7), (7, 11), (11, 12), (3, 12)]:
        q = Rotation.random(random_state=rng).as_quat()
        lines.append(
            f"EDGE_SE3:QUAT {i} {j} "
            + " ".join(repr(float(v)) for v in [*rng.normal(size=3), *q])
            + " "
            + _upper(_spd(rng, 6))
        )
    se3 = _write(tmp_path, "\n".join(lines) + "\n", "se3.g2o")
    se2 = _write(tmp_path, SE2_TEXT, "se2.g2o")
    for src in (se2, se3):
        pg = load_g2o(src)
        out = tmp_path / ("copy_" + src.name)
        save_g2o(out, pg)
        back = load_g2o(out)
        assert back.kind == pg.kind
        np.testing.assert_array_equal(back.vertex_ids, pg.vertex_ids)
        np.testing.assert_array_equal(back.edges, pg.edges)
        np.testing.assert_array_equal(back.anchored, pg.anchored)
        np.testing.assert_allclose(_params(back.values), _params(pg.values), atol=1e-15)
        np.testing.assert_allclose(
            np.asarray(back.between.measurement.parameters()),
            np.asarray(pg.between.measurement.parameters()),
            atol=1e-15,
        )
        for x, y in [(back, pg)]:
            Rx = np.asarray(x.between.noise.sqrt_information)
            Ry = np.asarray(y.between.noise.sqrt_information)
            np.testing.assert_allclose(Rx, Ry, rtol=1e-12, atol=1e-12)
        assert not list(tmp_path.glob(".*.tmp"))  # the temporary file is gone
    assert load_g2o(se3).anchored.tolist() == [1]  # FIX 7 is the second pose


def test_save_values_only(tmp_path):
    from eqsmooth.io import save_g2o
    from eqsmooth.lie import SE2

    poses = SE2.from_xy_theta(
        np.array([0.0, 1.5]), np.array([2.0, -1.0]), np.array([0.1, -3.0])
    )
    out = tmp_path / "v.g2o"
    save_g2o(out, {"pose": poses}, vertex_ids=np.array([4, 9]))
    rows = [line.split() for line in out.read_text().splitlines()]
    assert [r[:2] for r in rows] == [["VERTEX_SE2", "4"], ["VERTEX_SE2", "9"]]
    np.testing.assert_allclose(
        np.array([r[2:] for r in rows], float),
        [[0, 2, 0.1], [1.5, -1, -3.0]],
        atol=1e-15,
    )
    with pytest.raises(ValueError, match="vertex_ids"):
        save_g2o(out, poses, vertex_ids=np.array([1, 2, 3]))
    with pytest.raises(TypeError, match="SE2 or SE3"):
        save_g2o(out, {"pose": np.zeros((2, 3))})


def test_edges_only_file_composes_odometry(tmp_path):
    from eqsmooth.io import load_g2o
    from eqsmooth.manifold import local

    text = (
        "EDGE_SE2 2 4 1.0 0.0 0.5 10 0 0 10 0 10\n"
        "EDGE_SE2 4 6 1.0 0.5 -0.2 10 0 0 10 0 10\n"
        "EDGE_SE2 2 6 1.8 1.1 0.2 10 0 0 10 0 10\n"
    )
    pg = load_g2o(_write(tmp_path, text))
    np.testing.assert_array_equal(pg.vertex_ids, [2, 4, 6])
    x = pg.values["pose"]
    expected = (
        _se2_matrix(0, 0, 0) @ _se2_matrix(1.0, 0.0, 0.5) @ _se2_matrix(1.0, 0.5, -0.2)
    )
    np.testing.assert_allclose(np.asarray(x.as_matrix())[2], expected, atol=1e-14)
    # Odometry edges fit exactly; the loop closure carries the error.
    r = local(
        pg.between.measurement, x[pg.edges[:, 0]].inverse() @ x[pg.edges[:, 1]], 1
    )
    np.testing.assert_allclose(np.asarray(r)[:2], 0, atol=1e-14)
    assert np.abs(np.asarray(r)[2]).max() > 1e-3


# --------------------------------------------------------------------- errors


V0 = "VERTEX_SE2 0 0 0 0\n"
V1 = "VERTEX_SE2 1 1 0 0\n"
E01 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
ONE6 = " 1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n"


@pytest.mark.parametrize(
    "text, line, match",
    [
        (V0 + "VERTEX_XY 1 2 3\n", 2, "unsupported tag 'VERTEX_XY'"),
        ("VERTEX_SE2 0 0 0\n", 1, r"VERTEX_SE2 needs 4 fields .*got 3"),
        (V0 + V1 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 x\n", 3, "cannot read 'x'"),
        (V0 + V1 + "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1\n", 3, "integer id"),
        (V0 + E01, 2, "vertex 1, which has no VERTEX_SE2"),
        (V0 + V1 + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", 3, "itself"),
        (V0 + V1 + V1 + E01, 3, "vertex 1 defined twice"),
        (V0 + V1 + "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n", 3, "not positive definite"),
        (V0 + V1 + "EDGE_SE2 0 1 1 0 nan 1 0 0 1 0 1\n", 3, "non-finite"),
        (V0 + "VERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n", 2, "mixes 2-D and 3-D"),
        (
            "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n"
            "EDGE_SE3:QUAT 0 1 0 0 0 0 0 0 1" + ONE6,
            1,
            "quaternion of norm 0",
        ),
        (V0 + V1 + "FIX 5\n" + E01, 3, "unknown vertex 5"),
    ],
)
def test_errors_name_file_and_line(tmp_path, text, line, match):
    from eqsmooth.io import load_g2o

    path = _write(tmp_path, text)
    with pytest.raises(ValueError, match=match) as info:
        load_g2o(path)
    assert f"{path}:{line}:" in str(info.value)


def test_errors_without_line(tmp_path):
    from eqsmooth.io import load_g2o

    with pytest.raises(FileNotFoundError):
        load_g2o(tmp_path / "missing.g2o")
    with pytest.raises(ValueError, match="no pose vertices or edges"):
        load_g2o(_write(tmp_path, "# nothing\n"))
    with pytest.raises(ValueError, match="no EDGE_SE2 lines"):
        load_g2o(_write(tmp_path, "VERTEX_SE2 0 0 0 0\n"))
    with pytest.raises(ValueError, match="vertex 8 is not connected to vertex 0"):
        load_g2o(_write(tmp_path, E01 + "EDGE_SE2 8 9 1 0 0 1 0 0 1 0 1\n"))
    with pytest.raises((ValueError, TypeError), match="se3_information"):
        load_g2o(_write(tmp_path, SE2_TEXT), se3_information="ceres")  # pyright: ignore
    path = _write(tmp_path, V0 + "LANDMARK 1 2\n" + V1 + E01)
    assert load_g2o(path, skip_unsupported=True).num_poses == 2


def test_invalid_information_repairs(tmp_path):
    from eqsmooth.io import load_g2o

    # Cross terms larger than the diagonal (as in cubicle.g2o's odometry edges).
    info = np.diag([10.0, 10, 10, 10, 10, 10])
    info[2, 3] = info[3, 2] = 1e3
    path = _write(tmp_path, _se3_graph_text(info, [1, 0, 0], [0, 0, 0, 1]))
    with pytest.raises(ValueError, match="1 of 1 edges"):
        load_g2o(path)
    for mode in ("clip", "block_diagonal"):
        with pytest.warns(UserWarning, match="1 of 1 EDGE_SE3:QUAT information"):
            pg = load_g2o(path, invalid_information=mode)
        R = np.asarray(pg.between.noise.sqrt_information)[0]
        assert np.all(np.linalg.eigvalsh(R.T @ R) > 0)
    half = np.array([1, 1, 1, 0.5, 0.5, 0.5])
    np.testing.assert_allclose(R.T @ R, np.diag(10 * half * half), rtol=1e-12)


# ------------------------------------------------------------------ synthetic


def test_synthetic_pose_graph_2d():
    import eqsmooth as eqs
    from eqsmooth.io import synthetic_pose_graph_2d

    pg, truth = synthetic_pose_graph_2d(40, seed=3)
    pg2, _ = synthetic_pose_graph_2d(40, seed=3)
    np.testing.assert_array_equal(_params(pg.values), _params(pg2.values))
    assert pg.num_poses == 40 and pg.num_edges > 39  # odometry + loop closures
    sol = eqs.least_squares(
        pg.graph, pg.values, eqs.GaussNewton(eqs.DenseCholesky()), max_steps=10
    )
    initial, final = float(sol.stats["initial_cost"]), float(sol.stats["final_cost"])
    assert final < 0.05 * initial
    # The estimate is closer to the truth than dead reckoning.
    err0 = np.abs(_params(pg.values)[:, 2:] - np.asarray(truth.translation())).max()
    err1 = np.abs(_params(sol.value)[:, 2:] - np.asarray(truth.translation())).max()
    assert err1 < err0


# ----------------------------------------------------------------- real data


def _solve_file(name: str, max_steps: int, linear: str):
    import eqsmooth as eqs
    from eqsmooth.io import load_g2o

    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} not found: the g2o data sets live in ../shared/data/g2o")
    pg = load_g2o(path)
    solver = eqs.solve.SparseLU() if linear == "sparse" else eqs.PCG()
    sol = eqs.least_squares(
        pg.graph,
        pg.values,
        eqs.LevenbergMarquardt(solver),
        max_steps=max_steps,
        throw=False,
    )
    return pg, sol


_SOLVED = {}
# LM runs to convergence (ftol = 1e-8): intel takes 4 (SparseLU) to 14 (PCG)
# steps.
_STEPS = {"intel.g2o": 50, "smallGrid3D.g2o": 50}


def _solved(name: str, linear: str = "pcg"):
    if (name, linear) not in _SOLVED:
        _SOLVED[name, linear] = _solve_file(name, _STEPS[name], linear)
    return _SOLVED[name, linear]


@pytest.mark.parametrize(
    "name, factor", [("intel.g2o", 10.0), ("smallGrid3D.g2o", 300.0)]
)
def test_real_data_cost_decreases(name, factor):
    import eqsmooth as eqs

    pg, sol = _solved(name)
    assert sol.result == eqs.RESULTS.successful  # converged, not out of steps
    initial, final = float(sol.stats["initial_cost"]), float(sol.stats["final_cost"])
    np.testing.assert_allclose(initial, _cost(pg, pg.values), rtol=1e-12)
    assert final < initial / factor, (initial, final)


@pytest.mark.parametrize(
    "name, linear, rtol",
    [
        ("intel.g2o", "pcg", 1e-6),
        ("intel.g2o", "sparse", 1e-6),
        ("smallGrid3D.g2o", "pcg", 1e-6),
    ],
)
def test_real_data_matches_gtsam(name, linear, rtol):
    gtsam = pytest.importorskip(
        "gtsam", reason="GTSAM not installed (pip install gtsam)"
    )
    from eqsmooth.io import from_gtsam, to_gtsam

    pg, sol = _solved(name, linear)
    graph, initial = to_gtsam(pg)
    np.testing.assert_allclose(
        graph.error(initial), float(sol.stats["initial_cost"]), rtol=1e-10
    )
    np.testing.assert_allclose(
        _cost(pg, from_gtsam(pg, initial)), graph.error(initial), rtol=1e-10
    )
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(0.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
    ours, theirs = float(sol.stats["final_cost"]), graph.error(result)
    assert ours >= theirs * (1 - 1e-9)  # GTSAM's direct solves reach the optimum
    np.testing.assert_allclose(ours, theirs, rtol=rtol)
