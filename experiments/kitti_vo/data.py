"""KITTI-10 visual odometry data: the real-data loader, a renderer, folds, metrics.

Two sources of 50 x 150 RGB views feed the same experiment:

- **Real data** (`load_kitti10_sequence`): the preprocessed KITTI-10 layout
  read by the code of Yi et al. (tu-rbo's release): `{root}/{seq}/image_2/
  *_<frame>.png` and `image_3/` (50 x 150 x 3 uint8), `{root}/{seq}_image1.txt`
  and `{root}/{seq}_image2.txt` (one 3 x 4 camera pose per line, 12 floats).
  Those images are not available on this machine.
- **Rendered views on real KITTI trajectories** (`Renderer`): the real
  ground-truth poses of sequences 00-10 (`../shared/data/kitti_poses`) drive
  a camera over a procedurally textured world (textured ground, a road with
  markings along the driven path, vertical structures beside it) with
  per-frame nuisances (brightness changes, motion blur, passing occluders,
  stretches with little texture, pixel noise). Rendering is deterministic
  from `(seed, sequence)` and done on demand, about 0.3 ms per frame. A
  pre-declared data variant (`VARIANTS`, `reliability_variant`) adds
  per-frame faults of real driving video.

Both give `Trajectory` objects (2-D ground-truth poses plus an image
source), which the folds, splits and metrics below use alike. The 2-D
conversion follows the paper's: x = camera z (forward), y = -camera x, and
the heading from the rotation's forward axis.
"""

import dataclasses
import re
from pathlib import Path

import numpy as np

from .._data import data_root, require


SEQUENCES = (0, 2, 3, 4, 5, 6, 7, 8, 9, 10)  # fold f tests on SEQUENCES[f]
# Frames per sequence (KITTI odometry ground truth, 00..10).
FRAME_COUNTS = dict(
    enumerate((4541, 1101, 4661, 801, 271, 2761, 1101, 1101, 4071, 1591, 1201))
)
NUM_FOLDS = len(SEQUENCES)
IMAGE_SHAPE = (50, 150, 3)
DT = 0.1036  # mean frame spacing of KITTI odometry (s)
# Lateral offsets (m, left positive) of the colour cameras image_2 / image_3
# from camera 0, whose poses KITTI publishes (KITTI calibration: P2, P3).
CAMERA_OFFSETS = {"image_2": 0.06, "image_3": -0.48}
CAMERAS = tuple(CAMERA_OFFSETS)
PRETRAIN_HOLDOUT = 205  # sensor pretraining: all frames but the last 205
SMOOTHER_FRAMES = 200  # smoother / EKF training: the last 200 frames
EVAL_WINDOW = 100  # evaluation subsequences (states)

# $EQSMOOTH_DATA/kitti_poses, or ../shared/data/kitti_poses beside the checkout.
DEFAULT_POSES_DIR = data_root() / "kitti_poses"


# ---------------------------------------------------------------------------
# Poses
# ---------------------------------------------------------------------------


def read_poses(path: str | Path) -> np.ndarray:
    """KITTI pose file -> `(N, 3, 4)` float64 `[R | t]` matrices."""
    try:
        text = Path(path).read_bytes().decode("ascii")
    except UnicodeDecodeError as err:
        raise ValueError(
            f"{path}: not a KITTI pose file (a byte that is not text at offset "
            f"{err.start}); a pose file holds 12 floats per line"
        ) from None
    if not text.strip():
        raise ValueError(f"{path}: no poses (an empty file)")
    try:
        data = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise ValueError(f"{path}: not a KITTI pose file ({e})") from e
    if data.size == 0:
        raise ValueError(f"{path}: no poses (an empty file)")
    if data.shape[1] != 12:
        raise ValueError(f"{path}: expected 12 floats per line, got {data.shape[1]}")
    bad = np.flatnonzero(~np.all(np.isfinite(data), axis=1))
    if bad.size:
        raise ValueError(
            f"{path}: lines {(bad[:8] + 1).tolist()} hold non-finite numbers (nan or "
            "inf); a pose file holds 12 finite floats per line"
        )
    poses = data.reshape(-1, 3, 4)
    # The files print 6-7 significant digits: rotations are orthonormal to
    # about 1e-6; anything far off is not a rotation (a column order mix-up).
    R = poses[:, :, :3]
    error = np.abs(np.einsum("nij,nkj->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > 1e-3) | (np.linalg.det(R) < 0))
    if bad.size:
        raise ValueError(
            f"{path}: lines {(bad[:8] + 1).tolist()} do not hold a rotation in "
            "their first three columns of each row (R Rᵀ ≠ I or det < 0; a KITTI "
            "line is the row-major 3x4 matrix [R | t])"
        )
    return poses


def poses_to_2d(poses: np.ndarray) -> np.ndarray:
    """`(N, 3, 4)` camera poses -> `(N, 3)` planar `(x, y, θ)`.

    x is the camera's z (forward), y is minus its x (so y points left), and θ
    the heading of the camera's optical axis in that plane.
    """
    R, t = poses[:, :, :3], poses[:, :, 3]
    forward = R[:, :, 2]  # the optical axis in the first camera's frame
    theta = np.arctan2(-forward[:, 0], forward[:, 2])
    return np.stack([t[:, 2], -t[:, 0], theta], axis=1)


def offset_camera(xyt: np.ndarray, lateral: float) -> np.ndarray:
    """Planar poses of a camera mounted `lateral` metres to the left."""
    x, y, th = xyt.T
    return np.stack([x - lateral * np.sin(th), y + lateral * np.cos(th), th], axis=1)


def velocities(xyt: np.ndarray, dt: float = DT) -> np.ndarray:
    """`(N, 2)` forward speed and yaw rate of the motion `t -> t+1`.

    The last row repeats the one before, as in
    `eqsmooth.factors.VehicleState.from_poses`.
    """
    d = xyt[1:] - xyt[:-1]
    c, s = np.cos(xyt[:-1, 2]), np.sin(xyt[:-1, 2])
    fwd = c * d[:, 0] + s * d[:, 1]
    dth = np.angle(np.exp(1j * d[:, 2]))
    v = np.stack([fwd, dth], axis=1) / dt
    return np.concatenate([v, v[-1:]], axis=0)


def mirror_poses(xyt: np.ndarray) -> np.ndarray:
    """The mirrored trajectory (reflection about the x axis)."""
    return xyt * np.array([1.0, -1.0, -1.0])


# ---------------------------------------------------------------------------
# Trajectories: ground truth + image source
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """One camera trajectory of one sequence, possibly mirrored.

    **Fields:** `seq`, `camera` (`"image_2"`/`"image_3"`), `mirrored`,
    `poses` (`(N, 3)` planar ground truth), `source` (an object with
    `images(camera, frames) -> (n, 50, 150, 3) uint8`). Mirrored copies flip
    the images left-right and the trajectory about its x axis.
    """

    seq: int
    camera: str
    mirrored: bool
    poses: np.ndarray
    source: object

    @property
    def num_frames(self) -> int:
        return self.poses.shape[0]

    @property
    def name(self) -> str:
        return f"{self.seq:02d}/{self.camera}" + ("/mirrored" if self.mirrored else "")

    def images(self, frames) -> np.ndarray:
        imgs = self.source.images(self.camera, np.asarray(frames))
        return imgs[:, :, ::-1] if self.mirrored else imgs


def with_mirrors(trajs: list[Trajectory]) -> list[Trajectory]:
    """Every trajectory followed by its mirrored copy."""
    out = []
    for t in trajs:
        out.append(t)
        out.append(dataclasses.replace(t, mirrored=True, poses=mirror_poses(t.poses)))
    return out


# ---------------------------------------------------------------------------
# Real data: the preprocessed KITTI-10 layout
# ---------------------------------------------------------------------------

_FRAME = re.compile(r"_(\d+)\.png$")


def _read_png(path: Path) -> np.ndarray:
    try:
        from PIL import Image
    except ImportError:  # matplotlib reads PNG without Pillow
        import matplotlib.image as mpimg

        return (np.asarray(mpimg.imread(path))[..., :3] * 255 + 0.5).astype(np.uint8)
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)


@dataclasses.dataclass(frozen=True)
class ImageArrays:
    """Images held in memory, `{camera: (N, 50, 150, 3) uint8}`."""

    arrays: dict

    def images(self, camera: str, frames: np.ndarray) -> np.ndarray:
        return self.arrays[camera][frames]


def load_kitti10_sequence(root: str | Path, seq: int) -> list[Trajectory]:
    """Read one sequence of the preprocessed KITTI-10 release.

    **Arguments:**

    - `root`: the folder holding `{seq}/image_2/`, `{seq}/image_3/`,
        `{seq}_image1.txt` and `{seq}_image2.txt` (`seq` written with two
        digits, `00`..`10`).
    - `seq`: the sequence number.

    **Returns:** two [`Trajectory`][]s (image_2 with the poses of
    `_image1.txt`, image_3 with those of `_image2.txt`).
    """
    root = Path(root)
    name = f"{seq:02d}"
    arrays, trajs = {}, []
    for camera, pose_file in (("image_2", "image1"), ("image_3", "image2")):
        folder = root / name / camera
        files = sorted(
            (int(m.group(1)), p)
            for p in folder.glob("*.png")
            if (m := _FRAME.search(p.name)) is not None
        )
        if not files:
            raise FileNotFoundError(f"no *_<frame>.png images in {folder}")
        frames = [f for f, _ in files]
        if frames != list(range(frames[0], frames[0] + len(frames))):
            raise ValueError(f"{folder}: frame numbers are not consecutive")
        images = np.stack([_read_png(p) for _, p in files])
        if images.shape[1:] != IMAGE_SHAPE:
            raise ValueError(
                f"{folder}: images have shape {images.shape[1:]}, expected "
                f"{IMAGE_SHAPE}"
            )
        poses = poses_to_2d(read_poses(root / f"{name}_{pose_file}.txt"))
        if poses.shape[0] != images.shape[0]:
            raise ValueError(
                f"{name}_{pose_file}.txt has {poses.shape[0]} poses but {folder} "
                f"has {images.shape[0]} images"
            )
        arrays[camera] = images
        trajs.append(Trajectory(seq, camera, False, poses, None))
    source = ImageArrays(arrays)
    return [dataclasses.replace(t, source=source) for t in trajs]


# ---------------------------------------------------------------------------
# Renderer: real KITTI trajectories, procedural world
# ---------------------------------------------------------------------------

H, W = IMAGE_SHAPE[:2]
CAMERA_HEIGHT = 1.65  # m (KITTI)
FOCAL = 88.0  # px: about 81 degrees of horizontal field of view over 150 px
HORIZON_ROW = 23.5
MAX_RANGE = 70.0  # m; beyond this the ground fades into haze
MAP_RESOLUTION = 0.25  # m per ground-map cell
ROAD_HALF_WIDTH = 4.0
SKY = np.array([150.0, 180.0, 215.0])
HAZE = np.array([170.0, 175.0, 180.0])


def _smooth_noise(rng, shape, cell: int) -> np.ndarray:
    """Value noise: a coarse random grid, bilinearly upsampled to `shape`."""
    gh, gw = shape[0] // cell + 2, shape[1] // cell + 2
    grid = rng.random((gh, gw))
    yy = np.arange(shape[0]) / cell
    xx = np.arange(shape[1]) / cell
    y0, x0 = yy.astype(int), xx.astype(int)
    fy, fx = (yy - y0)[:, None], (xx - x0)[None, :]
    a = grid[y0][:, x0]
    b = grid[y0][:, x0 + 1]
    c = grid[y0 + 1][:, x0]
    d = grid[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


@dataclasses.dataclass
class World:
    """The procedural world of one sequence (built once, a few MB)."""

    origin: np.ndarray  # world (x, y) of map cell (0, 0)
    ground: np.ndarray  # (h, w, 3) uint8 colour map
    objects: np.ndarray  # (K, 8): x, y, radius, height, r, g, b, pattern
    low_texture: np.ndarray  # (N,) bool: frame in a texture-poor stretch
    gain: np.ndarray  # (N,) brightness factor
    blur: np.ndarray  # (N,) horizontal motion-blur width (px)
    noise: np.ndarray  # (N,) pixel-noise std (0-255 scale)
    occluder: np.ndarray  # (N, 4): centre column, half width, top row, shade
    # Variants only (see `reliability_variant`): the frame whose capture each
    # frame slot shows, and whether occluders carry a texture moving with them.
    source: np.ndarray | None = None
    striped: bool = False


def _stamp(mask, ci, cj, rad):
    # Set mask to True within `rad` cells of each (ci, cj).
    r = int(np.ceil(rad))
    off = np.arange(-r, r + 1)
    di, dj = np.meshgrid(off, off, indexing="ij")
    keep = di**2 + dj**2 <= rad**2
    di, dj = di[keep], dj[keep]
    ii = (ci[:, None] + di[None]).ravel()
    jj = (cj[:, None] + dj[None]).ravel()
    ok = (ii >= 0) & (ii < mask.shape[0]) & (jj >= 0) & (jj < mask.shape[1])
    mask[ii[ok], jj[ok]] = True


def _cells(lo, x, y):
    """Map cells of world coordinates."""
    return (
        ((x - lo[0]) / MAP_RESOLUTION).astype(int),
        ((y - lo[1]) / MAP_RESOLUTION).astype(int),
    )


def _path(rng, xyt: np.ndarray) -> dict:
    """Arc length, texture-poor stretches (about 15% of the path) and dense
    path samples (every 0.5 m) for road and markings."""
    step = np.linalg.norm(np.diff(xyt[:, :2], axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(step)])
    low = np.zeros(xyt.shape[0], bool)
    s = rng.uniform(20, 200)
    while s < arc[-1]:
        length = rng.uniform(30, 90)
        low |= (arc >= s) & (arc < s + length)
        s += length + rng.uniform(150, 500)
    dense = np.arange(0, arc[-1], 0.5)
    ang = np.interp(dense, arc, np.unwrap(xyt[:, 2]))
    return dict(
        arc=arc,
        low=low,
        dense=dense,
        px=np.interp(dense, arc, xyt[:, 0]),
        py=np.interp(dense, arc, xyt[:, 1]),
        dlow=np.interp(dense, arc, low.astype(float)) > 0.5,
        normal=np.stack([-np.sin(ang), np.cos(ang)], 1),
    )


def _ground(rng, shape, lo, path: dict) -> tuple[np.ndarray, np.ndarray]:
    """The ground texture (grass, road, markings, crossings, flat stretches)
    and the road mask."""
    arc, dense, dlow = path["arc"], path["dense"], path["dlow"]
    px, py, normal = path["px"], path["py"], path["normal"]
    # Ground: grass-like multi-scale noise, with darker and lighter patches.
    n1 = _smooth_noise(rng, shape, 40)
    n2 = _smooth_noise(rng, shape, 6)
    n3 = rng.random(shape)
    tex = 0.45 * n1 + 0.35 * n2 + 0.2 * n3
    base = np.array([95.0, 120.0, 60.0])
    ground = base[None, None] * (0.6 + 0.8 * tex[..., None])
    # Road: asphalt with fine grain; markings dashed on the centre, solid edges.
    road = np.zeros(shape, bool)
    ci, cj = _cells(lo, px + 1.8 * normal[:, 0], py + 1.8 * normal[:, 1])
    _stamp(road, ci, cj, ROAD_HALF_WIDTH / MAP_RESOLUTION)
    # Fine grain plus stains and patches about a metre across (repairs, wet
    # spots): texture that a camera near the road can see move.
    patches = _smooth_noise(rng, shape, 4)
    grain = 0.7 + 0.25 * n3 + 0.35 * patches
    ground[road] = np.array([85.0, 85.0, 90.0]) * grain[road][:, None]
    marks = np.zeros(shape, bool)
    dashed = (dense % 9.0) < 4.5
    for lateral, sel in ((1.8, dashed), (1.8 + 3.6, True), (1.8 - 3.6, True)):
        keep = sel & ~dlow if isinstance(sel, np.ndarray) else ~dlow
        ci, cj = _cells(
            lo,
            px[keep] + lateral * normal[keep, 0],
            py[keep] + lateral * normal[keep, 1],
        )
        _stamp(marks, ci, cj, 0.6)
    # Occasional crossings: bands of stripes across the road.
    for s in rng.uniform(0, arc[-1], size=max(1, int(arc[-1] / 250))):
        sel = (dense > s) & (dense < s + 3) & ~dlow
        for lat in np.arange(-2.0, 5.8, 0.8):
            ci, cj = _cells(
                lo, px[sel] + lat * normal[sel, 0], py[sel] + lat * normal[sel, 1]
            )
            _stamp(marks, ci, cj, 0.8)
    ground[marks] = [230.0, 230.0, 220.0]
    # Texture-poor stretches: the ground near them is a flat, even colour.
    flat = np.zeros(shape, bool)
    ci, cj = _cells(lo, px[dlow], py[dlow])
    if ci.size:
        _stamp(flat, ci[::4], cj[::4], 25.0 / MAP_RESOLUTION)
        ground[flat] = 0.7 * ground[flat] + 0.3 * np.array([100.0, 100.0, 95.0])
        ground[flat & ~marks] = np.array([98.0, 100.0, 92.0])
    return np.clip(ground, 0, 255).astype(np.uint8), road


def _structures(rng, lo, path: dict, road: np.ndarray) -> np.ndarray:
    """Vertical structures beside the path (none in texture-poor stretches,
    none standing on the road where the path comes back): `(k, 8)` rows of
    `(x, y, radius, height, r, g, b, kind)`."""
    arc, dense, dlow = path["arc"], path["dense"], path["dlow"]
    px, py, normal = path["px"], path["py"], path["normal"]
    objs = []
    s = 0.0
    while s < arc[-1]:
        s += rng.uniform(6, 18)
        i = min(int(s / 0.5), dense.size - 1)
        if dlow[i]:
            continue
        for side in (-1.0, 1.0):
            if rng.random() < 0.25:
                continue
            kind = rng.integers(3)
            radius = (0.25, 1.5, 4.0)[kind] * rng.uniform(0.7, 1.3)
            height = (5.0, 6.0, 11.0)[kind] * rng.uniform(0.6, 1.4)
            lat = 1.8 + side * (ROAD_HALF_WIDTH + 2.0 + radius + rng.uniform(0, 6))
            x = px[i] + lat * normal[i, 0]
            y = py[i] + lat * normal[i, 1]
            colour = (
                rng.uniform(150, 230, 3)
                if kind == 0
                else ([40, 110, 40] + rng.uniform(-20, 30, 3))
                if kind == 1
                else rng.uniform(60, 220, 3)
            )
            objs.append([x, y, radius, height, *colour, kind])
    objects = np.asarray(objs, np.float64).reshape(-1, 8)
    if objects.size:
        oi, oj = _cells(lo, objects[:, 0], objects[:, 1])
        objects = objects[~road[oi, oj]]
    return objects


def _nuisances(seed: int, seq: int, N: int) -> tuple[np.ndarray, ...]:
    """Per-frame gain, motion blur, pixel noise and passing occluders."""
    frng = np.random.default_rng([seed, seq, 11])
    # Brightness: a slow log-normal drift, plus shadows/tunnels (dark spells).
    drift = np.cumsum(frng.normal(0, 0.03, N))
    k = min(101, N)
    drift -= np.convolve(drift, np.ones(k) / k, mode="same")[:N]
    gain = np.exp(drift)
    t = 0
    while t < N:
        t += int(frng.integers(40, 200))
        n = int(frng.integers(3, 25))
        gain[t : t + n] *= frng.uniform(0.15, 0.5)
    # Motion blur: mostly none, sometimes strong.
    blur = np.where(frng.random(N) < 0.15, frng.integers(3, 12, N), 0).astype(float)
    # Pixel noise: mostly mild, sometimes heavy.
    noise = np.where(frng.random(N) < 0.1, frng.uniform(15, 45, N), 2.0)
    # Passing occluders: a near object sweeping across the view for a few frames.
    occ = np.zeros((N, 4))
    occ[:, 1] = -1
    t = 0
    while t < N:
        t += int(frng.integers(30, 120))
        n = int(frng.integers(3, 9))
        start, end = frng.uniform(-40, 190, 2)
        width = frng.uniform(25, 70)
        top = frng.uniform(-10, 25)
        shade = frng.uniform(20, 200)
        for k in range(n):
            if t + k < N:
                occ[t + k] = [start + (end - start) * k / n, width, top, shade]
    return gain, blur, noise, occ


def build_world(xyt: np.ndarray, seed: int, seq: int) -> World:
    """Build the world around a sequence's (camera 0) trajectory."""
    rng = np.random.default_rng([seed, seq, 7])
    margin = MAX_RANGE + 10.0
    lo = xyt[:, :2].min(0) - margin
    hi = xyt[:, :2].max(0) + margin
    shape = tuple(((hi - lo) / MAP_RESOLUTION).astype(int) + 1)
    path = _path(rng, xyt)
    ground, road = _ground(rng, shape, lo, path)
    objects = _structures(rng, lo, path, road)
    gain, blur, noise, occ = _nuisances(seed, seq, xyt.shape[0])
    return World(lo, ground, objects, path["low"], gain, blur, noise, occ)


# Pre-declared data variants (docs/tutorial/visual-odometry.md): name -> seed.
VARIANTS = {"reliability": 33}
BLUR_PX_PER_RAD_S = 20.0  # yaw-rate motion blur: about 8 px at 0.4 rad/s
EXPOSURE_PER_RAD_S = 0.4  # auto-exposure step std per frame, per rad/s of yaw


def reliability_variant(world: World, xyt: np.ndarray, seed: int, seq: int) -> World:
    """The "reliability" variant: per-frame faults that real driving video has.

    - Repeated and dropped frames: 3% of the frame slots show the previous
      capture again (the pair before them sees no motion, the pair after
      them two frames' motion) and 2% show the next capture early.
    - Motion blur tied to the yaw rate: `BLUR_PX_PER_RAD_S * |ω|` pixels
      (the larger of it and the world's own blur).
    - Exposure changes tied to the yaw rate: the log brightness follows
      `x_t = 0.8 x_{t-1} + EXPOSURE_PER_RAD_S |ω_t| ε_t` (the camera turning
      towards and away from the light), on top of the world's gain.
    - Moving occluders that bias the flow: each passing occluder carries
      stripes that move with it, so its own motion reads as image motion.
    """
    rng = np.random.default_rng([seed, seq, 17])
    N = xyt.shape[0]
    yaw = np.abs(velocities(xyt)[:, 1])
    source = np.arange(N)
    u = rng.random(N)
    repeat, drop = (u < 0.03) & (source > 0), (u > 0.98) & (source < N - 1)
    source[repeat] -= 1
    source[drop] += 1
    step = EXPOSURE_PER_RAD_S * yaw * rng.standard_normal(N)
    x = np.zeros(N)
    for t in range(1, N):
        x[t] = 0.8 * x[t - 1] + step[t]
    return dataclasses.replace(
        world,
        gain=world.gain * np.exp(x),
        blur=np.maximum(world.blur, np.round(BLUR_PX_PER_RAD_S * yaw)),
        source=source,
        striped=True,
    )


# Per-pixel ground rays, in the camera's frame (forward, left), fixed.
_ROWS = np.arange(H, dtype=np.float64)[:, None] + 0.5
_COLS = np.arange(W, dtype=np.float64)[None, :] + 0.5
_BELOW = np.broadcast_to(_ROWS > HORIZON_ROW + 0.5, (H, W))
with np.errstate(divide="ignore"):
    _DEPTH = np.where(
        _BELOW, CAMERA_HEIGHT * FOCAL / np.maximum(_ROWS - HORIZON_ROW, 1e-6), np.inf
    )
_LEFT = -(_COLS - W / 2) / FOCAL * _DEPTH
_FWD_G, _LEFT_G = _DEPTH[_BELOW], _LEFT[_BELOW]
# Level of detail of each ground pixel. A pixel row spans a stretch of ground
# that grows with the square of its depth (about 0.7 m at 10 m, 2.8 m at 20 m);
# point-sampling the 0.25 m map there would alias, and the texture would
# flicker instead of moving with the camera. Each pixel therefore reads, with
# bilinear interpolation, the box-filtered map level whose cells match the
# larger of its depth and lateral footprints (a mip-map), as a camera
# integrating over the pixel would see it.
MAP_LEVELS = 6
with np.errstate(divide="ignore"):
    _dr = np.maximum(_ROWS - HORIZON_ROW, 0.75)
    _SPAN = np.broadcast_to(
        np.maximum(CAMERA_HEIGHT * FOCAL / (_dr * _dr - 0.25), CAMERA_HEIGHT / _dr),
        (H, W),
    )[_BELOW]
_LOD = np.clip(np.round(np.log2(np.maximum(_SPAN / MAP_RESOLUTION, 1.0))), 0, 5)
_LOD_GROUPS = tuple(
    (int(lv), np.nonzero(_LOD == lv)[0])
    for lv in range(MAP_LEVELS)
    if (_LOD == lv).any()
)
_HAZE_W = np.clip(_FWD_G / MAX_RANGE, 0, 1) ** 1.5
_KEEP_G = (1 - _HAZE_W[:, None]).astype(np.float32)
_HAZE_G = (HAZE[None] * _HAZE_W[:, None]).astype(np.float32)
_SKY_IMG = (
    SKY[None, None] * (0.8 + 0.2 * (_ROWS / HORIZON_ROW))[..., None]
    + np.zeros((1, W, 1))
).astype(np.float32)
_OCCLUDER_TINT = np.array([0.9, 0.9, 1.0], np.float32)
_NOISE_BANK = 31


def _mip_levels(ground: np.ndarray, levels: int) -> list[np.ndarray]:
    """The ground map and its 2 x 2 box-filtered reductions, float32."""
    out = [ground.astype(np.float32)]
    for _ in range(1, levels):
        g = out[-1]
        h, w = (g.shape[0] // 2) * 2, (g.shape[1] // 2) * 2
        g = g[:h, :w]
        out.append(
            0.25 * (g[0::2, 0::2] + g[1::2, 0::2] + g[0::2, 1::2] + g[1::2, 1::2])
        )
    return out


def _bilinear(level: np.ndarray, i: np.ndarray, j: np.ndarray, k: int) -> np.ndarray:
    """Bilinear lookup at level-0 cell coordinates `(i, j)` in map level `k`."""
    scale = 0.5**k
    u = np.clip(i * scale - 0.5, 0, level.shape[0] - 1.001)
    v = np.clip(j * scale - 0.5, 0, level.shape[1] - 1.001)
    i0, j0 = u.astype(np.int64), v.astype(np.int64)
    fu, fv = (u - i0)[:, None].astype(np.float32), (v - j0)[:, None].astype(np.float32)
    a, b = level[i0, j0], level[i0 + 1, j0]
    c, d = level[i0, j0 + 1], level[i0 + 1, j0 + 1]
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


class Renderer:
    """Deterministic 50 x 150 views along a sequence's real trajectory.

    **Arguments:**

    - `xyt`: `(N, 3)` planar camera-0 poses of the sequence.
    - `seed`, `seq`: fix the world and the nuisances.
    - `variant`: `None` (the default world) or a name in `VARIANTS`.

    `images(camera, frames)` renders the views of `camera` (`"image_2"` or
    `"image_3"`) at `frames`; `nuisances(frames)` returns the per-frame
    nuisance levels (for plots).
    """

    def __init__(self, xyt: np.ndarray, seed: int, seq: int, variant=None):
        self.xyt = np.asarray(xyt, np.float64)
        self.seed, self.seq = int(seed), int(seq)
        self.world = build_world(self.xyt, seed, seq)
        if variant is not None:
            if variant not in VARIANTS:
                raise ValueError(f"unknown variant {variant!r}: not in {VARIANTS}")
            self.world = reliability_variant(self.world, self.xyt, seed, seq)
        self._levels = _mip_levels(self.world.ground, MAP_LEVELS)
        rng = np.random.default_rng([seed, seq, 13])
        self._noise = rng.standard_normal((_NOISE_BANK, H, W + 17, 3), np.float32)

    def nuisances(self, frames) -> dict:
        w = self.world
        frames = np.asarray(frames)
        return {
            "gain": w.gain[frames],
            "blur": w.blur[frames],
            "noise": w.noise[frames],
            "occluded": w.occluder[frames, 1] > 0,
            "low_texture": w.low_texture[frames],
            "misframed": (w.source[frames] != frames)
            if w.source is not None
            else np.zeros(frames.shape, bool),
        }

    def images(self, camera: str, frames) -> np.ndarray:
        frames = np.atleast_1d(np.asarray(frames))
        if self.world.source is not None:  # repeated / dropped frames
            frames = self.world.source[frames]
        poses = offset_camera(self.xyt[frames], CAMERA_OFFSETS[camera])
        cam = CAMERAS.index(camera)
        return np.stack([self.render(p, int(f), cam) for p, f in zip(poses, frames)])

    def render(self, pose: np.ndarray, frame: int, cam: int = 0) -> np.ndarray:
        """One view from camera pose `(x, y, θ)` with frame `frame`'s nuisances."""
        w = self.world
        x, y, th = pose
        c, s = np.cos(th), np.sin(th)
        img = _SKY_IMG.copy()
        # Ground: intersect each pixel's ray with the ground plane, look up the map.
        i = ((x - w.origin[0]) + c * _FWD_G - s * _LEFT_G) * (1 / MAP_RESOLUTION)
        j = ((y - w.origin[1]) + s * _FWD_G + c * _LEFT_G) * (1 / MAP_RESOLUTION)
        ground = np.empty((i.size, 3), np.float32)
        for level, idx in _LOD_GROUPS:
            ground[idx] = _bilinear(self._levels[level], i[idx], j[idx], level)
        img[_BELOW] = ground * _KEEP_G + _HAZE_G
        # Vertical structures: nearest cylinder per column (a column z-buffer).
        ob = w.objects
        if ob.size:
            dx, dy = ob[:, 0] - x, ob[:, 1] - y
            fwd = c * dx + s * dy
            left = -s * dx + c * dy
            vis = (
                (fwd > 1.0) & (fwd < MAX_RANGE) & (np.abs(left) < 1.2 * fwd + ob[:, 2])
            )
            if vis.any():
                self._draw_objects(img, ob[vis], fwd[vis], left[vis])
        # Passing occluder (a near vehicle or sign): a flat dark shape.
        oc = w.occluder[frame]
        if oc[1] > 0:
            c0 = int(np.clip(oc[0] - oc[1], 0, W))
            c1 = int(np.clip(oc[0] + oc[1], 0, W))
            r0 = int(np.clip(np.ceil(oc[2]), 0, H))
            shade = oc[3] * _OCCLUDER_TINT
            if w.striped:  # stripes that move with the occluder
                stripes = 0.6 + 0.4 * ((_COLS[0, c0:c1] - oc[0]) // 10 % 2)
                shade = shade * stripes[:, None]
            img[r0:, c0:c1] = shade
        # Motion blur along rows (box filter by cumulative sums).
        b = int(w.blur[frame])
        if b > 1:
            pad = np.concatenate(
                [np.repeat(img[:, :1], b, 1), img, np.repeat(img[:, -1:], b, 1)], 1
            )
            cs = np.cumsum(pad, axis=1)
            lo = b // 2
            img = (cs[:, lo + b : lo + b + W] - cs[:, lo : lo + W]) * (1.0 / b)
        img *= np.float32(w.gain[frame])
        # Pixel noise from a fixed bank, picked and shifted by (cam, frame).
        k = (frame * 7919 + cam * 104729) % _NOISE_BANK
        img += self._noise[k, :, k % 17 : k % 17 + W] * np.float32(w.noise[frame])
        np.clip(img, 0, 255, out=img)
        return img.astype(np.uint8)

    def _draw_objects(self, img, o, f, lft):
        u = W / 2 - FOCAL * lft / f
        hw = FOCAL * o[:, 2] / f + 0.5
        cols = _COLS[0]
        # Coverage of each column by each object, with the edge columns partly
        # covered (anti-aliased), so that sub-pixel motion changes the image.
        alpha_all = np.clip(hw[:, None] + 0.5 - np.abs(cols[None] - u[:, None]), 0, 1)
        cover = alpha_all > 0  # (K, W)
        depth = np.where(cover, f[:, None], np.inf)
        k = np.argmin(depth, axis=0)
        hit = np.isfinite(depth[k, np.arange(W)])
        if not hit.any():
            return
        cidx = np.nonzero(hit)[0]
        k = k[cidx]
        fk, ok = f[k], o[k]
        top = HORIZON_ROW - FOCAL * (ok[:, 3] - CAMERA_HEIGHT) / fk
        bot = HORIZON_ROW + FOCAL * CAMERA_HEIGHT / fk
        r0 = int(np.clip(np.floor(top.min()), 0, H))
        r1 = int(np.clip(np.ceil(bot.max()) + 1, 0, H))
        rows = _ROWS[r0:r1, :1]
        mask = (rows >= top[None]) & (rows <= bot[None])  # (r, n)
        # Surface pattern: storeys and bays on buildings, bands on the rest.
        z = CAMERA_HEIGHT - (rows - HORIZON_ROW) * (fk / FOCAL)[None]
        a = (cols[cidx] - u[k]) / hw[k]
        kind = ok[:, 7][None]
        pat = np.where(
            kind == 2,
            0.55 + 0.45 * ((np.floor(z * (1 / 1.6)) + np.floor(a * 3 + 5)) % 2),
            np.where(
                kind == 1,
                0.7 + 0.3 * np.cos(z * 2.3 + a * 4),
                0.6 + 0.4 * ((z % 1.2) < 0.6),
            ),
        )
        shade = 0.75 + 0.25 * np.sqrt(np.clip(1 - a * a, 0, 1))
        hz = np.clip(fk / MAX_RANGE, 0, 1) ** 1.5
        colour = (ok[:, 4:7] * (1 - hz)[:, None])[None] * (pat * shade[None])[
            ..., None
        ] + (HAZE[None] * hz[:, None])[None]
        alpha = alpha_all[k, cidx].astype(np.float32)[None, :, None]
        block = img[r0:r1, cidx]
        blended = alpha * colour + (1 - alpha) * block
        block[mask] = blended[mask]
        img[r0:r1, cidx] = block


def rendered_sequence(
    seq: int,
    seed: int = 0,
    poses_dir: str | Path = DEFAULT_POSES_DIR,
    variant: str | None = None,
) -> list[Trajectory]:
    """The two camera trajectories of a sequence, with rendered views
    (of the default world, or of a data variant in `VARIANTS`)."""
    path = require(
        Path(poses_dir) / f"{seq:02d}.txt",
        f"the KITTI ground-truth poses of sequence {seq:02d}",
        "the KITTI odometry benchmark's 'ground truth poses' download (00.txt..10.txt)",
        "--poses-dir",
    )
    xyt = poses_to_2d(read_poses(path))
    renderer = Renderer(xyt, seed, seq, variant)
    return [
        Trajectory(seq, cam, False, offset_camera(xyt, CAMERA_OFFSETS[cam]), renderer)
        for cam in CAMERAS
    ]


# ---------------------------------------------------------------------------
# Folds, splits, windows and metrics
# ---------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FoldSpec:
    """Which sequences fold `fold` trains, validates and tests on."""

    fold: int
    test: int
    valid: int
    train: tuple[int, ...]


def fold_spec(fold: int) -> FoldSpec:
    """Fold `f` tests on `SEQUENCES[f]` and validates on `SEQUENCES[f+1]`.

    Sequence 01 is never used. The validation sequence (for checkpoint
    selection) is never the test sequence and is not trained on.
    """
    if not 0 <= fold < NUM_FOLDS:
        raise ValueError(f"fold must be in 0..{NUM_FOLDS - 1}, got {fold}")
    test = SEQUENCES[fold]
    valid = SEQUENCES[(fold + 1) % NUM_FOLDS]
    train = tuple(s for s in SEQUENCES if s not in (test, valid))
    return FoldSpec(fold, test, valid, train)


def pretrain_frames(num_frames: int) -> np.ndarray:
    """Frames for sensor pretraining: all but the last `PRETRAIN_HOLDOUT`."""
    return np.arange(max(num_frames - PRETRAIN_HOLDOUT, 0))


def smoother_frames(num_frames: int) -> np.ndarray:
    """Frames for smoother / EKF training: the last `SMOOTHER_FRAMES`."""
    return np.arange(max(num_frames - SMOOTHER_FRAMES, 0), num_frames)


def windows(frames: np.ndarray, length: int, stride: int | None = None) -> np.ndarray:
    """Start frames of windows of `length` states (plus one image after them).

    A window of `length` states uses `length + 1` consecutive frames: the
    velocity of state t is the motion to frame t+1 and is measured from the
    image pair (t, t+1). With `stride=None` the windows are disjoint.
    """
    stride = length if stride is None else stride
    first, last = int(frames[0]), int(frames[-1])
    return np.arange(first, last - length + 1, stride)


def window_metrics(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Final-step translation error per metre (m/m) and rotation error (deg/m).

    **Arguments:** `est`, `truth`: `(T, 3)` planar poses of one window.

    **Returns:** `(|p̂_T − p_T| / L, |θ̂_T − θ_T| (deg) / L)` with `L` the
    ground-truth path length of the window.
    """
    length = float(np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1)))
    length = max(length, 1e-6)
    trans = float(np.linalg.norm(est[-1, :2] - truth[-1, :2])) / length
    dth = np.angle(np.exp(1j * (est[-1, 2] - truth[-1, 2])))
    return trans, float(np.degrees(abs(dth))) / length


def whole_window_metrics(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Whole-window errors: like `window_metrics`, averaged over all T states.

    **Returns:** `(mean_t |p̂_t − p_t| / L, mean_t |θ̂_t − θ_t| (deg) / L)`.
    """
    length = float(np.sum(np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1)))
    length = max(length, 1e-6)
    trans = float(np.mean(np.linalg.norm(est[:, :2] - truth[:, :2], axis=1))) / length
    dth = np.angle(np.exp(1j * (est[:, 2] - truth[:, 2])))
    return trans, float(np.mean(np.degrees(np.abs(dth)))) / length
