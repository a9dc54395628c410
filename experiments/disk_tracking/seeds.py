"""Seed variance: the protocol's key heads trained again from other model seeds.

A difference between two rows means something only if it is larger than
what retraining the same row moves. For a few test folds, the heads of the
key rows are trained again, on the committed sensors (the sensor is not
retrained: this is the heads' seed variance, given the sensor), with other
model seeds (initialisation and batch order):

    python -m experiments.disk_tracking --sensor-from results/disk \\
        --model-seed S --folds 0 1 2 --methods ... \\
        --out results/disk_seeds/seedS --work runs/disk_seedS

`summarise` reads them beside seed 0 (the committed `fold_K.json` under the
protocol's folder) and, where the fresh-data stage exists, seed 0 trained
again (`fresh/fold_K.json`: same seed, same sensor, another process), and
writes `seeds.json` and `seeds.md` under the seeds' folder.
"""

import json
from pathlib import Path

import numpy as np

import eqsmooth as eqs

from . import report


# Paired differences whose seed spread is reported: (extension, baseline).
PAIRS = (
    ("smoother_hetero_surrogate_learndyn_view", "lstm_bi"),
    ("smoother_hetero_surrogate", "lstm_bi"),
    ("smoother_hetero_surrogate", "ekf_hetero_mse"),
    ("smoother_hetero_surrogate_learndyn_view", "smoother_hetero_surrogate"),
)


def _seed_dirs(root: Path) -> dict[int, Path]:
    dirs = {}
    for p in root.glob("seed*"):
        if p.is_dir() and p.name[4:].isdigit():
            dirs[int(p.name[4:])] = p
    return dict(sorted(dirs.items()))


def _runs(base: Path, root: Path) -> dict[str, dict[int, dict[str, float]]]:
    """{run name: {fold: {method: test RMSE}}}: seed 0 as committed, seed 0
    trained again (the fresh stage), and each seed folder."""
    runs: dict[str, dict[int, dict[str, float]]] = {}
    runs["seed 0"] = {
        f["fold"]: {m: r["test_rmse"] for m, r in f["records"].items()}
        for f in report.load_folds(base)
    }
    fresh = sorted((base / "fresh").glob("fold_*.json"))
    if fresh:
        runs["seed 0 again"] = {}
        for p in fresh:
            f = json.loads(p.read_text())
            runs["seed 0 again"][f["fold"]] = {
                m: r["test_rmse"] for m, r in f["records"].items()
            }
    for seed, d in _seed_dirs(root).items():
        if seed == 0:
            continue
        runs[f"seed {seed}"] = {
            f["fold"]: {m: r["test_rmse"] for m, r in f["records"].items()}
            for f in report.load_folds(d)
        }
    return runs


def _spread(values: dict[str, dict[int, float]], folds: list[int]) -> dict:
    """Per run: the mean over `folds`; and the within-fold sample std across
    runs, pooled over folds (root mean of the per-fold variances)."""
    names = list(values)
    table = np.array([[values[n][k] for k in folds] for n in names])  # runs × folds
    within = float(np.sqrt(np.mean(table.var(axis=0, ddof=1))))
    return dict(
        runs=names,
        folds=folds,
        values=table.tolist(),
        mean_per_run=table.mean(axis=1).tolist(),
        within_fold_seed_std=within,
        between_fold_std_seed0=(
            float(table[0].std(ddof=1)) if len(folds) > 1 else None
        ),
    )


def summarise(base: Path, root: Path) -> tuple[dict, str]:
    """`seeds.json` and `seeds.md` under `root` (folders `seedS` of
    protocol runs with `--model-seed S`), against seed 0 under `base`.

    Only folds and methods present in every run are used. Raises
    `FileNotFoundError` when `root` has no finished seed run."""
    base, root = Path(base), Path(root)
    runs = _runs(base, root)
    if not any(runs[n] for n in runs if n not in ("seed 0", "seed 0 again")):
        raise FileNotFoundError(f"no seedS/fold_K.json (S > 0) under {root}")
    folds = sorted(set.intersection(*(set(r) for r in runs.values())))
    if not folds:
        raise FileNotFoundError(f"no fold is finished in every run under {root}")
    # The sensor is the same in every run (not a head): left out.
    methods = [
        m
        for m in report.LABELS
        if m != "virtual_sensor" and all(m in runs[n][k] for n in runs for k in folds)
    ]
    rows = {
        m: _spread({n: {k: runs[n][k][m] for k in folds} for n in runs}, folds)
        for m in methods
    }
    pairs = {}
    for a, b in PAIRS:
        if a in rows and b in rows:
            diff = {n: {k: runs[n][k][a] - runs[n][k][b] for k in folds} for n in runs}
            s = _spread(diff, folds)
            signs = np.sign(np.array(s["values"]))
            s["same_sign_everywhere"] = bool(np.all(signs == signs.flat[0]))
            s["negative_cells"] = int(np.sum(signs < 0))
            s["cells"] = int(signs.size)
            pairs[f"{a} - {b}"] = s
    names = list(runs)
    head = "| row | " + " | ".join(names) + " | seed std within a fold |"
    rule = "|---" * (len(names) + 2) + "|"
    lines = [
        f"Seed variance of the heads on the committed sensors, test folds "
        f"{folds}: test RMSE (px) averaged over those folds per run, and the "
        "sample std across runs within a fold, pooled over the folds. "
        "`seed 0` is the committed protocol; `seed 0 again` the same seed "
        "trained again by the fresh-data stage; the other seeds change "
        "the heads' initialisation and batch order.",
        "",
        head,
        rule,
    ]
    for m, s in rows.items():
        cells = [f"{v:.3f}" for v in s["mean_per_run"]]
        lines.append(
            f"| {report.LABELS[m]} | "
            + " | ".join(cells)
            + f" | {s['within_fold_seed_std']:.3f} |"
        )
    lines += [
        "",
        "Paired differences (negative: the first is better), averaged over the "
        "folds per run; the seed std of the per-fold difference; and the "
        "(fold, run) cells where it is negative:",
        "",
        "| difference | "
        + " | ".join(names)
        + " | seed std within a fold | cells below 0 |",
        "|---" * (len(names) + 3) + "|",
    ]
    for key, s in pairs.items():
        a, b = key.split(" - ")
        cells = [f"{v:+.3f}" for v in s["mean_per_run"]]
        lines.append(
            f"| {report.LABELS[a]} − {report.LABELS[b]} | "
            + " | ".join(cells)
            + f" | {s['within_fold_seed_std']:.3f} | {s['negative_cells']}/"
            f"{s['cells']} |"
        )
    record = dict(
        benchmark="disk_tracking_seeds",
        base=str(base),
        runs=names,
        folds=folds,
        rows=rows,
        paired=pairs,
    )
    text = "\n".join(lines) + "\n"
    report.write_json(root / "seeds.json", record)
    eqs.learn.atomic_write(root / "seeds.md", lambda f: f.write(text.encode()))
    return record, text
