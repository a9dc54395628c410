"""More never-seen folds, with their sampling spread, and the covariances' scores.

`fresh.py` scored every fold's models on one never-seen fold (fold 10), so
its error bars count only the variation between the ten models. This stage
scores the committed heads (`heads/fold_K/<method>.eqx`, evaluation only,
nothing trained) on further folds of the same generator and data seed,
`FIRST_FRESH_MORE + K` for K = 0..9 (folds 11..20: no training, validation
or test split uses them; the protocol's folds are 0..9 and fresh.py's is 10).

Pairing, to fit the compute: fresh fold `11 + K` is scored by the sensor and
heads of test fold K only, so each fresh fold costs one sensor pass and one
pass of each head. The same pass scores the heads on their own committed
test fold K again (a check that the loaded heads give the committed
`fold_K.json` test RMSE) and scores the covariances of the probabilistic
rows on both sets (`uncertainty.py`).

Per pair it writes `fresh_more/fold_F.json` (F = 11 + K): per-sequence
position RMSE of every method on fold F, the uncertainty scores on fold F
and on test fold K, and the timings. The file is first written after the
test fold (section `test`), then again with the fresh fold (`fresh`); a
finished section is skipped when the command runs again. `summarise`
pools the finished pairs into `fresh_more.json` (every `PAIRS`
comparison and every row's mean with a two-level bootstrap interval:
folds resampled, then sequences within each fold) and `uncertainty.json`.

    python -m experiments.disk_tracking.fresh_more                 # all pairs
    python -m experiments.disk_tracking.fresh_more --pairs 0 1
    python -m experiments.disk_tracking.fresh_more --summarise-only
"""

import argparse
import dataclasses
import json
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs
from experiments._provenance import git_hash

from . import (
    data as D,
    fresh,
    models as M,
    protocol,
    report,
    train as T,
    uncertainty as U,
)


try:  # the blocks and a flag, instead of an error on a singular system
    from eqsmooth.solve._posterior._marginals import _marginal_covariances
except ImportError:  # pragma: no cover - private helper moved
    _marginal_covariances = None


FIRST_FRESH_MORE = fresh.FRESH_FOLD + 1  # 11: fold 10 is fresh.py's
BOOTSTRAP_SAMPLES = 2000
BOOTSTRAP_SEED = 20261129
METHODS = T.Config().methods
# fresh.py's comparisons, and the out-of-view factor's own gain (issue 58).
PAIRS = fresh.PAIRS + (
    ("smoother_hetero_surrogate_learndyn_view", "smoother_hetero_surrogate_learndyn"),
)


def fresh_more_fold(k: int) -> int:
    """The never-seen fold scored by test fold `k`'s heads."""
    return FIRST_FRESH_MORE + k


def head_sigma(results: Path, fold: int) -> float:
    """σ₀ of fold `fold`'s noise heads: the committed sensor's validation RMSE.

    The heteroscedastic head keeps `1/σ₀` as a static field (not a leaf of
    the `.eqx` file), so the template must be built with the fold's own σ₀
    (`fold_K.json`'s virtual-sensor `val_rmse`, what `protocol.run_fold`
    passed as `sigma`).
    """
    rec = json.loads((results / f"fold_{fold}.json").read_text())["records"]
    return float(rec["virtual_sensor"]["val_rmse"])


def load_head(cfg: T.Config, results: Path, fold: int, method: str, num_features):
    """The committed head `heads/fold_K/<method>.eqx` under `results`."""
    key = jax.random.key(0)
    sigma = head_sigma(results, fold)
    family, kind, *_ = method.split("_")
    if method == "smoother_hetero_finetune":
        template = T.FinetuneModel(
            T.make_sensor(cfg, key),
            T.make_smoother_model("hetero", sigma, key, cfg.dtype),
        )
    elif family in ("smoother", "ekf"):
        template = T.make_smoother_model(
            kind, sigma, key, cfg.dtype, T.view_factor(method)
        )
        if "learndyn" in method.split("_")[3:]:
            template = dataclasses.replace(template, learn_dynamics=True)
    elif family == "lstm":
        template = T._cast(
            M.LstmTracker(key, kind == "bi", num_features, hidden=cfg.lstm_hidden),
            cfg.dtype,
        )
    else:
        raise ValueError(f"no committed head for {method!r}")
    path = results / "heads" / f"fold_{fold}" / f"{method}.eqx"
    return eqx.tree_deserialise_leaves(path, template)


@eqx.filter_jit
def _smooth_with_covariance(model, meas, counts, x0, max_steps: int):
    """MAP positions `(B, T, 2)` (`train.smooth_one`, the evaluation's own
    solve), their Laplace marginal covariances `(B, T, 2, 2)` and the solves'
    outcomes."""

    def one(m, c, x):
        xs, outcome = T.smooth_one(model, m, c, x, max_steps)
        lin = eqs.solve.linearize(model.graph(m, c, x), {"x": xs})
        if _marginal_covariances is None:  # raises on a singular system
            cov = eqs.marginal_covariances(lin, groups=["x"])["x"][:, :2, :2]
        else:
            blocks, ok = _marginal_covariances(lin, None, ("x",))
            cov = jnp.where(ok, blocks["x"][:, :2, :2], jnp.nan)
        return xs[:, :2], cov, outcome

    return jax.vmap(one)(meas, counts, x0)


@eqx.filter_jit
def _ekf_with_covariance(model, meas, counts, x0):
    xs, ps = jax.vmap(T.ekf_one, in_axes=(None, 0, 0, 0))(model, meas, counts, x0)
    return xs[..., :2], ps[..., :2, :2]


@eqx.filter_jit
def _positions(sensor, images):
    return jax.vmap(sensor)(images)


def finetuned_measurements(model, split: T.Split, batch: int) -> np.ndarray:
    """The fine-tuned CNN's positions `(N, T, 2)` on every frame of `split`."""
    t = split.fold.num_frames
    images = split.images.reshape((split.n * t,) + split.images.shape[2:])
    out = []
    for i in range(0, images.shape[0], batch):
        ims = jnp.asarray(images[i : i + batch])
        count = ims.shape[0]
        if count < batch:
            ims = jnp.concatenate(
                [ims, jnp.zeros((batch - count,) + ims.shape[1:], ims.dtype)]
            )
        out.append(np.asarray(_positions(model.sensor, ims))[:count])
    return np.concatenate(out).reshape(split.n, t, 2)


def evaluate(cfg: T.Config, method: str, model, split: T.Split):
    """`method`'s positions `(N, T, 2)`, covariances `(N, T, 2, 2)` (None for
    the LSTMs) and solve outcomes `(N,)` (None but for smoothers)."""
    data = split.sequences(cfg.dtype)
    steps = cfg.eval_solver_steps
    family = method.split("_")[0]
    if method == "smoother_hetero_finetune":
        data = dict(data, meas=finetuned_measurements(model, split, cfg.eval_batch))
        model = model.smoother
    if family == "smoother":
        return T.predict_split(
            lambda m, b: _smooth_with_covariance(
                m, b["meas"], b["counts"], b["truth"][:, 0], steps
            ),
            model,
            data,
        )
    if family == "ekf":
        pred, cov = T.predict_split(
            lambda m, b: _ekf_with_covariance(
                m, b["meas"], b["counts"], b["truth"][:, 0]
            ),
            model,
            data,
        )
        return pred, cov, None
    if family == "lstm":
        pred = T.predict_split(T.lstm_positions, model, T._lstm_data(split, cfg.dtype))
        return pred, None, None
    raise ValueError(f"unknown method {method!r}")


def per_sequence_rmse(pred, truth) -> np.ndarray:
    """Per-coordinate RMSE of each sequence `(N,)` (all frames, as `train.rmse`)."""
    e = np.asarray(pred, np.float64) - np.asarray(truth, np.float64)
    return np.sqrt(np.mean(e * e, axis=(1, 2)))


def load_split(cfg: T.Config, fold: int, n: int, cache_dir: Path) -> T.Split:
    """The first `n` sequences of generator fold `fold` and their images."""
    data = D.load_fold(cfg.data_seed, fold, n, cfg.num_frames, cache_dir)
    return T.Split(data, D.fold_images(data, cache_dir))


def score_split(cfg, results, heads_fold, split, methods, log) -> dict:
    """Every method's per-sequence RMSE and (probabilistic rows) uncertainty
    scores on `split`, with the committed sensor and heads of `heads_fold`."""
    truth = split.fold.positions
    rmse = {"virtual_sensor": per_sequence_rmse(split.sensor, truth)}
    unc, solves, seconds = {}, {}, {}
    assert split.features is not None
    for method in methods:
        t0 = time.perf_counter()
        model = load_head(cfg, results, heads_fold, method, split.features.shape[-1])
        pred, cov, outcomes = evaluate(cfg, method, model, split)
        rmse[method] = per_sequence_rmse(pred, truth)
        if cov is not None:
            unc[method] = U.fold_summary(U.gaussian_scores(pred, cov, truth))
        if outcomes is not None:
            solves[method] = {
                n: int(np.sum(outcomes == i)) for i, n in enumerate(T.SOLVE_OUTCOMES)
            }
        seconds[method] = time.perf_counter() - t0
        extra = ""
        if method in unc:
            u = unc[method]
            extra = (
                f", NLL {u['nll']:.3f} nats/frame, NEES {u['nees']:.2f}, "
                f"cov68 {u['coverage']['0.68']:.3f} cov95 {u['coverage']['0.95']:.3f}"
            )
        log(
            f"  {method}: {T.rmse(pred, truth):.3f} px{extra} ({seconds[method]:.0f} s)"
        )
    return dict(rmse=rmse, uncertainty=unc, solves=solves, seconds=seconds)


def run_pair(cfg, k, results, out, work, n, methods, log) -> Path:
    """Score test fold `k`'s committed sensor and heads on fresh fold `11 + k`
    and on test fold `k`; write `out/fresh_more/fold_F.json`."""
    f_idx = fresh_more_fold(k)
    used = set(range(cfg.num_folds)) | {fresh.FRESH_FOLD}
    if f_idx in used:
        raise ValueError(f"fold {f_idx} is used by the protocol or fresh.py")
    path = out / "fresh_more" / f"fold_{f_idx}.json"
    record = json.loads(path.read_text()) if path.exists() else None
    if record is None:
        record = dict(
            benchmark="disk_tracking_fresh_more",
            fresh_fold=f_idx,
            heads_fold=k,
            pairing=f"fresh fold {f_idx} is scored by the committed sensor and "
            f"heads of test fold {k} only (heads/fold_{k}/, sensor_fold{k}.eqx)",
            data_seed=cfg.data_seed,
            head_sigma=head_sigma(results, k),
            git_hash=git_hash(),
            machine=report.machine(),
        )
    sensor = fresh.committed_sensor(cfg, results, k)
    cache = work / "cache"
    for section, fold in (("test", k), ("fresh", f_idx)):
        if section in record:
            log(f"pair {k}: {section} fold {fold} already scored, skipped")
            continue
        t0 = time.perf_counter()
        split = load_split(cfg, fold, n, cache)
        t_data = time.perf_counter() - t0
        protocol.cached_outputs(
            sensor, split, cfg, work / f"sensor{k}_fold{fold}_n{n}.npz"
        )
        t_sensor = time.perf_counter() - t0 - t_data
        log(
            f"pair {k}, {section} fold {fold}: {split.n} sequences (data "
            f"{t_data:.0f} s, sensor {t_sensor:.0f} s)"
        )
        scores = score_split(cfg, results, k, split, methods, log)
        rec = dict(
            fold=fold,
            sequences=split.n,
            fold_rmse={
                m: float(np.sqrt(np.mean(v**2))) for m, v in scores["rmse"].items()
            },
            per_sequence_rmse={
                m: [round(float(x), 5) for x in v] for m, v in scores["rmse"].items()
            },
            uncertainty=scores["uncertainty"],
            solves=scores["solves"],
            seconds=dict(data=t_data, sensor=t_sensor, **scores["seconds"]),
            load_average=os.getloadavg(),
        )
        rec["seconds"]["total"] = time.perf_counter() - t0
        if section == "test":
            committed = json.loads((results / f"fold_{k}.json").read_text())["records"]
            rec["committed_test_rmse"] = {
                m: committed[m]["test_rmse"] for m in rec["fold_rmse"] if m in committed
            }
        record[section] = rec
        report.write_json(path, record, report.jsonable)
        log(f"pair {k}, {section} fold {fold}: {rec['seconds']['total']:.0f} s")
    return path


# ---------------------------------------------------------------------------
# Summary: two-level bootstrap over folds and sequences
# ---------------------------------------------------------------------------


def bootstrap(mse: np.ndarray, samples: int, seed: int) -> np.ndarray:
    """Two-level bootstrap of the mean over folds of each fold's RMSE.

    `mse`: `(M, F, N)` per-sequence mean squared errors of M methods on F
    folds of N sequences. Each draw resamples the F folds with replacement,
    then the N sequences of every drawn fold with replacement (the same draw
    for every method: paired), and returns `mean_f sqrt(mean_n mse)`.
    Returns `(samples, M)`.
    """
    rng = np.random.default_rng(seed)
    m, f, n = mse.shape
    out = np.empty((samples, m))
    for b in range(samples):
        folds = rng.integers(0, f, size=f)
        seqs = rng.integers(0, n, size=(f, n))
        per_fold = np.sqrt(mse[:, folds[:, None], seqs].mean(axis=2))
        out[b] = per_fold.mean(axis=1)
    return out


def _interval(draws: np.ndarray) -> list[float]:
    return [float(np.percentile(draws, 2.5)), float(np.percentile(draws, 97.5))]


def load_pairs(out: Path) -> list[dict]:
    paths = sorted(
        (out / "fresh_more").glob("fold_*.json"),
        key=lambda p: int(p.stem.split("_")[1]),
    )
    return [json.loads(p.read_text()) for p in paths]


def summarise(out: Path, samples: int = BOOTSTRAP_SAMPLES) -> tuple[dict, str]:
    """`fresh_more.json` (and its markdown) from the finished pairs."""
    pairs = [p for p in load_pairs(out) if "fresh" in p]
    if not pairs:
        raise FileNotFoundError(f"no finished fresh_more/fold_F.json under {out}")
    n = min(p["fresh"]["sequences"] for p in pairs)
    methods = [
        m
        for m in report.LABELS
        if all(m in p["fresh"]["per_sequence_rmse"] for p in pairs)
    ]
    mse = np.array(
        [
            [np.asarray(p["fresh"]["per_sequence_rmse"][m][:n]) ** 2 for p in pairs]
            for m in methods
        ]
    )
    draws = bootstrap(mse, samples, BOOTSTRAP_SEED)
    point = np.sqrt(mse.mean(axis=2))  # (M, F) fold RMSE
    old_path = out / "fresh.json"
    old = json.loads(old_path.read_text())["rows"] if old_path.exists() else {}
    rows, lines = {}, []
    for i, m in enumerate(methods):
        s = report.mean_se(point[i])
        rows[m] = dict(
            mean=s["mean"],
            stderr_over_folds=s["stderr"],
            bootstrap_95=_interval(draws[:, i]),
            folds=s["folds"],
            fresh_fold_10_mean=old.get(m, {}).get("fresh", {}).get("mean"),
        )
        lo, hi = rows[m]["bootstrap_95"]
        ten = rows[m]["fresh_fold_10_mean"]
        lines.append(
            f"| {report.LABELS[m]} | {s['mean']:.3f} [{lo:.3f}, {hi:.3f}] | "
            + ("—" if ten is None else f"{ten:.3f}")
            + " |"
        )
    paired, plines = {}, []
    for a, b in PAIRS:
        if a not in methods or b not in methods:
            continue
        ia, ib = methods.index(a), methods.index(b)
        d = point[ia] - point[ib]
        s = report.mean_se(d)
        dd = draws[:, ia] - draws[:, ib]
        paired[f"{a} - {b}"] = dict(
            mean=s["mean"],
            stderr_over_folds=s["stderr"],
            bootstrap_95=_interval(dd),
            bootstrap_fraction_below_0=float(np.mean(dd < 0)),
            better_folds=int(np.sum(d < 0)),
            folds=s["folds"],
        )
        lo, hi = paired[f"{a} - {b}"]["bootstrap_95"]
        plines.append(
            f"| {report.LABELS[a]} − {report.LABELS[b]} | {s['mean']:+.3f} "
            f"[{lo:+.3f}, {hi:+.3f}] | {int(np.sum(d < 0))}/{len(d)} |"
        )
    seconds = [p["fresh"]["seconds"]["total"] for p in pairs]
    record = dict(
        benchmark="disk_tracking_fresh_more",
        fresh_folds=[p["fresh_fold"] for p in pairs],
        heads_of_test_fold=[p["heads_fold"] for p in pairs],
        pairing="fresh fold 11+K is scored by the committed sensor "
        "(sensor_foldK.eqx) and heads (heads/fold_K/) of test fold K only: "
        "evaluation, nothing trained; folds 11.. are used by no split of the "
        "protocol (folds 0-9) nor by fresh.py (fold 10)",
        sequences_per_fold=n,
        statistic="per-coordinate position RMSE (px) of each fold, mean over "
        "folds; differences paired by fold",
        bootstrap=dict(
            levels="two: the folds resampled with replacement, then the "
            "sequences within each drawn fold with replacement (the same draws "
            "for every method)",
            samples=samples,
            seed=BOOTSTRAP_SEED,
            interval="2.5 and 97.5 percentiles",
        ),
        rows=rows,
        paired=paired,
        seconds_per_fresh_fold=dict(
            median=float(np.median(seconds)), all=[round(s, 1) for s in seconds]
        ),
    )
    report.write_json(out / "fresh_more.json", record, report.jsonable)
    table = (
        f"More never-seen folds ({len(pairs)}: folds {record['fresh_folds']}, "
        f"{n} sequences each): fold 11+K scored by test fold K's committed "
        "heads; mean over folds of the per-fold RMSE (px) with a two-level "
        f"(folds, then sequences) bootstrap 95% interval (B = {samples}).\n\n"
        "| method | folds 11.. [95% interval] | fold 10 (fresh.json) |\n"
        "|---|---|---|\n" + "\n".join(lines) + "\n\n"
        "| difference | mean [95% interval] (px) | folds better |\n|---|---|---|\n"
        + "\n".join(plines)
        + "\n"
    )
    return record, table


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", type=Path, default=Path("results/disk"))
    p.add_argument("--out", type=Path, default=None, help="default: --results")
    p.add_argument("--work", type=Path, default=Path("runs/disk_fresh_more"))
    p.add_argument("--pairs", type=int, nargs="+", default=list(range(10)))
    p.add_argument("--sequences", type=int, default=D.SEQUENCES_PER_FOLD)
    p.add_argument("--methods", nargs="+", default=list(METHODS))
    p.add_argument("--summarise-only", action="store_true")
    p.add_argument("--bootstrap-samples", type=int, default=BOOTSTRAP_SAMPLES)
    a = p.parse_args(argv)
    out = a.out or a.results
    jax.config.update("jax_default_matmul_precision", "highest")
    cfg = T.Config()
    if not a.summarise_only:
        for k in a.pairs:
            log_file = out / "fresh_more" / f"fold_{fresh_more_fold(k)}.log"
            log_file.parent.mkdir(parents=True, exist_ok=True)

            def log(msg, log_file=log_file):
                print(msg, flush=True)
                with open(log_file, "a") as f:
                    f.write(msg + "\n")

            run_pair(cfg, k, a.results, out, a.work, a.sequences, a.methods, log)
    _, table = summarise(out, a.bootstrap_samples)
    print(table)
    print(U.markdown(U.summarise(out, load_pairs(out))))


if __name__ == "__main__":
    main()
