"""XLA's cost analysis (flops, bytes accessed) of the chain solve (SE(2) +
velocity, T = 1e4, 10 fixed steps, BlockTridiagonal) and of the T = 200
training step (K = 3, batch 32; unrolled and truncated k = 1), for the
eqsmooth that is imported: a noise-free comparison of the work two source
trees compile, beside the timings (these machines are shared). Another
checkout's eqsmooth comes first with `-P` (the working directory not
searched for modules) and `PYTHONPATH`:

    python -m benchmarks.xla_cost [--json PATH]
    PYTHONPATH=TREE:. python -P -m benchmarks.xla_cost [--json PATH]
"""

import argparse
import json
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

import eqsmooth as eqs

from . import chain, train_step as ts
from ._common import xla_cost


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", default=None)
    path = parser.parse_args(argv).json
    jax.config.update("jax_enable_x64", True)
    graph, values = chain.se2vel_problem(10_000)
    solve = chain.make_solve(eqs.BlockTridiagonal(), 10)
    out = {"chain_solve": xla_cost(solve.lower(graph, values).compile())}
    truths, meas = ts.simulate(200, ts.BATCH, jnp.float64)
    graphs = eqx.filter_vmap(lambda m: ts.build_graph(m, jnp.float64))(meas)
    theta = jnp.full((2,), 1.0 / ts.MEAS_SIGMA, jnp.float64)
    adjoints = {"unrolled": eqs.UnrolledAdjoint(), "truncated": eqs.TruncatedAdjoint(1)}
    for name, adjoint in adjoints.items():  # K = 3 steps
        step = ts.eqsmooth_step(eqs.BlockTridiagonal(), 3, adjoint)
        jitted = jax.jit(lambda a, b, c: step(a, b, c))
        out["train_" + name] = xla_cost(jitted.lower(theta, graphs, truths).compile())
    print(json.dumps(out))
    if path:
        Path(path).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
