"""One segment's IMU + GPS smoother, the learned noise, training and scores.

The noise model is a Module of log-sigmas; the loss solves a segment's graph
with `eqsmooth.least_squares` (implicit adjoint) and scores the withheld GPS
fixes; `eqsmooth.learn.train` does the optimisation and keeps the model of
lowest validation loss.
"""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import eqsmooth as eqs
import eqsmooth.learn as eql

from .data import Config, fold_split, outage_mask, take


GRAVITY = 9.8
GPS_VARIANCE = 0.07  # GTSAM's example: GPS precision 1 / 0.07
VELOCITY_SIGMA = 1000.0
BIAS_PRIOR_SIGMAS = (0.1,) * 3 + (5e-5,) * 3
NAMES = ("accelerometer", "gyroscope", "accelerometer_bias", "gyroscope_bias")


class ImuNoise(eqx.Module):
    """The four learned IMU sigmas, as logs (accelerometer, gyroscope,
    accelerometer-bias and gyroscope-bias walk); integration sigma 0."""

    log_sigma: Float[Array, "4"]

    @staticmethod
    def from_metadata(meta: dict) -> "ImuNoise":
        keys = (
            "AccelerometerSigma",
            "GyroscopeSigma",
            "AccelerometerBiasSigma",
            "GyroscopeBiasSigma",
        )
        return ImuNoise(jnp.log(jnp.array([meta[k] for k in keys])))

    def sigmas(self) -> dict[str, float]:
        return dict(zip(NAMES, np.exp(np.asarray(self.log_sigma)).tolist()))


def imu_parts(noise: ImuNoise, seg: dict):
    """`(params, pim, walk)` of one segment: the IMU parameters of `noise`'s
    sigmas, its intervals' preintegration and the bias walk's sigmas."""
    sigma = jnp.exp(noise.log_sigma)
    params = eqs.ImuParams.make_u(
        GRAVITY, accelerometer_sigma=sigma[0], gyroscope_sigma=sigma[1]
    )
    s = seg["samples"]
    pim = eqs.preintegrate(
        params, s[..., 1:4], s[..., 4:7], s[..., 0], mask=seg["mask"]
    )
    walk = eqs.factors.bias_walk_sigmas(sigma[2], sigma[3], seg["count"])
    return params, pim, walk


def build(noise: ImuNoise, seg: dict, used: np.ndarray, pim=None):
    """The graph and initial values of one segment (`seg`: one example of
    `data.segments`, no leading axis); `used`: the keyframes whose GPS fix
    enters the graph; `pim`: the intervals' preintegration, if not the one
    of `noise`'s sigmas (`protocol_2`'s per-interval sigmas)."""
    params, own_pim, walk = imu_parts(noise, seg)
    pim = own_pim if pim is None else pim
    V = eqs.Var
    gps_ids = np.flatnonzero(used)
    graph = eqs.FactorGraph(
        [
            *eqs.factors.imu_chain(pim, params, walk),
            eqs.TranslationPriorFactor(
                V("x", gps_ids),
                seg["gps"][gps_ids],
                eqs.IsotropicNoise.from_sigma(float(np.sqrt(GPS_VARIANCE))),
            ),
            eqs.PriorFactor(
                V("v", [0]),
                jnp.zeros((1, 3)),
                eqs.IsotropicNoise.from_sigma(VELOCITY_SIGMA),
            ),
            eqs.PriorFactor(
                V("b", [0]),
                jnp.zeros((1, 6)),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(BIAS_PRIOR_SIGMAS)),
            ),
        ]
    )
    n = seg["gps"].shape[0]
    rot = eqs.SO3.from_z_radians(seg["yaw"])
    values = {
        "x": eqs.SE3.from_rotation_and_translation(rot, seg["pos"]),
        "v": seg["vel"],
        "b": jnp.zeros((n, 6)),
    }
    return graph, values


def solve(noise: ImuNoise, seg: dict, cfg: Config, build=build):
    """The segment's batch solve; `build(noise, seg, used)` makes its graph
    (`protocol_2` passes its per-interval one)."""
    used = ~outage_mask(cfg)
    graph, values = build(noise, seg, used)
    solver = eqs.LevenbergMarquardt(ftol=1e-10, gtol=1e-8, xtol=1e-10)
    sol = eqs.least_squares(
        graph, values, solver, max_steps=cfg.max_solver_steps, throw=False
    )
    return graph, sol


def make_loss(cfg: Config, build=build):
    """Mean squared horizontal error at the withheld fixes of one segment
    (a batch of one), through the solve."""
    withheld = np.flatnonzero(outage_mask(cfg))

    def loss(noise: ImuNoise, batch: dict):
        seg = jax.tree_util.tree_map(lambda x: x[0], batch)
        _, sol = solve(noise, seg, cfg, build)
        p = sol.value["x"].translation()[withheld]
        err = p[:, :2] - seg["gps"][withheld, :2]
        return jnp.mean(jnp.sum(err * err, axis=-1))

    return loss


def score(noise: ImuNoise, seg: dict, cfg: Config, build=build) -> dict:
    """The declared metrics of one segment: horizontal RMS and max error at
    the withheld fixes, and the mean NLL of those fixes under the position
    marginal plus GPS noise."""
    withheld = np.flatnonzero(outage_mask(cfg))
    seg = jax.tree_util.tree_map(jnp.asarray, seg)
    graph, sol = solve(noise, seg, cfg, build)
    x = sol.value["x"]
    cov = eqs.marginal_covariances(sol, groups=["x"])["x"]  # (n, 6, 6), (v, w)
    R = x.rotation().as_matrix()
    world = R @ cov[:, :3, :3] @ jnp.swapaxes(R, -1, -2)
    p = x.translation()
    e = seg["gps"] - p
    cal = eql.gaussian_calibration(
        e[withheld], world[withheld] + GPS_VARIANCE * jnp.eye(3)[None]
    )
    h = np.linalg.norm(np.asarray(e[withheld, :2]), axis=-1)
    return {
        "rms_horizontal_m": float(np.sqrt(np.mean(h**2))),
        "max_horizontal_m": float(h.max()),
        "nll": float(np.mean(np.asarray(cal.nll))),
        "valid_covariances": int(np.sum(np.asarray(cal.valid))),
        "solver_result": str(sol.result),
        "solver_steps": int(sol.stats["num_steps"]),
        "withheld_fixes": int(len(withheld)),
    }


def learn_constant(
    meta: dict, data: dict, fold: int, cfg: Config, init=None, build=build
):
    """The `learned_constant` row: train on the fold's training segments,
    select on its validation segment (`init`, `build`: another model and its
    graph, as `protocol_2`'s `learned_hetero`)."""
    split = fold_split(fold, cfg)
    loss = make_loss(cfg, build)
    t0 = time.perf_counter()
    result = eql.train(
        ImuNoise.from_metadata(meta) if init is None else init,
        loss,
        take(data, split["train"]),
        optimizer=eql.make_optimizer(cfg.learning_rate),
        num_steps=cfg.num_steps,
        batch_size=1,
        seed=0,
        validation=eql.Validation(take(data, split["valid"]), every=cfg.valid_every),
        logging=eql.Logging(every=1, progress=False),
    )
    return result, time.perf_counter() - t0


def run_fold(meta: dict, data: dict, fold: int, cfg: Config) -> dict:
    """Both declared rows on one fold: train, select, then score the test
    segment (the only place a test number is computed)."""
    split = fold_split(fold, cfg)
    result, train_s = learn_constant(meta, data, fold, cfg)
    rows = {
        "metadata": ImuNoise.from_metadata(meta),
        "learned_constant": result.best_model,
    }
    test = take(data, split["test"])
    seg = {k: v[0] for k, v in test.items()}
    out = {
        "fold": fold,
        "split": split,
        "test_time_s": [float(seg["time"][0]), float(seg["time"][-1])],
        "training": {
            "seconds": train_s,
            "best_step": int(result.best_step),
            "best_valid_loss_m2": float(result.best_valid_loss),
            "history": list(result.history),
        },
        "rows": {},
    }
    for name, model in rows.items():
        out["rows"][name] = {"sigmas": model.sigmas(), **score(model, seg, cfg)}
    return out
