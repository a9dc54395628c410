"""The `JᵢᵀJⱼ` blocks of the normal matrix: batched `einsum` against `block_gram`.

The solvers form the Gram blocks of every factor stack with
`eqsmooth.solve._linear._small_blocks.block_gram` (a sum of outer
products, which XLA fuses into one loop over the rows; it was called
`block_matmul`, with its first argument transposed by the caller, when
`benchmarks/results/gram_blocks.json` was recorded, and the records keep
that label). This script puts the batched `einsum` it replaced back in its
place (the module attribute the chain assembly looks up) and times, in one
process, alternating the two in `--rounds` rounds:

- `factorize`: `eqs.solve.factorize(lin, BlockTridiagonal())` of a chain's
  linearisation, the public call that assembles and factorises (used by
  the marginals), for `chain.py`'s `se2vel` and `vehicle` problems;
- `iteration`: one Gauss-Newton iteration (linearise, assemble, factorise,
  solve, retract) as one program, as inside a solve.

Per configuration the minimum over `--repeats` calls is kept per round
(this machine's timings vary by tens of percent between calls), and the
record gives every round and their minimum.

    python benchmarks/gram_blocks.py --json benchmarks/results/gram_blocks.json
"""

import argparse

import jax
import jax.numpy as jnp
from _common import markdown_table, time_fn, write_json
from chain import make_iteration, se2vel_problem, vehicle_problem

import eqsmooth as eqs
import eqsmooth.solve._linear._block_tridiagonal as chain_module
from eqsmooth.solve._linear._small_blocks import block_gram


jax.config.update("jax_enable_x64", True)


def _einsum(a, b):
    # What the assembly computed before: Jᵢᵀ Jⱼ per row as one batched einsum.
    return jnp.einsum("nmd,nme->nde", a, b)


PRODUCTS = {"einsum": _einsum, "block_gram": block_gram}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[10_000, 100_000])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    builders = {"se2vel": se2vel_problem, "vehicle": vehicle_problem}
    records = []
    for T in args.sizes:
        for problem, build in builders.items():
            graph, values = build(T)
            lin = eqs.linearize(graph, values)
            rounds: dict = {}
            for _ in range(args.rounds):
                for name, product in PRODUCTS.items():
                    chain_module.block_gram = product
                    ls = eqs.BlockTridiagonal()
                    parts = {
                        "factorize": (
                            jax.jit(lambda lin: eqs.solve.factorize(lin, ls)),
                            (lin,),
                        ),
                        "iteration": (make_iteration(ls), (graph, values)),
                    }
                    for stage, (fn, fn_args) in parts.items():
                        repeats = args.repeats if T < 100_000 else 3
                        _, _, times = time_fn(fn, *fn_args, repeats=repeats)
                        rounds.setdefault((stage, name), []).append(min(times) * 1e3)
            chain_module.block_gram = block_gram
            for (stage, name), ms in rounds.items():
                rec = {
                    "benchmark": "gram_blocks",
                    "config": {
                        "problem": problem,
                        "T": T,
                        "stage": stage,
                        "product": name,
                    },
                    "problem": problem,
                    "T": T,
                    "stage": stage,
                    "product": name,
                    "rounds_min_ms": ms,
                    "min_ms": min(ms),
                }
                print(
                    f"{problem:8s} T={T:<7d} {stage:10s} {name:13s} "
                    f"min {min(ms):8.2f} ms  rounds {[round(m, 2) for m in ms]}",
                    flush=True,
                )
                records.append(rec)
            if args.json:  # after every problem, so a stopped run keeps its cells
                write_json(args.json, records)
    print(markdown_table(records, ["problem", "T", "stage", "product", "min_ms"]))


if __name__ == "__main__":
    main()
