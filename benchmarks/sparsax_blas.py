"""One CHOLMOD factorisation + solve inside sparsax, per BLAS, on g2o normal matrices.

sparsax's wheel bundles a generic ATLAS; with the `mkl` wheel installed,
eqsmooth loads MKL's runtime library before sparsax so that CHOLMOD's BLAS
calls bind to MKL (`eqsmooth.solve.sparsax_blas`). The binding is fixed per
process, so each mode runs in its own child process:

- `mkl`: sparsax imported through eqsmooth (MKL, one thread);
- `bundled`: sparsax imported before eqsmooth touches it (the wheel's ATLAS);
- `simplicial`: the bundled BLAS with CHOLMOD's simplicial (non-BLAS)
  factorisation (`sparsax.set_options(supernodal="simplicial")`).

The matrix is `JᵀJ + 1e-3·I` at the file's initial values (as
`sparse_factor.py` builds it). Each timed call changes the values slightly,
so CHOLMOD refactorises (sparsax skips the numeric factorisation when the
values are unchanged); `median_s` is over `--repeats` calls after one
warm-up, `residual` is `‖Ax − 1‖ / √n`.

    python benchmarks/sparsax_blas.py --files sphere2500 torus3D parking-garage \\
        --json benchmarks/results/sparsax_blas.json
"""

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path


HERE = Path(__file__).resolve().parent
MODES = ["bundled", "mkl", "simplicial"]


def child(mode: str, files: list[str], repeats: int) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    if mode in ("bundled", "simplicial"):
        import sparsax  # before eqsmooth: binds the wheel's own BLAS
    import jax.numpy as jnp
    import numpy as np
    import scipy.sparse as sp

    sys.path.insert(0, str(HERE))
    import sparse_factor

    from eqsmooth.solve._linear._sparsax import _import_sparsax, sparsax_blas

    sparsax = _import_sparsax()
    if mode == "simplicial":
        sparsax.set_options(supernodal="simplicial")
    out = {"blas": sparsax_blas(), "files": {}}
    for name in files:
        A = sparse_factor.normal_matrix(sparse_factor.DATA / f"{name}.g2o")
        U = sp.triu(A).tocoo()
        rows, cols = U.row.astype(np.int32), U.col.astype(np.int32)
        values = jnp.asarray(U.data)
        b = jnp.ones((A.shape[0],))
        solve = jax.jit(lambda v, b: sparsax.solve(rows, cols, v, b))
        x = solve(values, b).block_until_ready()
        times = []
        for i in range(repeats):
            v = (values * (1.0 + 1e-9 * (i + 1))).block_until_ready()
            t0 = time.perf_counter()
            x = solve(v, b).block_until_ready()
            times.append(time.perf_counter() - t0)
        residual = float(np.linalg.norm(A @ np.asarray(x) - 1.0) / np.sqrt(A.shape[0]))
        out["files"][name] = {
            "unknowns": A.shape[0],
            "median_s": statistics.median(times),
            "min_s": min(times),
            "residual": residual,
        }
        print(
            f"{mode:10s} {name:15s} {out['files'][name]}", file=sys.stderr, flush=True
        )
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument(
        "--files", nargs="*", default=["sphere2500", "torus3D", "parking-garage"]
    )
    parser.add_argument("--modes", nargs="*", default=MODES, choices=MODES)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.files, args.repeats)))
        return
    from _common import write_json

    results = {}
    for mode in args.modes:
        cmd = [
            sys.executable,
            __file__,
            "--child",
            mode,
            "--repeats",
            str(args.repeats),
        ]
        done = subprocess.run(
            cmd + ["--files", *args.files], capture_output=True, text=True, check=True
        )
        results[mode] = json.loads(done.stdout.strip().splitlines()[-1])
    print(
        f"{'file':15s} " + " ".join(f"{m:>12s}" for m in args.modes) + "   (median s)"
    )
    for name in args.files:
        cells = " ".join(
            f"{results[m]['files'][name]['median_s']:12.4f}" for m in args.modes
        )
        print(f"{name:15s} {cells}")
    if args.json:
        records = [
            {
                "benchmark": "sparsax_blas",
                "config": {"file": name, "mode": m, "blas": results[m]["blas"]},
                **results[m]["files"][name],
            }
            for m in args.modes
            for name in args.files
        ]
        write_json(args.json, records)


if __name__ == "__main__":
    main()
