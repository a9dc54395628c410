"""Learn the KITTI drive's IMU noise end to end and score it in GPS outages.

What it runs: the protocol declared in `docs/tutorial/imu.md` (copy in
`results/kitti_imu/protocol.md`). GTSAM's KITTI drive is cut into five
contiguous segments; fold `f` tests on segment `f`, selects on the next and
trains on the other three. In every segment the GPS is withheld in two
30-keyframe outages. Rows: the metadata sigmas (hand-tuned), and four
constant sigmas learned end to end through the batch smoother (the loss is
the squared horizontal error at the withheld fixes of a training segment,
differentiated by the implicit adjoint; the validation loss picks the
checkpoint). Scores on the test segment: RMS and max horizontal error at the
withheld fixes, and their NLL under the smoother's position marginals plus
the GPS noise. Each fold writes `fold_<f>.json`; `--summary` pools the
committed fold files into `summary.json` and `summary.md` (paired
differences against the metadata row).

Runtime on 2 CPU cores shared with other jobs (load average 5-10): the five
declared folds in one process took 134-287 s each, 16 minutes in all
(`seconds` in each `fold_<f>.json`), much of it compilation (later folds
reuse the compiled programs); `--quick` (one fold of 16-keyframe segments,
2 training steps; not the protocol) 61 s in `tests/test_kitti_imu.py`
with JAX's compilation cache warm, about 4 minutes cold, nearly all
compilation.

    python -m experiments.kitti_imu --quick --out /tmp/kitti_imu_quick
    python -m experiments.kitti_imu --folds 0 1 2 3 4
    python -m experiments.kitti_imu --summary

Data: GTSAM's `KittiEquivBiasedImu.txt`, `KittiEquivBiasedImu_metadata.txt`
and `KittiGps_converted.txt`, from `--data-dir` or the gtsam wheel
(`gtsam.findExampleDataFile`).
"""

import json
import sys
import time

import jax


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402

from .._cli import experiment_parser  # noqa: E402
from .._provenance import git_hash  # noqa: E402
from . import data as D, experiment as E, report as R  # noqa: E402


def main(argv=None):
    p = experiment_parser(
        __doc__,
        quick="one fold of 16-keyframe segments, 2 training steps (not the protocol)",
        out="results/kitti_imu",
        folds="folds to run (default: all five; with --quick, fold 0)",
    )
    p.add_argument("--data-dir", default=None)
    p.add_argument(
        "--summary", action="store_true", help="pool the fold files in --out only"
    )
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.summary:
        R.write_summary(args.out)
        return
    eqs.enable_compilation_cache()
    cfg = D.QUICK if args.quick else D.Config()
    folds = args.folds or ([0] if args.quick else list(range(cfg.num_segments)))
    meta, imu, gps = D.load(args.data_dir)
    data = D.segments(meta, imu, gps, cfg)
    for fold in folds:
        t0 = time.perf_counter()
        out = E.run_fold(meta, data, fold, cfg)
        out["seconds"] = time.perf_counter() - t0
        out["config"] = {**cfg.__dict__, "quick": bool(args.quick)}
        out["command"] = "python -m experiments.kitti_imu " + " ".join(sys.argv[1:])
        out["commit"] = git_hash()
        out["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        path = args.out / f"fold_{fold}.json"
        path.write_text(json.dumps(out, indent=2, default=float) + "\n")
        rows = out["rows"]
        print(
            f"fold {fold}: "
            + ", ".join(
                f"{k} rms {v['rms_horizontal_m']:.3f} m max {v['max_horizontal_m']:.3f}"
                f" m nll {v['nll']:.3f}"
                for k, v in rows.items()
            )
            + f" (best step {out['training']['best_step']}, {out['seconds']:.0f} s)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    main()
