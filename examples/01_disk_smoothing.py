"""Smooth a noisy track of the paper's disk dynamics with a factor graph.

What it shows: how to write a smoother in eqsmooth — a state group with a
leading time axis, a dynamics factor written as a plain function, a
position-measurement factor, a prior — and how to solve it exactly with the
block-tridiagonal Gauss-Newton solver, batched over many sequences with
`jax.vmap`. It prints the per-coordinate position RMSE of the raw
measurements and of the smoothed estimate, and saves a plot.

Dynamics (Yi et al. 2021, disk tracking): p' = p + v, v' = v − 0.05 p −
0.0075 sign(v) v², with process noise std 0.1 (position) and 2 (velocity);
positions measured with std 5 px.

Runtime on 2 CPU cores: about 10 s with `--quick` (mostly compilation),
about 20 s for the default 256 sequences × 200 steps.

    python examples/01_disk_smoothing.py --quick --out results/demo
"""

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs


SPRING, DRAG = 0.05, 0.0075
Q_POS, Q_VEL, R_MEAS = 0.1, 2.0, 5.0


def dynamics(x):
    """One step of the disk dynamics on the state x = (px, py, vx, vy)."""
    p, v = x[:2], x[2:]
    return jnp.concatenate([p + v, v - SPRING * p - DRAG * jnp.sign(v) * v * v])


def simulate(key, num_seqs: int, num_steps: int):
    k0, k1, k2, k3 = jax.random.split(key, 4)
    p0 = jax.random.uniform(k0, (num_seqs, 2), minval=-60.0, maxval=60.0)
    v0 = 3.0 * jax.random.normal(k1, (num_seqs, 2))
    noise = jax.random.normal(k2, (num_steps - 1, num_seqs, 4)) * jnp.array(
        [Q_POS, Q_POS, Q_VEL, Q_VEL]
    )

    def step(x, w):
        nxt = jax.vmap(dynamics)(x) + w
        return nxt, nxt

    x0 = jnp.concatenate([p0, v0], axis=1)
    _, xs = jax.lax.scan(step, x0, noise)
    states = jnp.concatenate([x0[None], xs], axis=0).swapaxes(0, 1)  # (B, T, 4)
    meas = states[..., :2] + R_MEAS * jax.random.normal(k3, states[..., :2].shape)
    return states, meas


def transition_residual(x_prev, x_next, data, params):
    return x_next - dynamics(x_prev)


def measurement_residual(x, data, params):
    return x[:2] - data


def build_graph(measurements, num_steps: int) -> eqs.FactorGraph:
    t = np.arange(num_steps)
    dyn = eqs.FunctionFactor(
        transition_residual,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.DiagonalNoise.from_sigmas(jnp.array([Q_POS, Q_POS, Q_VEL, Q_VEL])),
    )
    obs = eqs.FunctionFactor(
        measurement_residual,
        (eqs.Var("x", t),),
        eqs.IsotropicNoise.from_sigma(R_MEAS),
        data=measurements,
    )
    return eqs.FactorGraph([dyn, obs])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small, fast run")
    parser.add_argument("--out", type=Path, default=Path("results/disk_smoothing"))
    parser.add_argument("--seqs", type=int, default=256)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.quick:
        args.seqs, args.steps = 16, 50

    states, meas = simulate(jax.random.key(args.seed), args.seqs, args.steps)
    solver = eqs.GaussNewton(eqs.BlockTridiagonal())

    @jax.jit
    def smooth_batch(meas):
        def one(m):
            graph = build_graph(m, args.steps)
            # Initialise at the measurements with zero velocity.
            init = {"x": jnp.concatenate([m, jnp.zeros_like(m)], axis=1)}
            sol = eqs.least_squares(graph, init, solver, max_steps=20, throw=False)
            return (
                sol.value["x"],
                sol.stats["num_steps"],
                sol.result == eqs.RESULTS.successful,
            )

        return jax.vmap(one)(meas)

    t0 = time.perf_counter()
    est, steps, codes = jax.block_until_ready(smooth_batch(meas))
    t1 = time.perf_counter()
    est, steps, codes = jax.block_until_ready(smooth_batch(meas))
    t2 = time.perf_counter()

    def rmse(a, b):
        return float(jnp.sqrt(jnp.mean((a - b) ** 2)))

    print(
        f"{args.seqs} sequences x {args.steps} steps{' (quick)' if args.quick else ''}"
    )
    print("| estimate | position RMSE (px, per coordinate) |")
    print("|---|---|")
    print(f"| raw measurements | {rmse(meas, states[..., :2]):.3f} |")
    print(f"| smoothed (MAP) | {rmse(est[..., :2], states[..., :2]):.3f} |")
    print(
        f"Gauss-Newton steps: mean {float(jnp.mean(steps)):.1f}, all converged: "
        f"{bool(jnp.all(codes))}; first call {t1 - t0:.2f} s (with compile), "
        f"second {t2 - t1:.3f} s"
    )

    args.out.mkdir(parents=True, exist_ok=True)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot(*states[0, :, :2].T, "k-", label="truth")
    ax.plot(*meas[0].T, "r.", ms=3, label="measurements")
    ax.plot(*est[0, :, :2].T, "b-", label="smoothed")
    ax.set_aspect("equal")
    ax.legend()
    ax.set_title("Disk dynamics: MAP smoothing")
    fig.savefig(args.out / "disk_smoothing.png", dpi=120, bbox_inches="tight")
    print(f"saved {args.out / 'disk_smoothing.png'}")


if __name__ == "__main__":
    main()
