"""Fixed-lag smoothing of an SE(2) pose chain against GTSAM's fixed-lag smoothers.

T poses, odometry, a noisy pose fix on every pose and (`--closures`) a loop
closure every 4th step to the pose `--span` steps back. eqsmooth runs
`eqs.filters.fixed_lag_smoother(lag=L)` as one jitted scan (per update: run
time / T) with `LevenbergMarquardt()` (the default; "eqsmooth_lm", the
reference), `GaussNewton()` and `FixedStepGaussNewton(3)` (unrolled adjoint).
GTSAM's Batch- and IncrementalFixedLagSmoother get smoother lag L - 2 (L poses
per update, as eqsmooth's window), one timed `update` per step. `max_diff`:
the largest tangent difference of the newest pose from the reference
(`max_diff_before`: before the first marginalisation). `--se2vel`: an SE(2) +
velocity chain (GTSAM through Python CustomFactors with numeric Jacobians: its
values compare, its time does not). `--first-window-only`: GTSAM's graph error
at the first marginalisation, at GTSAM's answer and eqsmooth's. `--per-update`:
a robot's loop without and with closures (`max_back` = `--span`),
`FixedLagSmoother.update_rows` (arrays in, state on the device; also with
`throw=False`), `update` (factors) and GTSAM's `update`, each call timed with
its estimate awaited (`max_diff`: from update_rows'); `dispatch_floor`: a
jitted call taking and returning the state, doing nothing.

    python -m benchmarks.fixed_lag --json benchmarks/results/fixed_lag.json
    python -m benchmarks.fixed_lag --closures \
        --json benchmarks/results/fixed_lag_closures.json
    python -m benchmarks.fixed_lag --first-window-only --lags 4 10 50 \
        --json benchmarks/results/fixed_lag_first_window.json
    python -m benchmarks.fixed_lag --se2vel --steps 100 --lags 10 50 \
        --json benchmarks/results/fixed_lag_se2vel.json
    OPENBLAS_NUM_THREADS=1 python -m benchmarks.fixed_lag --per-update \
        --json benchmarks/results/fixed_lag_per_update.json
"""

import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs

from ._common import cli, optional, time_host, write_json


jax.config.update("jax_enable_x64", True)
ODO, FIX, LOOP = (np.array(s) for s in ([0.05, 0.05, 0.02], [0.5, 0.5, 0.1], [0.1] * 3))
COV0, fls = 1e-4, eqs.filters.fixed_lag_smoother


def problem(T: int, span: int, closures: bool, seed: int = 0):
    rng = np.random.default_rng(seed)
    turn = 0.1 * np.sin(np.arange(T - 1) / 7)
    u = np.column_stack([np.ones(T - 1), np.zeros(T - 1), turn])
    truth = [eqs.SE2.identity(dtype=jnp.float64)]
    for k in range(T - 1):
        truth.append(truth[-1] @ eqs.SE2.exp(jnp.asarray(u[k])))
    truth = eqs.SE2(jnp.stack([p.parameters() for p in truth]))
    noise = lambda n, s: eqs.SE2.exp(jnp.asarray(s * rng.normal(size=(n, 3))))
    diag = lambda s: eqs.DiagonalNoise.from_sigmas(jnp.asarray(s))
    t, x = np.arange(T), lambda ids: eqs.Var("x", ids)
    odo = truth[t[:-1]].inverse() @ truth[t[1:]] @ noise(T - 1, ODO)
    fix = truth @ noise(T, FIX)
    trans = eqs.BetweenFactor(x(t[:-1]), x(t[1:]), odo, diag(ODO))
    data = dict(trans=trans, fix=eqs.PriorFactor(x(t), fix, diag(FIX)))
    data |= dict(odo=np.asarray(odo.parameters()), fixes=np.asarray(fix.parameters()))
    data |= dict(closures=(), pairs=[])
    if closures:
        a, b = np.arange(0, T - span, 4), np.arange(span, T, 4)
        rel = truth[a].inverse() @ truth[b] @ noise(len(a), LOOP)
        data["closures"] = eqs.BetweenFactor(x(a), x(b), rel, diag(LOOP))
        data["pairs"] = list(zip(a.tolist(), b.tolist(), np.asarray(rel.parameters())))
    return data


def timed_fixed_lag(trans, meas, mean0, cov0, lag, solver, adjoint, repeats, links=()):
    """eqsmooth's estimates, first call's seconds, median seconds per update."""
    o = dict(lag=lag, solver=solver, adjoint=adjoint)
    run = eqx.filter_jit(lambda tr, m, c: fls(tr, m, mean0, cov0, closures=c, **o).mean)
    call = lambda: jax.block_until_ready(run(trans, meas, links))
    first, times, mean = time_host(call, repeats)
    return mean, first, statistics.median(times) / (trans.num_rows + 1)


# GTSAM's Pose2 of SE(2) parameters `(cos, sin, x, y)`
_pose = lambda gtsam, r: gtsam.Pose2(r[2], r[3], np.arctan2(r[1], r[0]))


def gtsam_run(gtsam, smoother, data):
    pose, diag = (lambda r: _pose(gtsam, r)), gtsam.noiseModel.Diagonal.Sigmas
    est, times = [], []
    for t in range(len(data["fixes"])):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if t == 0:
            cov = gtsam.noiseModel.Gaussian.Covariance(COV0 * np.eye(3))
            graph.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), cov))
            values.insert(0, gtsam.Pose2())
        else:
            odo = pose(data["odo"][t - 1])
            graph.add(gtsam.BetweenFactorPose2(t - 1, t, odo, diag(ODO)))
            values.insert(t, est[-1].compose(odo))
        graph.add(gtsam.PriorFactorPose2(t, pose(data["fixes"][t]), diag(FIX)))
        for a, rel in [(a, rel) for a, b, rel in data["pairs"] if b == t]:
            graph.add(gtsam.BetweenFactorPose2(a, t, pose(rel), diag(LOOP)))
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        stamps.insert((t, float(t)))
        t0 = time.perf_counter()
        smoother.update(graph, values, stamps)
        times.append(time.perf_counter() - t0)
        est.append(smoother.calculateEstimatePose2(t))
    xyt = np.array([[e.x(), e.y(), e.theta()] for e in est])
    return eqs.SE2.from_xy_theta(*xyt.T), statistics.median(times)


def gtsam_smoothers(gtsam, lag: int):
    lm = gtsam.LevenbergMarquardtParams()
    lm.setRelativeErrorTol(1e-12)
    lm.setAbsoluteErrorTol(1e-14)
    lm.setMaxIterations(100)
    held = float(lag - 2)
    return {
        "BatchFixedLagSmoother": gtsam.BatchFixedLagSmoother(held, lm),
        "IncrementalFixedLagSmoother": gtsam.IncrementalFixedLagSmoother(held),
    }


def first_marginal_window(gtsam, lag: int) -> dict:
    """GTSAM's graph error after the first marginalisation (the smoother's
    graph after update `lag - 1` plus update `lag`'s factors) at GTSAM's
    answer (its LM optimizer) and at eqsmooth's window (30 GN steps)."""
    data, mean0 = problem(lag + 1, 1, False), eqs.SE2.identity(dtype=jnp.float64)
    gn = eqs.FixedStepGaussNewton(num_steps=30)
    sol = fls(data["trans"], data["fix"], mean0, COV0 * jnp.eye(3), lag=lag, solver=gn)
    ours = np.asarray(sol.windows[lag].parameters())
    lm = gtsam_smoothers(gtsam, lag)["BatchFixedLagSmoother"].params()
    head = dict(data, fixes=data["fixes"][:lag], odo=data["odo"][: lag - 1], pairs=[])
    smoother = gtsam.BatchFixedLagSmoother(float(lag - 2), lm)
    gtsam_run(gtsam, smoother, head)
    pose, sig = (lambda r: _pose(gtsam, r)), gtsam.noiseModel.Diagonal.Sigmas
    odo, mine = pose(data["odo"][lag - 1]), gtsam.Values()
    for i, r in enumerate(ours):
        mine.insert(i + 1, pose(r))
    new = [gtsam.BetweenFactorPose2(lag - 1, lag, odo, sig(ODO))]
    new.append(gtsam.PriorFactorPose2(lag, pose(data["fixes"][lag]), sig(FIX)))
    start = lambda v: v.insert(lag, v.atPose2(lag - 1).compose(odo))
    return _window_errors(gtsam, smoother, lm, new, start, mine)


def _window_errors(gtsam, smoother, lm, new, start, mine) -> dict:
    """The error of the smoother's graph + `new` at GTSAM's answer and `mine`."""
    graph = gtsam.NonlinearFactorGraph(smoother.getFactors())
    init = gtsam.Values(smoother.calculateEstimate())
    for f in new:
        graph.add(f)
    start(init)
    theirs = gtsam.LevenbergMarquardtOptimizer(graph, init, lm).optimize()
    return dict(gtsam_error=graph.error(theirs), eqsmooth_error=graph.error(mine))


# --- the SE(2) + velocity chain (GTSAM: Pose2 and Vector3 keys, CustomFactors)

DT, VEL0 = 0.1, np.array([0.8, 0.1, 0.6])
TRANS_SIG, GPS_SIG = np.array([0.02, 0.02, 0.03, 0.05, 0.05, 0.05]), 0.1


def _car_trans(a, b, data, params):
    pred = {"pose": a["pose"] @ eqs.SE2.exp(DT * a["vel"]), "vel": a["vel"]}
    return eqs.local(pred, b)


_car_gps = lambda x, data, params: x["pose"].translation() - data


def se2vel_problem(T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    vel, poses = [VEL0], [eqs.SE2.identity(dtype=jnp.float64)]
    for _ in range(T - 1):
        poses.append(poses[-1] @ eqs.SE2.exp(jnp.asarray(DT * vel[-1])))
        vel.append(vel[-1] + 0.05 * rng.normal(size=3))
    pos = np.stack([np.asarray(p.translation()) for p in poses])
    gps = pos + GPS_SIG * rng.normal(size=pos.shape)
    t, var = np.arange(T), lambda ids: eqs.Var("s", ids)
    noise = eqs.DiagonalNoise.from_sigmas(jnp.asarray(TRANS_SIG))
    trans = eqs.FunctionFactor(_car_trans, (var(t[:-1]), var(t[1:])), noise)
    noise = eqs.IsotropicNoise.from_sigma(jnp.asarray(GPS_SIG))
    meas = eqs.FunctionFactor(_car_gps, (var(t),), noise, data=jnp.asarray(gps))
    mean0 = {"pose": eqs.SE2.identity(dtype=jnp.float64), "vel": jnp.asarray(VEL0)}
    return trans, meas, mean0, gps


def _numeric_jacobians(gtsam, error, values, keys, jacobians, h=1e-6):
    """`error(values)`, and (when asked) its central-difference Jacobians in
    GTSAM's tangent coordinates of each key (Pose2 at even keys, 3-vector at
    odd): a CustomFactor's error function."""
    for j, k in enumerate(keys if jacobians is not None else ()):
        at = values.atPose2(k).retract if k % 2 == 0 else values.atVector(k).__add__
        moved = lambda step, k=k, at=at: error(_with(gtsam, values, k, at(step)))
        cols = [(moved(e) - moved(-e)) / (2 * h) for e in h * np.eye(3)]
        jacobians[j] = np.column_stack(cols)
    return error(values)


def _with(gtsam, values, key, value):
    out = gtsam.Values(values)
    out.update(key, value)
    return out


def _se2vel_factors(gtsam, gps):
    """GTSAM factors of the chain: pose keys 2t, velocity keys 2t+1."""
    P, V = (lambda t: 2 * t), (lambda t: 2 * t + 1)

    def custom(noise, keys, err):
        f = lambda _, values, jac: _numeric_jacobians(gtsam, err, values, keys, jac)
        return gtsam.CustomFactor(noise, keys, f)

    def trans_factor(t):
        def error(values):
            pa, va = values.atPose2(P(t - 1)), values.atVector(V(t - 1))
            pred = pa.compose(gtsam.Pose2.Expmap(DT * va)).between(values.atPose2(P(t)))
            dv = values.atVector(V(t)) - va
            return np.concatenate([gtsam.Pose2.Logmap(pred), dv])

        noise = gtsam.noiseModel.Diagonal.Sigmas(TRANS_SIG)
        return custom(noise, [P(t - 1), V(t - 1), P(t), V(t)], error)

    def gps_factor(t):
        noise = gtsam.noiseModel.Isotropic.Sigma(2, GPS_SIG)
        return custom(noise, [P(t)], lambda v: v.atPose2(P(t)).translation() - gps[t])

    return P, V, trans_factor, gps_factor


def gtsam_se2vel(gtsam, smoother, gps, T: int):
    """GTSAM's smoother on the same chain, one update per step."""
    P, V, trans_factor, gps_factor = _se2vel_factors(gtsam, gps)
    est, times = [], []
    for t in range(T):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        stamps = gtsam.FixedLagSmootherKeyTimestampMap()
        pa, va = est[-1] if t else (gtsam.Pose2(), VEL0)
        values.insert(P(t), pa.compose(gtsam.Pose2.Expmap(DT * va)) if t else pa)
        values.insert(V(t), va)
        if t == 0:
            sig = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(COV0) * np.ones(3))
            graph.add(gtsam.PriorFactorPose2(P(0), gtsam.Pose2(), sig))
            graph.add(gtsam.PriorFactorVector(V(0), VEL0, sig))
        else:
            graph.add(trans_factor(t))
        graph.add(gps_factor(t))
        stamps.insert((P(t), float(t)))
        stamps.insert((V(t), float(t)))
        t0 = time.perf_counter()
        smoother.update(graph, values, stamps)
        times.append(time.perf_counter() - t0)
        e = smoother.calculateEstimate()
        est.append((e.atPose2(P(t)), e.atVector(V(t))))
    xyt = np.array([[p.x(), p.y(), p.theta()] for p, _ in est])
    vel = np.array([v for _, v in est])
    return {"pose": eqs.SE2.from_xy_theta(*xyt.T), "vel": jnp.asarray(vel)}, times


def se2vel_first_window(gtsam, lag: int) -> dict:
    """`first_marginal_window` on the SE(2) + velocity chain (eqsmooth: LM)."""
    trans, meas, mean0, gps = se2vel_problem(lag + 1)
    tight = eqs.LevenbergMarquardt(ftol=1e-14, gtol=1e-14, xtol=1e-14)
    sol = fls(trans, meas, mean0, COV0 * jnp.eye(6), lag=lag, solver=tight)
    window = jax.tree_util.tree_map(lambda a: a[lag], sol.windows)
    lm = gtsam_smoothers(gtsam, lag)["BatchFixedLagSmoother"].params()
    smoother = gtsam.BatchFixedLagSmoother(float(lag - 2), lm)
    gtsam_se2vel(gtsam, smoother, np.asarray(gps), lag)
    P, V, trans_factor, gps_factor = _se2vel_factors(gtsam, np.asarray(gps))
    mine = gtsam.Values()
    params, vel = np.asarray(window["pose"].parameters()), np.asarray(window["vel"])
    for i, (r, v) in enumerate(zip(params, vel)):
        mine.insert(P(i + 1), _pose(gtsam, r))
        mine.insert(V(i + 1), v)
    new, ks = [trans_factor(lag), gps_factor(lag)], (P(lag), V(lag))
    start = lambda v: [
        v.insert(k, g(k - 2)) for k, g in zip(ks, (v.atPose2, v.atVector))
    ]
    return _window_errors(gtsam, smoother, lm, new, start, mine)


def se2vel_record(gtsam, T: int, lag: int, repeats: int) -> dict:
    trans, meas, mean0, gps = se2vel_problem(T)
    rec = dict(benchmark="fixed_lag_se2vel", T=T, lag=lag)
    fs = eqs.FixedStepGaussNewton(num_steps=3), eqs.UnrolledAdjoint()
    # undamped Gauss-Newton does not converge in every window of this chain
    lm = eqs.LevenbergMarquardt(), eqs.ImplicitAdjoint()
    means = {}
    for name, solver in (("eqsmooth_fixed3", fs), ("eqsmooth_lm", lm)):
        run = (trans, meas, mean0, COV0 * jnp.eye(6), lag, *solver, repeats)
        means[name], first, per = timed_fixed_lag(*run)
        rec[name] = dict(first_call_s=first, ms_per_update=1e3 * per)
    diff = lambda a: tangent_diff(a, means["eqsmooth_lm"])
    rec["eqsmooth_fixed3"]["max_diff"] = float(diff(means["eqsmooth_fixed3"]).max())
    if gtsam:
        smoother = gtsam_smoothers(gtsam, lag)["BatchFixedLagSmoother"]
        est, times = gtsam_se2vel(gtsam, smoother, np.asarray(gps), T)
        d, ms = diff(est), 1e3 * statistics.median(times)
        b = rec["BatchFixedLagSmoother"] = dict(ms_per_update_python_factors=ms)
        b |= dict(max_diff=float(d.max()), max_diff_before=float(d[:lag].max()))
        rec["first_marginal_window"] = se2vel_first_window(gtsam, lag)
    return rec


# per step, the largest tangent coordinate of `local(a, b)`
tangent_diff = lambda a, b: np.abs(np.asarray(eqs.local(a, b, batch_ndim=1))).max(1)


def chain_record(gtsam, data, lag: int, a) -> dict:
    """eqsmooth's three solvers and GTSAM's two smoothers on the pose chain."""
    rec = dict(benchmark="fixed_lag", T=a.steps, lag=lag)
    rec |= dict(closures=a.closures, span=a.span)
    implicit = eqs.ImplicitAdjoint()
    solvers = dict(
        eqsmooth_lm=(eqs.LevenbergMarquardt(), implicit),  # the default
        eqsmooth_gn=(eqs.GaussNewton(), implicit),
        eqsmooth_fixed3=(eqs.FixedStepGaussNewton(num_steps=3), eqs.UnrolledAdjoint()),
    )
    mean0, cov0, means = eqs.SE2.identity(dtype=jnp.float64), COV0 * jnp.eye(3), {}
    for name, (solver, adjoint) in solvers.items():
        run = (data["trans"], data["fix"], mean0, cov0, lag, solver, adjoint, a.repeats)
        means[name], first, per = timed_fixed_lag(*run, data["closures"])
        rec[name] = dict(first_call_s=first, ms_per_update=1e3 * per)
    ref = means["eqsmooth_lm"]
    for name in ("eqsmooth_gn", "eqsmooth_fixed3"):
        rec[name]["max_diff"] = float(tangent_diff(means[name], ref).max())
    for name, smoother in (gtsam_smoothers(gtsam, lag) if gtsam else {}).items():
        est, median = gtsam_run(gtsam, smoother, data)
        diff = tangent_diff(est, ref)
        rec[name] = dict(ms_per_update=1e3 * median, max_diff=float(diff.max()))
        rec[name]["max_diff_before"] = float(diff[: min(lag, a.steps)].max())
    if gtsam and not a.closures:
        rec["first_marginal_window"] = first_marginal_window(gtsam, lag)
    return rec


def per_update_record(gtsam, data, lag: int, max_back: int) -> dict:
    """`--per-update`: inputs built before the timed calls (one closure row
    per step, absent ones masked); medians over the calls after the first."""
    T, one = len(data["fixes"]), (eqs.Var("x", [0]), eqs.Var("x", [1]))
    odo, fix = (eqs.SE2(jnp.asarray(data[k])) for k in ("odo", "fixes"))
    back, rel = np.zeros((T, 1), int), np.tile([1.0, 0, 0, 0], (T, 1))
    for a, b, r in data["pairs"]:
        back[b], rel[b] = b - a, r
    on, rel, closed = back > 0, eqs.SE2(jnp.asarray(rel)), bool(data["pairs"])
    noise = eqs.DiagonalNoise.from_sigmas(jnp.asarray(LOOP))
    loop = lambda k, n: eqs.BetweenFactor(*one, rel[k : k + 1], n)
    trans = lambda k: eqs.BetweenFactor(*one, odo[k - 1 : k], data["trans"].noise)
    prior = lambda k: eqs.PriorFactor(one[1], fix[k : k + 1], data["fix"].noise)
    f, init = eqs.factors.per_row_fields, (trans(1), prior(0))
    init += (loop(0, noise), max_back) if closed else ()
    steps = [(trans(k), prior(k)) for k in range(1, T)]
    rows = [(f(a), (f(b),)) for a, b in steps]
    for k in range(1, T) if closed else ():  # (active, closure rows, back, active)
        rows[k - 1] += (None, f(loop(k, noise)), back[k], on[k])
    rec, ests = dict(benchmark="fixed_lag_per_update", T=T, lag=lag), {}
    rec |= dict(closures=closed, max_back=max_back if closed else None)
    for name, throw, method, args in (
        ("update_rows", True, "update_rows", rows),
        ("update_rows_throw_false", False, "update_rows", rows),
        ("update", True, "update", steps),
    )[: 3 - closed]:  # with closures: `update` is not timed
        smoother = eqs.filters.FixedLagSmoother(lag=lag, throw=throw)
        mean0, update = eqs.SE2.identity(dtype=jnp.float64), getattr(smoother, method)
        state, x = smoother.init(mean0, COV0 * jnp.eye(3), *init)
        out, times = [x], []
        for step in args:
            t0 = time.perf_counter()
            state, x = jax.block_until_ready(update(state, *step))
            times.append(time.perf_counter() - t0)
            out.append(x)
        ests[name] = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *out)
        rec[name] = dict(first_call_s=times[0], median_s=statistics.median(times[1:]))
    med = rec["update_rows"]["median_s"]
    rec |= dict(median_s=med, compile_s=rec["update_rows"]["first_call_s"] - med)
    rec["dispatch_floor"] = dispatch_floor(state, rows[-1])
    diff = lambda est: float(tangent_diff(est, ests["update_rows"]).max())
    for name in list(ests)[1:]:  # the same estimates
        rec[name]["max_diff"] = diff(ests[name])
    for name, smoother in (gtsam_smoothers(gtsam, lag) if gtsam else {}).items():
        est, median = gtsam_run(gtsam, smoother, data)
        rec[name] = dict(median_s=median, max_diff=diff(est))
    return rec


def dispatch_floor(state, step, calls: int = 200) -> dict:
    """Median seconds of a call taking `state` and a step's rows and returning
    the state (`t + 1`) and newest pose: `eqx.filter_jit`, `jax.jit` of leaves."""
    bump = lambda s, _: (eqx.tree_at(lambda s: s.t, s, s.t + 1), s.window[-1])
    arrays, rest = eqx.partition((state, step), eqx.is_array)
    leaves, tree = jax.tree_util.tree_flatten(arrays)
    whole = lambda ls: bump(*eqx.combine(tree.unflatten(ls), rest))
    bare = jax.jit(lambda ls: eqx.filter(whole(ls), eqx.is_array))
    run = lambda f, *a: time_host(lambda: jax.block_until_ready(f(*a)), calls)[1]
    times = dict(filter_jit_s=run(eqx.filter_jit(bump), state, step))
    times["jax_jit_s"] = run(bare, leaves)
    return {k: statistics.median(v) for k, v in times.items()} | dict(
        leaves=len(leaves)
    )


def main():
    ap = cli(__doc__)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--lags", type=int, nargs="+", default=[10, 50, 200])
    ap.add_argument("--closures", action="store_true")
    ap.add_argument("--span", type=int, default=8, help="closure span (< every lag)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--first-window-only", action="store_true", help="no timing")
    ap.add_argument("--se2vel", action="store_true", help="SE(2) + velocity chain")
    ap.add_argument("--per-update", action="store_true", help="update_rows per call")
    a = ap.parse_args()
    gtsam = optional("gtsam", " (GTSAM's fixed-lag smoothers)")
    chain = not (a.se2vel or a.first_window_only)
    data = problem(a.steps, a.span, a.closures) if chain else None
    loops = problem(a.steps, a.span, True) if a.per_update else None
    records = []
    for lag in a.lags:
        if a.se2vel:
            new = [se2vel_record(gtsam, a.steps, lag, a.repeats)]
        elif a.per_update:  # without, then with closures
            new = [per_update_record(gtsam, d, lag, a.span) for d in (data, loops)]
        elif a.first_window_only:
            new = [dict(lag=lag, **first_marginal_window(gtsam, lag))]
        else:
            new = [chain_record(gtsam, data, lag, a)]
        print(*new, sep="\n", flush=True)
        records += new
    if a.json:
        write_json(a.json, records, dict(options=vars(a)))


if __name__ == "__main__":
    main()
