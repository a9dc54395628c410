"""Reading and writing pose graphs in the g2o text format."""

import collections
import os
import tempfile
import warnings
from pathlib import Path
from typing import Literal

import numpy as np
from jaxtyping import Int, PyTree

from ..factors import BetweenFactor
from ..lie import AbstractLieGroup, SE2, SE3
from ._pose_graph import make_pose_graph, POSE, PoseGraph


# tag -> (kind, role, allowed numbers of fields after the tag)
_TAGS = {
    "VERTEX_SE2": ("se2", "vertex", (1 + 3,)),
    "EDGE_SE2": ("se2", "edge", (2 + 3 + 6,)),
    "EDGE2": ("se2", "edge", (2 + 3 + 6,)),
    "VERTEX_SE3:QUAT": ("se3", "vertex", (1 + 7,)),
    "EDGE_SE3:QUAT": ("se3", "edge", (2 + 7 + 21,)),
    "VERTEX3": ("se3", "vertex", (1 + 6,)),
    "EDGE3": ("se3", "edge", (2 + 6, 2 + 6 + 21)),
    "FIX": (None, "fix", None),
}
_FIELDS = {
    "VERTEX_SE2": "id x y theta",
    "EDGE_SE2": "id1 id2 dx dy dtheta and 6 information entries",
    "EDGE2": "id1 id2 dx dy dtheta and 6 information entries",
    "VERTEX_SE3:QUAT": "id x y z qx qy qz qw",
    "EDGE_SE3:QUAT": "id1 id2 x y z qx qy qz qw and 21 information entries",
    "VERTEX3": "id x y z roll pitch yaw",
    "EDGE3": "id1 id2 x y z roll pitch yaw, optionally 21 information entries",
}
# TORO's VERTEX2 has VERTEX_SE2's fields. TORO's EDGE2 lists its information
# as xx xy yy tt xt yt (as GTSAM's load2D reads it); `_TORO_INFO` reorders that
# to g2o's xx xy xt yy yt tt.
_ALIASES = {"VERTEX2": "VERTEX_SE2"}
_TORO_INFO = (0, 1, 4, 2, 5, 3)
_VERTEX = {"se2": "VERTEX_SE2", "se3": "VERTEX_SE3:QUAT"}
_EDGE = {"se2": "EDGE_SE2", "se3": "EDGE_SE3:QUAT"}
_DIM = {"se2": 3, "se3": 6}
# Scaling from g2o's SE(3) error (translation, quaternion vector part ≈ ω/2)
# to eqsmooth's tangent (translation, ω): e_g2o ≈ D r.
_HALF_ANGLE = np.array([1.0, 1.0, 1.0, 0.5, 0.5, 0.5])
# GTSAM's Pose3 tangent (ω, v) to eqsmooth's (v, ω) and back.
_SWAP = np.array([3, 4, 5, 0, 1, 2])


class _Lines:
    """The lines of one tag: line numbers and token lists."""

    def __init__(self):
        self.linenos: list[int] = []
        self.tokens: list[list[str]] = []

    def __len__(self):
        return len(self.linenos)


def _fail(path, lineno, message):
    where = f"{path}:{lineno}" if lineno is not None else str(path)
    raise ValueError(f"{where}: {message}")


def _tokenize(path: Path, skip_unsupported: bool) -> dict[str, _Lines]:
    found: dict[str, _Lines] = collections.defaultdict(_Lines)
    with open(path, "rb") as fh:
        for lineno, raw in enumerate(fh, 1):
            try:
                line = raw.decode("utf-8")
            except UnicodeDecodeError as e:
                _fail(
                    path,
                    lineno,
                    f"not UTF-8 text: byte {raw[e.start : e.start + 1]!r} at column "
                    f"{e.start + 1} (is this a binary file, or in another encoding?)",
                )
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            tag = _ALIASES.get(tokens[0], tokens[0])
            if tag not in _TAGS:
                if skip_unsupported:
                    continue
                _fail(
                    path,
                    lineno,
                    f"unsupported tag {tag!r}; eqsmooth reads "
                    f"{', '.join([*_TAGS, *_ALIASES])} (pass skip_unsupported=True "
                    "to ignore "
                    "other lines)",
                )
            lines = found[tag]
            lines.linenos.append(lineno)
            lines.tokens.append(tokens)
    return found


def _numbers(path, tag: str, lines: _Lines, start: int, stop: int | None, dtype):
    """Fields `start:stop` of every line as one array, or an error naming the line."""
    rows = [t[start:stop] for t in lines.tokens]
    try:
        out = np.array(rows, dtype=dtype)
    except (ValueError, OverflowError):
        convert = int if dtype is np.int64 else float
        for lineno, row in zip(lines.linenos, rows):
            for tok in row:
                try:
                    value = convert(tok)
                    if convert is int and not (
                        np.iinfo(np.int64).min <= value <= np.iinfo(np.int64).max
                    ):
                        raise OverflowError
                except (ValueError, OverflowError):
                    what = "an integer id" if convert is int else "a number"
                    if convert is int and tok.lstrip("+-").isdigit():
                        what = "a 64-bit integer id (out of range)"
                    _fail(path, lineno, f"{tag}: cannot read {tok!r} as {what}")
        raise
    if dtype is np.float64:
        bad = ~np.all(np.isfinite(out), axis=1)
        if bad.any():
            k = int(np.argmax(bad))
            _fail(path, lines.linenos[k], f"{tag}: non-finite number")
    return out


def _check_counts(path, tag: str, lines: _Lines) -> None:
    allowed = _TAGS[tag][2]
    counts = np.fromiter((len(t) - 1 for t in lines.tokens), np.int64, len(lines))
    bad = ~np.isin(counts, allowed)
    if bad.any():
        k = int(np.argmax(bad))
        needs = " or ".join(map(str, allowed))
        _fail(
            path,
            lines.linenos[k],
            f"{tag} needs {needs} fields ({_FIELDS[tag]}), got {counts[k]}",
        )
    if len(allowed) > 1 and (counts != counts[0]).any():
        k = int(np.argmax(counts != counts[0]))
        _fail(
            path,
            lines.linenos[k],
            f"{tag} has {counts[k]} fields here but {counts[0]} on line "
            f"{lines.linenos[0]}: either every {tag} line has information entries "
            "or none has",
        )


def _unit_quaternions(path, tag, lines: _Lines, xyzw: np.ndarray) -> np.ndarray:
    """`(qw, qx, qy, qz)`, normalised, from g2o's `(qx, qy, qz, qw)`."""
    norm = np.linalg.norm(xyzw, axis=1)
    bad = norm < 1e-6
    if bad.any():
        k = int(np.argmax(bad))
        _fail(path, lines.linenos[k], f"{tag}: quaternion of norm {norm[k]:.3g}")
    q = xyzw / norm[:, None]
    return np.concatenate([q[:, 3:], q[:, :3]], axis=1)


def _upper_to_full(upper: np.ndarray, d: int) -> np.ndarray:
    rows, cols = np.triu_indices(d)
    full = np.zeros((upper.shape[0], d, d))
    full[:, rows, cols] = upper
    full[:, cols, rows] = upper
    return full


def _rpy_quaternions(rpy: np.ndarray) -> np.ndarray:
    """`(qw, qx, qy, qz)` of `Rz(yaw) Ry(pitch) Rx(roll)` from rows `(roll, pitch,
    yaw)`: the rotation of a `VERTEX3`/`EDGE3` line, as GTSAM's `Rot3::Ypr`."""
    (cr, cp, cy), (sr, sp, sy) = np.cos(rpy.T / 2), np.sin(rpy.T / 2)
    return np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=1,
    )


def _se2_params(xyt: np.ndarray) -> np.ndarray:
    return np.stack(
        [np.cos(xyt[:, 2]), np.sin(xyt[:, 2]), xyt[:, 0], xyt[:, 1]], axis=1
    )


# ---------------------------------------------------------------- numpy pose algebra
# Only used to build initial values when a file has no vertices.


def _quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    pw, pv = p[0], p[1:]
    qw, qv = q[0], q[1:]
    return np.concatenate([[pw * qw - pv @ qv], pw * qv + qw * pv + np.cross(pv, qv)])


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w, u = q[0], q[1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def _compose(kind: str, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    if kind == "se2":
        c1, s1, c2, s2 = a[0], a[1], b[0], b[1]
        xy = a[2:] + np.array([c1 * b[2] - s1 * b[3], s1 * b[2] + c1 * b[3]])
        return np.array([c1 * c2 - s1 * s2, s1 * c2 + c1 * s2, xy[0], xy[1]])
    q = _quat_mul(a[:4], b[:4])
    return np.concatenate([q / np.linalg.norm(q), a[4:] + _quat_rotate(a[:4], b[4:])])


def _inverse(kind: str, a: np.ndarray) -> np.ndarray:
    if kind == "se2":
        c, s, x, y = a
        return np.array([c, -s, -(c * x + s * y), s * x - c * y])
    q = np.concatenate([a[:1], -a[1:4]])
    return np.concatenate([q, -_quat_rotate(q, a[4:])])


def _initial_from_edges(
    path, kind: str, n: int, edges: np.ndarray, meas: np.ndarray, vertex_ids
) -> np.ndarray:
    """Initial poses by composing measurements: along the odometry chain if every
    consecutive pair of poses has an edge, else along a breadth-first spanning tree.
    Pose 0 is the identity."""
    identity = np.array([1.0, 0, 0, 0]) if kind == "se2" else np.eye(1, 7)[0]
    poses = np.empty((n, meas.shape[1]))
    poses[0] = identity
    forward = {}
    for e, (i, j) in enumerate(edges):
        forward.setdefault((int(i), int(j)), e)
    if all((k, k + 1) in forward for k in range(n - 1)):
        for k in range(n - 1):
            poses[k + 1] = _compose(kind, poses[k], meas[forward[(k, k + 1)]])
        return poses
    neighbours: list[list[tuple[int, int, bool]]] = [[] for _ in range(n)]
    for e, (i, j) in enumerate(edges):
        neighbours[i].append((e, j, False))
        neighbours[j].append((e, i, True))
    seen = np.zeros(n, bool)
    seen[0] = True
    queue = collections.deque([0])
    while queue:
        i = queue.popleft()
        for e, j, backwards in neighbours[i]:
            if seen[j]:
                continue
            z = _inverse(kind, meas[e]) if backwards else meas[e]
            poses[j] = _compose(kind, poses[i], z)
            seen[j] = True
            queue.append(j)
    if not seen.all():
        k = int(np.argmin(seen))
        _fail(
            path,
            None,
            f"the file has no vertices and vertex {int(vertex_ids[k])} is not "
            f"connected to vertex {int(vertex_ids[0])} by edges, so its initial "
            "value cannot be built",
        )
    return poses


# ---------------------------------------------------------------------- load


def _not_positive_definite(info: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    eig = np.linalg.eigvalsh(info)
    return ~(eig[:, 0] > 1e-12 * np.abs(eig[:, -1])), eig[:, 0]


def _checked_information(path, tag, lines, info, invalid: str) -> np.ndarray:
    bad, smallest = _not_positive_definite(info)
    if not bad.any():
        return info
    if invalid == "raise":
        k = int(np.argmax(bad))
        _fail(
            path,
            lines.linenos[k],
            f"{tag}: information matrix is not positive definite (smallest "
            f"eigenvalue {smallest[k]:.3g}); {int(bad.sum())} of {len(bad)} edges "
            "have this problem (see load_g2o's invalid_information option)",
        )
    info = info.copy()
    fixed = info[bad]
    d = info.shape[-1]
    if invalid == "block_diagonal":
        h = d // 2 if d == 6 else 2  # SE(3): 3 + 3; SE(2): (x, y) + θ
        fixed[:, :h, h:] = 0.0
        fixed[:, h:, :h] = 0.0
        still, _ = _not_positive_definite(fixed)
    else:
        still = np.ones(len(fixed), bool)
    if still.any():
        eig, vec = np.linalg.eigh(fixed[still])
        floor = 1e-6 * np.max(np.abs(eig), axis=1, keepdims=True)
        eig = np.maximum(eig, floor)
        fixed[still] = np.einsum("nij,nj,nkj->nik", vec, eig, vec)
    info[bad] = fixed
    warnings.warn(
        f"{path}: {int(bad.sum())} of {len(bad)} {tag} information matrices were not "
        f"positive definite and were repaired (invalid_information={invalid!r})",
        stacklevel=3,
    )
    return info


def _check_load_options(se3_information, invalid_information, dtype) -> None:
    if invalid_information not in ("raise", "clip", "block_diagonal"):
        raise ValueError(
            "invalid_information must be 'raise', 'clip' or 'block_diagonal', got "
            f"{invalid_information!r}"
        )
    if se3_information not in ("g2o", "gtsam"):
        raise ValueError(
            f"se3_information must be 'g2o' or 'gtsam', got {se3_information!r}"
        )
    if dtype is not None and np.dtype(dtype) not in (np.float32, np.float64):
        raise TypeError(
            f"load_g2o: dtype must be float32 or float64, got {np.dtype(dtype)}"
        )


def _kind(path, found, se3_information) -> tuple[str, list[str], list[str], str]:
    """`"se2"` or `"se3"`, its vertex and edge tags in the file, and how its SE(3)
    information was read; the line counts checked."""
    tags = [t for t in found if _TAGS[t][0] is not None]
    kinds = {_TAGS[t][0]: t for t in tags}
    if len(kinds) > 1:
        a, b = sorted(kinds.values(), key=lambda t: found[t].linenos[0])
        _fail(
            path,
            found[b].linenos[0],
            f"mixes 2-D and 3-D poses ({a} on line {found[a].linenos[0]}, {b} here)",
        )
    if not kinds:
        _fail(path, None, f"no pose vertices or edges ({', '.join(_FIELDS)})")
    kind = next(iter(kinds))
    for tag in tags:
        _check_counts(path, tag, found[tag])
    vtags = [t for t in tags if _TAGS[t][1] == "vertex"]
    etags = [t for t in tags if _TAGS[t][1] == "edge"]
    if not etags:
        _fail(path, None, f"has {vtags[0]} lines but no {_EDGE[kind]} lines")
    if "EDGE3" in found:
        if "EDGE_SE3:QUAT" in found and se3_information == "g2o":
            _fail(
                path,
                found["EDGE3"].linenos[0],
                "EDGE3 information is read as GTSAM reads it, which conflicts with "
                "se3_information='g2o' for this file's EDGE_SE3:QUAT lines (pass "
                "se3_information='gtsam')",
            )
        se3_information = "gtsam"
    return kind, vtags, etags, se3_information


def _merged(found, tags) -> _Lines:
    """The lines of several tags, tag after tag."""
    out = _Lines()
    for tag in tags:
        out.linenos += found[tag].linenos
        out.tokens += found[tag].tokens
    return out


def _edge_information(path, tag, lines, nums, se3_information) -> np.ndarray:
    """Information matrices in eqsmooth's tangent order from a tag's numbers."""
    if tag in ("EDGE_SE2", "EDGE2"):
        info = _upper_to_full(nums[:, 3:], 3)
        if tag == "EDGE2":
            # TORO's order, unless only g2o's gives a positive definite matrix
            # (e.g. GTSAM's w100_30.g2o and w20000.txt write EDGE2 lines in g2o's
            # order): GTSAM's load2D tells the two apart by their zero patterns.
            toro = _upper_to_full(nums[:, 3:][:, _TORO_INFO], 3)
            g2o = _not_positive_definite(toro)[0] & ~_not_positive_definite(info)[0]
            info = np.where(g2o[:, None, None], info, toro)
    elif tag == "EDGE3":
        if nums.shape[1] == 6:  # no information entries: unit information
            return np.broadcast_to(np.eye(6), (len(nums), 6, 6)).copy()
        info = _upper_to_full(nums[:, 6:], 6)[:, _SWAP][:, :, _SWAP]
    else:
        info = _upper_to_full(nums[:, 7:], 6)
        if se3_information == "g2o":
            info = info * _HALF_ANGLE[:, None] * _HALF_ANGLE[None, :]
    return info


def _pose_params(path, tag, lines, nums) -> np.ndarray:
    """Group parameters from a vertex's or edge's pose fields."""
    if tag in ("VERTEX_SE2", "EDGE_SE2", "EDGE2"):
        return _se2_params(nums[:, :3])
    if tag in ("VERTEX3", "EDGE3"):
        return np.concatenate([_rpy_quaternions(nums[:, 3:6]), nums[:, :3]], axis=1)
    q = _unit_quaternions(path, tag, lines, nums[:, 3:7])
    return np.concatenate([q, nums[:, :3]], axis=1)


def _edges(path, etags, found, se3_information, invalid_information):
    """The edges' vertex ids `(n, 2)`, measurements, information matrices and
    lines, in file order."""
    parts = []
    for tag in etags:
        lines = found[tag]
        eids = _numbers(path, tag, lines, 1, 3, np.int64)
        loops = eids[:, 0] == eids[:, 1]
        if loops.any():
            k = int(np.argmax(loops))
            _fail(
                path, lines.linenos[k], f"{tag} connects vertex {eids[k, 0]} to itself"
            )
        nums = _numbers(path, tag, lines, 3, None, np.float64)
        info = _edge_information(path, tag, lines, nums, se3_information)
        info = _checked_information(path, tag, lines, info, invalid_information)
        parts.append((eids, _pose_params(path, tag, lines, nums), info))
    lines = _merged(found, etags)
    order = np.argsort(lines.linenos, kind="stable")  # file order
    lines.linenos = [lines.linenos[k] for k in order]
    lines.tokens = [lines.tokens[k] for k in order]
    eids, meas, info = (np.concatenate(x)[order] for x in zip(*parts))
    return eids, meas, info, lines


def _vertices(path, vtags, found, etag, elines, eids):
    """The sorted vertex ids, their poses, and the edges as pose indices."""
    vlines = _merged(found, vtags)
    vids = np.concatenate([_numbers(path, t, found[t], 1, 2, np.int64) for t in vtags])
    vids = vids[:, 0]
    params = np.concatenate(
        [
            _pose_params(
                path, t, found[t], _numbers(path, t, found[t], 2, None, np.float64)
            )
            for t in vtags
        ]
    )
    vtag = "/".join(vtags)
    order = np.argsort(vids, kind="stable")
    vertex_ids = vids[order]
    dup = vertex_ids[1:] == vertex_ids[:-1]
    if dup.any():
        k = int(order[int(np.argmax(dup)) + 1])
        _fail(path, vlines.linenos[k], f"{vtag}: vertex {vids[k]} defined twice")
    idx = np.searchsorted(vertex_ids, eids).clip(0, len(vertex_ids) - 1)
    missing = vertex_ids[idx] != eids
    if missing.any():
        k = int(np.argmax(missing.any(axis=1)))
        vid = eids[k][missing[k]][0]
        _fail(
            path,
            elines.linenos[k],
            f"{etag} refers to vertex {vid}, which has no {vtag} line",
        )
    return vertex_ids, params[order], idx


def _fixed(path, flines, vertex_ids) -> np.ndarray:
    """The pose indices that `FIX` lines name."""
    fixed = []
    for lineno, tokens in zip(flines.linenos, flines.tokens):
        if len(tokens) < 2:
            _fail(path, lineno, "FIX needs at least one vertex id")
        one = _Lines()
        one.linenos, one.tokens = [lineno], [tokens]
        for vid in _numbers(path, "FIX", one, 1, None, np.int64)[0]:
            k = int(np.searchsorted(vertex_ids, vid))
            if k >= len(vertex_ids) or vertex_ids[k] != vid:
                _fail(path, lineno, f"FIX refers to unknown vertex {vid}")
            fixed.append(k)
    return np.unique(np.asarray(fixed, np.int64))


def load_g2o(
    path: str | os.PathLike,
    *,
    anchor: bool = True,
    anchor_sqrt_information: float = 1e6,
    se3_information: Literal["g2o", "gtsam"] = "g2o",
    invalid_information: Literal["raise", "clip", "block_diagonal"] = "raise",
    skip_unsupported: bool = False,
    dtype=None,
) -> PoseGraph:
    """Read a 2-D or 3-D pose graph from a g2o text file.

    Supported lines: `VERTEX_SE2 id x y theta`,
    `EDGE_SE2 id1 id2 dx dy dtheta I11 I12 I13 I22 I23 I33`,
    `VERTEX_SE3:QUAT id x y z qx qy qz qw`,
    `EDGE_SE3:QUAT id1 id2 x y z qx qy qz qw` followed by the 21 upper-triangular
    information entries (row by row), `FIX id ...`, blank lines and `#`
    comments. Quaternions are scalar-last in the file and are normalised.

    **TORO's tags** (GTSAM's `.graph` files), read as GTSAM's `load2D` and
    `load3D` read them:

    - `VERTEX2` has `VERTEX_SE2`'s fields. `EDGE2` has `EDGE_SE2`'s, its
        information listed as `I11 I12 I22 I33 I13 I23`, unless only g2o's
        order gives a positive definite matrix (GTSAM's `w100_30.g2o` and
        `w20000.txt` write diagonal matrices in g2o's order; GTSAM tells the
        two apart by their zero patterns).
    - `VERTEX3 id x y z roll pitch yaw` and
        `EDGE3 id1 id2 x y z roll pitch yaw` followed by 21 upper-triangular
        information entries, rotation `Rz(yaw) Ry(pitch) Rx(roll)`. The
        information is that of GTSAM's tangent (rotation first), as GTSAM
        reads it (so the result's `se3_information` is `"gtsam"`). `EDGE3`
        lines without information entries (GTSAM's
        `sphere_smallnoise.graph`) get unit information; GTSAM's `load3D`
        stops reading such a file after its first edge.
    - `EQUIV` lines are not read: pass `skip_unsupported=True`.

    Every edge becomes one row of a [`eqsmooth.factors.BetweenFactor`][] with
    residual `log(z⁻¹ xᵢ⁻¹ xⱼ)` in eqsmooth's tangent coordinates
    (translation first) and full square-root information.

    **Information matrices.** g2o's SE(2) error is `(x, y, θ)` of
    `z⁻¹ xᵢ⁻¹ xⱼ`, which agrees with the SE(2) logarithm to first order, so the
    matrix is used as it is. g2o's SE(3) error is `(x, y, z, qx, qy, qz)`, whose
    rotation part, the quaternion's vector part, is about half the rotation
    angle `ω/2`. With `se3_information="g2o"` (the default) the file's matrix
    `Λ` is converted to `D Λ D` with `D = diag(1, 1, 1, ½, ½, ½)`, so the cost
    agrees with g2o's to first order. With `"gtsam"` the matrix is used as the
    information of `(v, ω)` directly, as GTSAM's `readG2o` and Ceres's pose
    graph example do (its rotation weights are 4 times larger).

    **Vertex ids** need not be contiguous: pose `i` is the `i`-th smallest id
    (`PoseGraph.vertex_ids` keeps the map). If the file has no vertex lines at
    all (e.g. the SE-Sync versions of CSAIL, manhattan, kitti_00; GTSAM's
    `w20000.txt` and `sphere2500.txt`), the initial
    values compose the measurements along the odometry chain `(i, i+1)` if it
    is complete, else along a breadth-first spanning tree, starting from the
    identity at the first pose.

    **Gauge.** A pose graph's cost is invariant to moving every pose together,
    so with `anchor=True` a [`eqsmooth.factors.PriorFactor`][] with isotropic
    square-root information `anchor_sqrt_information` (σ = 10⁻⁶ by default)
    holds the `FIX`ed poses, or the first pose if there is no `FIX` line, at
    their initial values. It adds nothing to the initial cost.

    **Arguments:**

    - `path`: the file.
    - `anchor`: add the gauge prior (see above).
    - `anchor_sqrt_information`: its strength.
    - `se3_information`: `"g2o"` or `"gtsam"` (see above; `EDGE_SE3:QUAT`
        only).
    - `invalid_information`: what to do with information matrices that are
        not positive definite (some real data sets, e.g. cubicle, have
        thousands): `"raise"` (default); `"clip"` raises their eigenvalues to
        at least 10⁻⁶ times the largest; `"block_diagonal"` drops their
        translation–rotation cross terms (then clips if still needed).
        Repairs emit a `UserWarning` with their count.
    - `skip_unsupported`: ignore lines with other tags instead of raising.
    - `dtype`: float dtype of the arrays (default: JAX's default float;
        enable `jax_enable_x64` for real data sets).

    **Returns:** a [`eqsmooth.io.PoseGraph`][].

    **Raises:** `FileNotFoundError`, or `ValueError` naming the file and line
    for an unsupported tag, a wrong number of fields, an unreadable number, a
    repeated vertex, an edge to a vertex without a vertex line, a self-loop or
    an information matrix that is not positive definite (with
    `invalid_information="raise"`).
    """
    _check_load_options(se3_information, invalid_information, dtype)
    path = Path(path)
    found = _tokenize(path, skip_unsupported)
    kind, vtags, etags, se3_information = _kind(path, found, se3_information)
    eids, meas, info, elines = _edges(
        path, etags, found, se3_information, invalid_information
    )
    if vtags:
        etag = "/".join(etags)
        vertex_ids, poses, edges = _vertices(path, vtags, found, etag, elines, eids)
    else:
        vertex_ids, edges = np.unique(eids, return_inverse=True)
        edges = edges.reshape(eids.shape)
        poses = _initial_from_edges(
            path, kind, len(vertex_ids), edges, meas, vertex_ids
        )
    anchored = np.zeros((0,), np.int64)
    if "FIX" in found:
        anchored = _fixed(path, found["FIX"], vertex_ids)
    return make_pose_graph(
        kind,
        poses,
        np.asarray(edges, np.int64),
        meas,
        info,
        vertex_ids=vertex_ids,
        anchor=anchor,
        anchored=anchored,
        anchor_sqrt_information=anchor_sqrt_information,
        se3_information=se3_information,
        dtype=dtype,
    )


# ---------------------------------------------------------------------- save


def _fmt(rows: np.ndarray) -> list[str]:
    # repr() is the shortest text that reads back to the same float.
    return [" ".join(map(repr, r)) for r in rows.tolist()]


def _vertex_rows(kind: str, params: np.ndarray) -> np.ndarray:
    if kind == "se2":
        theta = np.arctan2(params[:, 1], params[:, 0])
        return np.stack([params[:, 2], params[:, 3], theta], axis=1)
    q = params[:, :4]
    return np.concatenate([params[:, 4:], q[:, 1:], q[:, :1]], axis=1)


def _group_of(data) -> tuple[str, np.ndarray]:
    if isinstance(data, SE2):
        return "se2", np.asarray(data.unit_complex_xy, np.float64).reshape(-1, 4)
    if isinstance(data, SE3):
        return "se3", np.asarray(data.wxyz_xyz, np.float64).reshape(-1, 7)
    raise TypeError(
        "save_g2o writes SE2 or SE3 poses; got "
        f"{type(data).__name__} (pass a PoseGraph, a values dict with a 'pose' "
        "group, or a stacked SE2/SE3)"
    )


def save_g2o(
    path: str | os.PathLike,
    data: PoseGraph | dict | AbstractLieGroup,
    *,
    values: PyTree | None = None,
    vertex_ids: Int[np.ndarray, " N"] | None = None,
) -> None:
    """Write poses (and edges) to a g2o text file, atomically.

    The file is written to a temporary file in the same folder and then moved
    over `path` with `os.replace`, so readers never see a partial file.

    **Arguments:**

    - `path`: the output file.
    - `data`: a [`eqsmooth.io.PoseGraph`][] (vertices, `FIX` lines for its
        anchored poses, and its edges with their information converted back to
        the g2o convention it was read with), or just poses: a values dict
        whose `"pose"` group (or only group) is a stacked
        [`eqsmooth.lie.SE2`][]/[`eqsmooth.lie.SE3`][], or such a stack itself
        (vertices only).
    - `values`: poses to write instead of `data`'s own initial values (e.g.
        `solution.value` after a solve): a values dict or a stacked group.
    - `vertex_ids`: ids to write (default: the pose graph's ids, else `0..N-1`).
    """
    graph = None
    if isinstance(data, PoseGraph):
        graph = data
        if values is None:
            values = data.values
        if vertex_ids is None:
            vertex_ids = data.vertex_ids
    elif values is None:
        values = data
    if isinstance(values, dict):
        if POSE in values:
            values = values[POSE]
        elif len(values) == 1:
            values = next(iter(values.values()))
        else:
            raise ValueError(
                f"save_g2o: values has groups {sorted(values)}; expected a 'pose' "
                "group or a single group"
            )
    kind, params = _group_of(values)
    n = params.shape[0]
    if vertex_ids is None:
        vertex_ids = np.arange(n)
    vertex_ids = np.asarray(vertex_ids, np.int64)
    if vertex_ids.shape != (n,):
        raise ValueError(
            f"save_g2o: {n} poses but vertex_ids has shape {vertex_ids.shape}"
        )
    if graph is not None and (graph.kind != kind or graph.num_poses != n):
        raise ValueError(
            f"save_g2o: the pose graph has {graph.num_poses} {graph.kind} poses but "
            f"the values have {n} {kind} poses"
        )

    out = [
        f"{_VERTEX[kind]} {i} {row}"
        for i, row in zip(vertex_ids.tolist(), _fmt(_vertex_rows(kind, params)))
    ]
    if graph is not None:
        if len(graph.anchored):
            out.append("FIX " + " ".join(map(str, vertex_ids[graph.anchored].tolist())))
        out.extend(_edge_lines(graph, kind, vertex_ids))

    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write("\n".join(out))
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _edge_lines(graph: PoseGraph, kind: str, vertex_ids: np.ndarray) -> list[str]:
    factor: BetweenFactor = graph.between
    noise = factor.noise
    if not noise.is_gaussian or noise.active_rows() is not None:
        raise TypeError(
            "save_g2o: edges need a Gaussian noise model without masked rows (a "
            f"g2o edge holds one information matrix), got {noise.name}"
        )
    _, meas = _group_of(factor.measurement)
    E, d = factor.num_rows, _DIM[kind]
    R = np.asarray(noise.sqrt_information_rows(E, d), np.float64)
    info = np.swapaxes(R, 1, 2) @ R
    if kind == "se3" and graph.se3_information == "g2o":
        info = info / (_HALF_ANGLE[:, None] * _HALF_ANGLE[None, :])
    rows, cols = np.triu_indices(d)
    nums = np.concatenate([_vertex_rows(kind, meas), info[:, rows, cols]], axis=1)
    a, b = factor.variables
    ids = np.stack([vertex_ids[a.ids], vertex_ids[b.ids]], axis=1).tolist()
    tag = _EDGE[kind]
    return [f"{tag} {i} {j} {row}" for (i, j), row in zip(ids, _fmt(nums))]
