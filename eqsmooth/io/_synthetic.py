import numpy as np

from ..lie import SE2
from ._pose_graph import default_dtype, make_pose_graph, PoseGraph


def _relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(x, y, θ)` of `a⁻¹ b` for poses given as `(x, y, θ)` rows."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    dtheta = np.angle(np.exp(1j * (b[:, 2] - a[:, 2])))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dtheta], axis=1)


def _compose(a: np.ndarray, z: np.ndarray) -> np.ndarray:
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array(
        [a[0] + c * z[0] - s * z[1], a[1] + s * z[0] + c * z[1], a[2] + z[2]]
    )


def synthetic_pose_graph_2d(
    num_poses: int = 400,
    *,
    seed: int = 0,
    grid_size: int = 10,
    turn_probability: float = 0.3,
    closure_probability: float = 0.5,
    sigma_xy: float = 0.05,
    sigma_theta: float = 0.02,
    anchor: bool = True,
    dtype=None,
) -> tuple[PoseGraph, SE2]:
    """A deterministic, Manhattan-like 2-D pose graph with loop closures.

    A robot walks on a square grid of `grid_size × grid_size` cells with unit
    steps, turning left or right by 90° with probability `turn_probability`
    at each step (and whenever it would leave the grid). Odometry edges join
    consecutive poses; when the robot enters a cell it visited before (not on
    the previous step), a loop-closure edge to one earlier visit is added with
    probability `closure_probability`. Every measurement is the true relative
    pose plus Gaussian noise (`sigma_xy` on x and y, `sigma_theta` on θ), and
    the information matrices are the matching diagonal. The initial values
    compose the noisy odometry, so they drift the way dead reckoning does.

    The same `seed` always gives the same graph (numpy's `default_rng`).

    **Arguments:**

    - `num_poses`: number of poses `N ≥ 2`.
    - `seed`: random seed.
    - `grid_size`, `turn_probability`, `closure_probability`: the walk.
    - `sigma_xy`, `sigma_theta`: measurement noise standard deviations.
    - `anchor`: add the gauge prior on pose 0 (see [`eqsmooth.io.load_g2o`][]).
    - `dtype`: float dtype (default: JAX's default float).

    **Returns:** `(pose_graph, truth)`: a [`eqsmooth.io.PoseGraph`][] and the
    true poses as a stacked [`eqsmooth.lie.SE2`][].
    """
    if num_poses < 2:
        raise ValueError(
            f"synthetic_pose_graph_2d needs num_poses >= 2, got {num_poses}"
        )
    if grid_size < 2:
        raise ValueError(
            f"synthetic_pose_graph_2d needs grid_size >= 2, got {grid_size}"
        )
    rng = np.random.default_rng(seed)
    steps = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    cells = np.zeros((num_poses, 2), np.int64)
    heading = np.zeros(num_poses, np.int64)
    for k in range(1, num_poses):
        h = heading[k - 1]
        if rng.random() < turn_probability:
            h = (h + rng.choice([1, 3])) % 4
        for turn in (0, 1, 3, 2):  # straight, left, right, back: stay on the grid
            nxt = cells[k - 1] + steps[(h + turn) % 4]
            if np.all((nxt >= 0) & (nxt < grid_size)):
                h = (h + turn) % 4
                break
        heading[k] = h
        cells[k] = cells[k - 1] + steps[h]
    truth = np.concatenate(
        [cells.astype(float), heading[:, None] * (np.pi / 2)], axis=1
    )

    pairs = [(k, k + 1) for k in range(num_poses - 1)]
    visits: dict[tuple[int, int], list[int]] = {}
    for k in range(num_poses):
        key = (int(cells[k, 0]), int(cells[k, 1]))
        earlier = [j for j in visits.get(key, []) if j < k - 1]
        if earlier and rng.random() < closure_probability:
            pairs.append((int(earlier[rng.integers(len(earlier))]), k))
        visits.setdefault(key, []).append(k)
    edges = np.asarray(pairs, np.int64)

    sigmas = np.array([sigma_xy, sigma_xy, sigma_theta])
    rel = _relative(truth[edges[:, 0]], truth[edges[:, 1]])
    meas = rel + rng.normal(size=rel.shape) * sigmas
    info = np.broadcast_to(np.diag(1.0 / sigmas**2), (len(edges), 3, 3))

    init = np.zeros_like(truth)
    init[0] = truth[0]
    for k in range(num_poses - 1):
        init[k + 1] = _compose(init[k], meas[k])

    def params(xyt):
        return np.stack(
            [np.cos(xyt[:, 2]), np.sin(xyt[:, 2]), xyt[:, 0], xyt[:, 1]], axis=1
        )

    pg = make_pose_graph(
        "se2", params(init), edges, params(meas), info, anchor=anchor, dtype=dtype
    )
    dtype = default_dtype() if dtype is None else dtype
    return pg, SE2(params(truth).astype(dtype))
