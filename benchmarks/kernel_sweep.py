"""A robust-kernel sweep on one graph: named kernels against KernelChoice.

With the named kernels (`HuberNoise`, `TukeyNoise`, ...) each kernel class is
static structure of the compiled solve, so a sweep compiles once per kernel;
with `RobustNoise(base, KernelChoice(K), k)` the kernel is data and the sweep
is one program. Each mode runs in a fresh process: a 4-pose SE(2) loop with
each of the nine kernels on its odometry, Levenberg-Marquardt; the wall time
and the XLA compilations of the sweep (`programs`: their names), apart from
those made before it while building the poses and noise models eagerly
(`setup_compilations`).

    python -m benchmarks.kernel_sweep --json benchmarks/results/kernel_sweep.json
"""

import json
import time

from ._common import cli, compile_log, run_child, se2, write_json


def child(mode: str) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    import eqsmooth as eqs

    F = eqs.factors
    # The nine kernels, in KernelChoice's order.
    KERNELS = (F.Huber, F.Cauchy, F.Tukey, F.GemanMcClure, F.Welsch, F.DCS, F.Fair)
    KERNELS += (F.L2WithDeadZone, F.TruncatedQuadratic)
    jax.config.update("jax_enable_x64", True)
    compiles = compile_log()

    odo = se2([[2, 0, 0], [2, 0, np.pi / 2], [2, 0, np.pi / 2], [2, 0, np.pi / 2]])
    init = se2([[0.4, 0.1, 0.15], [2.3, 0.1, -0.2], [4.1, 0.2, 1.6], [4.0, 2.1, 3.1]])
    base = eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1]))
    prior_noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.3, 0.3, 0.1]))
    prior = eqs.PriorFactor(eqs.Var("x", [0]), se2([[0, 0, 0]]), prior_noise)
    scale = jnp.asarray(1.345)
    ids = eqs.Var("x", [1, 2, 3, 0])
    setup = len(compiles)  # building the poses and noise models, eagerly
    t0 = time.perf_counter()
    for K in KERNELS:
        kernel = eqs.factors.KernelChoice(K) if mode == "choice" else K()
        noise = eqs.RobustNoise(base, kernel, scale)
        loop = eqs.BetweenFactor(eqs.Var("x", [0, 1, 2, 3]), ids, odo, noise)
        graph = eqs.FactorGraph([prior, loop])
        sol = eqs.least_squares(graph, {"x": init}, eqs.LevenbergMarquardt())
        jax.block_until_ready(sol.value)
    sweep_s = time.perf_counter() - t0
    swept = compiles[setup:]
    solves = [c for c in swept if "least_squares" in str(c[0])]
    rec = {"mode": mode, "kernels": len(KERNELS), "sweep_s": sweep_s}
    rec |= {"compilations": len(swept), "solve_compilations": len(solves)}
    rec |= {"compile_s": sum(c[1] for c in swept), "programs": [c[0] for c in swept]}
    return rec | {"setup_compilations": setup}


def main():
    p = cli(__doc__)
    p.add_argument("--child", choices=["named", "choice"])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--quick", action="store_true", help="one repeat")
    a = p.parse_args()
    if a.child:
        print(json.dumps(child(a.child)))
        return
    rows = []
    for _ in range(1 if a.quick else a.repeats):
        for mode in ("named", "choice"):
            rows.append(run_child("kernel_sweep", ["--child", mode]))
            r = rows[-1]
            print(
                f"{r['mode']:6s} {r['kernels']} kernels: sweep {r['sweep_s']:.2f} s, "
                f"{r['solve_compilations']} solve programs compiled, "
                f"{r['compilations']} compilations in the sweep "
                f"({r['compile_s']:.2f} s of XLA; {r['setup_compilations']} "
                "before it, building the graph's pieces)"
            )
    if a.json:
        write_json(a.json, rows)


if __name__ == "__main__":
    main()
