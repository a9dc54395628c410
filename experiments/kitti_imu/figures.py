"""The figures of the second protocol (docs/tutorial/imu.md), drawn from the
fold files only: nothing is solved or trained again.

    python -m experiments.kitti_imu.figures
    python -m experiments.kitti_imu.figures --docs docs/tutorial/img

writes into `--out` (default `results/kitti_imu/protocol_2`):

- `fig_trajectory.png`: the test segment of fold 0 (the first fold: a fixed
  rule, not a choice by the picture): GPS fixes, outages, and the batch
  smoother and the EKF, each with the metadata and the learned constant
  sigmas; and the horizontal distance of each estimate from the GPS fix
  along the segment.
- `fig_outage_error.png`: horizontal error at the withheld fixes against
  the seconds since the last fix, per row, pooled over the folds' outages:
  median and range.
- `fig_calibration.png`: expected against observed coverage of the
  withheld fixes for every row with a covariance, pooled over folds (each
  fold thin).

With `--docs DIR` each figure is also copied to `DIR/imu_<name>.png`, where
the tutorial reads it. Takes a few seconds.
"""

import argparse
import json
import shutil
from pathlib import Path

import numpy as np


OUT = Path("results/kitti_imu/protocol_2")
TRAJECTORY_FOLD = 0
ESTIMATORS = {
    "batch smoother": ("metadata", "learned_constant", "learned_hetero"),
    "EKF": ("metadata_ekf", "learned_constant_ekf"),
    "fixed-lag smoother (lag 10)": ("metadata_fixed_lag", "learned_constant_fixed_lag"),
}
COLOURS = {
    "metadata": "tab:red",
    "learned_constant": "tab:blue",
    "learned_hetero": "tab:green",
}
STYLES = {"": "-", "_ekf": "--", "_fixed_lag": ":"}


def _style(row: str) -> dict:
    """One colour per set of sigmas, one line style per estimator."""
    for suffix in ("_ekf", "_fixed_lag", ""):
        if row.endswith(suffix):
            base = row[: len(row) - len(suffix)] if suffix else row
            return {"color": COLOURS[base], "linestyle": STYLES[suffix]}
    raise AssertionError(row)


def load(out: Path) -> list[dict]:
    """The declared protocol's fold files under `out` that hold the figures'
    record (quick runs refused)."""
    folds = [json.loads(p.read_text()) for p in sorted(out.glob("fold_*.json"))]
    folds = [f for f in folds if not f["config"]["quick"]]
    if not folds:
        raise SystemExit(f"no fold files of the declared protocol in {out}")
    missing = [f["fold"] for f in folds if "test_segment" not in f]
    if missing:
        print(
            f"fold files {missing} in {out} have no per-fix record (older runs), "
            "left out: rerun them with `python -m experiments.kitti_imu.protocol_2`"
        )
    folds = [f for f in folds if "test_segment" in f]
    if not folds:
        raise SystemExit(f"no fold file in {out} has the per-fix record")
    return folds


def _names(folds: list[dict]) -> str:
    return ", ".join(str(f["fold"]) for f in folds)


def trajectory_figure(fold: dict, path: Path) -> None:
    import matplotlib.pyplot as plt

    seg = fold["test_segment"]
    t = np.asarray(seg["time_s"])
    gps = np.stack([seg["gps_x"], seg["gps_y"]], -1)
    withheld = np.zeros(len(t), bool)
    withheld[seg["withheld_keyframes"]] = True
    rows = ("metadata", "learned_constant", "metadata_ekf", "learned_constant_ekf")
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.6))
    ax.plot(*gps[~withheld].T, "k.", ms=4, label="GPS fix (used)")
    ax.plot(
        *gps[withheld].T, "o", mfc="none", mec="0.5", ms=4, label="GPS fix (withheld)"
    )
    for r in rows:
        v = fold["rows"][r]
        ax.plot(v["trajectory_x"], v["trajectory_y"], lw=1.3, label=r, **_style(r))
    ax.set_aspect("equal", "datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    ax.set_title("positions of the test segment's keyframes", fontsize=9)
    for o in seg["outages"]:
        bx.axvspan(o["last_fix_s"], o["next_fix_s"], color="0.9", lw=0)
    for r in rows:
        v = fold["rows"][r]
        p = np.stack([v["trajectory_x"], v["trajectory_y"]], -1)
        bx.plot(t, np.linalg.norm(p - gps, axis=-1), lw=1.2, label=r, **_style(r))
    bx.set_yscale("log")
    bx.set_ylim(bottom=1e-2)
    bx.set_xlabel("time (s after the drive's first keyframe)")
    bx.set_ylabel("horizontal distance from the GPS fix (m)")
    bx.set_title("grey: the outages (between the fixes that bound them)", fontsize=9)
    bx.legend(fontsize=7)
    fig.suptitle(
        f"KITTI IMU + GPS, test segment of fold {fold['fold']} "
        "(fold 0 by rule), outages of 30 fixes",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def outage_error_figure(folds: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(ESTIMATORS), figsize=(12, 4.2), sharey=True)
    for ax, (title, rows) in zip(axes, ESTIMATORS.items()):
        for r in rows:
            # One curve per outage of each fold; the n-th withheld fixes of
            # the outages lie within a fraction of a second of each other.
            curves, seconds = [], []
            for f in folds:
                s = np.asarray(f["test_segment"]["seconds_into_outage"])
                k = np.asarray(f["test_segment"]["withheld_keyframes"])
                h = np.asarray(f["rows"][r]["per_fix"]["horizontal_error_m"])
                for a, b in f["config"]["outages"]:
                    inside = (k >= a) & (k < b)
                    curves.append(h[inside])
                    seconds.append(s[inside])
            c, seconds = np.stack(curves), np.mean(seconds, axis=0)
            ax.fill_between(seconds, c.min(0), c.max(0), alpha=0.15, lw=0, **_colour(r))
            ax.plot(seconds, np.median(c, 0), lw=1.5, label=r, **_style(r))
        ax.set_yscale("log")
        ax.set_title(title, fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
    axes[0].set_ylabel("horizontal error at the withheld fix (m)")
    fig.supxlabel("seconds since the last GPS fix (mean over the outages)", fontsize=9)
    fig.suptitle(
        f"Error during the outages: {2 * len(folds)} outages (test folds "
        f"{_names(folds)}, 2 each), median (line) and range (band)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _colour(row: str) -> dict:
    return {"color": _style(row)["color"]}


def coverage(cdf: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Observed coverage at each nominal level: the fraction of fixes inside
    the level's χ² region of their predicted distribution (CDF value at or
    below the level)."""
    return np.mean(cdf[None, :] <= levels[:, None], axis=1)


def calibration_figure(folds: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    levels = np.linspace(0, 1, 201)
    rows = [r for r in folds[0]["rows"] if "chi2_cdf" in folds[0]["rows"][r]["per_fix"]]
    fig, ax = plt.subplots(figsize=(6.2, 5.6))
    ax.plot([0, 1], [0, 1], "k:", lw=1, label="calibrated")
    for r in rows:
        per_fold = [np.asarray(f["rows"][r]["per_fix"]["chi2_cdf"]) for f in folds]
        for c in per_fold:
            ax.plot(levels, coverage(c, levels), lw=0.5, alpha=0.35, **_style(r))
        pooled = coverage(np.concatenate(per_fold), levels)
        ax.plot(levels, pooled, lw=1.8, label=r, **_style(r))
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("expected coverage (χ²₃ region of position covariance + GPS noise)")
    ax.set_ylabel("observed coverage of the withheld fixes")
    ax.legend(fontsize=7, loc="upper left")
    n = sum(len(f["test_segment"]["withheld_keyframes"]) for f in folds)
    ax.set_title(
        f"Calibration: withheld fixes of test folds {_names(folds)} pooled "
        f"({n} fixes); thin: each fold\nbelow the diagonal: the covariance is "
        "too small (overconfident)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--docs", type=Path, default=None, help="copy the figures here")
    args = p.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    folds = load(args.out)
    by_fold = {f["fold"]: f for f in folds}
    if TRAJECTORY_FOLD not in by_fold:
        raise SystemExit(f"fold {TRAJECTORY_FOLD} (the trajectory figure's) is missing")
    paths = [
        args.out / f"fig_{n}.png" for n in ("trajectory", "outage_error", "calibration")
    ]
    trajectory_figure(by_fold[TRAJECTORY_FOLD], paths[0])
    outage_error_figure(folds, paths[1])
    calibration_figure(folds, paths[2])
    for path in paths:
        print(f"{path} ({path.stat().st_size // 1024} KB)")
        if args.docs is not None:
            shutil.copyfile(path, args.docs / f"imu_{path.name[4:]}")
    return 0


if __name__ == "__main__":
    main()
