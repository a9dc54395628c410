"""A two-level preconditioner for pose graphs: a smoother plus rigid-body
motions of blocks of consecutive poses as the coarse space."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._precision import einsum
from .._linearization import Linearization, Tangent
from ._pcg import AbstractPreconditioner, ChainPreconditioner


def _links(lin: Linearization, name: str, count: int, dim: int):
    """One factor row joining each pair of consecutive variables `t, t + 1`.

    Returns `(pieces, where)`: `pieces` lists `(factor, rows, slot_t, slot_t1)`
    (static numpy) and `where[t]` is the position of the row for link `t` in
    their concatenation, or -1 where no binary row with square `dim × dim`
    blocks joins `t` and `t + 1`.
    """
    pieces, starts, where = [], 0, np.full(max(count - 1, 0), -1)
    for fi, fl in enumerate(lin.factors):
        if len(fl.variables) != 2 or fl.residual.shape[-1] != dim:
            continue
        a, b = fl.variables
        if a.group != name or b.group != name or a.is_dynamic or b.is_dynamic:
            continue
        ia, ib = np.asarray(a.ids), np.asarray(b.ids)
        for rows, t, slots in (
            (np.nonzero(ib == ia + 1)[0], ia, (0, 1)),
            (np.nonzero(ia == ib + 1)[0], ib, (1, 0)),
        ):
            if len(rows) == 0:
                continue
            free = where[t[rows]] < 0
            rows = rows[free]
            # The first row per link wins (np.unique keeps first occurrences).
            _, first = np.unique(t[rows], return_index=True)
            rows = rows[first]
            if len(rows) == 0:
                continue
            where[t[rows]] = starts + np.arange(len(rows))
            pieces.append((fi, rows, *slots))
            starts += len(rows)
    return pieces, where


def rigid_prolongation(
    lin: Linearization, name: str, count: int, dim: int, size: int
) -> Float[Array, "_N _d _d"]:
    """`T_i`: the tangent at variable `i` of a rigid motion of its block.

    A relative-pose factor `r(X_t, X_{t+1})` is unchanged when both poses
    move by the same rigid motion, so its Jacobian blocks satisfy
    `J_t T_t + J_{t+1} T_{t+1} = 0`: `T_{t+1} = −J_{t+1}⁻¹ J_t T_t`, chained
    from `T = I` at the first variable of each block of `size`. A link
    without such a factor, or with a singular block, uses `T_{t+1} = T_t`.
    """
    pieces, where = _links(lin, name, count, dim)
    eye = jnp.eye(dim, dtype=lin.dtype)
    num_blocks = -(-count // size)
    if pieces:
        ja = jnp.concatenate([lin.factors[f].jacobians[s][r] for f, r, s, _ in pieces])
        jb = jnp.concatenate([lin.factors[f].jacobians[s][r] for f, r, _, s in pieces])
        k = -jnp.linalg.solve(jb, ja)
        good = jnp.all(jnp.isfinite(k), axis=(1, 2))
        k = jnp.where(good[:, None, None], k, eye)
        link = jnp.where(
            jnp.asarray(where >= 0)[:, None, None], k[np.maximum(where, 0)], eye
        )
    else:
        link = jnp.broadcast_to(eye, (max(count - 1, 0), dim, dim))
    # into[i]: the map from variable i - 1 to i (identity at i = 0 and padding).
    pad = num_blocks * size - count
    into = jnp.concatenate(
        [eye[None], link, jnp.broadcast_to(eye, (pad, dim, dim))]
    ).reshape(num_blocks, size, dim, dim)

    def step(t, j_and_k):
        j, k = j_and_k
        t = jnp.where(j == 0, eye, einsum("gde,gef->gdf", k, t))
        return t, t

    start = jnp.broadcast_to(eye, (num_blocks, dim, dim))
    _, ts = jax.lax.scan(step, start, (jnp.arange(size), jnp.swapaxes(into, 0, 1)))
    return jnp.swapaxes(ts, 0, 1).reshape(num_blocks * size, dim, dim)[:count]


def _coarse_inverse(lin, damping, name, t, agg, num_blocks, dim):
    """The inverse of the coarse matrix `PᵀHP`, dense, through its Cholesky
    factor (zero, so no coarse correction, if it cannot be factorised)."""
    ac = jnp.zeros((num_blocks, num_blocks, dim, dim), lin.dtype)
    for fl in lin.factors:
        if fl.residual.shape[0] == 0:
            continue
        ids = [np.asarray(v.ids) for v in fl.variables]
        g = [einsum("nmd,nde->nme", j, t[i]) for j, i in zip(fl.jacobians, ids)]
        for a in range(len(g)):
            for b in range(len(g)):
                blk = einsum("nme,nmf->nef", g[a], g[b])
                ac = ac.at[agg[ids[a]], agg[ids[b]]].add(blk)
    if damping is not None:
        blk = einsum("nde,nd,ndf->nef", t, damping[name].astype(lin.dtype), t)
        ac = ac.at[agg, agg].add(blk)
    n = num_blocks * dim
    ac = jnp.swapaxes(ac, 1, 2).reshape(n, n)
    ac = 0.5 * (ac + ac.T)
    eps = jnp.asarray(jnp.finfo(lin.dtype).eps, lin.dtype)
    scale = jnp.max(jnp.abs(jnp.diagonal(ac)))
    ac = ac + (16 * eps * scale) * jnp.eye(n, dtype=lin.dtype)
    chol = jnp.linalg.cholesky(ac)
    inv = jax.scipy.linalg.cho_solve((chol, True), jnp.eye(n, dtype=lin.dtype))
    inv = 0.5 * (inv + inv.T)
    return jnp.where(jnp.all(jnp.isfinite(inv)), inv, jnp.zeros_like(inv))


class TwoLevelPreconditioner(AbstractPreconditioner):
    """A smoother plus a coarse correction by rigid motions of pose blocks.

    For pose graphs whose loop closures are many and long-range (e.g. GTSAM's
    `w10000.graph`), where [`eqsmooth.solve.ChainPreconditioner`][] and
    [`eqsmooth.solve.BlockJacobi`][] leave CG with the smooth, graph-wide
    error modes. The poses are split into blocks of `aggregate_size`
    consecutive ones; the coarse space lets each block move as one rigid
    body, its tangent at pose `i` computed from the odometry factors'
    Jacobian blocks (a relative-pose factor does not change when both of its
    poses move rigidly), so no values are needed. The coarse matrix `PᵀHP`
    (`N d / aggregate_size` square, dense) is inverted through its Cholesky
    factor once per linear solve; one application is the smoother's plus
    `P (PᵀHP)⁻¹ Pᵀ v` (additive, so symmetric positive definite): a few
    batched small products and one dense matrix-vector product.

    Requires a graph with one variable group (a pose graph); its variables
    numbered along the trajectory (g2o files are). The coarse matrix holds
    `(N d / aggregate_size)²` numbers (18 MB in float64 for 10,000 SE(2)
    poses at the default size) and its inversion costs `O((N d /
    aggregate_size)³)` per linear solve: a smaller `aggregate_size` cuts CG
    iterations (on `w10000.graph`, 10 instead of 20: 124 instead of 199 to a
    relative residual of 10⁻⁶) at that price.

    The coarse factorisation is a LAPACK Cholesky on CPU: call
    [`eqsmooth.set_xla_cpu_flags`][]`()` (its serial scheduler) before the
    first JAX computation there, or a large solve may hang in jaxlib 0.10
    (it did on `w10000.graph` and `sphere_smallnoise.graph`, 2026-11-29).

    **Arguments:**

    - `aggregate_size`: poses per coarse block (`>= 1`).
    - `smoother`: the preconditioner the coarse correction is added to
        (default [`eqsmooth.solve.ChainPreconditioner`][]).
    """

    aggregate_size: int = eqx.field(static=True, default=20)
    smoother: AbstractPreconditioner = eqx.field(default_factory=ChainPreconditioner)

    def __check_init__(self):
        size = self.aggregate_size
        if not isinstance(size, (int, np.integer)) or isinstance(size, bool):
            raise TypeError(
                "TwoLevelPreconditioner.aggregate_size must be an int, got "
                f"{type(size).__name__}"
            )
        if size < 1:
            raise ValueError(
                f"TwoLevelPreconditioner.aggregate_size must be >= 1, got {size}"
            )
        if not isinstance(self.smoother, AbstractPreconditioner):
            raise TypeError(
                "TwoLevelPreconditioner.smoother must be an AbstractPreconditioner "
                f"(e.g. ChainPreconditioner()), got {type(self.smoother).__name__}"
            )

    def build(self, lin, damping):
        if len(lin.layout) != 1:
            names = ", ".join(g.name for g in lin.layout)
            raise ValueError(
                "TwoLevelPreconditioner needs a graph with one variable group (a "
                f"pose graph); got groups {names}. Use ChainPreconditioner() or "
                "BlockJacobi()."
            )
        (g,) = lin.layout
        size = min(self.aggregate_size, g.count)
        num_blocks = -(-g.count // size)
        agg = np.arange(g.count) // size
        t = rigid_prolongation(lin, g.name, g.count, g.dim, size)
        inv = _coarse_inverse(lin, damping, g.name, t, agg, num_blocks, g.dim)
        smooth = self.smoother.build(lin, damping)
        name = g.name

        def apply(smooth, t, inv, v: Tangent) -> Tangent:
            out = dict(smooth(v))
            x = v[name].astype(t.dtype)
            c = jax.ops.segment_sum(einsum("nde,nd->ne", t, x), agg, num_blocks)
            c = (inv @ c.reshape(-1)).reshape(num_blocks, -1)
            out[name] = out[name] + einsum("nde,ne->nd", t, c[agg])
            return out

        return eqx.Partial(apply, smooth, t, inv)
