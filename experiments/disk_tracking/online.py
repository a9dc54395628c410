"""The online rows (issue 38): fixed-lag smoothers beside the EKF and the
batch smoother on the same folds, sensors and test sets, with latency.

Run by the protocol with `--methods ... online_hetero_lag<L> ...
--sensor-from results/disk` (the committed sensors, so the rows share the
sensor of the ten-fold table). `summarise` pools the folds of such a run:
test RMSE (mean ± sample std/√n over folds), the delayed estimates' RMSE,
inference time per frame (one test sequence as a batch of 32 copies,
compiled; median over folds), training minutes, and paired differences per
fold.
"""

from pathlib import Path

import numpy as np

from . import report


FILTER, BATCH = "ekf_hetero_mse", "smoother_hetero_surrogate"


def _online_methods(folds: list[dict]) -> list[str]:
    names = {m for f in folds for m in f["records"] if m.startswith("online_")}
    return sorted(names, key=lambda m: int(m.rsplit("lag", 1)[1]))


def summarise(out: Path) -> tuple[dict, str]:
    """`online.json` and its markdown table from every `fold_K.json` under
    `out` (a run with online methods)."""
    folds = report.load_folds(out)
    online = _online_methods(folds)
    if not folds or not online:
        raise FileNotFoundError(f"no fold_K.json with online methods under {out}")
    methods = [
        m
        for m in report.LABELS
        if m != "virtual_sensor" and all(m in f["records"] for f in folds)
    ]
    rows, lines = {}, []
    for m in methods:
        recs = [f["records"][m] for f in folds]
        s = report.mean_se([r["test_rmse"] for r in recs])
        lat = [r["latency_ms_per_step"] for r in recs if "latency_ms_per_step" in r]
        rows[m] = dict(
            test_rmse=s,
            latency_ms_per_step=float(np.median(lat)) if lat else None,
            train_minutes=float(np.median([r["seconds"] for r in recs]) / 60),
        )
        delayed = "—"
        if all("lagged_test_rmse" in r for r in recs):
            d = rows[m]["lagged_test_rmse"] = report.mean_se(
                [r["lagged_test_rmse"] for r in recs]
            )
            delayed = f"{d['mean']:.3f}" + (
                "" if d["stderr"] is None else f" ± {d['stderr']:.3f}"
            )
        se = "" if s["stderr"] is None else f" ± {s['stderr']:.3f}"
        latency = "—" if not lat else f"{np.median(lat):.3f}"
        lines.append(
            f"| {report.LABELS[m]} | {s['mean']:.3f}{se} | {delayed} | {latency} | "
            f"{rows[m]['train_minutes']:.1f} |"
        )
    paired, plines = {}, []
    # (first, its column, second, its column): online vs the filter, the
    # batch smoother vs online, the delayed estimates vs the batch smoother
    pairs = [(m, "test_rmse", FILTER, "test_rmse") for m in online]
    pairs += [(BATCH, "test_rmse", m, "test_rmse") for m in online]
    pairs += [(m, "lagged_test_rmse", BATCH, "test_rmse") for m in online]
    for a, ca, b, cb in pairs:
        if ca not in rows.get(a, {}) or cb not in rows.get(b, {}):
            continue
        delayed = " (delayed)" if ca == "lagged_test_rmse" else ""
        paired[f"{a}{delayed} - {b}"], line = report.paired(
            report.LABELS[a] + delayed,
            report.LABELS[b],
            rows[a][ca]["folds"],
            rows[b][cb]["folds"],
        )
        plines.append(line)
    record = dict(
        benchmark="disk_tracking_online",
        folds=[f["fold"] for f in folds],
        git_hashes=sorted({f["git_hash"] for f in folds}),
        rows=rows,
        paired=paired,
    )
    table = (
        f"Online rows: test folds {record['folds']}, the committed sensors, "
        "checkpoints selected on validation; per-coordinate test RMSE in pixels "
        "(mean ± sample std/√n over folds), inference time per frame after "
        "compilation for one test sequence run as the evaluation's batch of 32 "
        "copies (sensor outputs cached; median over folds; not a single "
        "sequence's latency), training minutes (median). The EKF and the "
        "fixed-lag smoothers answer at each frame; the batch smoother only "
        "after the whole sequence. The delayed column scores a fixed-lag "
        "smoother's estimate of each frame once `lag - 1` more frames have come "
        "in (the last frames of a sequence: at its end).\n\n"
        "| method | test RMSE | delayed: each frame when it leaves the window | "
        "ms per frame | training min |\n|---|---|---|---|---|\n"
        + "\n".join(lines)
        + "\n\nPaired over folds (negative: the first is better):\n\n"
        + report.PAIRED_HEAD
        + "\n".join(plines)
        + "\n"
    )
    report.write_json(out / "online.json", record)
    return record, table
