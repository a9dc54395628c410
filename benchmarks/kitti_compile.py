"""Why the KITTI vehicle chain's surrogate loss compiles slowly: size and time.

Measures, for the gradient of the surrogate loss (K = 3 unrolled Gauss-Newton
steps, `eqs.learn.surrogate_loss`) on the visual-odometry chain (SE(2) pose +
velocities, examples/kitti_vo) and on the disk-tracking chain
(examples/disk_tracking, Euclidean 4-D state), in one process:

- the number of jaxpr equations (sub-jaxprs included: scan bodies, jits),
  which does not depend on the machine's load;
- the number of HLO lines, the lowering and the XLA compile time
  (with `--compile`);
- for the vehicle chain, the equations attributed to the innermost eqsmooth
  function that emitted them (`--breakdown`), which shows where the size
  comes from.

    python benchmarks/kitti_compile.py --compile --breakdown \
        --json benchmarks/results/kitti_compile.json
"""

import argparse
import collections
import os
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
# Appended, so PYTHONPATH can point at another checkout's eqsmooth (before/after).
sys.path.append(str(ROOT))

from _common import machine  # noqa: E402

import eqsmooth  # noqa: E402
from eqsmooth.solve import linearize  # noqa: E402


def _sub_jaxprs(eqn):
    for p in eqn.params.values():
        for sub in p if isinstance(p, (list, tuple)) else [p]:
            if isinstance(sub, jax.extend.core.ClosedJaxpr):
                yield sub.jaxpr
            elif isinstance(sub, jax.extend.core.Jaxpr):
                yield sub


def count_eqns(jaxpr, counter=None) -> int:
    n = 0
    for e in jaxpr.eqns:
        n += 1
        if counter is not None:
            counter[_origin(e)] += 1
        for sub in _sub_jaxprs(e):
            n += count_eqns(sub, counter)
    return n


def _origin(eqn) -> str:
    tb = eqn.source_info.traceback
    if tb is None:
        return "?"
    for fr in tb.frames:
        f = fr.file_name
        if "/eqsmooth/lie/" in f:
            return f"lie/{Path(f).name}:{fr.function_name}"
        if "/eqsmooth/" in f or "kitti_vo" in f or "disk_tracking" in f:
            return f"{Path(f).parent.name}/{Path(f).name}:{fr.function_name}"
    return "?"


def vehicle_case(T: int):
    from kitti_vo import data as D, models as M

    rng = np.random.default_rng(0)
    xyt = np.cumsum(rng.normal(size=(T, 3)) * [1.0, 0.1, 0.02], 0)
    w = {
        "z": rng.normal(size=(T, 2)),
        "log_sigma": rng.normal(size=(T, 2)),
        "features": rng.normal(size=(T, 64)),
        "pose": np.stack(
            [np.cos(xyt[:, 2]), np.sin(xyt[:, 2]), xyt[:, 0], xyt[:, 1]], 1
        ),
        "velocity": D.velocities(xyt),
    }
    batch = {k: jnp.asarray(v[None], jnp.float32) for k, v in w.items()}
    model = M.Estimator(M.ConstantNoise(np.array([0.5, 0.05])))
    params, static = eqx.partition(model, eqx.is_array)

    def loss(p, b):
        return M.surrogate_loss(eqx.combine(p, static), b, 3)

    def lin(p, b):
        one = jax.tree.map(lambda a: a[0], b)
        m = eqx.combine(p, static)
        return linearize(m.graph(one), {"x": M.truth_state(one)})

    return {
        "vehicle_surrogate_grad": (jax.grad(loss), (params, batch)),
        "vehicle_linearize": (lin, (params, batch)),
    }


def disk_case(T: int):
    from disk_tracking import train as DT

    model = DT.make_smoother_model("const", 5.0, jax.random.key(0), jnp.float32)
    params, static = eqx.partition(model, eqx.is_array)
    meas, counts, truth = jnp.zeros((T, 2)), jnp.zeros((T,)), jnp.ones((T, 4))

    def loss(p, m, c, t):
        return DT.surrogate_loss_one(eqx.combine(p, static), m, c, t, 3)

    def lin(p, m, c, t):
        g = eqx.combine(p, static).graph(m, c, t[0])
        return linearize(g, {"x": t})

    return {
        "disk_surrogate_grad": (jax.grad(loss), (params, meas, counts, truth)),
        "disk_linearize": (lin, (params, meas, counts, truth)),
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--T", type=int, default=10, help="states per window")
    p.add_argument("--compile", action="store_true", help="also lower and compile")
    p.add_argument("--breakdown", action="store_true")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    cases = {**disk_case(args.T), **vehicle_case(args.T)}
    records = []
    for name, (fn, a) in cases.items():
        counter = collections.Counter()
        n = count_eqns(jax.make_jaxpr(fn)(*a).jaxpr, counter)
        rec = {
            "benchmark": "kitti_compile",
            "config": {"case": name, "T": args.T, "gn_steps": 3, "dtype": "float32"},
            "jaxpr_eqns": n,
            "loadavg_before": os.getloadavg(),
        }
        if args.compile and name.endswith("grad"):
            t0 = time.perf_counter()
            lowered = jax.jit(fn).lower(*a)
            t1 = time.perf_counter()
            rec["hlo_lines"] = lowered.as_text(dialect="hlo").count("\n")
            lowered.compile()
            t2 = time.perf_counter()
            rec.update(lower_s=t1 - t0, compile_s=t2 - t1)
            rec["loadavg_after"] = os.getloadavg()
        if args.breakdown and name == "vehicle_surrogate_grad":
            rec["eqns_by_origin"] = dict(counter.most_common(25))
        records.append(rec)
        print(
            f"| {name} | {n} | {rec.get('hlo_lines', '')} | "
            f"{rec.get('lower_s', float('nan')):.1f} | "
            f"{rec.get('compile_s', float('nan')):.1f} | "
            f"{os.getloadavg()[0]:.1f} |",
            flush=True,
        )
    if args.breakdown:
        lie = sum(
            v for k, v in records[2]["eqns_by_origin"].items() if k.startswith("lie/")
        )
        print(
            f"vehicle grad: {lie} of the top-25 origins' equations are in eqsmooth/lie"
        )
    if args.json:
        import json

        args.json.parent.mkdir(parents=True, exist_ok=True)
        out = {
            "machine": machine(),
            "eqsmooth": str(Path(eqsmooth.__file__).parent),
            "command": " ".join(sys.argv),
            "records": records,
        }
        args.json.write_text(json.dumps(out, indent=1, default=str))


if __name__ == "__main__":
    main()
