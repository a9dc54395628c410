"""Pool the fold files into the summary: per-fold values and paired
differences against the metadata row."""

import json
from pathlib import Path

import numpy as np


BASELINE = "metadata"
METRICS = ("rms_horizontal_m", "max_horizontal_m", "nll")


def write_summary(out: Path) -> dict:
    files = sorted(out.glob("fold_*.json"))
    folds = [json.loads(f.read_text()) for f in files]
    folds = [f for f in folds if not f["config"].get("quick")]
    if not folds:
        raise SystemExit(f"no fold files of the declared protocol in {out}")
    rows = list(folds[0]["rows"])
    summary = {"folds": [f["fold"] for f in folds], "rows": {}, "paired": {}}
    for row in rows:
        summary["rows"][row] = {m: [f["rows"][row][m] for f in folds] for m in METRICS}
        summary["rows"][row]["sigmas"] = [f["rows"][row]["sigmas"] for f in folds]
    for row in rows:
        if row == BASELINE:
            continue
        summary["paired"][row] = {}
        for m in METRICS:
            d = np.array(summary["rows"][row][m]) - np.array(
                summary["rows"][BASELINE][m]
            )
            summary["paired"][row][m] = {
                "differences": d.tolist(),
                "mean": float(d.mean()),
                "folds_better": int(np.sum(d < 0)),
                "folds": int(d.size),
            }
    summary["best_steps"] = [f["training"]["best_step"] for f in folds]
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (out / "summary.md").write_text(markdown(summary))
    return summary


def markdown(s: dict) -> str:
    lines = [
        "# KITTI IMU + GPS outages: summary",
        "",
        "From the committed `fold_<f>.json` files (`python -m experiments.kitti_imu "
        "--summary`); protocol in `protocol.md`. Errors against the withheld GPS "
        "fixes (the only ground truth), horizontal, metres; NLL in nats per fix.",
        "",
        "| fold | row | RMS (m) | max (m) | NLL |",
        "|---|---|---|---|---|",
    ]
    for i, fold in enumerate(s["folds"]):
        for row, v in s["rows"].items():
            lines.append(
                f"| {fold} | {row} | {v['rms_horizontal_m'][i]:.3f} | "
                f"{v['max_horizontal_m'][i]:.3f} | {v['nll'][i]:.3f} |"
            )
    lines += [
        "",
        f"Paired over {len(s['folds'])} folds, row minus metadata "
        "(negative: the row is better):",
        "",
        "| row | metric | mean difference | folds better | per fold |",
        "|---|---|---|---|---|",
    ]
    for row, metrics in s["paired"].items():
        for m, d in metrics.items():
            per = ", ".join(f"{x:+.3f}" for x in d["differences"])
            lines.append(
                f"| {row} | {m} | {d['mean']:+.3f} | {d['folds_better']}/"
                f"{d['folds']} | {per} |"
            )
    lines += ["", f"Selected training steps per fold: {s['best_steps']}", ""]
    return "\n".join(lines)
