"""XLA's cost analysis (flops, bytes accessed) of the chain solve (SE(2) +
velocity, T = 1e4, 10 fixed steps, BlockTridiagonal) and of the T = 200
training step (K = 3, batch 32; unrolled and truncated k = 1), for the
eqsmooth that is imported: a noise-free comparison of the work two source
trees compile, beside the timings (these machines are shared).

    PYTHONPATH=TREE python benchmarks/xla_cost.py TREE [--json PATH]
"""

import json
import sys


sys.path.insert(0, sys.argv[1] + "/benchmarks")
import chain  # noqa: E402
import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import train_step as ts  # noqa: E402

import eqsmooth as eqs  # noqa: E402


jax.config.update("jax_enable_x64", True)

out = {}
graph, values = chain.se2vel_problem(10_000)[:2]
solve = chain.make_solve(eqs.BlockTridiagonal(), 10)
c = solve.lower(graph, values).compile().cost_analysis()
c = c[0] if isinstance(c, list) else c
out["chain_solve"] = {k: c.get(k) for k in ("flops", "bytes accessed")}
T, K = 200, 3
truths, meas = ts.simulate(T, ts.BATCH, jnp.float64)[:2]
graphs = eqx.filter_vmap(lambda m: ts.build_graph(m, jnp.float64))(jnp.asarray(meas))
adjoints = (("unrolled", eqs.UnrolledAdjoint()), ("truncated", eqs.TruncatedAdjoint(1)))
for name, adj in adjoints:
    step = ts.eqsmooth_step(eqs.BlockTridiagonal(), K, adj)
    theta = jnp.full((2,), 1.0 / ts.MEAS_SIGMA, jnp.float64)
    jitted = jax.jit(lambda a, b, d: step(a, b, d))
    c = jitted.lower(theta, graphs, jnp.asarray(truths)).compile().cost_analysis()
    c = c[0] if isinstance(c, list) else c
    out["train_" + name] = {k: c.get(k) for k in ("flops", "bytes accessed")}
print(json.dumps(out))
if "--json" in sys.argv:
    with open(sys.argv[sys.argv.index("--json") + 1], "w") as fh:
        json.dump(out, fh, indent=1)
