"""Visual disk tracking: the first experiment of Yi et al. (IROS 2021), reproduced.

A red disk moves among 25 occluding coloured distractors in 120 x 120 images.
A virtual sensor reads its position; smoothers (factor graphs solved by
Gauss-Newton) with constant or heteroscedastic learned noise, EKFs with the
same models, and LSTM baselines are trained and compared by per-coordinate
position RMSE (pixels) on held-out folds. See docs/tutorial/disk-tracking.md.

The full protocol (10 folds x 505 sequences) runs on 2 CPU cores, under 75
minutes per fold, one fold per call or several. Every stage trains with
`eqsmooth.learn.train` and checkpoints under --work: kill the run and start
the same command again, and it resumes. A finished fold writes
`fold_K.json`, `fold_K.log` and `sensor_foldK.eqx` under --out, and is
skipped by later calls (`--rerun` evaluates it again with the current code,
training only stages that have no finished checkpoint); `summary.json` /
`summary.md` (mean ± std/√n over the finished folds) and the figures are
rewritten after each fold.

    python -m experiments.disk_tracking --quick --out results/disk_quick   # ~5 min
    python -m experiments.disk_tracking --folds 0 --out results/disk        # one fold

More never-seen folds (11..20, the committed heads, no training) and the
covariances' NLL/NEES/coverage: `python -m experiments.disk_tracking.fresh_more`.
"""

import argparse
import dataclasses
import json
from pathlib import Path

from experiments._cli import experiment_parser
from experiments.disk_tracking import (
    fresh,
    fresh_more,
    online,
    protocol,
    report,
    seeds,
    train,
)


_INT = ("sequences_per_fold", "sensor_steps", "sensor_batch", "fg_steps", "fg_batch")
_INT += ("lstm_steps", "lstm_batch", "finetune_steps", "eval_every", "data_seed")
_INT += ("model_seed", "max_train_sequences", "max_test_sequences")
_FLOAT = ("sensor_lr", "fg_lr", "lstm_lr", "finetune_lr")


def parse_args(argv=None) -> tuple[train.Config, argparse.Namespace]:
    p = experiment_parser(
        __doc__,
        quick="small run (~5 minutes)",
        out="results/disk",
        folds="test folds to run",
    )
    p.add_argument(
        "--work",
        type=Path,
        help="checkpoints and caches (default: runs/disk, or OUT/work with --quick)",
    )
    p.add_argument(
        "--rerun",
        action="store_true",
        help="run finished folds again with the current code: stages whose "
        "checkpoints are finished are only evaluated, new methods are trained",
    )
    p.add_argument(
        "--methods",
        nargs="+",
        choices=[*train.Config().methods, *train.EXTRA_METHODS],
    )
    p.add_argument("--sensor", choices=["heatmap", "paper"])
    p.add_argument(
        "--fresh",
        action="store_true",
        help="fresh-data confirmation of finished folds: retrain their heads from "
        "the committed sensors and evaluate once on a never-seen set (fold 10)",
    )
    p.add_argument(
        "--sensor-from",
        type=Path,
        help="use the virtual sensors committed under this results folder "
        "(sensor_foldK.eqx) instead of training them: new heads on the same "
        "sensor as that folder's rows",
    )
    p.add_argument(
        "--seed-summary",
        type=Path,
        metavar="ROOT",
        help="train nothing: compare the runs ROOT/seedS (made with --sensor-from "
        "OUT --model-seed S --out ROOT/seedS) with seed 0 under --out; writes "
        "ROOT/seeds.json and ROOT/seeds.md",
    )
    p.add_argument(
        "--docs", type=Path, help="also write the summary table into this page"
    )
    p.add_argument(
        "--images-on-device",
        action="store_true",
        help="evaluate the sensor from device-resident images (GPU)",
    )
    p.add_argument(
        "--matmul-precision",
        default="highest",
        choices=["default", "high", "highest"],
        help="jax_default_matmul_precision (GPUs may use TF32)",
    )
    for name in _INT + _FLOAT:
        p.add_argument(
            "--" + name.replace("_", "-"), type=int if name in _INT else float
        )
    a = p.parse_args(argv)
    overrides = {k: getattr(a, k) for k in _INT + _FLOAT + ("sensor",)}
    overrides = {k: v for k, v in overrides.items() if v is not None}
    if a.folds is not None:
        overrides["test_folds"] = tuple(a.folds)
    if a.methods is not None:
        overrides["methods"] = tuple(a.methods)
    overrides["images_on_device"] = a.images_on_device
    base = train.quick_config() if a.quick else train.Config()
    if a.work is None:
        a.work = a.out / "work" if a.quick else Path("runs/disk")
    if a.matmul_precision != "default":
        import jax

        jax.config.update("jax_default_matmul_precision", a.matmul_precision)
    return dataclasses.replace(base, **overrides), a


def main(argv=None):
    cfg, a = parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    label = "QUICK RUN" if cfg.quick else "full protocol"
    print(f"Disk tracking ({label}): test folds {list(cfg.test_folds)}")
    if a.seed_summary is not None:
        print(seeds.summarise(a.out, a.seed_summary)[1])
        return
    if a.fresh:
        return main_fresh(cfg, a)
    for k in cfg.test_folds:
        finished = (a.out / f"fold_{k}.json").exists()
        if finished and not a.rerun:
            print(f"fold {k}: already finished ({a.out / f'fold_{k}.json'}), skipped")
            continue
        if finished:
            # A re-run rewrites fold_K.json with the methods it runs: refuse
            # one that would drop rows the committed file has.
            saved = json.loads((a.out / f"fold_{k}.json").read_text())["records"]
            lost = sorted(set(saved) - {"virtual_sensor", *cfg.methods})
            if lost:
                raise SystemExit(
                    f"--rerun of fold {k} with --methods would drop {lost} from "
                    f"{a.out / f'fold_{k}.json'}; run every method, or write to "
                    "another --out"
                )
        log_file = a.out / f"fold_{k}.log"

        def log(msg, log_file=log_file):
            print(msg, flush=True)
            with open(log_file, "a") as f:
                f.write(msg + "\n")

        if finished:
            log(
                f"--- re-run with code {report.git_hash()}: finished stages are "
                "evaluated again, new ones trained"
            )

        sensor = None
        if a.sensor_from is not None:
            sensor = fresh.committed_sensor(cfg, a.sensor_from, k)
            log(f"sensor: {a.sensor_from / f'sensor_fold{k}.eqx'} (not trained)")
        result = protocol.run_fold(cfg, k, a.work, a.work / "cache", log, sensor)
        path = protocol.write_fold(a.out, dataclasses.asdict(cfg), result)
        log(f"fold {k} finished in {result['timings']['total_s'] / 60:.1f} min: {path}")
        if not (a.out / "fig_uncertainty.png").exists():
            report.figures(a.out, result, cfg.quick)
    _, table = report.write_summary(a.out, cfg.num_folds)
    if a.docs is not None:
        report.update_docs(a.docs, table)
    if (a.out / "fresh").is_dir():
        table += "\n" + fresh.summarise(a.out)[1]
        if (a.out / "fresh_more").is_dir():  # folds 11..: fresh_more.py
            table += "\n" + fresh_more.summarise(a.out)[1]
        (a.out / "summary.md").write_text(table)
    if any(m.startswith("online_") for m in cfg.methods):
        table += "\n" + online.summarise(a.out)[1]
        (a.out / "summary.md").write_text(table)
    print("\n" + table + f"\nresults in {a.out}")


def main_fresh(cfg: train.Config, a: argparse.Namespace) -> None:
    """`--fresh`: the never-seen set, fold by fold (finished ones skipped)."""
    for k in cfg.test_folds:
        if (a.out / "fresh" / f"fold_{k}.json").exists() and not a.rerun:
            print(f"fold {k}: fresh evaluation already finished, skipped")
            continue
        log_file = a.out / "fresh" / f"fold_{k}.log"
        log_file.parent.mkdir(parents=True, exist_ok=True)

        def log(msg, log_file=log_file):
            print(msg, flush=True)
            with open(log_file, "a") as f:
                f.write(msg + "\n")

        work = a.work / "fresh"
        path = fresh.run(cfg, k, a.out, work, a.work / "cache", log)
        log(f"fold {k}: fresh evaluation written to {path}")
    _, table = report.write_summary(a.out, cfg.num_folds)
    table += "\n" + fresh.summarise(a.out)[1]
    if (a.out / "fresh_more").is_dir():  # folds 11..: fresh_more.py
        table += "\n" + fresh_more.summarise(a.out)[1]
    (a.out / "summary.md").write_text(table)
    print("\n" + table + f"\nresults in {a.out}")


if __name__ == "__main__":
    main()
