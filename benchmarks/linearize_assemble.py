"""Per-step pieces of a pose-graph solve: pattern, linearisation, assembly.

For each g2o file, in one process: the time to build the sparsity pattern
(`eqsmooth.solve._linear._sparse._Pattern`, once per graph structure), and the
median time of the jitted linearisation (`linearize`) and of the jitted
assembly of `JᵀJ + 1e-3·I` (`assemble_sparse`) at the file's initial
values. With `--whiten`, also the XLA-on-CPU cost of whitening `n` Jacobian
blocks by a per-row `6 × 6` square-root information as one `(n, 6, 12)`
batch against two `(n, 6, 6)` batches.

Run it against two source trees to compare them:

    python benchmarks/linearize_assemble.py --whiten --json results.json
    PYTHONPATH=/path/to/old-tree python benchmarks/linearize_assemble.py
"""

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import write_json  # noqa: E402

import eqsmooth  # noqa: E402
from eqsmooth.io import load_g2o  # noqa: E402
from eqsmooth.solve._linear._linear_solver import NormalOperator  # noqa: E402
from eqsmooth.solve._linear._sparse import _Pattern, assemble_sparse  # noqa: E402
from eqsmooth.solve._linearization import linearize  # noqa: E402


DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "g2o"


def median_ms(fn, *args, repeats=21):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--files", nargs="*", default=["parking-garage", "sphere2500", "torus3D"]
    )
    parser.add_argument("--whiten", action="store_true")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    print(f"eqsmooth from {Path(eqsmooth.__file__).parent}")
    records = []
    for name in args.files:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            pg = load_g2o(DATA / f"{name}.g2o", invalid_information="block_diagonal")
        layout = pg.graph.validate(pg.values)
        variables = tuple(f.variables for f in pg.graph.factors)
        t0 = time.perf_counter()
        _Pattern(layout, variables)
        pattern_s = time.perf_counter() - t0
        lin = jax.jit(linearize)(pg.graph, pg.values)
        damping = {g.name: jnp.full((g.count, g.dim), 1e-3) for g in lin.layout}
        assemble = jax.jit(lambda lin, d: assemble_sparse(NormalOperator(lin, d)).data)
        rec = {
            "benchmark": "linearize_assemble",
            "config": {"file": name},
            "pattern_s": pattern_s,
            "linearize_ms": median_ms(jax.jit(linearize), pg.graph, pg.values),
            "assemble_ms": median_ms(assemble, lin, damping),
        }
        records.append(rec)
        print(
            f"{name:15s} pattern {rec['pattern_s']:.3f} s  linearize "
            f"{rec['linearize_ms']:.2f} ms  assemble {rec['assemble_ms']:.2f} ms"
        )
    if args.whiten:
        n = 9048
        rng = np.random.default_rng(0)
        R = jnp.asarray(rng.normal(size=(n, 6, 6)))
        J = jnp.asarray(rng.normal(size=(n, 6, 12)))
        halves = (J[:, :, :6], J[:, :, 6:])
        whiten = jax.jit(lambda R, J: jnp.einsum("nij,nj...->ni...", R, J))
        rec = {
            "benchmark": "whiten",
            "config": {"rows": n},
            "one_6x12_ms": median_ms(whiten, R, J),
            "two_6x6_ms": median_ms(lambda R: [whiten(R, h) for h in halves], R),
        }
        records.append(rec)
        print(
            f"whiten {n} rows: one (n,6,12) batch {rec['one_6x12_ms']:.2f} ms, "
            f"two (n,6,6) batches {rec['two_6x6_ms']:.2f} ms"
        )
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
