"""Is the covariance right? NLL, NEES and coverage of the disk estimators.

A smoother (and an EKF) returns a covariance with every estimate; this
module scores it against the ground truth, frame by frame, on the 2-D
position marginal `N(p̂_t, Σ_t)` (`Σ_t` the 2 x 2 position block: the
Laplace marginal `(JᵀJ)⁻¹` of the smoother at its MAP,
[`eqsmooth.marginal_covariances`][]; the EKF's filtered covariance):

- NLL: `½ eᵀΣ⁻¹e + ½ log det Σ + log 2π` nats per frame, `e = p − p̂`;
- NEES: `eᵀΣ⁻¹e`, χ²(2)-distributed when the estimator is consistent;
- coverage at level `q`: the fraction of frames with `NEES ≤ χ²₂⁻¹(q)
  = −2 log(1 − q)` (the ellipse holding `q` of the predicted mass).

Frame 0 is left out: every estimator is given the true first state (a tight
prior), so its error there says nothing. The consistency band of a
sequence: its mean NEES over the `T' = 19` scored frames lies inside
`[χ²_{2T'}(0.025), χ²_{2T'}(0.975)] / T'` (the band a consistent estimator
with independent frame errors meets 95% of the time; a smoother's errors are
correlated in time, so the band is nominal). The frame band:
`χ²₂(0.025) ≤ NEES ≤ χ²₂(0.975)` (95% for a consistent estimator).

`fresh_more.py` computes these per sequence while it scores the heads;
`summarise` pools them into `uncertainty.json` and draws the calibration
figure.
"""

from pathlib import Path

import numpy as np

from .._uncertainty import fold_summary as fold_summary, LEVELS, sequence_scores
from . import report


FIRST_SCORED_FRAME = 1

# Probabilistic rows with committed heads (no fixed-lag heads are committed).
PROBABILISTIC = (
    "smoother_hetero_surrogate",
    "smoother_hetero_nll",
    "smoother_hetero_implicit",
    "smoother_hetero_surrogate_learndyn",
    "smoother_hetero_surrogate_learndyn_view",
    "smoother_hetero_finetune",
    "smoother_const_surrogate",
    "smoother_const_nll",
    "ekf_hetero_mse",
    "ekf_hetero_nll",
    "ekf_const_mse",
    "ekf_const_nll",
)

# Paired over folds: (extension, our baseline).
PAIRS = (
    ("smoother_hetero_surrogate", "ekf_hetero_mse"),
    ("smoother_hetero_nll", "ekf_hetero_nll"),
    ("smoother_hetero_nll", "smoother_hetero_surrogate"),
    ("smoother_hetero_surrogate_learndyn", "smoother_hetero_surrogate"),
    ("smoother_hetero_surrogate_learndyn_view", "smoother_hetero_surrogate"),
    ("smoother_hetero_finetune", "smoother_hetero_surrogate"),
    ("smoother_hetero_surrogate", "smoother_const_surrogate"),
    ("ekf_hetero_nll", "ekf_hetero_mse"),
)


def gaussian_scores(pred, cov, truth) -> dict:
    """Per-sequence scores of positions `pred (N, T, 2)` with covariances
    `cov (N, T, 2, 2)` against `truth (N, T, 2)`, frames from
    `FIRST_SCORED_FRAME` on ([`eqsmooth.learn.gaussian_calibration`][] per
    frame, `experiments._uncertainty.sequence_scores` per sequence). A
    sequence with a covariance that is not finite and positive definite on
    some frame is `valid = False` (its scores NaN)."""
    s = slice(FIRST_SCORED_FRAME, None)
    e = np.asarray(truth, np.float64)[:, s] - np.asarray(pred, np.float64)[:, s]
    return sequence_scores(e, np.asarray(cov, np.float64)[:, s], LEVELS)


def _rows(folds: list[dict], section: str) -> dict[str, list[dict]]:
    """`{method: [fold summary, ...]}` over `folds` (pair files) of one section."""
    out: dict[str, list[dict]] = {}
    for f in folds:
        for m, s in f.get(section, {}).get("uncertainty", {}).items():
            out.setdefault(m, []).append(s)
    return out


def _table(rows: dict[str, list[dict]], n: int) -> dict:
    keys = ("nll", "nees", "sequences_in_band", "frames_in_band")
    table = {}
    for m in PROBABILISTIC:
        recs = rows.get(m, [])
        if len(recs) != n:
            continue
        table[m] = {k: report.mean_se([r[k] for r in recs]) for k in keys}
        for q in ("0.68", "0.95"):
            table[m][f"coverage_{q}"] = report.mean_se([r["coverage"][q] for r in recs])
        table[m]["invalid_sequences"] = int(sum(r["invalid_sequences"] for r in recs))
    return table


def _paired(table: dict) -> dict:
    out = {}
    for a, b in PAIRS:
        if a not in table or b not in table:
            continue
        row = {}
        for k in ("nll", "nees", "coverage_0.95"):
            d = np.asarray(table[a][k]["folds"]) - np.asarray(table[b][k]["folds"])
            s = report.mean_se(d)
            if k == "nll":
                s["better_folds"] = int(np.sum(d < 0))
            else:  # closer to the nominal value
                nominal = 2.0 if k == "nees" else 0.95
                da = np.abs(np.asarray(table[a][k]["folds"]) - nominal)
                db = np.abs(np.asarray(table[b][k]["folds"]) - nominal)
                s["closer_to_nominal_folds"] = int(np.sum(da < db))
            row[k] = s
        out[f"{a} - {b}"] = row
    return out


def calibration_figure(rows: dict[str, list[dict]], path: Path, title: str) -> None:
    """Expected vs observed coverage, pooled (mean) over folds, per method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.2, 5.2))
    ax.plot([0, 1], [0, 1], "k:", lw=1, label="calibrated")
    colours = plt.get_cmap("tab20").colors
    for i, m in enumerate(PROBABILISTIC):
        if m not in rows:
            continue
        obs = [np.mean([r["coverage"][str(q)] for r in rows[m]]) for q in LEVELS]
        style = "-" if m.startswith("smoother") else "--"
        ax.plot(LEVELS, obs, style, color=colours[i], marker="o", ms=3, lw=1.2, label=m)
    ax.set_xlabel("expected coverage (χ²₂ ellipse of the position marginal)")
    ax.set_ylabel("observed coverage of the true position")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def summarise(out: Path, folds: list[dict]) -> dict:
    """`uncertainty.json` and `fig_calibration.png` under `out` from the pair
    files of `fresh_more.py` (`folds`)."""
    record: dict = dict(
        benchmark="disk_tracking_uncertainty",
        definitions=dict(
            marginal="2-D position marginal N(p̂_t, Σ_t): smoothers, the Laplace "
            "marginal (JᵀJ)⁻¹ at the MAP (eqsmooth.marginal_covariances, "
            "BlockTridiagonal selected inversion), position block; EKFs, the "
            "filtered covariance's position block",
            frames=f"frames {FIRST_SCORED_FRAME}..T-1 of each sequence (frame 0 "
            "is given to every estimator as the true first state)",
            nll="½ eᵀΣ⁻¹e + ½ log det Σ + log 2π, nats per frame (mean over the "
            "scored frames of a sequence, then over sequences)",
            nees="eᵀΣ⁻¹e per frame (2 for a consistent estimator); `nees` is the "
            "mean over sequences of each sequence's mean NEES",
            sequences_in_band="fraction of sequences whose mean NEES over its "
            "T'=19 scored frames lies in [χ²_{2T'}(0.025), χ²_{2T'}(0.975)]/T' = "
            "[1.20, 2.99] (eqsmooth.learn.nees_band(2, 19); before 2026-11-29 "
            "this text said [1.36, 2.78], which was wrong: the scores always used "
            "[1.20, 2.99]) (95% for a consistent estimator with independent frame "
            "errors; smoother errors are correlated in time, so nominal)",
            frames_in_band="fraction of frames with χ²₂(0.025) ≤ NEES ≤ "
            "χ²₂(0.975) (0.95 for a consistent estimator)",
            coverage="fraction of frames with NEES ≤ χ²₂⁻¹(q) = −2 log(1−q), "
            "q in LEVELS",
            invalid_sequences="sequences with a non-finite or non-positive-"
            "definite covariance on some frame, left out of the means",
            paired="a − b over folds, mean ± sample std/√n; NLL: folds where a is "
            "lower; NEES and 95% coverage: folds where a is closer to nominal "
            "(2, 0.95)",
        ),
        levels=list(LEVELS),
        not_scored=dict(
            lstm_uni="the LSTMs output no variance",
            lstm_bi="the LSTMs output no variance; a variance head on the "
            "bi-LSTM (issue 58) was not trained: not done",
            online_hetero_lagL="no fixed-lag heads are committed "
            "(results/disk_online has only their RMSE): not scored",
        ),
    )
    for section, label in (("test", "test_folds"), ("fresh", "fresh_folds")):
        done = [f for f in folds if f.get(section, {}).get("uncertainty")]
        if not done:
            continue
        rows = _rows(done, section)
        table = _table(rows, len(done))
        record[label] = dict(
            folds=[f[section]["fold"] for f in done],
            heads_of_test_fold=[f["heads_fold"] for f in done],
            sequences_per_fold=done[0][section]["sequences"],
            rows=table,
            paired=_paired(table),
            per_fold={m: rows[m] for m in table},
        )
    test = [f for f in folds if f.get("test", {}).get("uncertainty")]
    if test:
        calibration_figure(
            _rows(test, "test"),
            out / "fig_calibration.png",
            f"disk: calibration on the test folds "
            f"{','.join(str(f['heads_fold']) for f in test)} (mean over folds)",
        )
    report.write_json(out / "uncertainty.json", record)
    return record


def markdown(record: dict) -> str:
    """The tables of `uncertainty.json`: per row, mean ± se over folds."""

    def ms(s, digits=3):
        se = "" if s["stderr"] is None else f" ± {s['stderr']:.{digits}f}"
        return f"{s['mean']:.{digits}f}{se}"

    parts = []
    for label in ("test_folds", "fresh_folds"):
        if label not in record:
            continue
        r = record[label]
        lines = [
            f"Position marginals on the {label.replace('_', ' ')} {r['folds']} "
            f"({r['sequences_per_fold']} sequences each), mean ± se over folds:",
            "",
            "| row | NLL (nats/frame) | NEES | 68% coverage | 95% coverage "
            "| sequences in NEES band |",
            "|---|---|---|---|---|---|",
        ]
        for m, row in r["rows"].items():
            lines.append(
                f"| {report.LABELS[m]} | {ms(row['nll'])} | {ms(row['nees'], 2)} | "
                f"{ms(row['coverage_0.68'])} | {ms(row['coverage_0.95'])} | "
                f"{ms(row['sequences_in_band'])} |"
            )
        lines += [
            "",
            "| a − b | ΔNLL | folds a lower | Δ95% coverage |",
            "|---|---|---|---|",
        ]
        for k, d in r["paired"].items():
            lines.append(
                f"| {k} | {ms(d['nll'])} | {d['nll']['better_folds']}/"
                f"{len(r['folds'])} | {ms(d['coverage_0.95'])} |"
            )
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"
