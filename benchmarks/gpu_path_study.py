"""One-off study: CG iterations of PCG's preconditioners on large pose graphs.

1. LM with the sparse direct solver (`SparsaxCholesky`), recording every
   damped normal system `(JᵀJ + λD) δ = −Jᵀr` it solves (host callback).
2. At chosen LM steps, CG with each preconditioner to relative residual 1e-6
   and 1e-10 (iterations, seconds per iteration, build seconds).
3. The whole LM with `PCG(preconditioner)` (CG steps per LM step recorded by a
   host callback): final cost, LM steps, total CG steps.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.gpu_path_study \\
        --json benchmarks/results/pgo_gpu_path.json
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)

import gtsam  # noqa: E402

import eqsmooth as eqs  # noqa: E402
from eqsmooth.io import load_g2o  # noqa: E402
from eqsmooth.solve._linear._linear_solver import NormalOperator  # noqa: E402
from eqsmooth.solve._linearization import gradient  # noqa: E402
from eqsmooth.solve._misc import tree_dot  # noqa: E402


SYSTEMS: list = []
CG_STEPS: list = []


class RecordingSparsax(eqs.solve.SparsaxCholesky):
    def init(self, operator, options):
        def save(lin, d):  # host copies: the callback's buffers are not kept
            SYSTEMS.append(jax.tree_util.tree_map(np.array, (lin, d)))

        jax.debug.callback(save, operator.lin, operator.damping)
        return super().init(operator, options)


class CountingPCG(eqs.PCG):
    def compute(self, state, vector, options):
        x, result, stats = super().compute(state, vector, options)
        jax.debug.callback(lambda k: CG_STEPS.append(int(k)), stats["num_steps"])
        return x, result, stats


PRECONDITIONERS = {
    "jacobi": eqs.solve.BlockJacobi(),
    "chain": eqs.solve.ChainPreconditioner(),
    "twolevel": eqs.solve.TwoLevelPreconditioner(),
}


def curve_fn(pre, n):
    """Relative residual and the fraction of the exact step's model decrease
    left, after each of `n` PCG iterations (a scan: no early stop)."""

    @jax.jit
    def run(lin, damping, m_star):
        op = NormalOperator(lin, damping)
        b = {k: -v for k, v in gradient(lin).items()}
        apply = pre.build(lin, damping)
        bb = tree_dot(b, b)
        axpy = lambda a, x, y: jax.tree_util.tree_map(lambda u, v: a * u + v, x, y)  # noqa: E731
        z = apply(b)

        def body(c, _):
            x, r, p, rz = c
            ap = op.mv(p)
            alpha = rz / tree_dot(p, ap)
            x = axpy(alpha, p, x)
            r = axpy(-alpha, ap, r)
            z = apply(r)
            rz_new = tree_dot(r, z)
            p = axpy(rz_new / rz, p, z)
            # m(x) = -b.x + x.Hx/2 = -(b.x + r.x)/2 with r = b - Hx.
            m = -0.5 * (tree_dot(b, x) + tree_dot(r, x))
            return (x, r, p, rz_new), (jnp.sqrt(tree_dot(r, r) / bb), 1 - m / m_star)

        x0 = jax.tree_util.tree_map(jnp.zeros_like, b)
        _, (rel, left) = jax.lax.scan(body, (x0, b, z, tree_dot(b, z)), None, length=n)
        return rel, left

    return run


def exact_model(lin, damping):
    """m(δ*) = -b.δ*/2 of the exact step, by the sparse direct solver."""
    from eqsmooth.solve._linear._linear_solver import solve_normal

    delta, _ = solve_normal(eqs.solve.SparsaxCholesky(), lin, damping)
    b = {k: -v for k, v in gradient(lin).items()}
    return -0.5 * tree_dot(b, delta)


def first_below(a, tol):
    i = np.flatnonzero(np.asarray(a) <= tol)
    return int(i[0]) + 1 if len(i) else -1


def build_fn(pre):
    @jax.jit
    def run(lin, damping):
        apply = pre.build(lin, damping)
        return [x for x in jax.tree_util.tree_leaves(apply) if isinstance(x, jax.Array)]

    return run


def timed(fn, *args, n=3):
    jax.block_until_ready(fn(*args))
    ts = []
    for _ in range(n):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        ts.append(time.perf_counter() - t)
    return min(ts), out


def study_system(lin, damping, pres, max_cg):
    out = {}
    m_star = exact_model(lin, damping)
    for name in pres:
        pre = PRECONDITIONERS[name]
        t_n, (rel, left) = timed(curve_fn(pre, max_cg), lin, damping, m_star, n=1)
        t_10, _ = timed(curve_fn(pre, 10), lin, damping, m_star, n=3)
        rel, left = np.asarray(rel), np.asarray(left)
        rec = {
            f"iters_rel_{t:g}": first_below(rel, t) for t in (1e-2, 1e-4, 1e-6, 1e-10)
        }
        rec |= {f"iters_model_{t:g}": first_below(left, t) for t in (1e-1, 1e-2, 1e-4)}
        rec["rel_residual_at"] = {
            n: float(rel[n - 1]) for n in (10, 50, 100, 500, max_cg) if n <= max_cg
        }
        rec["model_left_at"] = {
            n: float(left[n - 1]) for n in (10, 50, 100, 500, max_cg) if n <= max_cg
        }
        rec["s_per_iter"] = (t_n - t_10) / (max_cg - 10)
        rec["build_s"], _ = timed(build_fn(pre), lin, damping)
        out[name] = rec
        print(name, rec, flush=True)
    return out


def lm_run(pg, lm_kw, linear, max_steps):
    solver = eqs.LevenbergMarquardt(linear, **lm_kw)
    t = time.perf_counter()
    sol = eqs.least_squares(
        pg.graph, pg.values, solver, max_steps=max_steps, throw=False
    )
    jax.block_until_ready(sol)
    return sol, time.perf_counter() - t


def main():
    p = argparse.ArgumentParser()
    p.add_argument(
        "--files", nargs="*", default=["w10000.graph", "sphere_smallnoise.graph"]
    )
    p.add_argument("--steps", nargs="*", type=int, default=[0, 1, 2, -1])
    p.add_argument("--pres", nargs="*", default=["jacobi", "chain"])
    p.add_argument("--lm-pres", nargs="*", default=["chain"])
    p.add_argument("--max-cg", type=int, default=3000)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--pcg-max-steps", nargs="*", type=int, default=[500])
    p.add_argument("--reference", nargs="*", type=float, default=[])
    p.add_argument("--json", default=None)
    args = p.parse_args()
    data = Path(gtsam.__file__).parent / "Data"
    sesync = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"
    records = []
    for f in args.files:
        if f.endswith(".g2o"):
            pg = load_g2o(sesync / f, invalid_information="block_diagonal")
        else:
            pg = load_g2o(data / f, skip_unsupported=True, se3_information="gtsam")
        lm_kw = {"damping_update": "fixed"} if "sphere_smallnoise" in f else {}
        SYSTEMS.clear()
        sol, direct_s = lm_run(pg, lm_kw, RecordingSparsax(), args.max_steps)
        rec = {"file": f, "poses": pg.num_poses, "edges": pg.num_edges, "lm": lm_kw}
        rec["direct"] = {
            "final_cost": float(sol.stats["final_cost"]),
            "num_steps": int(sol.stats["num_steps"]),
            "num_accepted": int(sol.stats["num_accepted"]),
            "first_call_s": direct_s,
            "systems": len(SYSTEMS),
        }
        ref = dict(zip(args.files, args.reference)).get(f)
        if ref:
            hist = np.asarray(sol.stats["cost_history"])[
                : int(sol.stats["num_steps"]) + 1
            ]
            ok = np.flatnonzero(hist <= ref * (1 + 1e-6))
            rec["direct"]["steps_to_reference"] = int(ok[0]) if len(ok) else -1
            rec["reference"] = ref
        print(f, rec["direct"], flush=True)
        systems = list(SYSTEMS)
        rec["systems"] = {}
        for s in args.steps:
            idx = s if s >= 0 else len(systems) + s
            lin, damping = systems[idx]
            lam = float(jnp.max(jnp.concatenate([v.ravel() for v in damping.values()])))
            print(f"{f} system {idx} (cost {float(lin.cost):.6g})", flush=True)
            r = study_system(lin, damping, args.pres, args.max_cg)
            r["cost"] = float(lin.cost)
            r["max_damping_entry"] = lam
            rec["systems"][str(idx)] = r
        ref = dict(zip(args.files, args.reference)).get(f)
        for name in args.lm_pres:
            for cap in args.pcg_max_steps:
                CG_STEPS.clear()
                linear = CountingPCG(
                    preconditioner=PRECONDITIONERS[name], max_steps=cap
                )
                sol, s = lm_run(pg, lm_kw, linear, args.max_steps)
                hist = np.asarray(sol.stats["cost_history"])
                r = {
                    "final_cost": float(sol.stats["final_cost"]),
                    "num_steps": int(sol.stats["num_steps"]),
                    "num_accepted": int(sol.stats["num_accepted"]),
                    "first_call_s": s,
                    "total_cg_steps": int(sum(CG_STEPS)),
                    "cg_steps": list(CG_STEPS),
                }
                if ref:
                    ok = np.flatnonzero(hist[: r["num_steps"] + 1] <= ref * (1 + 1e-6))
                    r["steps_to_reference"] = int(ok[0]) if len(ok) else -1
                    r["cg_steps_to_reference"] = (
                        int(sum(CG_STEPS[: r["steps_to_reference"]])) if len(ok) else -1
                    )
                rec[f"pcg_{name}_{cap}"] = r
                print(
                    f,
                    name,
                    cap,
                    {k: v for k, v in r.items() if k != "cg_steps"},
                    flush=True,
                )
                if args.json:
                    Path(args.json).write_text(json.dumps(records + [rec], indent=1))
        records.append(rec)
        if args.json:
            Path(args.json).write_text(json.dumps(records, indent=1))


def main_plain():
    """Without host callbacks (a callback before a solve with the two-level
    preconditioner left XLA:CPU waiting forever here): the systems from
    `least_squares(max_steps=k)`'s final state, and the LM with plain PCG."""
    from eqsmooth.solve._nonlinear._descent import marquardt_damping

    p = argparse.ArgumentParser()
    p.add_argument("file")
    p.add_argument("--ks", nargs="*", type=int, default=[1, 10])
    p.add_argument("--pres", nargs="*", default=["twolevel"])
    p.add_argument("--max-cg", type=int, default=300)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--reference", type=float, default=None)
    p.add_argument("--one-call", action="store_true")
    p.add_argument("--json", default=None)
    args = p.parse_args(sys.argv[2:])
    f = args.file
    pg = load_g2o(
        Path(gtsam.__file__).parent / "Data" / f,
        skip_unsupported=True,
        se3_information="gtsam",
    )
    lm_kw = {"damping_update": "fixed"} if "sphere_smallnoise" in f else {}
    lm = eqs.LevenbergMarquardt(**lm_kw)
    rec = {"file": f, "lm": lm_kw, "reference": args.reference, "systems": {}}
    for k in args.ks:
        sol, _ = lm_run(pg, lm_kw, eqs.SparsaxCholesky(), k)
        lin, lam = sol.state.lin, sol.state.damping
        damping = marquardt_damping(lin, lam, lm.min_diagonal, lm.max_diagonal)
        print(
            f,
            "after",
            k,
            "steps: cost",
            float(lin.cost),
            "lambda",
            float(lam),
            flush=True,
        )
        r = study_system(lin, damping, args.pres, args.max_cg)
        rec["systems"][str(k)] = r | {"cost": float(lin.cost), "lambda": float(lam)}
        if args.json:
            Path(args.json).write_text(json.dumps(rec, indent=1))
    for name in args.pres:
        linear = eqs.PCG(preconditioner=PRECONDITIONERS[name])
        sol, s = lm_run(pg, lm_kw, linear, args.max_steps)
        hist = np.asarray(sol.stats["cost_history"])[: int(sol.stats["num_steps"]) + 1]
        r = {
            "final_cost": float(sol.stats["final_cost"]),
            "num_steps": int(sol.stats["num_steps"]),
            "num_accepted": int(sol.stats["num_accepted"]),
            "first_call_s": s,
        }
        if args.reference:
            ok = np.flatnonzero(hist <= args.reference * (1 + 1e-6))
            r["steps_to_reference"] = int(ok[0]) if len(ok) else -1
        if not args.one_call:
            t = time.perf_counter()
            jax.block_until_ready(lm_run(pg, lm_kw, linear, args.max_steps)[0])
            r["second_call_s"] = time.perf_counter() - t
        rec[f"pcg_{name}"] = r
        print(f, name, r, flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(rec, indent=1))


if __name__ == "__main__":
    main_plain() if sys.argv[1:2] == ["plain"] else main()
