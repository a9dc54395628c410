"""Porting GTSAM's ISAM2 loop: a growing Pose2 graph, one pose per update,
solved by `eqs.solve.IncrementalSmoother` and (when gtsam is installed) by
GTSAM's `ISAM2` with default parameters in the same process.

Two replays: `square`, the shape of GTSAM's Pose2ISAM2Example (a square
driven in laps, 8 poses a lap, a loop closure to the pose one lap back at
3 of every 4 poses after the first lap); `w10000`, the first `--poses`
poses of GTSAM's `w10000.graph` (each added with its edges to earlier
poses; every edge with the same noise). Per update: the median wall time
of eqsmooth's updates that did not grow a buffer (the growths, each one
compile, are counted and timed apart) and of ISAM2's `update` +
`calculateEstimate`; `max_diff`: the largest tangent difference of each
library's final estimate from the batch Levenberg-Marquardt solution of
the whole graph. `--one-step` adds a run with one Gauss-Newton step per
update (`IncrementalSmoother(FixedStepGaussNewton(num_steps=1))`), as
iSAM2 relinearises once per update instead of iterating to convergence.
Each pose goes in with `IncrementalSmoother.update_rows` (the edges into
it as arrays, a block of as many rows as the most edges into one pose,
the absent ones masked; built before the clock starts, as ISAM2's factor
graph is), or with `update` and factor objects given `--update` (built
after the clock starts, as before 2026-11-29). `first_update_s`:
`update_rows`' first call, which compiles its program (out of the median).
A run takes about 2 minutes for `square` and 10 for `w10000` (200 poses)
on a loaded 2-core machine, most of it compiling.

    OPENBLAS_NUM_THREADS=1 python examples/isam2_replay.py --replays square \
        --one-step --json benchmarks/results/incremental.json

(`OPENBLAS_NUM_THREADS=1`: on a busy machine jaxlib's LAPACK calls on
OpenBLAS threads can be a hundred times slower.)
"""

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth as eqs  # noqa: E402


SIGMAS = np.array([0.2, 0.2, np.deg2rad(5.0)])


def square(poses: int) -> list:
    """Edges `(a, b, (x, y, θ))`, `a < b`, with noise of `SIGMAS`."""
    rng = np.random.default_rng(0)
    edges = [
        (i, i + 1, (2.0, 0.0, np.pi / 2 if i % 2 else 0.0)) for i in range(poses - 1)
    ]
    edges += [(i - 8, i, (0.0, 0.0, 0.0)) for i in range(8, poses) if i % 4]
    return [(a, b, np.asarray(m) + SIGMAS * rng.normal(size=3)) for a, b, m in edges]


def w10000(poses: int, path: str) -> list:
    edges = []
    for line in open(path):
        f = line.split()
        if f and f[0] == "EDGE2" and max(int(f[1]), int(f[2])) < poses:
            a, b, (x, y, t) = int(f[1]), int(f[2]), np.array(f[3:6], float)
            if a > b:  # the same edge from b to a: the inverse measurement
                c, s = np.cos(t), np.sin(t)
                a, b, x, y, t = b, a, -c * x - s * y, s * x - c * y, -t
            edges.append((a, b, np.array([x, y, t])))
    return edges


def se2(xyt) -> eqs.SE2:
    xyt = np.asarray(xyt, float).reshape(-1, 3)
    return eqs.SE2.from_xy_theta(*(jnp.asarray(c) for c in xyt.T))


def tangent_diff(a: eqs.SE2, b: eqs.SE2) -> float:
    return float(np.abs(np.asarray((a.inverse() @ b).log())).max())


def eqsmooth_replay(edges, poses: int, solver, rows: bool) -> tuple[dict, eqs.SE2]:
    noise = eqs.DiagonalNoise.from_sigmas(jnp.asarray(SIGMAS))

    def between(a, b, m):
        return eqs.BetweenFactor(
            eqs.Var("pose", [a]), eqs.Var("pose", [b]), se2(m), noise
        )

    odom = {b: m for a, b, m in edges if b == a + 1}
    into = [[e for e in edges if e[1] == j] for j in range(poses)]
    prior = eqs.PriorFactor(eqs.Var("pose", [0]), se2([0, 0, 0]), noise)
    smoother = eqs.solve.IncrementalSmoother(solver)
    t0 = time.perf_counter()
    first = eqs.FactorGraph([prior, between(0, 1, odom[1])])
    state = smoother.init(first, {"pose": se2([[0, 0, 0], odom[1]])})
    jax.block_until_ready(state.values)
    init_s = time.perf_counter() - t0
    times, growths, first_s = [], [], None
    # update_rows: each update's edges as one block of k rows (the most edges
    # into one pose), the absent ones masked, so that one program serves all.
    k = max(len(e) for e in into)
    for j in range(2, poses):
        last = state.estimate()["pose"].unit_complex_xy[-1:]  # host numpy
        guess = eqs.SE2(jnp.asarray(last)) @ se2(odom[j])
        capacity = state.capacity
        if rows:  # the update's data, built before the clock (as ISAM2's graph)
            es = into[j] + into[j][:1] * (k - len(into[j]))
            xyt = np.array([m for _, _, m in es])
            c, s = np.cos(xyt[:, 2]), np.sin(xyt[:, 2])
            measured = eqs.SE2(np.stack([c, s, xyt[:, 0], xyt[:, 1]], axis=1))
            ids = (np.array([e[0] for e in es]), np.array([e[1] for e in es]))
            active = np.arange(k) < len(into[j])
        t0 = time.perf_counter()
        if rows:
            state = smoother.update_rows(
                state,
                [None, {"measurement": measured}],
                [None, ids],
                [None, active],
                {"pose": guess},
            )
        else:
            factors = [between(*e) for e in into[j]]
            state = smoother.update(state, factors, {"pose": guess})
        jax.block_until_ready(state.values)
        dt = time.perf_counter() - t0
        if state.capacity != capacity:
            growths.append(dt)
        elif rows and first_s is None:
            first_s = dt  # update_rows' first call compiles its program
        else:
            times.append(dt)
    est = eqs.SE2(jnp.asarray(state.estimate()["pose"].unit_complex_xy))
    full = eqs.FactorGraph(
        eqs.factors.merge_stacks([prior] + [between(*e) for e in edges])
    )
    batch = eqs.least_squares(full, {"pose": est}, eqs.LevenbergMarquardt()).value[
        "pose"
    ]
    rec = dict(
        init_s=init_s,
        median_ms=1e3 * statistics.median(times),
        growths=len(growths),
        growth_s=sum(growths),
        **({"first_update_s": first_s} if rows else {}),
        capacity=str(state.capacity),
        max_diff=tangent_diff(batch, est),
    )
    return rec, batch


def isam2_replay(gtsam, edges, poses: int, batch: eqs.SE2) -> dict:
    X, noise = gtsam.symbol_shorthand.X, gtsam.noiseModel.Diagonal.Sigmas(SIGMAS)
    odom = {b: m for a, b, m in edges if b == a + 1}
    isam, times = gtsam.ISAM2(), []
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(), noise))
    values.insert(X(0), gtsam.Pose2())
    isam.update(graph, values)
    estimate = isam.calculateEstimate()
    for j in range(1, poses):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for a, b, m in (e for e in edges if e[1] == j):
            graph.add(gtsam.BetweenFactorPose2(X(a), X(b), gtsam.Pose2(*m), noise))
        values.insert(X(j), estimate.atPose2(X(j - 1)).compose(gtsam.Pose2(*odom[j])))
        t0 = time.perf_counter()
        isam.update(graph, values)
        estimate = isam.calculateEstimate()
        times.append(time.perf_counter() - t0)
    p = [estimate.atPose2(X(i)) for i in range(poses)]
    est = se2([[q.x(), q.y(), q.theta()] for q in p])
    return dict(
        median_ms=1e3 * statistics.median(times), max_diff=tangent_diff(batch, est)
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--poses", type=int, nargs=2, default=[41, 200], help="square, w10000"
    )
    ap.add_argument("--replays", nargs="+", default=["square", "w10000"])
    ap.add_argument("--json", default=None, help="write the records here")
    ap.add_argument(
        "--one-step",
        action="store_true",
        help="also run one Gauss-Newton step per update (FixedStepGaussNewton(1))",
    )
    ap.add_argument(
        "--update",
        action="store_true",
        help="add each pose with update (factor objects) instead of update_rows",
    )
    args = ap.parse_args()
    try:
        import gtsam
    except ImportError:
        gtsam = None
        print("gtsam is not installed: eqsmooth only, and no w10000 replay")
    replays = [("square", square(args.poses[0]), args.poses[0])]
    if gtsam and "w10000" in args.replays:
        path = gtsam.findExampleDataFile("w10000.graph")
        replays.append(("w10000", w10000(args.poses[1], path), args.poses[1]))
    records = []
    for name, edges, poses in replays:
        if name not in args.replays:
            continue
        rows = not args.update
        rec, batch = eqsmooth_replay(edges, poses, eqs.LevenbergMarquardt(), rows)
        rec = dict(replay=name, poses=poses, edges=len(edges), eqsmooth=rec)
        if args.one_step:
            # One Gauss-Newton step per update, as iSAM2 relinearises once.
            one_step = eqs.FixedStepGaussNewton(num_steps=1)
            one, _ = eqsmooth_replay(edges, poses, one_step, rows)
            rec["eqsmooth_one_step"] = one
        if gtsam:
            rec["isam2"] = isam2_replay(gtsam, edges, poses, batch)
            rec["ratio"] = rec["eqsmooth"]["median_ms"] / rec["isam2"]["median_ms"]
            if args.one_step:
                rec["ratio_one_step"] = one["median_ms"] / rec["isam2"]["median_ms"]
        print(json.dumps(rec), flush=True)
        records.append(rec)
    if args.json:
        meta = dict(
            command="OPENBLAS_NUM_THREADS=1 python examples/isam2_replay.py --poses "
            + " ".join(map(str, args.poses))
            + " --replays "
            + " ".join(args.replays)
            + (" --one-step" if args.one_step else "")
            + (" --update" if args.update else ""),
            jax=jax.__version__,
            gtsam=getattr(gtsam, "__version__", None),
            cpus=os.cpu_count(),
            load_average=os.getloadavg(),
            date=time.strftime("%Y-%m-%d"),
        )
        Path(args.json).write_text(
            json.dumps(dict(meta=meta, records=records), indent=1)
        )


if __name__ == "__main__":
    main()
