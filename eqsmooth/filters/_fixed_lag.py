"""A differentiable fixed-lag smoother on manifolds, built from factors.

Each step adds the newest state, marginalises the state that leaves the
window into a Gaussian prior on its successor (the Schur complement of the
normal matrix at the current estimates: GTSAM's convention), and solves the
window by Gauss-Newton. One step is a pure function of the window, so a
recorded sequence is one `lax.scan`, batched with `vmap` and differentiated
through the solves with the adjoints of [`eqsmooth.solve.least_squares`][].
"""

import dataclasses

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

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
from ..solve import (
    AbstractAdjoint,
    AbstractGraphSolver,
    ImplicitAdjoint,
    least_squares,
    LevenbergMarquardt,
)
from ._ekf import (
    _chain_order,
    _checked_measurements,
    _layers,
    _row_dim,
    _value_and_jac,
    checked_covariance,
)
from ._rows import check_gaussian, check_rows, row_whitening


class FixedLagSolution(eqx.Module):
    """What [`eqsmooth.filters.fixed_lag_smoother`][] returns.

    **Fields:**

    - `mean`: the online estimate of every state, `x_{t|0:t}` (the newest
        state of the window solved at step `t`), leading axis `T`.
    - `lagged_mean`: the estimate of `x_t` when it leaves the window,
        `x_{t|0:t+L-1}` (the states of the last window: at the end), leading
        axis `T`.
    - `windows`: every step's solved window, leading axes `(T, L)`; slot `i`
        of step `t` holds the state of time `window_start[t] + i` (slots past
        `t` are unused before the window fills).
    - `window_start`: the time of each window's first slot, `(T,)`.
    - `prior_mean`: the mean of the Gaussian prior on each window's first
        state (the marginal of everything that left the window, or the
        initial belief), leading axis `T`. With `closures` the prior spans
        the window's first `S` states; this is its marginal on the first.
    - `prior_covariance`: its covariance in the tangent coordinates of
        `prior_mean`, `(T, d, d)`.
    """

    mean: PyTree
    lagged_mean: PyTree
    windows: PyTree
    window_start: Array
    prior_mean: PyTree
    prior_covariance: Float[Array, "T d d"]


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
    (span, order) group, by their later time (for the window's stacks)."""

    factor: AbstractFactor
    rows: dict  # per-row fields
    R: Array  # (n, m, m)
    span: np.ndarray  # (n,) later time - earlier time
    swap: np.ndarray  # (n,) the factor's first variable is the later state
    early: tuple[np.ndarray, np.ndarray]  # (T, K) table and mask by earlier time
    late: tuple[tuple[int, bool, np.ndarray, np.ndarray], ...]  # (s, swap, table, mask)


@dataclasses.dataclass(frozen=True)
class _Model:
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


def _model(transition, measurements, links, mean0, dtype) -> _Model:
    group, perm = _chain_order(transition)
    d = tangent_dim(mean0)
    T = transition.num_rows + 1
    trans_R, _ = row_whitening(transition, d, dtype)
    trans_rows = _take(per_row_fields(transition), jnp.asarray(perm))
    rows, Rs, tables, masks = [], [], [], []
    for f in measurements:
        m = _row_dim(f, per_row_fields(f), mean0)
        R, _ = row_whitening(f, m, dtype)
        _, table, mask = _layers(f.variables[0].ids, T)
        rows.append(per_row_fields(f))
        Rs.append(R)
        tables.append(table)
        masks.append(mask)
    link_models = tuple(_link_model(f, mean0, T, dtype) for f in links)
    S = max([1] + [int(lk.span.max()) for lk in link_models])
    return _Model(
        transition,
        trans_rows,
        trans_R[perm],
        tuple(measurements),
        tuple(rows),
        tuple(Rs),
        tuple(tables),
        tuple(masks),
        link_models,
        group,
        T,
        S,
    )


def _link_model(factor: AbstractFactor, mean0, T: int, dtype) -> _Links:
    ia, ib = (np.asarray(v.ids) for v in factor.variables)
    rows = per_row_fields(factor)
    R, _ = row_whitening(factor, _row_dim(factor, rows, mean0, mean0), dtype)
    early, late = np.minimum(ia, ib), np.maximum(ia, ib)
    span, swap = late - early, ia > ib
    _, table, mask = _layers(early, T)
    groups = []
    for s in np.unique(span):
        for sw in (False, True):
            idx = np.flatnonzero((span == s) & (swap == sw))
            if idx.size:
                _, t_late, m_late = _layers(late[idx], T)
                groups.append((int(s), sw, idx[t_late], m_late))
    return _Links(factor, rows, R, span, swap, (table, mask), tuple(groups))


def _predict(model: _Model, x_prev, t, prediction_steps: int):
    """`x_t` from `x_{t-1}` by Newton steps on the transition residual."""
    d = tangent_dim(x_prev)
    dtype = model.trans_R.dtype
    row = with_rows(model.transition, _take(model.trans_rows, t - 1))
    W = model.trans_R[t - 1]
    b = x_prev
    for _ in range(prediction_steps):

        def r_w(db, b=b):
            return mm(W, row.residual(x_prev, retract(b, db)))

        r, B = _value_and_jac(r_w, d, dtype)
        b = retract(b, -jnp.linalg.solve(B, r))
    return b


def _slot(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


def _marginal_residuals(model: _Model, prior, xs, tau):
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


def _floor(model: _Model, tau) -> Float[Array, " Sd"]:
    """A floor on the information of each of the prior's `S` slots: `√ε`
    times the diagonal of the transition `tau -> tau+1`'s information, per
    tangent coordinate. Slots a link may reach but no factor has informed
    yet then keep a factorisable prior; the floor is scaled by the process
    noise, not by the belief on `x_0` (a tight initial covariance must not
    pin the later states)."""
    R = model.trans_R[jnp.clip(tau, 0, model.T - 2)]
    info = jnp.sum(R * R, axis=0)
    return jnp.sqrt(jnp.finfo(R.dtype).eps) * jnp.tile(info, model.S)


def _marginalise(model: _Model, prior, xs, tau):
    """The prior on slots `1..S` left by marginalising slot 0 (time `tau`):
    the factors touching it (the prior, its measurements, the transition
    `tau -> tau+1`, links from it) linearised at the current estimates `xs`
    of slots `0..S`, then the Schur complement on slots `1..S`."""
    residuals, n = _marginal_residuals(model, prior, xs, tau)
    d = n // (model.S + 1)
    r, J = _value_and_jac(residuals, n, prior[1].dtype)
    H, b = mm(J.T, J), mm(J.T, r)
    H00, H01, H11 = H[:d, :d], H[:d, d:], H[d:, d:]
    K = jnp.linalg.solve(H00, jnp.concatenate([H01, b[:d, None]], axis=1))
    S = H11 - mm(H01.T, K[:, :-1])
    S = 0.5 * (S + S.T)
    if model.S > 1:
        S = S + jnp.diag(_floor(model, tau + 1))
    g = b[d:] - mm(H01.T, K[:, -1])
    L = jnp.linalg.cholesky(S)
    c = jax.scipy.linalg.solve_triangular(L, g, lower=True)
    anchor = jax.tree_util.tree_map(lambda a: a[1:], xs)
    return anchor, L.T, c


def _unit(dtype) -> IsotropicNoise:
    return IsotropicNoise(sqrt_precision=jnp.asarray(1.0, dtype))


def _window_graph(model: _Model, values, prior, start, t, lag: int):
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


def _step(model, lag, solver, adjoint, prediction_steps, carry, t, max_steps=100):
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
    sol = least_squares(
        graph, {model.group: values}, solver, adjoint=adjoint, max_steps=max_steps
    )
    values = sol.value[model.group]
    return (values, prior), (values, start, prior)


def fixed_lag_smoother(
    transition: AbstractFactor,
    measurements: AbstractFactor | tuple[AbstractFactor, ...],
    initial_mean: PyTree,
    initial_covariance: Float[ArrayLike, "d d"],
    *,
    lag: int,
    closures: AbstractFactor | tuple[AbstractFactor, ...] = (),
    solver: AbstractGraphSolver = LevenbergMarquardt(),
    adjoint: AbstractAdjoint = ImplicitAdjoint(),
    prediction_steps: int = 1,
    max_steps: int = 100,
) -> FixedLagSolution:
    """Fixed-lag smoothing of a chain `x_0 → … → x_{T−1}`, one step at a time.

    At step `t` the window holds the `lag` newest states (fewer at the
    start). The new state is predicted from the transition, the state that
    leaves the window is marginalised into a Gaussian prior on its successor
    (the Schur complement of the normal matrix of the factors that touch it,
    linearised at the current estimates, as GTSAM's
    `BatchFixedLagSmoother` does; the prior is then kept linear in the
    tangent space of that estimate, the "first-estimate" choice), and the
    window is solved by `solver` from the previous estimates. With
    `lag ≥ T` the last window is the batch smoother's solution; with a
    linear-Gaussian model the newest state is the Kalman filter's marginal
    for every `lag`, and the prior on a window's first state is the
    filter's prediction.

    The factors are those of [`eqsmooth.filters.ekf`][]: `transition`, a
    stack whose rows link `x_t` to `x_{t+1}` with a residual that determines
    `x_{t+1}`, and measurement stacks touching one state each (several rows
    per time step allowed), with Gaussian noise; and `closures`, links
    between two states inside the window (loop closures).

    **Arguments:**

    - `transition`, `measurements`: as for [`eqsmooth.filters.ekf`][].
    - `initial_mean`, `initial_covariance`: the Gaussian belief on `x_0`
        (covariance in its tangent coordinates).
    - `lag`: the number of states in the window, `1 ≤ lag ≤ T`.
    - `closures`: factor stacks whose rows link two states of the chain at
        most `lag − 1` steps apart (loop closures, skip links). A row enters
        the window with its later state and is marginalised with its
        earlier one, so the prior then spans the states up to the longest
        link ahead (a dense Gaussian on those `S` states, every state with
        an information floor of `√ε` times the transition's information,
        so that states no factor has informed yet keep it factorisable).
    - `solver`: the window's solver. By default
        [`eqsmooth.solve.LevenbergMarquardt`][]: damped and converging, so
        every window is solved (a window that does not converge within
        `max_steps` raises). [`eqsmooth.solve.FixedStepGaussNewton`][]`(K)`
        with `UnrolledAdjoint()` gives every update the same cost (the
        paper's K unrolled steps), but K undamped steps are not a solved
        window on every chain: on the SE(2) + velocity chain of
        `benchmarks/fixed_lag.py` the estimates drift about 1 away from the
        solved windows' within 100 steps, with K = 3 and with K = 10.
    - `adjoint`: how each window solve is differentiated (see
        [`eqsmooth.solve.least_squares`][]): implicit by default (exact at a
        solved window); `UnrolledAdjoint()` differentiates the iterations
        themselves (for `FixedStepGaussNewton`).
    - `prediction_steps`: Newton steps that predict a new state from the
        transition.
    - `max_steps`: the iteration limit of each window solve (a converging
        `solver`; `FixedStepGaussNewton` runs its `num_steps`). Under
        `UnrolledAdjoint` every window runs all `max_steps` iterations
        (masked once converged): a warm-started window converges in a few,
        so keep it small there.

    **Returns:** a [`eqsmooth.filters.FixedLagSolution`][].
    """
    measurements, closures = _checked_arguments(
        transition, measurements, closures, lag, solver
    )
    T = transition.num_rows + 1
    d = tangent_dim(initial_mean)
    cov0 = checked_covariance("fixed_lag_smoother", initial_covariance, d)
    dtype = cov0.dtype
    model = _model(transition, measurements, closures, initial_mean, dtype)
    prior = _initial_prior(model.S, initial_mean, cov0, _floor(model, 0))
    values = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (lag, *jnp.shape(a))), initial_mean
    )

    def step(carry, t):
        return _step(model, lag, solver, adjoint, prediction_steps, carry, t, max_steps)

    _, (windows, start, priors) = lax.scan(step, (values, prior), jnp.arange(T))
    return _solution(windows, start, priors, lag, T)


def _checked_arguments(transition, measurements, closures, lag, solver):
    """`fixed_lag_smoother`'s checks: the measurement and closure stacks as
    tuples, or an error naming the argument."""
    if isinstance(lag, bool) or not isinstance(lag, int) or lag < 1:
        raise ValueError(f"fixed_lag_smoother: lag must be an int >= 1, got {lag!r}")
    if not isinstance(transition, AbstractFactor):
        raise TypeError(
            "fixed_lag_smoother: transition must be an AbstractFactor, got "
            f"{type(transition).__name__}"
        )
    measurements = _checked_measurements(transition, measurements)
    if not measurements:
        raise ValueError("fixed_lag_smoother: give at least one measurement stack")
    T = transition.num_rows + 1
    if lag > T:
        raise ValueError(
            f"fixed_lag_smoother: lag {lag} is longer than the {T} states of the "
            "chain (use lag = T for the batch smoother's answer)"
        )
    if not isinstance(solver, AbstractGraphSolver):
        raise TypeError(
            "fixed_lag_smoother: solver must be an eqsmooth graph solver such as "
            f"LevenbergMarquardt or FixedStepGaussNewton, got {type(solver).__name__}"
        )
    closures = _checked_closures(transition, closures, lag)
    for f in (transition, *measurements, *closures):
        _check_finite_rows(f)
    return measurements, closures


def _initial_prior(S: int, mean0, cov0, floor=None):
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


def _checked_closures(transition, closures, lag: int) -> tuple[AbstractFactor, ...]:
    """The link stacks as a tuple, each checked against the chain and the lag."""
    if isinstance(closures, AbstractFactor):
        closures = (closures,)
    closures = tuple(closures)
    group, _ = _chain_order(transition)
    T = transition.num_rows + 1
    for f in closures:
        if not isinstance(f, AbstractFactor):
            raise TypeError(
                "fixed_lag_smoother: closures must be AbstractFactor stacks, got "
                f"{type(f).__name__}"
            )
        name = type(f).__name__
        if len(f.variables) != 2 or any(v.group != group for v in f.variables):
            raise ValueError(
                f"fixed_lag_smoother: closure factor {name} must link two states of "
                f"group {group!r}; it touches "
                f"{[(v.group, len(v)) for v in f.variables]}"
            )
        ia, ib = (np.asarray(v.ids) for v in f.variables)
        if ia.size == 0:
            raise ValueError(f"fixed_lag_smoother: closure factor {name} has no rows")
        span = np.abs(ib - ia)
        for bad, why in (
            (span == 0, "a link must join two different states"),
            (
                span >= lag,
                f"a link must join states at most lag - 1 = {lag - 1} steps "
                f"apart: it would reach outside the window of {lag} states",
            ),
            (np.maximum(ia, ib) >= T, f"the chain has only T = {T} states"),
        ):
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"fixed_lag_smoother: closure factor {name} row {k} links times "
                    f"{int(ia[k])} and {int(ib[k])}: {why} ({int(bad.sum())} such "
                    "rows)"
                )
        check_rows(f)
        check_gaussian(f.noise, f"fixed_lag_smoother: closure factor {name}")
    return closures


def _check_finite_rows(factor: AbstractFactor) -> None:
    """A non-finite measurement would fail every window it enters: name the
    stack and the rows up front (concrete arrays only; traced ones are the
    solver's to report)."""
    bad = None
    for leaf in jax.tree_util.tree_leaves(per_row_fields(factor)):
        if isinstance(leaf, jax.core.Tracer) or not eqx.is_inexact_array(leaf):
            continue
        a = np.asarray(leaf)
        rows = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        bad = rows if bad is None else bad | rows
    if bad is not None and bad.any():
        raise ValueError(
            f"fixed_lag_smoother: factor {type(factor).__name__} has non-finite "
            f"data in rows {np.flatnonzero(bad)[:10].tolist()} (times "
            f"{factor.variables[0].ids[bad][:10].tolist()}); drop those rows or "
            "mask them in the smoother's own graph"
        )


def _prior_moments(anchor, R, c):
    """Mean and covariance of the first slot's marginal of the prior
    `½‖R [local(anchorᵢ, xᵢ)]ᵢ + c‖²`."""
    first = _slot(anchor, 0)
    d = tangent_dim(first)
    mean = retract(first, -jnp.linalg.solve(R, c)[:d])
    return mean, jnp.linalg.inv(mm(R.T, R))[:d, :d]


def _solution(windows, start, priors, lag: int, T: int) -> FixedLagSolution:
    pmean, pcov = jax.vmap(_prior_moments)(*priors)
    t = np.arange(T)
    start_np = np.maximum(t - lag + 1, 0)
    online = jax.tree_util.tree_map(lambda w: w[t, t - start_np], windows)
    # x_t leaves the window after step t + lag - 1 (or stays to the end).
    final = np.minimum(t + lag - 1, T - 1)
    lagged = jax.tree_util.tree_map(lambda w: w[final, t - start_np[final]], windows)
    # (fields in order: mean, lagged_mean, windows, window_start, prior_mean,
    # prior_covariance)
    return FixedLagSolution(online, lagged, windows, start, pmean, pcov)
