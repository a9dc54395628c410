"""Visual odometry on KITTI-10: the second experiment of Yi et al. (IROS 2021).

A vehicle state `(T ∈ SE(2), v, ω)` is smoothed by a factor graph (prior on
the first state, learned constant-velocity dynamics noise, one velocity
factor per frame from a CNN virtual sensor reading
`[image_{t+1}, image_{t+1} − image_t]`). Smoothers with constant or
heteroscedastic noise, trained end to end (surrogate loss) or by joint NLL,
are compared with EKFs built from the same factors and an LSTM, by the
final-step translation error per metre (m/m) and rotation error per metre
(deg/m) on disjoint length-100 windows of the held-out sequence.

Data: the KITTI images are not available here, so by default the views are
**rendered views on real KITTI trajectories**: the real ground-truth poses
of sequences 00-10 (`--poses-dir`, default `../shared/data/kitti_poses`,
from the KITTI odometry benchmark's ground-truth download) drive a camera
over a procedural world with per-frame nuisances
(experiments/kitti_vo/data.py).
Results on it are not the paper's experiment. With `--real-data-dir` the
preprocessed KITTI-10 release of the paper's code is read instead.

Output under --out (default results/kitti): fold_K.json (every row, per-window
errors, timings, config, git hash, machine), sensor_foldK.eqx (the frozen
virtual sensor), fig_trajectories_foldK.png, fig_noise_foldK.png, and
work/ (checkpoints and sensor caches; not meant to be committed). Rerunning
the same command resumes: finished methods are skipped, others continue
from their checkpoints.

Runtime on 2 CPU cores: --quick (fold 3, test sequence 04, two training
sequences, one camera, a few dozen steps) a few minutes; a full fold is
budgeted at 90 minutes.

    python -m experiments.kitti_vo --quick --out /tmp/kitti_quick
    python -m experiments.kitti_vo --folds 0 1 --out results/kitti
    python -m experiments.kitti_vo --uncertainty --folds 0 --out results/kitti
    python -m experiments.kitti_vo --uncertainty --report-only  # pool them
    python -m experiments.kitti_vo --variant reliability --folds 0 \
        --out results/kitti_variant   # the pre-declared data variant
"""

import dataclasses
import gc
from pathlib import Path

import jax

from experiments._cli import experiment_parser
from experiments.kitti_vo import (
    data as D,
    experiment as E,
    report,
    uncertainty as U,
)


def parse_args(argv=None):
    p = experiment_parser(
        __doc__,
        quick="small CPU run (CI)",
        out="results/kitti",
        folds="folds to run (default: all; quick: 3)",
    )
    p.add_argument("--methods", nargs="+", choices=E.METHODS)
    p.add_argument("--poses-dir", default=str(D.DEFAULT_POSES_DIR))
    p.add_argument(
        "--real-data-dir",
        help="the preprocessed KITTI-10 release ({seq}/image_2, {seq}_image1.txt ...)",
    )
    p.add_argument(
        "--variant",
        choices=sorted(D.VARIANTS),
        help="a pre-declared data variant of the rendered views (its own data "
        "seed; see docs/tutorial/visual-odometry.md), e.g. --out "
        "results/kitti_variant",
    )
    p.add_argument("--data-seed", type=int, help="default 0, or the variant's seed")
    p.add_argument("--model-seed", type=int)
    p.add_argument("--sensor-steps", type=int)
    p.add_argument("--steps", type=int, help="smoother / EKF training steps")
    p.add_argument("--lstm-steps", type=int)
    p.add_argument("--no-figures", action="store_true")
    p.add_argument(
        "--docs",
        type=Path,
        help="also write the summary table into this page (between its "
        "kitti-results markers), e.g. docs/tutorial/visual-odometry.md",
    )
    p.add_argument(
        "--uncertainty",
        action="store_true",
        help="issue 58: load each fold's committed sensor, train the rows with "
        "a covariance again (and the bi-LSTM variance row), check their test "
        "scores against fold_K.json, save the heads to heads/foldK/ and write "
        "uncertainty_fold_K.json (a fold whose file is complete is skipped); "
        "with --report-only: pool the finished folds into uncertainty.json and "
        "fig_calibration.png",
    )
    p.add_argument(
        "--report-only",
        action="store_true",
        help="run nothing: rebuild summary.md/json (and --docs) from the fold "
        "JSONs under --out",
    )
    args = p.parse_args(argv)
    cfg = E.quick_config() if args.quick else E.Config()
    if args.variant is not None:
        if args.real_data_dir:
            p.error("--variant changes the rendered views; not with --real-data-dir")
        cfg = dataclasses.replace(
            cfg, variant=args.variant, data_seed=D.VARIANTS[args.variant]
        )
    updates = {
        "methods": tuple(args.methods) if args.methods else None,
        "poses_dir": args.poses_dir,
        "real_data_dir": args.real_data_dir,
        "data_seed": args.data_seed,
        "model_seed": args.model_seed,
        "sensor_steps": args.sensor_steps,
        "steps": args.steps,
        "lstm_steps": args.lstm_steps,
    }
    cfg = dataclasses.replace(
        cfg, **{k: v for k, v in updates.items() if v is not None}
    )
    folds = args.folds or ([3] if args.quick else list(range(D.NUM_FOLDS)))
    return cfg, folds, args


def main(argv=None):
    cfg, folds, args = parse_args(argv)
    if args.uncertainty:
        if args.report_only:
            record = U.summarise(args.out)
            if record is not None:
                print(U.markdown(record))
                report.write_summary(args.out)  # summary.md's section
            return
        for fold in folds:
            U.run_fold(cfg, fold, args.out)
            gc.collect()
            jax.clear_caches()
        return
    for fold in [] if args.report_only else folds:
        state = E.run_fold(cfg, fold, args.out)
        if not args.no_figures:
            report.figures(state, fold, args.out)
        print(report.fold_table(state["result"]))
        # Free the fold's compiled programs: each XLA:CPU executable holds
        # memory mappings, and three folds in one process reached the
        # kernel's limit (vm.max_map_count) and died in LLVM ("Unable to
        # allocate section memory") during fold 2.
        del state
        gc.collect()
        jax.clear_caches()
    table = report.write_summary(args.out)
    print(table)
    if args.docs is not None:
        report.update_docs(args.docs, table)


if __name__ == "__main__":
    main()
