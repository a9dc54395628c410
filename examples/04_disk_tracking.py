"""Visual disk tracking: the first experiment of Yi et al. (IROS 2021), reproduced.

A red disk moves among 25 occluding coloured distractors in 120 x 120 images.
A CNN virtual sensor reads its position; smoothers (factor graphs solved by
Gauss-Newton) with constant or heteroscedastic learned noise, EKFs with the
same models, and LSTM baselines are trained and compared by per-coordinate
position RMSE (pixels) on held-out folds. See docs/tutorial/disk-tracking.md.

What it writes under --out: results.json (config, seeds, git hash, machine,
timings, per-fold and summary numbers), results.md (the table), the figures
fig_trajectories.png (paper Fig. 4) and fig_uncertainty.png (paper Fig. 5),
and per fold the pretrained virtual sensor (sensor_fold{k}.eqx, reusable
with --sensor-weights-dir) and the trained noise models.

Runtime: --quick (one test fold, 48 training sequences from two folds, a few
hundred steps) takes under ten minutes on 2 CPU cores (6 min on loaded ones)
and prints a table labelled QUICK; its sensor starts from a target-colour
first layer (a quick-mode aid, not the paper's protocol). The full protocol
(10 folds x 505 sequences, paper-length training) is meant for a GPU: run one
or a few folds per call with --folds.

    python examples/04_disk_tracking.py --quick --out results/disk_quick
    python examples/04_disk_tracking.py --folds 0 --images-on-device --out results/disk
"""

import argparse
import dataclasses
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parent))
try:
    import eqsmooth  # noqa: F401
except ImportError:  # not installed (e.g. a bare GPU image): use the checkout
    sys.path.insert(1, str(Path(__file__).resolve().parents[1]))

from disk_tracking import report, train  # noqa: E402


def parse_args(argv=None) -> tuple[train.Config, Path]:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("--quick", action="store_true", help="small CPU run (~10 minutes)")
    p.add_argument(
        "--pretrain-sensor",
        action="store_true",
        help="quick mode: pretrain the sensor even if committed weights exist",
    )
    p.add_argument(
        "--sensor-colour-init",
        action=argparse.BooleanOptionalAction,
        help="start the sensor's first conv as a target-colour detector (a "
        "quick-mode aid, on by default with --quick; not the paper's protocol)",
    )
    p.add_argument("--out", type=Path, default=Path("results/disk_tracking"))
    p.add_argument("--folds", type=int, nargs="+", help="test folds to run")
    p.add_argument(
        "--methods",
        nargs="+",
        choices=list(train.Config().methods),
        help="subset of methods (default: all)",
    )
    p.add_argument("--data-seed", type=int)
    p.add_argument("--model-seed", type=int)
    p.add_argument("--cache-dir", help="cache generated folds (.npz) here")
    p.add_argument(
        "--sensor-weights-dir",
        help="load sensor_fold{k}.eqx from here instead of pretraining",
    )
    p.add_argument(
        "--images-on-device",
        action="store_true",
        help="render training/validation images once and keep them on the device",
    )
    p.add_argument(
        "--matmul-precision",
        default="highest",
        choices=["default", "high", "highest"],
        help="jax_default_matmul_precision (GPUs may use TF32 by default, too "
        "coarse for the Gauss-Newton normal equations)",
    )
    for name in (
        "sequences_per_fold",
        "sensor_steps",
        "sensor_batch",
        "fg_steps",
        "fg_batch",
        "lstm_steps",
        "lstm_batch",
        "eval_every",
        "max_train_sequences",
        "max_test_sequences",
    ):
        p.add_argument("--" + name.replace("_", "-"), type=int)
    for name in ("sensor_lr", "fg_lr", "lstm_lr"):
        p.add_argument("--" + name.replace("_", "-"), type=float)
    a = p.parse_args(argv)
    overrides = {
        k: v
        for k, v in vars(a).items()
        if v is not None
        and k
        not in (
            "quick",
            "out",
            "folds",
            "methods",
            "images_on_device",
            "pretrain_sensor",
            "matmul_precision",
        )
    }
    if a.folds is not None:
        overrides["test_folds"] = tuple(a.folds)
    if a.methods is not None:
        overrides["methods"] = tuple(a.methods)
    if a.images_on_device:
        overrides["images_on_device"] = True
    cfg = (
        train.quick_config(a.pretrain_sensor, **overrides)
        if a.quick
        else dataclasses.replace(train.Config(), **overrides)
    )
    if a.matmul_precision != "default":
        import jax

        jax.config.update("jax_default_matmul_precision", a.matmul_precision)
    return cfg, a.out


def main(argv=None):
    cfg, out = parse_args(argv)
    t0 = time.perf_counter()
    label = "QUICK RUN" if cfg.quick else "full protocol"
    print(f"Disk tracking ({label}): test folds {list(cfg.test_folds)}")
    fold_results = []
    for k in cfg.test_folds:
        fold_results.append(train.run_fold(cfg, k, out))
    timings = dict(
        total_s=time.perf_counter() - t0,
        per_fold=[fr["timings"] for fr in fold_results],
    )
    _, table = report.write_results(out, dataclasses.asdict(cfg), fold_results, timings)
    figs = report.figures(out, fold_results[0], cfg.quick)
    print()
    print(table)
    print(
        f"total {timings['total_s']:.0f} s; results in {out}/results.json, "
        f"{out}/results.md; figures: {', '.join(str(f) for f in figs)}"
    )


if __name__ == "__main__":
    main()
