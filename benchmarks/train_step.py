"""Time of one training step (forward + backward) of the surrogate loss.

The paper's learning task (Yi et al., 2021): a batch of 32 disk-tracking
graphs, state [px, py, vx, vy], dynamics `p' = p + v`,
`v' = v − 0.05 p − 0.0075 sign(v) v²` with fixed noise, position measurements
whose noise square-root precision (2 numbers, shared by the batch) is learned.
The surrogate loss starts the solver at the ground truth, runs K Gauss-Newton
steps (`FixedStepGaussNewton`) and takes the mean squared error to the ground
truth. One unit of work = `jax.value_and_grad` of the batch-mean loss with
respect to the square-root precision, jitted.

Measured for K = 3, 5 and T = 20, 200, 2000, for every adjoint (unrolled,
truncated k = 1, implicit: `GaussNewton` capped at K steps, since the
implicit adjoint refuses a fixed-step solve that stops short of a stationary
point) and linear solver (BlockTridiagonal; DenseCholesky only for T <= 200;
PCG), next to a dense JAX reference in this script (the whole Jacobian by
`jax.jacfwd`, dense Cholesky normal equations, K steps unrolled; infeasible
at T = 2000, recorded as not measured there).

Theseus (Pineda et al. 2022), when importable, solves the same problem in the
same process (a `th.Vector(4)` per step, `th.AutoDiffCostFunction`s, the
learned parameter as a `th.DiagonalCostWeight`, `th.GaussNewton` with
exactly K steps, in a `th.TheseusLayer`; CHOLMOD, or dense Cholesky at T =
20; backward modes unroll and implicit). Installing it (CPU, a separate
virtual environment; `apt-get install libsuitesparse-dev` first):

    pip install torch==2.13.0 cython setuptools wheel
    pip install --no-build-isolation scikit-sparse==0.4.16 theseus-ai
    pip install -e ".[test]"

`grad_rel_err` is the relative difference to the reference gradient: ~0 for
unrolled; truncated k = 1 and implicit are other gradients by design.
`median_s`: median over repeats after warm-up; `compile_s`: first call minus
median; `ratio`: median_s / the reference's median_s of the same (K, T) in
the same run. On a shared machine set `OPENBLAS_NUM_THREADS=1` (an
oversubscribed OpenBLAS made the dense reference 10-100x slower).

    python -m benchmarks.train_step             # all configurations
    python -m benchmarks.train_step --quick     # T = 20, K = 3 (< 1 min)
    python -m benchmarks.train_step --json benchmarks/results/train_step.json \\
        --markdown benchmarks/results/train_step.md
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs

from ._common import (
    cli,
    disk_dynamics,
    disk_position,
    disk_step,
    machine,
    markdown_table,
    optional,
    record,
    time_fn,
    time_host,
    write_json,
    write_text,
)


BATCH = 32
DYN_SIGMAS = (0.1, 0.1, 0.5, 0.5)
MEAS_SIGMA = 5.0
SOLVERS = {
    "BlockTridiagonal": eqs.BlockTridiagonal(),
    "DenseCholesky": eqs.DenseCholesky(),
    "PCG": eqs.PCG(),
}
ADJOINTS = {
    "unrolled": eqs.UnrolledAdjoint(),
    "truncated(k=1)": eqs.TruncatedAdjoint(1),
    "implicit": eqs.ImplicitAdjoint(),
}


def simulate(T: int, batch: int, dtype, seed: int = 0):
    """Ground-truth trajectories `(B, T, 4)` and measurements `(B, T, 2)`."""
    rng = np.random.default_rng(seed)
    x = np.zeros((batch, T, 4))
    x[:, 0, :2] = rng.normal(scale=30.0, size=(batch, 2))
    x[:, 0, 2:] = rng.normal(scale=3.0, size=(batch, 2))
    for t in range(1, T):
        x[:, t] = np.asarray(disk_step(jnp.asarray(x[:, t - 1]))) + rng.normal(
            size=(batch, 4)
        ) * np.asarray(DYN_SIGMAS)
    meas = x[:, :, :2] + rng.normal(scale=MEAS_SIGMA, size=(batch, T, 2))
    return jnp.asarray(x, dtype), jnp.asarray(meas, dtype)


def build_graph(meas, dtype):
    """One disk graph (used under vmap over the batch of measurements)."""
    T = meas.shape[0]
    t = np.arange(T)
    return eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                disk_dynamics,
                (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                eqs.DiagonalNoise(sqrt_precision=1.0 / jnp.asarray(DYN_SIGMAS, dtype)),
            ),
            eqs.FunctionFactor(
                disk_position,
                (eqs.Var("x", t),),
                eqs.DiagonalNoise(
                    sqrt_precision=jnp.full((2,), 1.0 / MEAS_SIGMA, dtype)
                ),
                data=meas,
            ),
        ]
    )


def eqsmooth_step(linear_solver, K: int, adjoint):
    # The implicit adjoint refuses to differentiate a fixed-step solve that
    # stops short of a stationary point: it gets Gauss-Newton capped at K
    # steps (the same iterations; its gradient is the implicit one at them).
    if isinstance(adjoint, eqs.ImplicitAdjoint):
        solver = eqs.GaussNewton(linear_solver)
    else:
        solver = eqs.FixedStepGaussNewton(linear_solver, num_steps=K)

    def one(theta, graph, truth):
        graph = eqx.tree_at(lambda g: g.factors[1].noise.sqrt_precision, graph, theta)
        x = eqs.least_squares(
            graph, {"x": truth}, solver, max_steps=K, adjoint=adjoint, throw=False
        ).value["x"]
        return jnp.mean((x - truth) ** 2)

    def loss(theta, graphs, truths):
        per = eqx.filter_vmap(one, in_axes=(None, 0, 0))(theta, graphs, truths)
        return jnp.mean(per)

    return eqx.filter_jit(jax.value_and_grad(loss))


def dense_reference_step(K: int):
    """The same loss, written with a dense Jacobian and dense normal equations."""

    def residual(theta, meas, x_flat):
        T = meas.shape[0]
        x = x_flat.reshape(T, 4)
        w = (1.0 / jnp.asarray(DYN_SIGMAS)).astype(x.dtype)
        dyn = (x[1:] - disk_step(x[:-1])) * w[None, :]
        obs = (x[:, :2] - meas) * theta[None, :]
        return jnp.concatenate([dyn.reshape(-1), obs.reshape(-1)])

    def one(theta, meas, truth):
        x = truth.reshape(-1)
        for _ in range(K):
            r = residual(theta, meas, x)
            J = jax.jacfwd(residual, argnums=2)(theta, meas, x)
            H = J.T @ J
            g = J.T @ r
            x = x + jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(H), -g)
        return jnp.mean((x.reshape(truth.shape) - truth) ** 2)

    def loss(theta, meas, truths):
        per = jax.vmap(one, in_axes=(None, 0, 0))(theta, meas, truths)
        return jnp.mean(per)

    return jax.jit(jax.value_and_grad(loss))


def _dyn_err(optim_vars, aux_vars):
    import torch

    a, b = optim_vars[0].tensor, optim_vars[1].tensor
    p, v = a[:, :2], a[:, 2:]
    step = torch.cat([p + v, v - 0.05 * p - 0.0075 * torch.sign(v) * v * v], dim=1)
    return b - step


def _meas_err(optim_vars, aux_vars):
    return optim_vars[0].tensor[:, :2] - aux_vars[0].tensor


def theseus_step(meas, truths, K: int, solver: str, backward: str):
    """`fn()`: one forward + backward of a Theseus layer for the same batch,
    returning `(loss, grad)` as numpy."""
    import theseus as th
    import torch

    dtype = torch.float64 if meas.dtype == jnp.float64 else torch.float32
    meas_t = torch.from_numpy(np.array(meas)).to(dtype)
    truth_t = torch.from_numpy(np.array(truths)).to(dtype)
    B, T, _ = truth_t.shape
    xs = [th.Vector(4, name=f"x{t}", dtype=dtype) for t in range(T)]
    ys = [th.Variable(meas_t[:, t], name=f"y{t}") for t in range(T)]
    dyn_w = th.DiagonalCostWeight(
        th.Variable(1.0 / torch.tensor([DYN_SIGMAS], dtype=dtype), name="dyn_w")
    )
    theta0 = torch.full((1, 2), 1.0 / MEAS_SIGMA, dtype=dtype)
    meas_w = th.DiagonalCostWeight(th.Variable(theta0.clone(), name="theta"))
    objective = th.Objective(dtype=dtype)
    for t in range(T - 1):
        pair = [xs[t], xs[t + 1]]
        dyn = th.AutoDiffCostFunction(pair, _dyn_err, 4, dyn_w, name=f"dyn{t}")
        objective.add(dyn)
    for t in range(T):
        kw = {"aux_vars": [ys[t]], "name": f"meas{t}"}
        objective.add(th.AutoDiffCostFunction([xs[t]], _meas_err, 2, meas_w, **kw))
    cls = {"CHOLMOD": th.CholmodSparseSolver, "dense Cholesky": th.CholeskyDenseSolver}
    tol = {"abs_err_tolerance": 0.0, "rel_err_tolerance": 0.0}
    optimizer = th.GaussNewton(
        objective, linear_solver_cls=cls[solver], max_iterations=K, step_size=1.0, **tol
    )
    layer = th.TheseusLayer(optimizer)
    inputs = {f"x{t}": truth_t[:, t] for t in range(T)}
    inputs.update({f"y{t}": meas_t[:, t] for t in range(T)})
    options = {"backward_mode": backward, "verbose": False}
    options["track_best_solution"] = False

    def fn():
        theta = theta0.clone().requires_grad_(True)
        sol, _ = layer.forward({**inputs, "theta": theta}, optimizer_kwargs=options)
        x = torch.stack([sol[f"x{t}"] for t in range(T)], dim=1)
        loss = torch.mean((x - truth_t) ** 2)
        loss.backward()
        return float(loss.detach()), theta.grad.detach().numpy()[0]

    return fn


def _rel_err(g, ref):
    g, ref = np.asarray(g), np.asarray(ref)
    return float(np.linalg.norm(g - ref) / max(np.linalg.norm(ref), 1e-300))


def parse(argv):
    parser = cli(__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--markdown", default=None)
    parser.add_argument("--sizes", type=int, nargs="*", default=None)
    parser.add_argument("--steps", type=int, nargs="*", default=None)
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-reference", action="store_true", help="skip dense JAX")
    parser.add_argument("--theseus-max-T", type=int, default=2000)
    parser.add_argument("--solvers", nargs="*", default=list(SOLVERS))
    parser.add_argument("--adjoints", nargs="*", default=list(ADJOINTS))
    parser.add_argument(
        "--theseus-backward",
        nargs="*",
        default=["unroll", "implicit"],
        choices=["unroll", "implicit"],
        help="(unroll at T = 2000 needed more than 24 GiB here)",
    )
    return parser.parse_args(argv)


def missing_reference(args, T: int, K: int, dtype) -> dict:
    """The record of a dense JAX reference not measured, saying why."""
    rec = _record(args, T, K, "dense JAX reference") | {"median_s": None}
    if args.no_reference:
        return rec | {"note": "not measured (--no-reference)"}
    gib = BATCH * 6 * T * 4 * T * dtype.itemsize / 2**30
    note = f"not measured: dense J is (6T x 4T) per graph, {gib:.0f} GiB "
    return rec | {"note": note + "for the batch"}


def _record(args, T: int, K: int, method: str, **extra) -> dict:
    """A record of T, K, the batch, dtype, `extra` and the method."""
    config = {"T": T, "K": K, "batch": BATCH, "dtype": args.dtype} | extra
    return record("train_step", config | {"method": method})


def write_markdown(path, m, table):
    text = "# Training step: forward + backward of the surrogate loss\n\n"
    text += f"- command: `{m['command']}`; git {m['git']}; jax {m['jax']}\n"
    text += f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}, backend "
    text += f"{m['backend']}; load average at start {m['load_average'][0]:.1f}\n"
    write_text(path, text + "\n" + table)


COLUMNS = ["T", "K", "method", "median_s", "compile_s", "ratio", "grad_rel_err"]
COLUMNS += ["speedup_vs_theseus", "note"]


def methods(args):
    """The Theseus configurations, eqsmooth solvers and adjoints to measure."""
    theseus = []
    if optional("theseus") is not None:
        theseus = [("CHOLMOD", "unroll"), ("CHOLMOD", "implicit")]
        theseus += [("dense Cholesky", "unroll")]
        theseus = theseus[:1] if args.quick else theseus
        theseus = [c for c in theseus if c[1] in args.theseus_backward]
    adjoints = [a for a in ADJOINTS if a in args.adjoints]
    solvers = [s for s in SOLVERS if s in args.solvers]
    if args.quick:
        adjoints = [a for a in adjoints if a in ("unrolled", "implicit")]
        solvers = [s for s in solvers if s == "BlockTridiagonal"]
    return theseus, {s: SOLVERS[s] for s in solvers}, {a: ADJOINTS[a] for a in adjoints}


def main(argv=None):
    args = parse(argv)
    m = machine()  # git hash, load and thread settings when the run started
    theseus_configs, solvers, adjoints = methods(args)
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.dtype(args.dtype)
    sizes = args.sizes or ([20] if args.quick else [20, 200, 2000])
    steps = args.steps or ([3] if args.quick else [3, 5])
    records, theseus_times = [], {}

    def measured(T, K, ref, method, fn, host=False, **extra):
        """Time `fn()` (a Theseus layer's on the host), record, save, print."""
        if host:
            first, times, _ = time_host(fn, args.repeats)
            median = float(np.median(times))
        else:
            first, median, _ = time_fn(fn, repeats=args.repeats)
        val, grad = fn()
        rec = _record(args, T, K, method, **extra) | {"median_s": median}
        rec |= {"compile_s": first - median, "loss": float(val)}
        text = ""
        if ref is not None:
            rec["reference_median_s"] = ref["median_s"]
            rec["ratio"] = median / ref["median_s"]
            rec["grad_rel_err"] = _rel_err(grad, ref["grad"])
            err = rec["grad_rel_err"]
            text = f"  ratio {rec['ratio']:6.3f}  grad rel err {err:.1e}"
        if host:  # a Theseus row: the reference for the speed-up column
            theseus_times[(T, K, method)] = median
        th_key = (T, K, "Theseus CHOLMOD unroll")
        if not host and th_key in theseus_times:
            rec["theseus_cholmod_s"] = theseus_times[th_key]
            rec["speedup_vs_theseus"] = theseus_times[th_key] / median
        records.append(rec)
        # Written after every record: a run stopped part-way keeps its rows.
        if args.json:
            write_json(args.json, records, {"machine_at_start": m})
        what, secs = ("first call", first) if host else ("compile", first - median)
        line = f"T={T:<5d} K={K} {method:34s} {median * 1e3:10.2f} ms  {what}"
        print(f"{line} {secs:6.2f} s{text}", flush=True)
        return rec, grad

    for T in sizes:
        truths, meas = simulate(T, BATCH, dtype)
        graphs = eqx.filter_vmap(lambda m: build_graph(m, dtype))(meas)
        theta = jnp.full((2,), 1.0 / MEAS_SIGMA, dtype)
        for K in steps:
            ref = None
            if args.no_reference or T > 200:
                records.append(missing_reference(args, T, K, dtype))
            else:
                dense = dense_reference_step(K)
                call = lambda: dense(theta, meas, truths)
                rec, grad = measured(T, K, None, "dense JAX reference", call)
                rec |= {"reference_median_s": rec["median_s"], "ratio": 1.0}
                ref = {"median_s": rec["median_s"], "grad": grad}
            if not theseus_configs:
                note = "not measured: Theseus is not installed"
                rec = _record(args, T, K, "Theseus")
                records.append(rec | {"median_s": None, "note": note})
            for tsolver, tback in theseus_configs:
                if (tsolver == "dense Cholesky" and T > 20) or T > args.theseus_max_T:
                    continue
                fn = theseus_step(meas, truths, K, tsolver, tback)
                measured(T, K, ref, f"Theseus {tsolver} {tback}", fn, host=True)
            for sname, ls in solvers.items():
                if sname == "DenseCholesky" and T > 200:
                    continue
                for aname, adjoint in adjoints.items():
                    step = eqsmooth_step(ls, K, adjoint)
                    call = lambda: step(theta, graphs, truths)
                    method = f"eqsmooth {sname} {aname}"
                    measured(T, K, ref, method, call, solver=sname, adjoint=aname)
    table = markdown_table(records, COLUMNS)
    print()
    print(table)
    if args.json:
        write_json(args.json, records, {"machine_at_start": m})
    if args.markdown:
        write_markdown(args.markdown, m, table)


if __name__ == "__main__":
    main()
