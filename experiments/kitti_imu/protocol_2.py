"""The second declared protocol's rows (docs/tutorial/imu.md, "a second
protocol"): per-interval sigmas from a network (`learned_hetero`), and the
metadata and learned constant sigmas run in the EKF and the fixed-lag
smoother. Data, folds, outages, loss, training and selection are the first
protocol's (`experiment.py`).

    python -m experiments.kitti_imu.protocol_2 --folds 0 1 2 3 4
    python -m experiments.kitti_imu.protocol_2 --quick --out /tmp/p2

Every run writes each fold's file again (nothing is skipped). Besides the
declared scores, a fold file keeps what `figures.py` draws: per row, the
horizontal error of each withheld fix (and, for rows with a covariance, its
NLL, squared Mahalanobis distance and χ²₃ CDF value) and the estimated
keyframe positions; and the test segment's GPS fixes, times and outages.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jaxtyping import Array, Float  # noqa: E402

import eqsmooth as eqs  # noqa: E402
import eqsmooth.learn as eql  # noqa: E402

from .._provenance import git_hash  # noqa: E402
from . import data as D  # noqa: E402
from .experiment import (  # noqa: E402
    BIAS_PRIOR_SIGMAS,
    build,
    GPS_VARIANCE,
    GRAVITY,
    imu_parts,
    ImuNoise,
    learn_constant,
    score,
    solve,
    VELOCITY_SIGMA,
)


OUT = Path("results/kitti_imu/protocol_2")
LAG = 10
ATTITUDE_SIGMA = 1.0  # rad, about the track's yaw (the example's first_state)
FIRST_POSITION_SIGMA = 1.0  # m


def interval_features(seg: dict) -> Float[Array, "n 4"]:
    """Mean and standard deviation of the accelerometer norm and of the
    gyroscope norm over each interval's samples."""
    s, m = seg["samples"], seg["mask"].astype(float)
    count = jnp.sum(m, axis=-1)
    out = []
    for cols in (slice(1, 4), slice(4, 7)):
        norm = jnp.linalg.norm(s[..., cols], axis=-1)
        mean = jnp.sum(norm * m, axis=-1) / count
        var = jnp.sum((norm - mean[:, None]) ** 2 * m, axis=-1) / count
        out += [mean, jnp.sqrt(var)]
    return jnp.stack(out, -1)


class HeteroNoise(eqx.Module):
    """`learned_hetero`: the constant log-sigmas plus a network's per-interval
    offsets of the accelerometer and gyroscope log-sigmas."""

    constant: ImuNoise
    net: eqx.nn.MLP
    feature_mean: Float[Array, "4"]
    feature_std: Float[Array, "4"]

    @staticmethod
    def init(meta: dict, train: dict) -> "HeteroNoise":
        feats = jnp.concatenate(
            [
                interval_features(jax.tree_util.tree_map(lambda x: x[i], train))
                for i in range(train["gps"].shape[0])
            ]
        )
        net = eqx.nn.MLP(4, 2, 16, 1, activation=jnp.tanh, key=jax.random.key(0))
        last = net.layers[-1]
        net = eqx.tree_at(
            lambda n: (n.layers[-1].weight, n.layers[-1].bias),
            net,
            (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)),
        )
        return HeteroNoise(
            ImuNoise.from_metadata(meta), net, feats.mean(0), feats.std(0)
        )

    def interval_log_sigmas(self, seg: dict) -> Float[Array, "n 2"]:
        mean = jax.lax.stop_gradient(self.feature_mean)
        std = jax.lax.stop_gradient(self.feature_std)
        z = (interval_features(seg) - mean) / std
        return self.constant.log_sigma[:2] + jax.vmap(self.net)(z)

    def sigmas(self) -> dict:
        return self.constant.sigmas()


def hetero_pim(noise: HeteroNoise, seg: dict):
    """Each interval preintegrated with its own accelerometer and gyroscope
    sigmas (the same recursion, vmapped over intervals of one)."""
    log_s = noise.interval_log_sigmas(seg)
    s = seg["samples"]

    def one(ls, samples, mask):
        params = eqs.ImuParams.make_u(
            GRAVITY,
            accelerometer_sigma=jnp.exp(ls[0]),
            gyroscope_sigma=jnp.exp(ls[1]),
        )
        return eqs.preintegrate(
            params,
            samples[None, :, 1:4],
            samples[None, :, 4:7],
            samples[None, :, 0],
            mask=mask[None],
        )

    pim = jax.vmap(one)(log_s, s, seg["mask"])
    return jax.tree_util.tree_map(lambda a: a[:, 0], pim)


def hetero_build(noise: HeteroNoise, seg: dict, used: np.ndarray):
    """`experiment.build` with the per-interval preintegration (the IMU
    factors' noise is built from it)."""
    return build(noise.constant, seg, used, pim=hetero_pim(noise, seg))


def first_belief(seg: dict):
    """The belief on a segment's first keyframe (the example's
    `first_state`): mean `(pose, velocity, bias)` and covariance."""
    rot = eqs.SO3.from_z_radians(seg["yaw"][:1])[0]
    pose = eqs.SE3.from_rotation_and_translation(rot, seg["gps"][0])
    mean = (pose, seg["vel"][0], jnp.zeros(6))
    sigmas = jnp.asarray(
        [FIRST_POSITION_SIGMA] * 3
        + [ATTITUDE_SIGMA] * 3
        + [VELOCITY_SIGMA] * 3
        + list(BIAS_PRIOR_SIGMAS)
    )
    return mean, jnp.diag(sigmas**2)


def _gps_residual(state, position, params):
    return state[0].translation() - position


def chain_model(noise: ImuNoise, seg: dict, used: np.ndarray):
    """The transition (`ImuTransitionFactor`, bias walk included) and the GPS
    stack of one segment, each keyframe one state."""
    params, pim, walk = imu_parts(noise, seg)
    ids = np.arange(seg["gps"].shape[0])
    transition = eqs.factors.ImuTransitionFactor(
        eqs.Var("s", ids[:-1]), eqs.Var("s", ids[1:]), pim, params, walk
    )
    gps_ids = np.flatnonzero(used)
    gps = eqs.FunctionFactor(
        _gps_residual,
        (eqs.Var("s", gps_ids),),
        eqs.IsotropicNoise.from_sigma(float(np.sqrt(GPS_VARIANCE))),
        data=jnp.asarray(seg["gps"][gps_ids]),
        residual_dim=3,
    )
    return transition, gps


def _floats(x) -> list[float]:
    return [float(v) for v in np.asarray(x)]


def _position_scores(p, world_cov, seg, withheld) -> dict:
    """The declared scores of the positions `p` at the withheld fixes, and
    per fix (in the order of `withheld`) what the figures draw: horizontal
    error and, with a covariance, NLL, squared Mahalanobis distance and its
    χ²₃ CDF value (position covariance plus the GPS noise, as the NLL);
    and every keyframe's estimated x, y."""
    e = seg["gps"][withheld] - p[withheld]
    h = np.linalg.norm(np.asarray(e[:, :2]), axis=-1)
    out = {
        "rms_horizontal_m": float(np.sqrt(np.mean(h**2))),
        "max_horizontal_m": float(h.max()),
        "withheld_fixes": int(len(withheld)),
    }
    per_fix = {"horizontal_error_m": _floats(h)}
    if world_cov is not None:
        cal = eql.gaussian_calibration(
            e, world_cov[withheld] + GPS_VARIANCE * jnp.eye(3)[None]
        )
        out["nll"] = float(np.mean(np.asarray(cal.nll)))
        out["valid_covariances"] = int(np.sum(np.asarray(cal.valid)))
        per_fix |= {
            "nll": _floats(cal.nll),
            "mahalanobis2": _floats(cal.nees),
            "chi2_cdf": _floats(cal.cdf),
        }
    out["per_fix"] = per_fix
    out["trajectory_x"] = _floats(p[:, 0])
    out["trajectory_y"] = _floats(p[:, 1])
    return out


def score_batch(noise: ImuNoise, seg: dict, cfg: D.Config, build=build) -> dict:
    """`experiment.score` (the declared scores, computed by the first
    protocol's code) and the per-fix record of the same solve, solved a
    second time because `score` keeps only the summaries."""
    out = score(noise, seg, cfg, build)
    withheld = np.flatnonzero(D.outage_mask(cfg))
    seg = jax.tree_util.tree_map(jnp.asarray, seg)
    _, sol = solve(noise, seg, cfg, build)
    x = sol.value["x"]
    cov = eqs.marginal_covariances(sol, groups=["x"])["x"]
    R = x.rotation().as_matrix()
    world = R @ cov[:, :3, :3] @ jnp.swapaxes(R, -1, -2)
    record = _position_scores(x.translation(), world, seg, withheld)
    return out | {k: record[k] for k in ("per_fix", "trajectory_x", "trajectory_y")}


def segment_record(seg: dict, cfg: D.Config) -> dict:
    """The test segment as the figures draw it: keyframe times, every GPS
    fix (withheld ones included), the withheld keyframes with their seconds
    since the last fix before their outage, and the outages."""
    t = np.asarray(seg["time"])
    withheld = np.flatnonzero(D.outage_mask(cfg))
    since = np.zeros(len(withheld))
    for a, b in cfg.outages:
        inside = (withheld >= a) & (withheld < b)
        since[inside] = t[withheld[inside]] - t[a - 1]
    return {
        "time_s": _floats(t),
        "gps_x": _floats(seg["gps"][:, 0]),
        "gps_y": _floats(seg["gps"][:, 1]),
        "withheld_keyframes": withheld.tolist(),
        "seconds_into_outage": _floats(since),
        "outages": [
            {
                "keyframes": [a, b],
                "last_fix_s": float(t[a - 1]),
                "next_fix_s": float(t[b]) if b < len(t) else None,
            }
            for a, b in cfg.outages
        ],
    }


def score_ekf(noise: ImuNoise, seg: dict, cfg: D.Config) -> dict:
    withheld = np.flatnonzero(D.outage_mask(cfg))
    seg = jax.tree_util.tree_map(jnp.asarray, seg)
    transition, gps = chain_model(noise, seg, ~D.outage_mask(cfg))
    mean, cov = first_belief(seg)
    sol = eqs.filters.ekf(transition, [gps], mean, cov, throw=False)
    pose = sol.mean[0]
    R = pose.rotation().as_matrix()
    world = R @ sol.covariance[:, :3, :3] @ jnp.swapaxes(R, -1, -2)
    return _position_scores(pose.translation(), world, seg, withheld)


def score_fixed_lag(noise: ImuNoise, seg: dict, cfg: D.Config) -> dict:
    withheld = np.flatnonzero(D.outage_mask(cfg))
    seg = jax.tree_util.tree_map(jnp.asarray, seg)
    transition, gps = chain_model(noise, seg, ~D.outage_mask(cfg))
    mean, cov = first_belief(seg)
    solver = eqs.LevenbergMarquardt(
        ftol=1e-10, gtol=1e-6, xtol=1e-9, initial_damping=1e-14
    )
    sol = eqs.filters.fixed_lag_smoother(
        transition, [gps], mean, cov, lag=LAG, solver=solver, max_steps=100
    )
    p = sol.lagged_mean[0].translation()
    return _position_scores(p, None, seg, withheld)


def run_fold(meta: dict, data: dict, fold: int, cfg: D.Config) -> dict:
    """The second protocol's rows on one fold: train and select
    `learned_constant` and `learned_hetero` (validation only), then score
    the test segment with every declared estimator."""
    split = D.fold_split(fold, cfg)
    constant, constant_s = learn_constant(meta, data, fold, cfg)
    init = HeteroNoise.init(meta, D.take(data, split["train"]))
    hetero, hetero_s = learn_constant(
        meta, data, fold, cfg, init=init, build=hetero_build
    )
    test = D.take(data, split["test"])
    seg = {k: v[0] for k, v in test.items()}
    metadata = ImuNoise.from_metadata(meta)
    learned = constant.best_model
    training = {}
    for key, res, sec in (
        ("learned_constant", constant, constant_s),
        ("learned_hetero", hetero, hetero_s),
    ):
        training[key] = {
            "seconds": sec,
            "best_step": int(res.best_step),
            "best_valid_loss_m2": float(res.best_valid_loss),
            "history": list(res.history),
        }
    rows = {
        "metadata": score_batch(metadata, seg, cfg),
        "learned_constant": score_batch(learned, seg, cfg),
        "learned_hetero": score_batch(hetero.best_model, seg, cfg, hetero_build),
        "metadata_ekf": score_ekf(metadata, seg, cfg),
        "learned_constant_ekf": score_ekf(learned, seg, cfg),
        "metadata_fixed_lag": score_fixed_lag(metadata, seg, cfg),
        "learned_constant_fixed_lag": score_fixed_lag(learned, seg, cfg),
    }
    return {
        "fold": fold,
        "split": split,
        "test_time_s": [float(seg["time"][0]), float(seg["time"][-1])],
        "training": training,
        "sigmas": {
            "learned_constant": learned.sigmas(),
            "learned_hetero_constant_part": hetero.best_model.sigmas(),
        },
        "rows": rows,
        "test_segment": segment_record(seg, cfg),
    }


PAIRS = (
    ("learned_hetero", "learned_constant"),
    ("learned_hetero", "metadata"),
    ("learned_constant_ekf", "metadata_ekf"),
    ("learned_constant_fixed_lag", "metadata_fixed_lag"),
)
METRICS = ("rms_horizontal_m", "max_horizontal_m", "nll")


def summary(out: Path) -> dict:
    """The declared report from the finished folds: each row's per-fold
    scores and the paired differences (row minus reference per fold, their
    mean, and on how many folds the row is lower)."""
    folds = [json.loads(p.read_text()) for p in sorted(Path(out).glob("fold_*.json"))]
    rows = sorted({r for f in folds for r in f["rows"]})
    per_row = {
        r: {m: [f["rows"][r].get(m) for f in folds] for m in METRICS} for r in rows
    }
    paired = {}
    for a, b in PAIRS:
        for m in METRICS:
            d = [
                f["rows"][a][m] - f["rows"][b][m]
                for f in folds
                if m in f["rows"][a] and m in f["rows"][b]
            ]
            if d:
                paired[f"{a} - {b}: {m}"] = {
                    "mean": float(np.mean(d)),
                    "lower_on": int(np.sum(np.asarray(d) < 0)),
                    "folds": len(d),
                    "per_fold": d,
                }
    record = {"folds": [f["fold"] for f in folds], "rows": per_row, "paired": paired}
    (Path(out) / "summary.json").write_text(json.dumps(record, indent=2) + "\n")
    lines = [
        "# KITTI IMU, second protocol: results",
        "",
        f"Folds: {record['folds']} (`python -m experiments.kitti_imu.protocol_2`; "
        "the protocol: `protocol_2.md`).",
        "",
        "| row | " + " | ".join(f"fold {f}" for f in record["folds"]) + " |",
        "|---|" + "---|" * len(folds),
    ]
    for r in rows:
        cells = []
        for f in folds:
            v = f["rows"][r]
            nll = f" / {v['nll']:.2f}" if "nll" in v else ""
            cells.append(f"{v['rms_horizontal_m']:.3f}{nll}")
        lines.append(f"| {r} | " + " | ".join(cells) + " |")
    lines += ["", "Cells: RMS horizontal error (m) / NLL (nats).", ""]
    lines += ["| paired difference | mean | lower on |", "|---|---|---|"]
    for k, v in paired.items():
        lines.append(f"| {k} | {v['mean']:+.3f} | {v['lower_on']} of {v['folds']} |")
    (Path(out) / "summary.md").write_text("\n".join(lines) + "\n")
    return record


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--folds", type=int, nargs="+", default=None)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--summary", action="store_true", help="pool the finished folds")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.summary:
        summary(args.out)
        return 0
    eqs.enable_compilation_cache()
    cfg = D.QUICK if args.quick else D.Config()
    folds = args.folds or ([0] if args.quick else list(range(cfg.num_segments)))
    meta, imu, gps = D.load(args.data_dir)
    data = D.segments(meta, imu, gps, cfg)
    commit = git_hash()  # the code as it was when the run started
    for fold in folds:
        path = args.out / f"fold_{fold}.json"
        t0 = time.perf_counter()
        out = run_fold(meta, data, fold, cfg)
        out["seconds"] = time.perf_counter() - t0
        out["config"] = {**cfg.__dict__, "quick": bool(args.quick)}
        out["command"] = "python -m experiments.kitti_imu.protocol_2 " + " ".join(
            sys.argv[1:]
        )
        out["commit"] = commit
        out["date"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        path.write_text(json.dumps(out, indent=2, default=float) + "\n")
        print(
            f"fold {fold}: "
            + "; ".join(
                f"{k} rms {v['rms_horizontal_m']:.3f} m"
                + (f" nll {v['nll']:.3f}" if "nll" in v else "")
                for k, v in out["rows"].items()
            )
            + f" ({out['seconds']:.0f} s)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    main()
