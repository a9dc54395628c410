import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int

from ..factors import (
    BetweenFactor,
    FactorGraph,
    IsotropicNoise,
    PriorFactor,
    SqrtInformationNoise,
    Var,
)
from ..lie import SE2, SE3


POSE = "pose"
"""Name of the variable group holding the poses of a [`eqsmooth.io.PoseGraph`][]."""

_GROUPS = {"se2": SE2, "se3": SE3}


class PoseGraph(eqx.Module):
    """A pose graph: relative-pose factors, initial values and file metadata.

    Made by [`eqsmooth.io.load_g2o`][] and
    [`eqsmooth.io.synthetic_pose_graph_2d`][]. Solve it with
    `least_squares(pg.graph, pg.values, solver)`.

    **Fields:**

    - `graph`: a [`eqsmooth.factors.FactorGraph`][] with one
        [`eqsmooth.factors.BetweenFactor`][] stack (one row per edge) and, when
        anchored, one [`eqsmooth.factors.PriorFactor`][] stack.
    - `values`: initial values `{"pose": SE2 or SE3 stacked over N poses}`.
    - `vertex_ids`: the file's id of each pose, in pose order (ids need not be
        contiguous; pose `i` is vertex `vertex_ids[i]`).
    - `anchored`: pose indices held by the gauge prior (empty if none).
    - `kind`: `"se2"` or `"se3"`.
    - `se3_information`: how the file's SE(3) information matrices were read
        (`"g2o"` or `"gtsam"`, see [`eqsmooth.io.load_g2o`][]); used to write
        them back.
    """

    graph: FactorGraph
    values: dict
    vertex_ids: Int[np.ndarray, " N"]
    anchored: Int[np.ndarray, " F"]
    kind: str = eqx.field(static=True)
    se3_information: str = eqx.field(static=True, default="g2o")

    def __check_init__(self):
        if self.kind not in _GROUPS:
            raise ValueError(
                f"PoseGraph.kind must be 'se2' or 'se3', got {self.kind!r}"
            )
        if self.se3_information not in ("g2o", "gtsam"):
            raise ValueError(
                "PoseGraph.se3_information must be 'g2o' or 'gtsam', got "
                f"{self.se3_information!r}"
            )

    @property
    def poses(self) -> SE2 | SE3:
        """The initial poses, stacked (`values["pose"]`)."""
        return self.values[POSE]

    @property
    def num_poses(self) -> int:
        """Number of poses `N`."""
        return int(self.vertex_ids.shape[0])

    @property
    def between(self) -> BetweenFactor:
        """The stacked relative-pose factor (one row per edge)."""
        for f in self.graph.factors:
            if isinstance(f, BetweenFactor):
                return f
        raise ValueError("this PoseGraph has no BetweenFactor")

    @property
    def num_edges(self) -> int:
        """Number of relative-pose edges (the anchor prior is not counted)."""
        return self.between.num_rows

    @property
    def edges(self) -> Int[np.ndarray, "E 2"]:
        """Pose indices `(i, j)` of every edge, in file order."""
        a, b = self.between.variables
        return np.stack([a.ids, b.ids], axis=1)


def _sqrt_information_np(information: np.ndarray) -> np.ndarray:
    # Lower-triangular R with RᵀR = Λ, from a Cholesky factor of the
    # order-reversed matrix (same construction as
    # SqrtInformationNoise.from_information, done in float64 numpy).
    flip = information[..., ::-1, ::-1]
    L = np.linalg.cholesky(flip)
    return np.swapaxes(L, -1, -2)[..., ::-1, ::-1]


def default_dtype():
    return jax.dtypes.canonicalize_dtype(jnp.float64)


def make_pose_graph(
    kind: str,
    poses: Float[np.ndarray, "N p"],
    edges: Int[np.ndarray, "E 2"],
    measurements: Float[np.ndarray, "E p"],
    information: Float[np.ndarray, "E d d"],
    *,
    vertex_ids: Int[np.ndarray, " N"] | None = None,
    anchor: bool = True,
    anchored: Int[np.ndarray, " F"] | None = None,
    anchor_sqrt_information: float = 1e6,
    se3_information: str = "g2o",
    dtype=None,
) -> PoseGraph:
    """Assemble a [`eqsmooth.io.PoseGraph`][] from numpy arrays.

    **Arguments:**

    - `kind`: `"se2"` or `"se3"`.
    - `poses`: group parameters of the initial poses (`SE2.unit_complex_xy` or
        `SE3.wxyz_xyz` layout), float64.
    - `edges`: pose indices `(i, j)` per edge; the residual is
        `log(z⁻¹ xᵢ⁻¹ xⱼ)`.
    - `measurements`: group parameters of the measured `xᵢ⁻¹ xⱼ`.
    - `information`: information matrices in eqsmooth's tangent order
        (translation first), positive definite.
    - `vertex_ids`: file ids of the poses (default `0..N-1`).
    - `anchor`: add the gauge prior on the `anchored` poses (default: pose 0).
    - `anchor_sqrt_information`: its isotropic square-root information.
    - `se3_information`: recorded on the result (see
        [`eqsmooth.io.load_g2o`][]).
    - `dtype`: float dtype of the arrays (default: JAX's default float).
    """
    group = _GROUPS[kind]
    dtype = default_dtype() if dtype is None else dtype
    n = poses.shape[0]
    if vertex_ids is None:
        vertex_ids = np.arange(n, dtype=np.int64)
    if not anchor:
        anchored = np.zeros((0,), np.int64)
    elif anchored is None or len(anchored) == 0:
        anchored = np.zeros((1,), np.int64)
    else:
        anchored = np.asarray(anchored, np.int64)
    values = {POSE: group(jnp.asarray(poses, dtype))}
    R = _sqrt_information_np(np.asarray(information, np.float64))
    factors = [
        BetweenFactor(
            Var(POSE, edges[:, 0]),
            Var(POSE, edges[:, 1]),
            group(jnp.asarray(measurements, dtype)),
            SqrtInformationNoise(jnp.asarray(R, dtype)),
        )
    ]
    if anchor:
        factors.append(
            PriorFactor(
                Var(POSE, anchored),
                group(jnp.asarray(poses[anchored], dtype)),
                IsotropicNoise(
                    sqrt_precision=jnp.asarray(anchor_sqrt_information, dtype)
                ),
            )
        )
    return PoseGraph(
        graph=FactorGraph(factors),
        values=values,
        vertex_ids=np.asarray(vertex_ids, np.int64),
        anchored=anchored,
        kind=kind,
        se3_information=se3_information,
    )
