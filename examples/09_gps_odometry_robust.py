"""GPS + odometry with outliers: robust kernels, and learning the kernel's scale.

What it shows: a planar trajectory (`SE2` poses) with odometry
(`BetweenFactor`) and GPS fixes (`TranslationPriorFactor`), 15 % of which are
gross outliers (multipath jumps of 5 to 15 m). The same graph is solved with
a Gaussian GPS model, with Huber, and with Tukey's biweight started from the
Huber solution (a non-convex kernel wants a good start); the script prints
the position RMSE of each. It then treats the Huber threshold as a
parameter and fits it with `eqsmooth.learn.train` (Adam) on the position
error of training trajectories, differentiating through the solve (implicit
adjoint), keeps the threshold with the lowest error on two validation
trajectories, and reports the error on two test trajectories before and
after. A JSON summary is saved in `--out`.

Runtime: with `--quick`, measured on 2 CPU cores shared with two other heavy
jobs, 90 s in all: 30 s for the three first solves and 39 s for the six
training steps with their validations, nearly all of it compilation. The
default size is not timed yet.

    python examples/09_gps_odometry_robust.py --quick --out results/09
"""

import argparse
import json
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth as eqs  # noqa: E402


# Compiled programs are kept on disk: a second run answers sooner.
eqs.enable_compilation_cache()


ODO_SIGMA = np.array([0.05, 0.05, 0.01])
GPS_SIGMA = 0.5


def make_data(T: int, seed: int):
    rng = np.random.default_rng(seed)
    heading = np.cumsum(0.15 * np.sin(np.arange(T) / 7.0))
    step = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    xy = np.cumsum(step, axis=0)
    truth = eqs.SE2.from_xy_theta(
        jnp.asarray(xy[:, 0]), jnp.asarray(xy[:, 1]), jnp.asarray(heading)
    )
    rel = truth[:-1].inverse() @ truth[1:]
    odo = rel @ eqs.SE2.exp(jnp.asarray(ODO_SIGMA * rng.standard_normal((T - 1, 3))))
    gps = xy + GPS_SIGMA * rng.standard_normal((T, 2))
    outlier = rng.random(T) < 0.15
    jump = rng.uniform(5, 15, T)[:, None] * np.stack(
        [np.cos(a := rng.uniform(0, 2 * np.pi, T)), np.sin(a)], axis=1
    )
    gps = np.where(outlier[:, None], gps + jump, gps)
    # Initial guess: the raw GPS fixes with the odometry headings.
    init = eqs.SE2.from_xy_theta(
        jnp.asarray(gps[:, 0]), jnp.asarray(gps[:, 1]), jnp.asarray(heading)
    )
    return truth, odo, jnp.asarray(gps), init, outlier


def make_graph(odo, gps, gps_noise):
    T = gps.shape[0]
    ids = np.arange(T)
    return eqs.FactorGraph(
        [
            eqs.BetweenFactor(
                eqs.Var("x", ids[:-1]),
                eqs.Var("x", ids[1:]),
                odo,
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(ODO_SIGMA)),
            ),
            eqs.TranslationPriorFactor(eqs.Var("x", ids), gps, gps_noise),
        ]
    )


def rmse(values, truth) -> float:
    """Position RMSE of the poses (m)."""
    d = values["x"].translation() - truth.translation()
    return float(jnp.sqrt(jnp.mean(jnp.sum(d * d, axis=1))))


def compare_kernels(truth, odo, gps, init, solver) -> dict:
    """Solve with a Gaussian, a Huber and (from Huber's answer) a Tukey GPS
    model; return the position RMSE of each and of the raw fixes."""
    base = eqs.IsotropicNoise.from_sigma(GPS_SIGMA)
    raw = np.asarray(gps) - np.asarray(truth.translation())
    results = {"gps_rmse": float(np.sqrt(np.mean(np.sum(raw**2, axis=1))))}
    t0 = time.perf_counter()
    gauss = eqs.least_squares(
        make_graph(odo, gps, base), {"x": init}, solver, max_steps=50
    )
    huber = eqs.least_squares(
        make_graph(odo, gps, eqs.HuberNoise(base, 1.345)),
        {"x": init},
        solver,
        max_steps=50,
    )
    tukey = eqs.least_squares(
        make_graph(odo, gps, eqs.TukeyNoise(base, 4.685)),
        huber.value,
        solver,
        max_steps=50,
    )
    for name, sol in (("gaussian", gauss), ("huber", huber), ("tukey", tukey)):
        results[f"{name}_rmse"] = rmse(sol.value, truth)
    print(f"solves (with compilation): {time.perf_counter() - t0:.1f} s")
    return results


class HuberThreshold(eqx.Module):
    """The learned parameter: the log of the Huber threshold `k` (whitened units)."""

    log_k: jax.Array

    @property
    def k(self) -> float:
        return float(jnp.exp(self.log_k))


def position_mse(model: HuberThreshold, batch, solver) -> jax.Array:
    """Mean squared position error (m²) of the robust solves of a batch of
    trajectories, differentiable in the threshold through the solve."""
    base = eqs.IsotropicNoise.from_sigma(GPS_SIGMA)

    def one(truth, odo, gps, init):
        graph = make_graph(odo, gps, eqs.HuberNoise(base, jnp.exp(model.log_k)))
        sol = eqs.least_squares(graph, {"x": init}, solver, max_steps=50)
        d = sol.value["x"].translation() - truth.translation()
        return jnp.mean(jnp.sum(d * d, axis=1))

    return jnp.mean(jax.vmap(one)(*batch))


def stack(trajectories):
    """Trajectories `(truth, odo, gps, init)` stacked along a new leading axis."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trajectories)


def learn_threshold(train, valid, test, solver, steps: int) -> dict:
    """Fit the Huber threshold with `eqsmooth.learn.train` (Adam on log k,
    gradients through the solve); keep the threshold with the lowest
    validation error, and report the test error before and after."""

    def loss(model, batch):
        return position_mse(model, batch, solver)

    model = HuberThreshold(jnp.asarray(np.log(5.0)))  # a deliberately loose start
    test_loss = eqx.filter_jit(loss)
    test_before = float(test_loss(model, test))
    t0 = time.perf_counter()
    result = eqs.learn.train(
        model,
        loss,
        train,
        optimizer=eqs.learn.make_optimizer(0.2, warmup_steps=0, decay_steps=steps),
        num_steps=steps,
        batch_size=2,
        validation=eqs.learn.Validation(valid, every=max(steps // 4, 1)),
        logging=eqs.learn.Logging(progress=False),
    )
    best = result.best_model
    test_after = float(test_loss(best, test))
    for record in result.history:
        if "valid_loss" in record:
            print(f"  step {record['step']}: valid MSE {record['valid_loss']:.4f} m²")
    print(
        f"learned Huber k = {best.k:.3f} (best validation MSE at step "
        f"{result.best_step}, {time.perf_counter() - t0:.1f} s); "
        f"test MSE {test_before:.4f} -> {test_after:.4f} m²"
    )
    return dict(
        learned_k=best.k,
        best_step=int(result.best_step),
        test_mse_before=test_before,
        test_mse_after=test_after,
    )


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small, fast run (CI)")
    parser.add_argument(
        "--out", type=Path, default=Path("results/09_gps_odometry_robust")
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    T, train_steps, num_train = (60, 6, 2) if args.quick else (200, 40, 8)

    truth, odo, gps, init, outlier = make_data(T, args.seed)
    print(f"{T} poses, {int(outlier.sum())} GPS outliers")
    solver = eqs.LevenbergMarquardt()
    results = compare_kernels(truth, odo, gps, init, solver)
    print(
        f"position RMSE: raw GPS {results['gps_rmse']:.3f} m, Gaussian "
        f"{results['gaussian_rmse']:.3f} m, Huber {results['huber_rmse']:.3f} m, "
        f"Tukey (from Huber) {results['tukey_rmse']:.3f} m"
    )
    # Learn the Huber threshold on training trajectories, select it on
    # validation trajectories, test it on others.
    data = [make_data(T, args.seed + 1 + i)[:4] for i in range(num_train + 4)]
    train, valid, test = (
        stack(data[:num_train]),
        stack(data[num_train : num_train + 2]),
        stack(data[num_train + 2 :]),
    )
    results.update(learn_threshold(train, valid, test, solver, train_steps))

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gps_odometry_robust.json").write_text(json.dumps(results, indent=2))
    print(f"saved {args.out / 'gps_odometry_robust.json'}")


if __name__ == "__main__":
    main()
