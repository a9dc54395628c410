"""Planar landmark SLAM with bearing-range measurements.

What it shows: the built-in measurement factors on a GTSAM-style planar SLAM
problem. A robot drives around a loop; odometry links consecutive poses
(`BetweenFactor`), and every landmark within sensor range is measured by
bearing and range (`BearingRangeFactor`), so each landmark is seen from
several poses. Poses (`SE2`) and landmarks (plain `(2,)` points) are two
variable groups of one graph, solved with Levenberg-Marquardt; the script
prints the pose and landmark errors before and after, the marginal
covariance of the first landmark and its cross-covariance with the last
pose (`joint_marginal_covariance`), and saves a plot and a JSON summary.

Runtime: with `--quick`, 80 s measured for the first solve (nearly all of
it compilation) on 2 CPU cores shared with another heavy job; expect less
on an idle machine. The default size is not timed yet.

    python examples/08_landmark_slam.py --quick --out results/08
"""

import argparse
import json
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth as eqs  # noqa: E402


# Compiled programs are kept on disk: a second run answers sooner.
eqs.enable_compilation_cache()


def make_problem(num_poses: int, num_landmarks: int, seed: int):
    """Ground truth, measurements and a dead-reckoning initial guess."""
    rng = np.random.default_rng(seed)
    # A circle of radius 10 with landmarks scattered around it.
    t = np.linspace(0, 2 * np.pi, num_poses, endpoint=False)
    xyt = np.stack([10 * np.cos(t), 10 * np.sin(t), t + np.pi / 2], axis=1)
    truth = eqs.SE2.from_xy_theta(*(jnp.asarray(xyt[:, i]) for i in range(3)))
    ang = rng.uniform(0, 2 * np.pi, num_landmarks)
    rad = rng.uniform(6, 14, num_landmarks)
    landmarks = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=1)

    odo_sigma = np.array([0.05, 0.05, 0.01])
    rel = truth[:-1].inverse() @ truth[1:]
    odo = rel @ eqs.SE2.exp(
        jnp.asarray(odo_sigma * rng.standard_normal((num_poses - 1, 3)))
    )

    # Every landmark within 8 m of a pose is observed from it.
    pose_ids, lm_ids = [], []
    for i in range(num_poses):
        d = np.linalg.norm(landmarks - xyt[i, :2], axis=1)
        for j in np.flatnonzero(d < 8.0):
            pose_ids.append(i)
            lm_ids.append(j)
    pose_ids, lm_ids = np.array(pose_ids), np.array(lm_ids)
    local = np.asarray(
        jax.vmap(lambda p, q: p.inverse().apply(q))(
            truth[pose_ids], jnp.asarray(landmarks[lm_ids])
        )
    )
    br_sigma = np.array([0.02, 0.1])
    bearing = np.arctan2(local[:, 1], local[:, 0]) + br_sigma[0] * rng.standard_normal(
        len(lm_ids)
    )
    rng_m = np.linalg.norm(local, axis=1) + br_sigma[1] * rng.standard_normal(
        len(lm_ids)
    )

    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]),
                truth[:1],
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.01, 0.01, 0.01])),
            ),
            eqs.BetweenFactor(
                eqs.Var("x", np.arange(num_poses - 1)),
                eqs.Var("x", np.arange(1, num_poses)),
                odo,
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(odo_sigma)),
            ),
            eqs.BearingRangeFactor(
                eqs.Var("x", pose_ids),
                eqs.Var("l", lm_ids),
                jnp.asarray(bearing),
                jnp.asarray(rng_m),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(br_sigma)),
            ),
        ]
    )
    # Initial guess: dead reckoning from the odometry; landmarks placed from
    # their first observation.
    poses = [truth[0]]
    for k in range(num_poses - 1):
        poses.append(poses[-1] @ odo[k])
    dead = eqs.SE2(jnp.stack([p.parameters() for p in poses]))
    first = {}
    for n, (i, j) in enumerate(zip(pose_ids, lm_ids)):
        first.setdefault(int(j), n)
    init_l = np.zeros((num_landmarks, 2))
    for j in range(num_landmarks):
        n = first.get(j)
        if n is None:
            init_l[j] = landmarks[j] + 1.0  # unseen: anything (kept by no factor)
            continue
        b, r = bearing[n], rng_m[n]
        init_l[j] = np.asarray(
            dead[int(pose_ids[n])].apply(jnp.array([r * np.cos(b), r * np.sin(b)]))
        )
    seen = np.zeros(num_landmarks, bool)
    seen[lm_ids] = True
    return (
        graph,
        truth,
        landmarks,
        {"x": dead, "l": jnp.asarray(init_l)},
        seen,
        len(lm_ids),
    )


def errors(values, truth, landmarks) -> tuple[float, float]:
    """Position RMSE of the poses and of the landmarks (m)."""
    pos = np.linalg.norm(
        np.asarray(values["x"].translation() - truth.translation()), axis=1
    )
    lm = np.linalg.norm(np.asarray(values["l"]) - landmarks, axis=1)
    return float(np.sqrt(np.mean(pos**2))), float(np.sqrt(np.mean(lm**2)))


def plot(path: Path, truth, landmarks, init, solved) -> None:
    """Poses and landmarks: truth, initial guess and solution."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print(f"saved {path.with_suffix('.json')} (no matplotlib: no plot)")
        return
    fig, ax = plt.subplots(figsize=(6, 6))
    for name, v, style in (
        ("truth", {"x": truth, "l": landmarks}, "k-"),
        ("initial", init, "r:"),
        ("solved", solved, "b-"),
    ):
        xy = np.asarray(v["x"].translation())
        ax.plot(xy[:, 0], xy[:, 1], style, label=f"{name} poses")
    ax.scatter(
        landmarks[:, 0], landmarks[:, 1], marker="*", c="k", label="true landmarks"
    )
    est = np.asarray(solved["l"])
    ax.scatter(est[:, 0], est[:, 1], marker="x", c="b", label="estimated landmarks")
    ax.set_aspect("equal")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    print(f"saved {path} and {path.with_suffix('.json').name}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small, fast run (CI)")
    parser.add_argument("--out", type=Path, default=Path("results/08_landmark_slam"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    num_poses, num_landmarks = (24, 8) if args.quick else (100, 30)

    graph, truth, landmarks, init, seen, n_obs = make_problem(
        num_poses, num_landmarks, args.seed
    )
    if not seen.all():
        # A landmark nobody sees has no factor: drop it from the problem.
        raise SystemExit("some landmark is never observed; try another --seed")
    print(
        f"{num_poses} poses, {num_landmarks} landmarks, "
        f"{n_obs} bearing-range measurements"
    )

    t0 = time.perf_counter()
    sol = eqs.least_squares(graph, init, eqs.LevenbergMarquardt(), max_steps=50)
    jax.block_until_ready(sol.value)
    t1 = time.perf_counter()
    print(
        f"solve (with compilation): {t1 - t0:.1f} s, "
        f"{int(sol.stats['num_steps'])} steps, result: {sol.result}"
    )
    before = errors(init, truth, landmarks)
    after = errors(sol.value, truth, landmarks)
    print(f"pose RMSE      {before[0]:8.3f} m -> {after[0]:.3f} m")
    print(f"landmark RMSE  {before[1]:8.3f} m -> {after[1]:.3f} m")

    # Uncertainty: landmark 0 and the last pose, jointly (the stored
    # linearisation of the solve is reused; no relinearisation).
    joint = np.asarray(
        eqs.joint_marginal_covariance(sol, [("l", 0), ("x", num_poses - 1)])
    )
    print("landmark 0 marginal std (m):", np.sqrt(np.diag(joint[:2, :2])).round(4))
    print("cross-covariance landmark 0 / last pose (x, y):\n", joint[:2, 2:4].round(5))

    args.out.mkdir(parents=True, exist_ok=True)
    summary = {
        "num_poses": num_poses,
        "num_landmarks": num_landmarks,
        "num_observations": n_obs,
        "pose_rmse_before": before[0],
        "pose_rmse_after": after[0],
        "landmark_rmse_before": before[1],
        "landmark_rmse_after": after[1],
        "landmark0_std": np.sqrt(np.diag(joint[:2, :2])).tolist(),
        "solve_s_with_compile": t1 - t0,
    }
    (args.out / "landmark_slam.json").write_text(json.dumps(summary, indent=2))
    plot(args.out / "landmark_slam.png", truth, landmarks, init, sol.value)


if __name__ == "__main__":
    main()
