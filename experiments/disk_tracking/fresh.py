"""Fresh-data confirmation: every fold's final models on a never-seen test set.

The ten-fold table was built while its test folds were visible (the
out-of-view row was designed after one fold's test numbers). This stage asks
the same models about data that no decision ever saw: "fold 10", 505
sequences from the same generator and seed with the next fold index, which no
training, validation or test split of the protocol uses.

For test fold K it loads the committed sensor (`sensor_foldK.eqx`), trains
every head again from it exactly as the protocol does (validation-selected
checkpoints, same seeds), checks the retrained heads against the committed
`fold_K.json` on fold K's test set, evaluates them once on the fresh set, and
writes `fresh/fold_K.json` and the heads (`heads/fold_K/<method>.eqx`, so the
rows can be evaluated again without training). `fresh.json` pools the
finished folds. Resumable like the protocol (checkpoints under --work).
"""

import json
import os
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import eqsmooth as eqs

from . import data as D, protocol, report, train as T


FRESH_FOLD = D.NUM_FOLDS  # the generator's next fold index: never used by the protocol

# Paired comparisons reported on the fresh set: (extension, our baseline).
PAIRS = (
    ("smoother_hetero_surrogate_learndyn_view", "lstm_bi"),
    ("smoother_hetero_surrogate", "lstm_bi"),
    ("smoother_hetero_surrogate", "lstm_uni"),
    ("smoother_hetero_surrogate", "ekf_hetero_mse"),
    ("smoother_hetero_surrogate_learndyn_view", "smoother_hetero_surrogate"),
    ("smoother_hetero_finetune", "smoother_hetero_surrogate"),
)


def fresh_split(cfg: T.Config, cache_dir: Path | None) -> T.Split:
    """The never-seen set: fold `FRESH_FOLD` of the protocol's generator."""
    if FRESH_FOLD in (cfg.train_folds or range(cfg.num_folds)):
        raise ValueError(f"fold {FRESH_FOLD} is a training fold of this config")
    fold = D.load_fold(
        seed=cfg.data_seed,
        fold=FRESH_FOLD,
        num_sequences=cfg.sequences_per_fold,
        num_frames=cfg.num_frames,
        cache_dir=cache_dir,
    )
    idx = np.arange(fold.num_sequences)
    if cfg.max_test_sequences is not None:
        idx = idx[: cfg.max_test_sequences]
    return T.Split(fold.subset(idx), D.fold_images(fold, cache_dir)[idx])


def committed_sensor(cfg: T.Config, out: Path, fold: int):
    """The virtual sensor of `fold` that the protocol committed under `out`."""
    path = out / f"sensor_fold{fold}.eqx"
    if not path.exists():
        raise FileNotFoundError(f"{path}: run the protocol's fold {fold} first")
    template = T.make_sensor(cfg, jax.random.key(0))
    return eqx.tree_deserialise_leaves(path, template)


def run(cfg: T.Config, fold: int, out: Path, work: Path, cache_dir, log=print) -> Path:
    """Retrain fold `fold`'s heads from its committed sensor, evaluate them on
    the fresh set, write `fresh/fold_K.json` and the heads; return its path."""
    committed = json.loads((out / f"fold_{fold}.json").read_text())["records"]
    sensor = committed_sensor(cfg, out, fold)
    res = protocol.run_fold(cfg, fold, work, cache_dir, log, sensor=sensor)
    fresh = fresh_split(cfg, cache_dir)
    fold_dir = Path(work) / f"fold_{fold}"
    protocol.cached_outputs(sensor, fresh, cfg, fold_dir / "sensor_fresh.npz")
    truth = fresh.fold.positions
    heads = out / "heads" / f"fold_{fold}"
    heads.mkdir(parents=True, exist_ok=True)
    rows = {"virtual_sensor": dict(fresh_rmse=T.rmse(fresh.sensor, truth))}
    for method, model in res["models"].items():
        pred, outcomes = protocol.predict(cfg, method, model, fresh)
        rec = res["records"][method]
        rows[method] = dict(
            fresh_rmse=T.rmse(pred, truth),
            test_rmse=rec["test_rmse"],
            committed_test_rmse=committed.get(method, {}).get("test_rmse"),
            val_rmse=rec["val_rmse"],
            best_step=rec["best_step"],
        )
        if outcomes is not None:
            rows[method]["fresh_solves"] = {
                n: int(np.sum(outcomes == i)) for i, n in enumerate(T.SOLVE_OUTCOMES)
            }
        eqs.learn.atomic_write(
            heads / f"{method}.eqx", lambda f, m=model: eqx.tree_serialise_leaves(f, m)
        )
        log(
            f"fresh {method}: {rows[method]['fresh_rmse']:.3f} px (fold {fold} test "
            f"{rec['test_rmse']:.3f}, committed {rows[method]['committed_test_rmse']})"
        )
    rows["virtual_sensor"]["test_rmse"] = res["records"]["virtual_sensor"]["test_rmse"]
    record = dict(
        benchmark="disk_tracking_fresh",
        fold=fold,
        fresh_fold=FRESH_FOLD,
        fresh_sequences=fresh.n,
        git_hash=res["git_hash"],
        machine=report.machine(),
        load_average=os.getloadavg(),
        timings=res["timings"],
        records=rows,
    )
    path = out / "fresh" / f"fold_{fold}.json"
    path.parent.mkdir(exist_ok=True)
    report.write_json(path, record, report.jsonable)
    return path


def summarise(out: Path) -> tuple[dict, str]:
    """`fresh.json` and its markdown table from every `fresh/fold_K.json`."""
    paths = sorted(
        (out / "fresh").glob("fold_*.json"), key=lambda p: int(p.stem.split("_")[1])
    )
    folds = [json.loads(p.read_text()) for p in paths]
    if not folds:
        raise FileNotFoundError(f"no fresh/fold_K.json under {out}")
    methods = [m for m in report.LABELS if all(m in f["records"] for f in folds)]
    rows, lines = {}, []
    for m in methods:
        recs = [f["records"][m] for f in folds]
        rows[m] = dict(
            fresh=report.mean_se([r["fresh_rmse"] for r in recs]),
            test_retrained=report.mean_se([r["test_rmse"] for r in recs]),
        )
        drift = [
            r["test_rmse"] - r["committed_test_rmse"]
            for r in recs
            if r.get("committed_test_rmse") is not None
        ]
        if drift:  # retrained heads vs the committed fold results, same test set
            rows[m]["max_abs_retrain_drift"] = float(np.max(np.abs(drift)))
        f, t = rows[m]["fresh"], rows[m]["test_retrained"]
        se = lambda s: "" if s["stderr"] is None else f" ± {s['stderr']:.3f}"
        lines.append(
            f"| {report.LABELS[m]} | {f['mean']:.3f}{se(f)} | {t['mean']:.3f}{se(t)} |"
        )
    paired, plines = {}, []
    for a, b in PAIRS:
        if a not in rows or b not in rows:
            continue
        paired[f"{a} - {b}"], line = report.paired(
            report.LABELS[a],
            report.LABELS[b],
            rows[a]["fresh"]["folds"],
            rows[b]["fresh"]["folds"],
        )
        plines.append(line)
    record = dict(
        benchmark="disk_tracking_fresh",
        fresh_fold=FRESH_FOLD,
        folds=[f["fold"] for f in folds],
        rows=rows,
        paired=paired,
    )
    table = (
        f"Fresh-data confirmation: each fold's final models (heads retrained from "
        f"the committed sensors, checkpoints selected on validation) evaluated "
        f"once on a never-seen set (fold {FRESH_FOLD}, "
        f"{folds[0]['fresh_sequences']} sequences), folds {record['folds']}; "
        "per-coordinate RMSE in pixels, mean ± sample std/√n over folds.\n\n"
        "| method | fresh set | own test fold (retrained heads) |\n|---|---|---|\n"
        + "\n".join(lines)
        + "\n\nPaired over folds on the fresh set (negative: the first is better):"
        "\n\n" + report.PAIRED_HEAD + "\n".join(plines) + "\n"
    )
    report.write_json(out / "fresh.json", record)
    return record, table
