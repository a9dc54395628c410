"""GTSAM's KITTI drive cut into the protocol's segments, folds and outages.

Everything here is NumPy: the segments are arrays of one shape (the IMU
samples of each keyframe interval padded to the drive's longest interval),
so every segment runs through one compiled program.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np


FILES = (
    "KittiEquivBiasedImu_metadata.txt",
    "KittiEquivBiasedImu.txt",
    "KittiGps_converted.txt",
)
FIRST_KEYFRAME = 1  # row 0 of the GPS file is 2.9 s before the IMU settles


@dataclass(frozen=True)
class Config:
    """The protocol's layout (the declared one is `Config()`)."""

    num_segments: int = 5
    segment_length: int = 93  # keyframes per segment
    outages: tuple[tuple[int, int], ...] = ((10, 40), (55, 85))  # [start, stop)
    num_steps: int = 45
    learning_rate: float = 0.05
    valid_every: int = 5
    max_solver_steps: int = 50


QUICK = Config(
    segment_length=16,
    outages=((4, 12),),
    num_steps=2,
    valid_every=1,
    max_solver_steps=20,
)


def find_files(data_dir: str | None) -> list[Path]:
    """GTSAM's three KITTI files, from `data_dir` or the gtsam wheel."""
    if data_dir is not None:
        paths = [Path(data_dir) / name for name in FILES]
    else:
        try:
            import gtsam
        except ImportError:
            raise SystemExit(
                "experiments.kitti_imu: give --data-dir (GTSAM's KITTI files) or "
                "install gtsam, whose wheel ships them"
            ) from None
        paths = [Path(gtsam.findExampleDataFile(name)) for name in FILES]
    for p in paths:
        if not p.is_file():
            raise SystemExit(f"experiments.kitti_imu: no such file {p}")
    return paths


def load(data_dir: str | None = None):
    """Metadata (a dict of floats), IMU rows `(t, dt, acc, gyro)` and GPS rows
    `(t, x, y, z)`."""
    meta_path, imu_path, gps_path = find_files(data_dir)
    with open(meta_path) as f:
        names = f.readline().split()
    meta = {k: float(v) for k, v in zip(names, np.loadtxt(meta_path, skiprows=1))}
    if any(meta[k] != 0 for k in names[:6]):
        raise SystemExit(f"{meta_path}: the IMU must be in the body frame")
    imu = np.loadtxt(imu_path, skiprows=1)
    gps = np.loadtxt(gps_path, skiprows=1, delimiter=",")
    return meta, imu, gps


def interval_rows(imu_t: np.ndarray, key_t: np.ndarray) -> list[np.ndarray]:
    """The IMU sample indices of each interval between consecutive keyframe
    times `key_t`: samples in `[t_0, t_1]` for the first interval, in
    `(t_{i-1}, t_i]` after it (a sample on a keyframe ends its interval, as
    in GTSAM's example)."""
    starts = np.searchsorted(imu_t, key_t[:-1], side="right")
    starts[0] = np.searchsorted(imu_t, key_t[0], side="left")
    stops = np.searchsorted(imu_t, key_t[1:], side="right")
    return [np.arange(a, b) for a, b in zip(starts, stops)]


def outage_mask(cfg: Config) -> np.ndarray:
    """`True` at a segment's keyframes whose GPS fix is withheld."""
    out = np.zeros(cfg.segment_length, bool)
    for a, b in cfg.outages:
        out[a:b] = True
    return out


def initial_guess(xyz: np.ndarray, withheld: np.ndarray):
    """Positions (withheld fixes replaced by linear interpolation in time
    order between the used ones), yaw along the track, finite-difference
    velocities: never reads a withheld fix."""
    k = np.arange(len(xyz))
    used = ~withheld
    pos = np.stack([np.interp(k, k[used], xyz[used, i]) for i in range(3)], axis=1)
    step = np.gradient(pos, axis=0)
    yaw = np.arctan2(step[:, 1], step[:, 0])
    return pos, yaw, step


def segments(meta, imu, gps, cfg: Config) -> dict[str, np.ndarray]:
    """The drive's segments stacked on a leading axis (one example each):
    `samples (S, L-1, K, 7)` as `(dt, acc, gyro)`, `mask (S, L-1, K)`,
    `count (S, L-1)` samples per interval, `gps (S, L, 3)` (every fix,
    withheld ones included: the losses read them), initial `pos`, `yaw`,
    `vel`, and `time (S, L)` seconds after the first keyframe."""
    length = cfg.segment_length
    last = FIRST_KEYFRAME + cfg.num_segments * length
    if last > len(gps):
        raise ValueError(
            f"{cfg.num_segments} segments of {length} keyframes need {last} GPS "
            f"rows, the file has {len(gps)}"
        )
    withheld = outage_mask(cfg)
    key = gps[FIRST_KEYFRAME:last]
    out = {k: [] for k in ("rows", "gps", "pos", "yaw", "vel", "time")}
    for s in range(cfg.num_segments):
        seg = key[s * length : (s + 1) * length]
        out["rows"].append(interval_rows(imu[:, 0], seg[:, 0]))
        out["gps"].append(seg[:, 1:])
        pos, yaw, vel = initial_guess(seg[:, 1:], withheld)
        out["pos"].append(pos)
        out["yaw"].append(yaw)
        out["vel"].append(vel)
        out["time"].append(seg[:, 0] - key[0, 0])
    width = max(len(r) for rows in out["rows"] for r in rows)
    index, mask, count = [], [], []
    for rows in out.pop("rows"):
        if min(len(r) for r in rows) == 0:
            raise ValueError("a keyframe interval holds no IMU sample")
        index.append([np.pad(r, (0, width - len(r)), mode="edge") for r in rows])
        mask.append([np.arange(width) < len(r) for r in rows])
        count.append([len(r) for r in rows])
    data = {k: np.asarray(v, np.float64) for k, v in out.items()}
    data["samples"] = imu[np.asarray(index)][..., 1:8]
    data["mask"] = np.asarray(mask)
    data["count"] = np.asarray(count, np.float64)
    return data


def fold_split(fold: int, cfg: Config) -> dict[str, list[int]]:
    """Test = segment `fold`, validation = the next one (cyclically), train =
    the rest."""
    n = cfg.num_segments
    if not 0 <= fold < n:
        raise ValueError(f"fold must be in 0..{n - 1}, got {fold}")
    valid = (fold + 1) % n
    return {
        "train": [s for s in range(n) if s not in (fold, valid)],
        "valid": [valid],
        "test": [fold],
    }


def take(data: dict, idx: list[int]) -> dict:
    return {k: v[np.asarray(idx)] for k, v in data.items()}
