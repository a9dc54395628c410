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

    python benchmarks/train_step.py             # all configurations
    python benchmarks/train_step.py --quick     # T = 20, K = 3 (< 1 min)
    python benchmarks/train_step.py --json benchmarks/results/train_step.json \\
        --markdown benchmarks/results/train_step.md
"""

import argparse

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _common import (
    machine,
    markdown_table,
    optional,
    time_fn,
    time_host,
    write_json,
    write_text,
)

import eqsmooth as eqs


BATCH = 32
DYN_SIGMAS = (0.1, 0.1, 0.5, 0.5)
MEAS_SIGMA = 5.0


def _step(x):
    p, v = x[..., :2], x[..., 2:]
    return jnp.concatenate(
        [p + v, v - 0.05 * p - 0.0075 * jnp.sign(v) * v * v], axis=-1
    )


def _disk_dyn(a, b, data, params):
    return b - _step(a)


def _disk_meas(x, data, params):
    return x[:2] - data


def simulate(T: int, batch: int, dtype, seed: int = 0):
    """Ground-truth trajectories `(B, T, 4)` and measurements `(B, T, 2)`."""
    rng = np.random.default_rng(seed)
    x = np.zeros((batch, T, 4))
    x[:, 0, :2] = rng.normal(scale=30.0, size=(batch, 2))
    x[:, 0, 2:] = rng.normal(scale=3.0, size=(batch, 2))
    for t in range(1, T):
        x[:, t] = np.asarray(_step(jnp.asarray(x[:, t - 1]))) + rng.normal(
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
                _disk_dyn,
                (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                eqs.DiagonalNoise(sqrt_precision=1.0 / jnp.asarray(DYN_SIGMAS, dtype)),
            ),
            eqs.FunctionFactor(
                _disk_meas,
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
        dyn = (x[1:] - _step(x[:-1])) * w[None, :]
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    parser.add_argument("--sizes", type=int, nargs="*", default=None)
    parser.add_argument("--steps", type=int, nargs="*", default=None)
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-reference", action="store_true", help="skip dense JAX")
    parser.add_argument("--theseus-max-T", type=int, default=2000)
    parser.add_argument(
        "--solvers", nargs="*", default=["BlockTridiagonal", "DenseCholesky", "PCG"]
    )
    parser.add_argument(
        "--adjoints", nargs="*", default=["unrolled", "truncated(k=1)", "implicit"]
    )
    parser.add_argument(
        "--theseus-backward",
        nargs="*",
        default=["unroll", "implicit"],
        choices=["unroll", "implicit"],
        help="(unroll at T = 2000 needed more than 24 GiB here)",
    )
    return parser.parse_args(argv)


def reference_record(args, T, K, theta, meas, truths, dtype):
    """The dense JAX reference of (T, K), or a record saying why it is missing."""
    config = {"T": T, "K": K, "batch": BATCH, "dtype": args.dtype}
    rec = {
        "benchmark": "train_step",
        "config": config | {"method": "dense JAX reference"},
    }
    rec |= {"T": T, "K": K, "method": "dense JAX reference"}
    if T > 200 or args.no_reference:
        gib = BATCH * 6 * T * 4 * T * dtype.itemsize / 2**30
        note = (
            "not measured (--no-reference)"
            if args.no_reference
            else (
                f"not measured: dense J is (6T x 4T) per graph, {gib:.0f} GiB "
                "for the batch"
            )
        )
        return rec | {"median_s": None, "note": note}, None
    fn = dense_reference_step(K)
    first, median, _ = time_fn(fn, theta, meas, truths, repeats=args.repeats)
    val, grad = fn(theta, meas, truths)
    print(
        f"T={T:<5d} K={K} {'dense JAX reference':34s} {median * 1e3:10.2f} ms  "
        f"compile {first - median:6.2f} s",
        flush=True,
    )
    rec |= {"median_s": median, "compile_s": first - median, "loss": float(val)}
    return rec | {"reference_median_s": median, "ratio": 1.0}, {
        "median_s": median,
        "grad": grad,
    }


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
    names = ("unrolled", "truncated(k=1)", "implicit")
    kinds = (eqs.UnrolledAdjoint(), eqs.TruncatedAdjoint(1), eqs.ImplicitAdjoint())
    adjoints = dict(zip(names, kinds))
    names = ("BlockTridiagonal", "DenseCholesky", "PCG")
    solvers = dict(zip(names, (eqs.BlockTridiagonal(), eqs.DenseCholesky(), eqs.PCG())))
    if args.quick:
        adjoints = {k: adjoints[k] for k in ("unrolled", "implicit")}
        solvers = {"BlockTridiagonal": solvers["BlockTridiagonal"]}
    solvers = {k: v for k, v in solvers.items() if k in args.solvers}
    return theseus, solvers, {k: v for k, v in adjoints.items() if k in args.adjoints}


def main(argv=None):
    args = parse(argv)
    m = machine()  # git hash, load and thread settings when the run started
    theseus_configs, solvers, adjoints = methods(args)
    theseus_times = {}
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.dtype(args.dtype)
    sizes = args.sizes or ([20] if args.quick else [20, 200, 2000])
    steps = args.steps or ([3] if args.quick else [3, 5])
    records = []

    def measured(T, K, ref, method, extra, first, median, val, grad, host=False):
        """Record, save and print one measured configuration."""
        config = {"T": T, "K": K, "batch": BATCH, "dtype": args.dtype}
        rec = {"benchmark": "train_step", "config": config | extra | {"method": method}}
        rec |= {"T": T, "K": K, "method": method, "median_s": median}
        rec |= {"compile_s": first - median, "loss": float(val)}
        text = ""
        if ref is not None:
            rec["reference_median_s"] = ref["median_s"]
            rec["ratio"] = median / ref["median_s"]
            rec["grad_rel_err"] = _rel_err(grad, ref["grad"])
            text = (
                f"  ratio {rec['ratio']:6.3f}  grad rel err {rec['grad_rel_err']:.1e}"
            )
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
        first_text = (
            f"first call {first:6.2f}" if host else f"compile {first - median:6.2f}"
        )
        print(
            f"T={T:<5d} K={K} {method:34s} {median * 1e3:10.2f} ms  "
            f"{first_text} s{text}",
            flush=True,
        )

    for T in sizes:
        truths, meas = simulate(T, BATCH, dtype)
        graphs = eqx.filter_vmap(lambda m: build_graph(m, dtype))(meas)
        theta = jnp.full((2,), 1.0 / MEAS_SIGMA, dtype)
        for K in steps:
            rec, ref = reference_record(args, T, K, theta, meas, truths, dtype)
            records.append(rec)
            if not theseus_configs:
                config = {"T": T, "K": K, "batch": BATCH, "dtype": args.dtype}
                records.append(
                    {
                        "benchmark": "train_step",
                        "config": config | {"method": "Theseus"},
                    }
                    | {"T": T, "K": K, "method": "Theseus", "median_s": None}
                    | {"note": "not measured: Theseus is not installed"}
                )
            for tsolver, tback in theseus_configs:
                if (tsolver == "dense Cholesky" and T > 20) or T > args.theseus_max_T:
                    continue
                fn = theseus_step(meas, truths, K, tsolver, tback)
                first, times, _ = time_host(fn, args.repeats)
                val, grad = fn()
                method = f"Theseus {tsolver} {tback}"
                median = float(np.median(times))
                measured(T, K, ref, method, {}, first, median, val, grad, host=True)
            for sname, ls in solvers.items():
                if sname == "DenseCholesky" and T > 200:
                    continue
                for aname, adjoint in adjoints.items():
                    fn = eqsmooth_step(ls, K, adjoint)
                    args_ = (theta, graphs, truths)
                    first, median, _ = time_fn(fn, *args_, repeats=args.repeats)
                    val, grad = fn(*args_)
                    extra = {"solver": sname, "adjoint": aname}
                    method = f"eqsmooth {sname} {aname}"
                    measured(T, K, ref, method, extra, first, median, val, grad)
    table = markdown_table(records, COLUMNS)
    print()
    print(table)
    if args.json:
        write_json(args.json, records, {"machine_at_start": m})
    if args.markdown:
        write_markdown(args.markdown, m, table)


if __name__ == "__main__":
    main()
