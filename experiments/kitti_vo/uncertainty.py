"""Is the covariance right? NLL, NEES and coverage of the KITTI estimators (issue 58).

Only the virtual sensors of the KITTI folds are committed
(`results/kitti/sensor_foldK.eqx`); the noise heads, EKFs and LSTMs were not
saved. `run_fold` (the CLI's `--uncertainty`) loads the committed sensor,
trains the probabilistic rows again with the fold's committed configuration
and seeds (the same `experiment.train_method` as the protocol), checks
their test scores against the committed `fold_K.json`, saves the trained
heads under `heads/foldK/` and scores each row's marginals on the test
windows (length 100; frame 0 is given to every estimator as the true first
state, so frames 1..99 are scored):

- planar position `(x, y)` (d = 2), the quantity behind the translation
  metric, and heading `θ` (d = 1), behind the rotation metric;
- smoothers: the Laplace marginal `(JᵀJ)⁻¹` at the MAP
  ([`eqsmooth.marginal_covariances`][]' selected inversion), EKFs: the
  filtered covariance; both live in the right-perturbation tangent
  `(ρ_x, ρ_y, δθ)` of the estimated pose, so the position block is rotated
  into the window frame, `R(θ̂) Σ_ρρ R(θ̂)ᵀ` (first order);
- `lstm_bi_var`: the bi-LSTM with a Gaussian variance head
  (`models.LstmVarianceOdometry`), a new row; the committed `lstm_bi` row
  is unchanged and has no variance.

The per-frame scores are [`eqsmooth.learn.gaussian_calibration`][]'s; the
per-window and per-fold pooling is `experiments._uncertainty`'s (shared with
disk tracking). `summarise` pools the finished folds into `uncertainty.json`
and draws `fig_calibration.png`. The KITTI experiment has no fixed-lag row.
"""

import dataclasses
import functools
import json
import math
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs
from eqsmooth.solve._posterior._marginals import _marginal_covariances

from .._provenance import git_hash
from .._uncertainty import fold_summary, LEVELS, sequence_scores
from . import data as D, experiment as E, models as M


LSTM_VARIANCE = "lstm_bi_var"
# Trained again and scored, in this order (the key comparison first).
METHODS = (
    "smoother_hetero_e2e",
    "smoother_const_e2e",
    "ekf_hetero",
    "ekf_const",
    "smoother_hetero_nll",
    "smoother_const_nll",
    LSTM_VARIANCE,
    "smoother_hetero_e2e_vel",
    "smoother_const_e2e_vel",
)
MARGINALS = {"position": (0, 1), "heading": (2,)}
FIRST_SCORED_FRAME = 1

# Paired over folds: (extension, our baseline).
PAIRS = (
    ("smoother_hetero_e2e", "smoother_const_e2e"),
    ("smoother_hetero_nll", "smoother_const_nll"),
    ("ekf_hetero", "ekf_const"),
    ("smoother_hetero_e2e", "ekf_hetero"),
    ("smoother_const_e2e", "ekf_const"),
    ("smoother_hetero_nll", "smoother_hetero_e2e"),
    ("smoother_hetero_e2e", LSTM_VARIANCE),
    ("smoother_hetero_nll", LSTM_VARIANCE),
)


def lstm_variance_key(fold_key):
    """The bi-LSTM variance row's keys: its mean network starts where the
    committed `lstm_bi` row's did (the same key), the head from the next
    key after `experiment.METHODS`."""
    return (
        E.method_key(fold_key, "lstm_bi"),
        jax.random.fold_in(fold_key, 10 + len(E.METHODS)),
    )


def build_model(method: str, sigmas, fold_key):
    if method == LSTM_VARIANCE:
        return M.LstmVarianceOdometry(*lstm_variance_key(fold_key))
    return E.build_model(method, sigmas, E.method_key(fold_key, method))


def loss_pair(method: str, cfg: E.Config):
    if method == LSTM_VARIANCE:
        return M.lstm_variance_loss, M.lstm_variance_loss
    return E.losses(method, cfg)


# ---------------------------------------------------------------------------
# Estimates with covariances
# ---------------------------------------------------------------------------


def _to_window_frame(est: jax.Array, pose_cov: jax.Array) -> jax.Array:
    """Planar covariance `(T, 3, 3)` in the window frame from the pose block
    `(T, 3, 3)` of the right-perturbation tangent at the estimate `(T, 3)`."""
    c, s = jnp.cos(est[:, 2]), jnp.sin(est[:, 2])
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    g = jnp.stack(
        [
            jnp.stack([c, -s, zero], -1),
            jnp.stack([s, c, zero], -1),
            jnp.stack([zero, zero, one], -1),
        ],
        -2,
    )
    return g @ pose_cov @ jnp.swapaxes(g, -1, -2)


def _one_with_covariance(kind: str, model, w):
    if kind == "lstm":
        est, cov = model.planar_and_covariance(w)
        return est, cov, jnp.all(jnp.isfinite(cov))
    if kind == "ekf":
        sol = M.run_ekf(model, w)
        est = M.planar_pose(sol.mean)
        pose_cov = sol.covariance[:, :3, :3]
        return est, _to_window_frame(est, pose_cov), jnp.all(jnp.isfinite(pose_cov))
    xs = M.smooth(model, w)
    lin = eqs.solve.linearize(model.graph(w), {"x": xs})
    blocks, ok = _marginal_covariances(lin, None, ("x",))
    est = M.planar_pose(xs)
    pose_cov = jnp.where(ok, blocks["x"][:, :3, :3], jnp.nan)
    return est, _to_window_frame(est, pose_cov), ok


@functools.cache
def _batched(kind: str):
    return eqx.filter_jit(
        lambda m, w: jax.vmap(lambda x: _one_with_covariance(kind, m, x))(w)
    )


def estimate_with_covariance(method: str, model, windows: dict, batch: int = 8):
    """Planar estimates `(N, T, 3)`, their covariances `(N, T, 3, 3)` in the
    window frame and whether each window's covariance came out (N,)."""
    kind = "lstm" if method == LSTM_VARIANCE else E.estimator_kind(method)
    fn = _batched(kind)
    n = windows["z"].shape[0]
    outs = []
    for i in range(0, n, batch):
        idx = np.arange(i, min(i + batch, n))
        idx = np.concatenate([idx, np.repeat(idx[-1:], batch - idx.size)])
        w = {k: jnp.asarray(v[idx]) for k, v in windows.items()}
        outs.append([np.asarray(a)[: min(batch, n - i)] for a in fn(model, w)])
    return tuple(np.concatenate([o[k] for o in outs]) for k in range(3))


def truth_planar(windows: dict) -> np.ndarray:
    return np.asarray(M.planar_pose(M.truth_state(jax.tree.map(jnp.asarray, windows))))


def score(est, cov, truth) -> dict:
    """`{marginal: fold summary}` over frames `FIRST_SCORED_FRAME..`."""
    s = slice(FIRST_SCORED_FRAME, None)
    err = np.asarray(truth, np.float64)[:, s] - np.asarray(est, np.float64)[:, s]
    err[..., 2] = np.mod(err[..., 2] + np.pi, 2 * np.pi) - np.pi
    out = {}
    for name, idx in MARGINALS.items():
        i = np.asarray(idx)
        c = cov[:, s][..., i[:, None], i[None, :]]
        out[name] = fold_summary(sequence_scores(err[..., i], c, LEVELS))
    return out


def window_metrics(est: np.ndarray, truth: np.ndarray) -> dict:
    """The experiment's test metrics (`experiment._row`'s means) of planar
    estimates."""
    m = np.array(
        [
            D.window_metrics(e, t) + D.whole_window_metrics(e, t)
            for e, t in zip(est, truth)
        ]
    )
    keys = (
        "trans_m_per_m",
        "rot_deg_per_m",
        "trans_m_per_m_whole",
        "rot_deg_per_m_whole",
    )
    return {k: float(np.mean(m[:, i])) for i, k in enumerate(keys)}


def reproduction(method: str, now: dict, committed: dict) -> dict:
    """The retrained row's test scores against the committed `fold_K.json`
    row (its fields of record, and `whole_window_from`, the scores of a
    model retrained by a later run, where present)."""
    old = committed.get("rows", {}).get(method)
    out: dict = {"now": now}
    if old is None:
        out["committed"] = None
        return out
    out["committed"] = {k: old.get(k) for k in now}
    out["difference"] = {
        k: None if old.get(k) is None else now[k] - old[k] for k in now
    }
    if "whole_window_from" in old:
        ref = old["whole_window_from"]
        out["committed_retrain"] = {
            k: ref[k] for k in ("trans_m_per_m", "rot_deg_per_m", "git", "best_step")
        }
        out["difference_retrain"] = {
            k: now[k] - ref[k] for k in ("trans_m_per_m", "rot_deg_per_m")
        }
    return out


# ---------------------------------------------------------------------------
# A fold
# ---------------------------------------------------------------------------


def _save_head(path: Path, model) -> None:
    eqs.learn.atomic_write(path, lambda f: eqx.tree_serialise_leaves(f, model))


def run_fold(cfg: E.Config, fold: int, out: Path) -> dict | None:
    """Train the probabilistic rows of fold `fold` again (the committed
    sensor `out/sensor_foldK.eqx` is loaded, never trained), score their
    marginals and write `out/uncertainty_fold_K.json` after each row, the
    heads to `out/heads/foldK/<method>.eqx`. A fold whose file lists every
    method is skipped (returns None); a killed run loses at most the row in
    progress (heads already saved are loaded, not trained again)."""
    out = Path(out)
    path = out / f"uncertainty_fold_{fold}.json"
    record = json.loads(path.read_text()) if path.exists() else {}
    # The configuration's methods that have a covariance, and the bi-LSTM
    # variance row.
    methods = [m for m in METHODS if m in cfg.methods or m == LSTM_VARIANCE]
    if all(m in record.get("rows", {}) for m in methods):
        print(f"fold {fold}: {path} has every row; skipped")
        return None
    fold_path = out / f"fold_{fold}.json"
    committed = json.loads(fold_path.read_text()) if fold_path.exists() else {}
    record.update(
        benchmark="kitti_vo_uncertainty",
        label=E.label(cfg),
        fold=fold,
        config=dataclasses.asdict(cfg),
        git=git_hash(),
        machine=E._machine(),
        committed_fold_git=committed.get("git"),
        levels=list(LEVELS),
        first_scored_frame=FIRST_SCORED_FRAME,
        marginals={k: list(v) for k, v in MARGINALS.items()},
        methods=methods,
    )
    record.setdefault("rows", {})
    timings = record.setdefault("timings", {})
    # Every run of this fold (a first one and any resumed ones) records its
    # wall time; the fold's total is their sum.
    run = {"started": time.strftime("%Y-%m-%dT%H:%M:%S"), "git": record["git"]}
    record.setdefault("runs", []).append(run)
    heads = out / "heads" / f"fold{fold}"
    work = out / "work" / f"fold_{fold}" / "uncertainty"
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()

    def save():
        run["wall_s"] = time.perf_counter() - t0
        timings["total_s"] = sum(r["wall_s"] for r in record["runs"])
        E._write_json(path, record)

    data = E.prepare_fold(cfg, fold, out, timings, train_sensor=False)
    train_w, valid_w, test_w = data["train"], data["valid"], data["test"]
    truth = truth_planar(test_w)
    fold_key = jax.random.key(cfg.model_seed + 1000 * fold)
    for method in methods:
        if method in record["rows"]:
            continue
        template = build_model(method, data["sigmas"], fold_key)
        head_path = heads / f"{method}.eqx"
        train_s, best_step = None, None
        if head_path.exists():
            model = eqx.tree_deserialise_leaves(head_path, template)
        else:
            res, train_s = E.train_method(
                cfg,
                fold_key,
                method,
                data["sigmas"],
                train_w,
                valid_w,
                work,
                model=template,
                loss_pair=loss_pair(method, cfg),
            )
            model, best_step = res.best_model, res.best_step
            _save_head(head_path, model)
        t1 = time.perf_counter()
        est, cov, ok = estimate_with_covariance(method, model, test_w)
        scores = score(est, cov, truth)
        eval_s = time.perf_counter() - t1
        now = window_metrics(est, truth)
        record["rows"][method] = {
            **scores,
            "windows_with_covariance": int(ok.sum()),
            "windows": int(ok.size),
            "test_scores": reproduction(method, now, committed),
            "best_step": best_step,
            "train_s": train_s,
            "eval_s": eval_s,
            "head": str(head_path.relative_to(out)),
            "head_bytes": head_path.stat().st_size,
        }
        p = scores["position"]
        print(
            f"{method}: {now['trans_m_per_m']:.4f} m/m; position NLL "
            f"{p['nll']:.3f}, NEES {p['nees']:.2f}, coverage 68% "
            f"{p['coverage']['0.68']:.3f} 95% {p['coverage']['0.95']:.3f}"
        )
        save()
    save()
    return record


# ---------------------------------------------------------------------------
# Pooling the finished folds
# ---------------------------------------------------------------------------


def mean_se(xs) -> dict:
    a = np.asarray(xs, np.float64)
    se = float(a.std(ddof=1) / math.sqrt(a.size)) if a.size > 1 else None
    return {"mean": float(a.mean()), "stderr": se, "folds": a.tolist()}


def _paired(table: dict, marginal: str, n: int) -> dict:
    """`a − b` over folds for `PAIRS` present in `table` (NLL: folds where
    `a` is lower; NEES and 95% coverage: folds where `a` is closer to the
    nominal value)."""
    nominal = {"nees": float(len(MARGINALS[marginal])), "coverage_0.95": 0.95}
    out = {}
    for a, b in PAIRS:
        if a not in table or b not in table:
            continue
        row = {}
        for k in ("nll", "nees", "coverage_0.68", "coverage_0.95"):
            fa = np.asarray(table[a][k]["folds"])
            fb = np.asarray(table[b][k]["folds"])
            s = mean_se(fa - fb)
            if k == "nll":
                s["a_lower_folds"] = int(np.sum(fa < fb))
            else:
                nom = nominal.get(k, 0.68)
                s["a_closer_to_nominal_folds"] = int(
                    np.sum(np.abs(fa - nom) < np.abs(fb - nom))
                )
            row[k] = s
        out[f"{a} - {b}"] = row
    return out


def _table(files: list[dict], marginal: str) -> dict:
    """Per method present in every file: mean ± se over folds."""
    table = {}
    for m in METHODS:
        recs = [f["rows"][m][marginal] for f in files if m in f.get("rows", {})]
        if len(recs) != len(files):
            continue
        row = {
            k: mean_se([r[k] for r in recs])
            for k in ("nll", "nees", "sequences_in_band", "frames_in_band")
        }
        for q in ("0.68", "0.95"):
            row[f"coverage_{q}"] = mean_se([r["coverage"][q] for r in recs])
        row["invalid_windows"] = int(sum(r["invalid_sequences"] for r in recs))
        table[m] = row
    return table


def calibration_figure(files: list[dict], path: Path) -> None:
    """Expected vs observed coverage (mean over the folds), per method, one
    panel per marginal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(MARGINALS), figsize=(11, 5.0))
    colours = plt.get_cmap("tab10").colors
    for ax, (marginal, idx) in zip(axes, MARGINALS.items()):
        ax.plot([0, 1], [0, 1], "k:", lw=1, label="calibrated")
        for i, m in enumerate(METHODS):
            recs = [f["rows"][m][marginal] for f in files if m in f.get("rows", {})]
            if len(recs) != len(files):
                continue
            obs = [np.mean([r["coverage"][str(q)] for r in recs]) for q in LEVELS]
            style = {"smoother": "-", "ekf": "--"}.get(m.split("_")[0], "-.")
            ax.plot(LEVELS, obs, style, color=colours[i], marker="o", ms=3, label=m)
        ax.set_xlabel(f"expected coverage (χ²_{len(idx)} region of the marginal)")
        ax.set_ylabel(f"observed coverage of the true {marginal}")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_title(f"{marginal} ({'x, y' if len(idx) == 2 else 'θ'})", fontsize=9)
        ax.legend(fontsize=6, loc="upper left")
    folds = ",".join(str(f["fold"]) for f in files)
    fig.suptitle(
        f"KITTI (rendered views): calibration on test folds {folds}, "
        "mean over folds, frames 1-99 of each 100-frame window",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _reproduction_table(files: list[dict], out: Path) -> dict:
    """Per method and fold: the retrained row's final-step m/m and deg/m
    minus the committed `fold_K.json` row's (for `lstm_bi_var`, minus the
    committed `lstm_bi` row's: the same mean network and recipe, plus the
    variance head and its loss)."""
    table: dict = {}
    for f in files:
        fold_path = out / f"fold_{f['fold']}.json"
        committed = json.loads(fold_path.read_text()) if fold_path.exists() else {}
        for m, row in f["rows"].items():
            now = row["test_scores"]["now"]
            ref = committed.get("rows", {}).get("lstm_bi" if m == LSTM_VARIANCE else m)
            if ref is None:
                continue
            entry = table.setdefault(
                m, {"compared_with": "lstm_bi" if m == LSTM_VARIANCE else m}
            )
            entry[str(f["fold"])] = {
                k: now[k] - ref[k] for k in ("trans_m_per_m", "rot_deg_per_m")
            }
            entry[str(f["fold"])]["committed_trans_m_per_m"] = ref["trans_m_per_m"]
    for entry in table.values():
        diffs = [v["trans_m_per_m"] for k, v in entry.items() if k != "compared_with"]
        entry["max_abs_trans_difference"] = float(np.max(np.abs(diffs)))
    return table


def finished_folds(out: Path) -> list[dict]:
    """The `uncertainty_fold_K.json` under `out` that hold every row they
    were run for (`methods`), by fold."""
    files = []
    for p in sorted(Path(out).glob("uncertainty_fold_*.json")):
        rec = json.loads(p.read_text())
        rows = rec.get("rows", {})
        if rec.get("methods") and all(m in rows for m in rec["methods"]):
            files.append(rec)
    return sorted(files, key=lambda r: r["fold"])


def summarise(out: Path) -> dict | None:
    """`uncertainty.json` and `fig_calibration.png` under `out` from the
    finished fold files (None, writing nothing, when there are none)."""
    out = Path(out)
    files = finished_folds(out)
    if not files:
        print(f"no finished uncertainty_fold_K.json under {out}")
        return None
    record: dict = dict(
        benchmark="kitti_vo_uncertainty",
        label=files[0]["label"],
        folds=[f["fold"] for f in files],
        fold_files=[f"uncertainty_fold_{f['fold']}.json" for f in files],
        git=[f["git"] for f in files],
        definitions=dict(
            marginals="position: the planar (x, y) in the window frame; heading: "
            "θ. Smoothers: the Laplace marginal (JᵀJ)⁻¹ at the MAP "
            "(eqsmooth.marginal_covariances' BlockTridiagonal selected "
            "inversion); EKFs: the filtered covariance; both in the right-"
            "perturbation tangent (ρx, ρy, δθ) of the estimate, the position "
            "block rotated into the window frame, R(θ̂)Σ_ρρR(θ̂)ᵀ (first order). "
            "lstm_bi_var: the bi-LSTM (mean trained by position MSE as lstm_bi) "
            "with a variance head on its hidden states (gradient stopped) giving "
            "σ of each velocity, pushed to first order through the integration, "
            "plus a learned random walk t·diag(q²); the head and q trained by the "
            "Gaussian NLL of the true planar pose, selected on MSE + NLL",
            frames="frames 1..99 of each disjoint 100-frame test window (frame 0 "
            "is given to every estimator as the true first state)",
            nll="½ eᵀΣ⁻¹e + ½ log det Σ + (d/2) log 2π per frame, nats (d = 2 "
            "position, 1 heading; eqsmooth.learn.gaussian_calibration); mean over "
            "a window's frames, then over windows",
            nees="eᵀΣ⁻¹e per frame (d for a consistent estimator); mean over a "
            "window's frames, then over windows",
            sequences_in_band="fraction of windows whose mean NEES over its 99 "
            "scored frames lies in eqsmooth.learn.nees_band(d, 99) (95% for a "
            "consistent estimator with independent frame errors; a smoother's and "
            "a filter's errors are correlated in time, so the band is nominal)",
            frames_in_band="fraction of frames with χ²_d(0.025) ≤ NEES ≤ "
            "χ²_d(0.975) (0.95 for a consistent estimator)",
            coverage="fraction of frames whose χ²_d CDF of the NEES is ≤ q (the "
            "truth inside the region of probability q), q in levels",
            invalid_windows="windows with a non-finite or non-positive-definite "
            "covariance on some frame, left out of the means",
            paired="a − b over folds, mean ± sample std/√n; NLL: folds where a is "
            "lower; NEES and coverage: folds where a is closer to nominal",
        ),
        levels=list(LEVELS),
        not_scored=dict(
            dead_reckoning="no covariance",
            lstm="outputs no variance (the variance head was added to the "
            "bi-LSTM only)",
            lstm_bi="the committed row, unchanged; outputs no variance (see "
            "lstm_bi_var)",
            derived_rows="the one-frame-late and noise-transfer rows are not scored",
            fixed_lag="the KITTI experiment has no fixed-lag row",
        ),
        windows_per_fold={
            str(f["fold"]): f["rows"][METHODS[0]]["windows"] for f in files
        }
        if all(METHODS[0] in f["rows"] for f in files)
        else None,
    )
    for marginal in MARGINALS:
        table = _table(files, marginal)
        record[marginal] = dict(rows=table, paired=_paired(table, marginal, len(files)))
    record["reproduction"] = _reproduction_table(files, out)
    record["per_fold"] = {
        str(f["fold"]): {
            m: {k: r[k] for k in (*MARGINALS, "test_scores", "train_s", "best_step")}
            for m, r in f["rows"].items()
        }
        for f in files
    }
    E._write_json(out / "uncertainty.json", record)
    calibration_figure(files, out / "fig_calibration.png")
    return record


def markdown(record: dict) -> str:
    """The tables of `uncertainty.json`: per row, mean ± se over folds."""

    def ms(s, digits=3):
        se = "" if s["stderr"] is None else f" ± {s['stderr']:.{digits}f}"
        return f"{s['mean']:.{digits}f}{se}"

    n = len(record["folds"])
    parts = [
        f"Finished folds: {record['folds']} ({n} of {D.NUM_FOLDS}); mean ± se "
        "over folds (no se with one fold). From `results/kitti/uncertainty.json`."
    ]
    for marginal in MARGINALS:
        r = record[marginal]
        d = len(MARGINALS[marginal])
        lines = [
            f"**{marginal}** (d = {d}; a consistent estimator has NEES {d}, "
            "coverage 0.68 and 0.95):",
            "",
            "| row | NLL (nats/frame) | NEES | 68% coverage | 95% coverage |",
            "|---|---|---|---|---|",
        ]
        for m, row in r["rows"].items():
            lines.append(
                f"| `{m}` | {ms(row['nll'])} | {ms(row['nees'], 2)} | "
                f"{ms(row['coverage_0.68'])} | {ms(row['coverage_0.95'])} |"
            )
        if r["paired"]:
            lines += [
                "",
                "| a − b | ΔNLL | folds a lower | Δ95% coverage |",
                "|---|---|---|---|",
            ]
            for k, p in r["paired"].items():
                lines.append(
                    f"| `{k}` | {ms(p['nll'])} | {p['nll']['a_lower_folds']}/{n} | "
                    f"{ms(p['coverage_0.95'])} |"
                )
        parts.append("\n".join(lines))
    rep = record.get("reproduction", {})
    if rep:
        lines = [
            "Retrained rows against the committed `fold_K.json` (final-step m/m, "
            "largest |difference| over the finished folds; `lstm_bi_var` against "
            "the committed `lstm_bi`, whose mean network and recipe it shares):",
            "",
            "| row | compared with | max \\|Δ m/m\\| |",
            "|---|---|---|",
        ]
        for m, e in rep.items():
            lines.append(
                f"| `{m}` | `{e['compared_with']}` | "
                f"{e['max_abs_trans_difference']:.2g} |"
            )
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"
