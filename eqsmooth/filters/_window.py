"""One step of the fixed-lag smoother: its window, prior and solve.

The chain's factors are kept as row arrays indexed by time
(`ChainRows`), so one step is a pure function of the window: predict the
new state, marginalise the state that leaves the window into a Gaussian
prior on its successors (the Schur complement of the normal matrix at the
current estimates), build the window's factor graph and solve it. The scan
of [`eqsmooth.filters.fixed_lag_smoother`][] and the online
[`eqsmooth.filters.FixedLagSmoother`][] run this same step.
"""

import dataclasses

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from .._precision import matmul as mm
from ..factors import (
    AbstractFactor,
    FactorGraph,
    IsotropicNoise,
    MaskedNoise,
    per_row_fields,
    PriorFactor,
    shared_field,
    Var,
    with_rows,
)
from ..manifold import local, retract, tangent_dim
from ..solve import least_squares
from ._banded import BandedCholesky
from ._chain import chain_order, residual_dim, time_layers, value_and_jacobian
from ._rows import row_whitening


class _TangentPrior(AbstractFactor):
    """A Gaussian prior on the first `S` slots of the window, kept in the
    tangent spaces of fixed anchors: residual `R · [local(aᵢ, xᵢ)]ᵢ + c`
    (one row; `anchor` stacks the `S` anchors)."""

    variables: tuple[Var, ...]
    noise: IsotropicNoise
    anchor: PyTree
    sqrt_information: Float[Array, "n Sd Sd"]
    offset: Float[Array, "n Sd"]

    def residual(self, *xs: PyTree) -> Float[Array, " Sd"]:
        return mm(self.sqrt_information, _stacked_local(self.anchor, xs)) + self.offset


def _stacked_local(anchors: PyTree, xs) -> Array:
    """`[local(anchors[i], xs[i])]ᵢ`, concatenated."""
    return jnp.concatenate(
        [
            local(jax.tree_util.tree_map(lambda a, i=i: a[i], anchors), x)
            for i, x in enumerate(xs)
        ]
    )


class _Rows(AbstractFactor):
    """Rows of a user's factor stack placed on window slots: residual
    `R_i · base_i(states)`, with `base_i` the stack's row `i` rebuilt from
    `rows` and `R_i` its square-root information (rows masked by `noise`)."""

    variables: tuple[Var, ...]
    noise: MaskedNoise
    rows: dict
    sqrt_information: Float[Array, "n m m"]
    base: AbstractFactor = shared_field()

    def residual(self, *states: PyTree) -> Float[Array, " m"]:
        return mm(
            self.sqrt_information, with_rows(self.base, self.rows).residual(*states)
        )


@dataclasses.dataclass(frozen=True)
class _Links:
    """One stack of factors linking two states of the chain (loop closures):
    rows indexed by their earlier time (for marginalisation) and, per
    (span, order) group, by their later time (for the window's stacks). A
    group whose span is `None` takes each row's span from `span` (data: the
    online smoother's closures), its earlier state by a dynamic index."""

    factor: AbstractFactor
    rows: dict  # per-row fields
    R: Array  # (n, m, m)
    span: np.ndarray | Array  # (n,) later time - earlier time
    swap: np.ndarray  # (n,) the factor's first variable is the later state
    early: tuple[
        np.ndarray, np.ndarray | Array
    ]  # (T, K) table and mask by earlier time
    late: tuple[tuple[int | None, bool, np.ndarray, np.ndarray | Array], ...]


@dataclasses.dataclass(frozen=True)
class ChainRows:
    """The chain's factors split into row arrays (indexed by time inside the
    scan) and the static rest."""

    transition: AbstractFactor
    trans_rows: dict  # per-row fields, in time order (row t: x_t -> x_t+1)
    trans_R: Array  # (T-1, d, d)
    measurements: tuple[AbstractFactor, ...]
    meas_rows: tuple[dict, ...]  # per stack: per-row fields (n_j rows)
    meas_R: tuple[Array, ...]  # per stack: (n_j, m_j, m_j)
    meas_table: tuple[np.ndarray, ...]  # per stack: (T, K_j) row of (t, layer)
    meas_mask: tuple[np.ndarray, ...]  # per stack: (T, K_j)
    links: tuple[_Links, ...]
    group: str
    T: int
    S: int  # slots of the window's prior: the longest span (1 for a chain)

    def stacks(self) -> list[tuple]:
        """Per measurement stack: (factor, rows, R, table, mask)."""
        return list(
            zip(
                self.measurements,
                self.meas_rows,
                self.meas_R,
                self.meas_table,
                self.meas_mask,
            )
        )


def _take(tree, index):
    """Rows `index` of every array leaf (a scalar index drops the row axis)."""
    return jax.tree_util.tree_map(
        lambda a: jnp.take(jnp.asarray(a), index, axis=0) if eqx.is_array(a) else a,
        tree,
    )


def chain_rows(transition, measurements, links, mean0, dtype) -> ChainRows:
    """The whole chain's rows: transition rows in time order, measurement
    rows as layers over time, and the link stacks (loop closures)."""
    group, perm = chain_order(transition)
    d = tangent_dim(mean0)
    T = transition.num_rows + 1
    trans_R, _ = row_whitening(transition, d, dtype)
    trans_rows = _take(per_row_fields(transition), jnp.asarray(perm))
    rows, Rs, tables, masks = [], [], [], []
    for f in measurements:
        m = residual_dim(f, per_row_fields(f), mean0)
        R, _ = row_whitening(f, m, dtype)
        _, table, mask = time_layers(f.variables[0].ids, T)
        rows.append(per_row_fields(f))
        Rs.append(R)
        tables.append(table)
        masks.append(mask)
    link_rows = tuple(_link_rows(f, mean0, T, dtype) for f in links)
    S = max([1] + [int(lk.span.max()) for lk in link_rows])
    return ChainRows(
        transition,
        trans_rows,
        trans_R[perm],
        tuple(measurements),
        tuple(rows),
        tuple(Rs),
        tuple(tables),
        tuple(masks),
        link_rows,
        group,
        T,
        S,
    )


def _link_rows(factor: AbstractFactor, mean0, T: int, dtype) -> _Links:
    ia, ib = (np.asarray(v.ids) for v in factor.variables)
    rows = per_row_fields(factor)
    R, _ = row_whitening(factor, residual_dim(factor, rows, mean0, mean0), dtype)
    early, late = np.minimum(ia, ib), np.maximum(ia, ib)
    span, swap = late - early, ia > ib
    _, table, mask = time_layers(early, T)
    groups = []
    for s in np.unique(span):
        for sw in (False, True):
            idx = np.flatnonzero((span == s) & (swap == sw))
            if idx.size:
                _, t_late, m_late = time_layers(late[idx], T)
                groups.append((int(s), sw, idx[t_late], m_late))
    return _Links(factor, rows, R, span, swap, (table, mask), tuple(groups))


def kept_links(factor: AbstractFactor, rows, R, back, T: int, S: int) -> _Links:
    """Links whose spans are data: `T` time steps of `k` rows each, row
    `v * k + j` linking time `v - back[v * k + j]` (the factor's first
    variable) to time `v` (its second); a `back` of 0 is no link. Rows are
    marginalised with their earlier state, whose successors they reach at
    most `S` steps ahead."""
    k = R.shape[0] // T
    table = np.arange(T * k).reshape(T, k)
    span = jnp.clip(back, 0, S)
    steps = np.arange(1, S + 1)
    later = np.arange(T)[:, None] + steps  # (T, S): the candidates' times
    inside = later <= T - 1
    later = np.minimum(later, T - 1)
    by_early = (later[:, :, None] * k + np.arange(k)).reshape(T, S * k)
    # the rows s steps after time tau that reach back s: those starting at tau
    starts = (span.reshape(T, k)[later] == steps[None, :, None]) & inside[..., None]
    late = ((None, False, table, span.reshape(T, k) >= 1),)
    return _Links(
        factor,
        rows,
        R,
        span,
        np.zeros(T * k, bool),
        (by_early, starts.reshape(T, S * k)),
        late,
    )


def _predict(model: ChainRows, x_prev, t, prediction_steps: int):
    """`x_t` from `x_{t-1}` by Newton steps on the transition residual."""
    d = tangent_dim(x_prev)
    dtype = model.trans_R.dtype
    row = with_rows(model.transition, _take(model.trans_rows, t - 1))
    W = model.trans_R[t - 1]
    b = x_prev
    for _ in range(prediction_steps):

        def r_w(db, b=b):
            return mm(W, row.residual(x_prev, retract(b, db)))

        r, B = value_and_jacobian(r_w, d, dtype)
        b = retract(b, -jnp.linalg.solve(B, r))
    return b


def _slot(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


def _marginal_residuals(model: ChainRows, prior, xs, tau):
    """The whitened residuals of the factors touching slot 0 (time `tau`),
    as a function of the tangent step of slots `0..S`."""
    anchor, R0, c0 = prior
    S, d = model.S, tangent_dim(_slot(xs, 0))
    trans = with_rows(model.transition, _take(model.trans_rows, tau))
    meas = [
        (f, rows, R, jnp.asarray(table)[tau], jnp.asarray(mask)[tau])
        for f, rows, R, table, mask in model.stacks()
    ]

    def residuals(delta):
        ys = [retract(_slot(xs, i), delta[i * d : (i + 1) * d]) for i in range(S + 1)]
        stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *ys)
        out = [mm(R0, _stacked_local(anchor, ys[:S])) + c0]
        out.append(mm(model.trans_R[tau], trans.residual(ys[0], ys[1])))
        for f, rows, R, index, active in meas:
            for k in range(active.shape[0]):
                r = mm(R[index[k]], with_rows(f, _take(rows, index[k])).residual(ys[0]))
                out.append(jnp.where(active[k], r, jnp.zeros_like(r)))
        for lk in model.links:
            table, mask = (jnp.asarray(a)[tau] for a in lk.early)
            for k in range(mask.shape[0]):
                row = table[k]
                other = _slot(stacked, jnp.asarray(lk.span)[row])
                swap = jnp.asarray(lk.swap)[row]
                a, b = (
                    jax.tree_util.tree_map(lambda p, q: jnp.where(swap, p, q), u, v)
                    for u, v in ((other, ys[0]), (ys[0], other))
                )
                r = mm(
                    lk.R[row], with_rows(lk.factor, _take(lk.rows, row)).residual(a, b)
                )
                out.append(jnp.where(mask[k], r, jnp.zeros_like(r)))
        return jnp.concatenate(out)

    return residuals, (S + 1) * d


def information_floor(model: ChainRows, tau) -> Float[Array, " Sd"]:
    """A floor on the information of each of the prior's `S` slots: `√ε`
    times the diagonal of the transition `tau -> tau+1`'s information, per
    tangent coordinate. Slots a link may reach but no factor has informed
    yet then keep a factorisable prior; the floor is scaled by the process
    noise, not by the belief on `x_0` (a tight initial covariance must not
    pin the later states)."""
    return floor_of(model.trans_R[jnp.clip(tau, 0, model.T - 2)], model.S)


def floor_of(R: Float[Array, "d d"], S: int) -> Float[Array, " Sd"]:
    """`information_floor` of a transition row's square-root information."""
    info = jnp.sum(R * R, axis=0)
    return jnp.sqrt(jnp.finfo(R.dtype).eps) * jnp.tile(info, S)


def _marginalise(model: ChainRows, prior, xs, tau):
    """The prior on slots `1..S` left by marginalising slot 0 (time `tau`):
    the factors touching it (the prior, its measurements, the transition
    `tau -> tau+1`, links from it) linearised at the current estimates `xs`
    of slots `0..S`, then the Schur complement on slots `1..S`."""
    residuals, n = _marginal_residuals(model, prior, xs, tau)
    d = n // (model.S + 1)
    r, J = value_and_jacobian(residuals, n, prior[1].dtype)
    H, b = mm(J.T, J), mm(J.T, r)
    H00, H01, H11 = H[:d, :d], H[:d, d:], H[d:, d:]
    K = jnp.linalg.solve(H00, jnp.concatenate([H01, b[:d, None]], axis=1))
    S = H11 - mm(H01.T, K[:, :-1])
    S = 0.5 * (S + S.T)
    if model.S > 1:
        S = S + jnp.diag(information_floor(model, tau + 1))
    g = b[d:] - mm(H01.T, K[:, -1])
    L = jnp.linalg.cholesky(S)
    c = jax.scipy.linalg.solve_triangular(L, g, lower=True)
    anchor = jax.tree_util.tree_map(lambda a: a[1:], xs)
    return anchor, L.T, c


def _unit(dtype) -> IsotropicNoise:
    # A NumPy constant stays concrete under `jit`: checked once here, not by
    # an error check (a host callback) in every compiled window solve.
    return IsotropicNoise(sqrt_precision=np.asarray(1.0, dtype))


def _window_graph(model: ChainRows, values, prior, start, t, lag: int):
    """The factor graph of the window whose first slot is time `start`."""
    g = model.group
    slots = np.arange(lag)
    times = start + jnp.asarray(slots)
    used = times <= t
    anchor, R0, c0 = prior
    stacks = [
        _TangentPrior(
            tuple(Var(g, [i]) for i in range(model.S)),
            _unit(R0.dtype),
            jax.tree_util.tree_map(lambda a: a[None], anchor),
            R0[None],
            c0[None],
        ),
        # Unused slots stay where they are (and add nothing once used).
        PriorFactor(
            Var(g, slots),
            jax.lax.stop_gradient(values),
            MaskedNoise(_unit(R0.dtype), ~used),
        ),
    ]
    if lag > 1:
        index = jnp.clip(times[:-1], 0, model.T - 2)
        stacks.append(
            _Rows(
                (Var(g, slots[:-1]), Var(g, slots[1:])),
                MaskedNoise(_unit(R0.dtype), used[1:]),
                _take(model.trans_rows, index),
                model.trans_R[index],
                model.transition,
            )
        )
    for f, rows, R, table, mask in model.stacks():
        clipped = jnp.clip(times, 0, model.T - 1)
        for k in range(mask.shape[1]):
            index = jnp.asarray(table[:, k])[clipped]
            active = jnp.asarray(mask[:, k])[clipped] & used
            stacks.append(
                _Rows(
                    (Var(g, slots),),
                    MaskedNoise(_unit(R0.dtype), active),
                    _take(rows, index),
                    R[index],
                    f,
                )
            )
    for lk in model.links:
        for span, swap, table, mask in lk.late:
            if span is None:
                stacks += _dynamic_links(lk, swap, table, mask, times, used, lag, g)
                continue
            k = slots[: lag - span]
            late = jnp.clip(start + k + span, 0, model.T - 1)
            pair = (
                (Var(g, k + span), Var(g, k)) if swap else (Var(g, k), Var(g, k + span))
            )
            for layer in range(mask.shape[1]):
                index = jnp.asarray(table[:, layer])[late]
                active = jnp.asarray(mask[:, layer])[late] & (start + k + span <= t)
                stacks.append(
                    _Rows(
                        pair,
                        MaskedNoise(_unit(R0.dtype), active),
                        _take(lk.rows, index),
                        lk.R[index],
                        lk.factor,
                    )
                )
    return FactorGraph(stacks)


def _dynamic_links(lk: _Links, swap: bool, table, mask, times, used, lag: int, g):
    """The window's stacks of links whose spans are data (`kept_links`): per
    layer, one row per window slot for the link arriving at that slot's
    time, reaching its earlier state by a dynamic index (rows whose earlier
    state has left the window were marginalised with it, and add nothing)."""
    slots = np.arange(lag)
    late = jnp.clip(times, 0, table.shape[0] - 1)
    unit = _unit(lk.R.dtype)
    out = []
    for layer in range(table.shape[1]):
        index = jnp.asarray(table[:, layer])[late]
        early = slots - jnp.asarray(lk.span)[index]
        active = jnp.asarray(mask)[late, layer] & used & (early >= 0)
        pair = (Var.dynamic(g, jnp.clip(early, 0, lag - 1)), Var(g, slots))
        out.append(
            _Rows(
                pair[::-1] if swap else pair,
                MaskedNoise(unit, active),
                _take(lk.rows, index),
                lk.R[index],
                lk.factor,
            )
        )
    return out


def window_step(
    model,
    lag,
    solver,
    adjoint,
    prediction_steps,
    carry,
    t,
    max_steps=100,
    throw=True,
):
    """Step `t` of the smoother: `carry = (window, prior)` to the new carry
    and `(window, its first slot's time, prior, the solve's result code)`.
    The new state is predicted from the newest; once the window is full the
    oldest state is marginalised into the prior; then the window is solved
    by `solver` (a failed solve raises when `throw`, else only its code
    says so)."""
    values, prior = carry
    last = jnp.minimum(t - 1, lag - 1)
    x_prev = jax.tree_util.tree_map(lambda a: a[jnp.maximum(last, 0)], values)
    x_new = lax.cond(
        t > 0,
        lambda: _predict(model, x_prev, jnp.maximum(t, 1), prediction_steps),
        lambda: x_prev,
    )

    def slide():
        ext = jax.tree_util.tree_map(
            lambda a, b: jnp.concatenate([a, b[None]]), values, x_new
        )
        xs = jax.tree_util.tree_map(lambda a: a[: model.S + 1], ext)
        new_prior = _marginalise(model, prior, xs, jnp.maximum(t - lag, 0))
        return jax.tree_util.tree_map(lambda a: a[1:], ext), new_prior

    def grow():
        slot = jnp.minimum(t, lag - 1)
        grown = jax.tree_util.tree_map(lambda a, b: a.at[slot].set(b), values, x_new)
        return grown, prior

    values, prior = lax.cond(t >= lag, slide, grow)
    start = jnp.maximum(t - lag + 1, 0)
    graph = _window_graph(model, values, prior, start, t, lag)
    solver = _banded_unless_chain(solver, model, lag, tangent_dim(x_prev))
    sol = least_squares(
        graph,
        {model.group: values},
        solver,
        adjoint=adjoint,
        max_steps=max_steps,
        throw=throw,
    )
    values = sol.value[model.group]
    return (values, prior), (values, start, prior, sol.result)


BANDED_MIN_BLOCKS = 4
"""The fewest blocks of `(S + 1) · d` coordinates for which a window with
closures is solved by `BandedCholesky` (below, a dense Cholesky costs less)."""


def _banded_unless_chain(solver, model: ChainRows, lag: int, d: int):
    """`solver` with a banded linear solver when the window is not a chain
    (closures, a prior on several slots) and the solver would choose one
    (its `linear_solver` is `None`): the window's factors link slots at most
    `S` apart, so its normal matrix is block tridiagonal in blocks of `S + 1`
    slots (the default would be a dense Cholesky of the window)."""
    chain = not model.links and model.S == 1
    if chain or getattr(solver, "linear_solver", False) is not None:
        return solver
    if -(-lag // (model.S + 1)) < BANDED_MIN_BLOCKS:
        return solver
    banded = BandedCholesky(block=(model.S + 1) * d)
    return eqx.tree_at(lambda s: s.linear_solver, solver, banded, is_leaf=_is_none)


def _is_none(x) -> bool:
    return x is None


def initial_prior(S: int, mean0, cov0, floor=None):
    """The belief on `x_0` as a prior on the window's first `S` slots (the
    others at the information `floor`, a vector over the `S` slots)."""
    d = cov0.shape[0]
    L0 = jnp.linalg.cholesky(cov0)
    R0 = jax.scipy.linalg.solve_triangular(L0, jnp.eye(d, dtype=cov0.dtype), lower=True)
    R = jnp.zeros((S * d, S * d), cov0.dtype).at[:d, :d].set(R0)
    if S > 1:
        R = R.at[d:, d:].set(jnp.diag(jnp.sqrt(floor[d:])))
    anchor = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (S, *a.shape)), mean0)
    return anchor, R, jnp.zeros((S * d,), cov0.dtype)
