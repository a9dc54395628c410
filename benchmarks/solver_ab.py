"""A/B of the nonlinear solvers between two checkouts, in one command.

Runs the same workloads against this checkout's `eqsmooth` and another
checkout's (e.g. a `git worktree` of the commit before a refactor), each
workload in a fresh process per round with the two trees alternating, and
reports medians and the ratio new/old. Answers (final cost, iterations) must
agree; a mismatch is printed.

Workloads (float64): an SE(2) chain of T = 10⁴ poses with odometry and
position fixes (Levenberg-Marquardt, later call); the README's 5-pose graph
(Levenberg-Marquardt, first call in a fresh process and later call); a
training step at T = 200 (value and gradient of a loss through K = 3
unrolled Gauss-Newton steps, and through Gauss-Newton with the implicit
adjoint; later call).

    git worktree add /tmp/eqs_before <commit>
    python -m benchmarks.solver_ab --before /tmp/eqs_before --rounds 5 \
        --json benchmarks/results/solver_family_ab.json
"""

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


WORKLOADS = (
    "chain_lm_T10000",
    "pose5_lm",
    "train_fixed_step_T200",
    "train_implicit_T200",
)

_CHILD = r"""
import json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import eqsmooth as eqs

name = sys.argv[1]
REPEAT = 31

def timed(f, *a):
    t0 = time.perf_counter(); out = jax.block_until_ready(f(*a))
    first = time.perf_counter() - t0
    later = []
    for _ in range(REPEAT):
        t0 = time.perf_counter(); jax.block_until_ready(f(*a))
        later.append(time.perf_counter() - t0)
    return out, first, float(np.median(later))

xyt = lambda r: eqs.SE2.from_xy_theta(*jnp.asarray(r).T)

def chain(T):
    rng = np.random.default_rng(0)
    steps = np.stack([np.full(T - 1, 1.0), np.zeros(T - 1), 0.05 * np.sin(np.arange(T - 1) / 20)], 1)
    poses = [np.zeros(3)]
    for s in steps:
        x, y, th = poses[-1]
        poses.append(np.array([x + np.cos(th) * s[0] - np.sin(th) * s[1],
                               y + np.sin(th) * s[0] + np.cos(th) * s[1], th + s[2]]))
    poses = np.array(poses)
    odo = steps + rng.normal(scale=[0.05, 0.05, 0.01], size=steps.shape)
    gps = poses[::10] + rng.normal(scale=[0.5, 0.5, 0.5], size=poses[::10].shape)
    t = np.arange(T)
    graph = eqs.FactorGraph([
        eqs.BetweenFactor(eqs.Var("x", t[:-1]), eqs.Var("x", t[1:]), xyt(odo),
                          eqs.DiagonalNoise.from_sigmas(jnp.array([0.05, 0.05, 0.01]))),
        eqs.PriorFactor(eqs.Var("x", t[::10]), xyt(gps),
                        eqs.DiagonalNoise.from_sigmas(jnp.array([0.5, 0.5, 1e3]))),
    ])
    init = {"x": xyt(poses + rng.normal(scale=[0.3, 0.3, 0.05], size=poses.shape))}
    return graph, init

def pose5():
    odometry = xyt([[2, 0, 0], [2, 0, jnp.pi / 2], [2, 0, jnp.pi / 2], [2, 0, jnp.pi / 2], [2, 0, jnp.pi / 2]])
    graph = eqs.FactorGraph([
        eqs.PriorFactor(eqs.Var("x", [0]), xyt([[0, 0, 0]]), eqs.DiagonalNoise.from_sigmas(jnp.array([0.3, 0.3, 0.1]))),
        eqs.BetweenFactor(eqs.Var("x", [0, 1, 2, 3, 4]), eqs.Var("x", [1, 2, 3, 4, 1]), odometry,
                          eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1]))),
    ])
    init = {"x": xyt([[0.5, 0, 0.2], [2.3, 0.1, -0.2], [4.1, 0.1, 1.6], [4.0, 2.1, 3.1], [2.1, 2.1, -1.6]])}
    return graph, init

def walk(T=200):
    t = np.arange(T)
    rng = np.random.default_rng(0)
    truth = jnp.cumsum(0.3 * jnp.asarray(rng.normal(size=(T, 1))), axis=0)
    meas = truth + jnp.asarray(rng.normal(size=(T, 1)))
    def graph_of(log_sigma):
        return eqs.FactorGraph([
            eqs.FunctionFactor(lambda a, b, d, p: b - a, (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                               eqs.IsotropicNoise.from_sigma(jnp.exp(log_sigma))),
            eqs.FunctionFactor(lambda x, d, p: x - d, (eqs.Var("x", t),), eqs.IsotropicNoise.from_sigma(1.0), data=meas),
        ])
    return graph_of, truth, meas

if name in ("chain_lm_T10000", "pose5_lm"):
    graph, init = chain(10_000) if name == "chain_lm_T10000" else pose5()
    solve = jax.jit(lambda g, v: eqs.least_squares(g, v, eqs.LevenbergMarquardt(), max_steps=50))
    sol, first, later = timed(solve, graph, init)
    answer = dict(cost=float(sol.stats["final_cost"]), steps=int(sol.stats["num_steps"]),
                  accepted=int(sol.stats["num_accepted"]))
else:
    graph_of, truth, meas = walk()
    if name == "train_fixed_step_T200":
        solver, adjoint, init = eqs.FixedStepGaussNewton(num_steps=3), eqs.UnrolledAdjoint(), {"x": truth}
    else:
        solver, adjoint, init = eqs.GaussNewton(), eqs.ImplicitAdjoint(), {"x": meas}
    def loss(p):
        sol = eqs.least_squares(graph_of(p), init, solver, adjoint=adjoint)
        return jnp.mean((sol.value["x"] - truth) ** 2)
    f = jax.jit(jax.value_and_grad(loss))
    (value, grad), first, later = timed(f, jnp.log(0.5))
    answer = dict(loss=float(value), grad=float(grad))
print(json.dumps(dict(first_call_s=first, later_call_s=later, answer=answer)))
"""


def run_child(tree: Path, name: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "JAX_PLATFORMS": "cpu"}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, name],
        env=env,
        cwd=str(tree),
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--before", type=Path, required=True, help="the other checkout")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--workloads", nargs="*", default=list(WORKLOADS))
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    after = Path(__file__).resolve().parents[1]
    trees = {"before": args.before.resolve(), "after": after}
    rows = {}
    for name in args.workloads:
        runs = {"before": [], "after": []}
        for r in range(args.rounds):
            order = ("before", "after") if r % 2 == 0 else ("after", "before")
            for which in order:
                runs[which].append(run_child(trees[which], name))
        row = {}
        for which, rs in runs.items():
            row[which] = dict(
                first_call_s=float(np.median([x["first_call_s"] for x in rs])),
                later_call_s=float(np.median([x["later_call_s"] for x in rs])),
                answer=rs[0]["answer"],
            )
        for k in ("first_call_s", "later_call_s"):
            row[f"ratio_{k}"] = row["after"][k] / row["before"][k]
        a, b = row["after"]["answer"], row["before"]["answer"]
        row["same_answer"] = all(
            np.isclose(a[k], b[k], rtol=1e-9, atol=1e-12) for k in a
        )
        rows[name] = row
        print(
            f"{name:24s} later {row['before']['later_call_s'] * 1e3:9.2f} -> "
            f"{row['after']['later_call_s'] * 1e3:9.2f} ms "
            f"(x{row['ratio_later_call_s']:.2f}); first "
            f"{row['before']['first_call_s']:.2f} -> {row['after']['first_call_s']:.2f} s "
            f"(x{row['ratio_first_call_s']:.2f}); same answer: {row['same_answer']} "
            f"{a}",
            flush=True,
        )
    record = dict(
        benchmark="solver_ab",
        command="python -m benchmarks.solver_ab " + " ".join(argv or sys.argv[1:]),
        before=str(trees["before"]),
        rounds=args.rounds,
        date=time.strftime("%Y-%m-%d"),
        load_average=os.getloadavg(),
        rows=rows,
    )
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))
    return record


if __name__ == "__main__":
    main()
