"""Which Hessian of the Laplace evidence should `eqsmooth.discover` use?

`discover` needs the curvature of the *profiled* evidence `ℓ(θ) = log p(y | θ)`
(the MAP re-solved at every θ) for its Newton steps, its confidence
intervals and the information matrix of its score test. Its scores are exact
gradients of `laplace_at_map`, which holds the MAP fixed and lets θ act
through one Gauss-Newton correction with the normal matrix held fixed.

This script compares, on every diagonal entry of the 1-D oscillator's
parameter vector (ten candidate coefficients and the log noise scales), in
float64:

- `profiled`: the second difference of the evidence with the MAP re-solved
  at θ ± h (the reference; slow, one MAP solve per point);
- `difference`: what `discover` uses, a central difference of the exact
  scores at the fixed MAP (`discover._fit.evaluate`);
- `jacfwd`: `jax.hessian` of `laplace_at_map` at the fixed MAP, the
  forward-over-reverse derivative of the same scores.

    python benchmarks/discover_hessian.py \
        --json benchmarks/results/discover_hessian.json
"""

import argparse
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from eqsmooth.discover._fit import (  # noqa: E402
    evaluate,
    feature_scales,
    log_marginal_at,
)
from eqsmooth.discover._model import _one_z, z_of  # noqa: E402


sys.path.insert(0, str(Path(__file__).parent))
from _common import markdown_table, write_json  # noqa: E402


B, T, SPRING = 24, 40, 0.05
Q, R, PRIOR = np.array([0.05, 0.5]), 1.0, np.array([20.0, 4.0])


def _dyn(x, u, params):
    return jnp.stack([x[0] + x[1], x[1] - params * x[0]])


def _meas(x, params):
    return x[:1]


def simulate(seed: int, drag: float) -> dc.Sequences:
    """The oscillator of `tests/test_discover.py`, with quadratic drag."""
    rng = np.random.default_rng(seed)
    x = np.stack([rng.normal(0, PRIOR[0], B), rng.normal(0, PRIOR[1], B)], 1)
    xs = []
    for _ in range(T):
        xs.append(x.copy())
        p, v = x[:, 0], x[:, 1]
        a = -SPRING * p - drag * v * np.abs(v)
        x = np.stack([p + v, v + a], 1) + rng.normal(size=(B, 2)) * Q
    y = np.stack(xs, 1)[..., :1] + R * rng.normal(size=(B, T, 1))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((B, 2)), initial_states=init)


@eqx.filter_jit
def jacfwd_hessian(model, z, data, xhat):
    h = jax.vmap(jax.hessian(_one_z), in_axes=(None, None, 0, 0, 0, 0))
    return jnp.sum(h(z, model, data.measurements, data.inputs, data.x0_mean, xhat), 0)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--drag", type=float, default=0.01)
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    library = dc.mechanical_library(
        [0], [1], 2, measured_positions=[0], coulomb_eps=1.0
    )
    model = dc.ChainModel(
        _dyn, _meas, jnp.asarray(SPRING), Q, np.array([R]), PRIOR, library
    )
    data = simulate(a.seed, a.drag)
    z = z_of(model)
    z[model.index("quadratic drag")] = 0.8 * a.drag
    P = len(z)
    init = np.asarray(data.initial_states)
    ev0 = evaluate(model, data, z, init, np.ones(len(library)))
    scales = feature_scales(model, data, ev0.xhat)
    t0 = time.perf_counter()
    ev = evaluate(model, data, z, ev0.xhat, scales, np.arange(P))
    t_diff = time.perf_counter() - t0
    t0 = time.perf_counter()
    H = np.asarray(jacfwd_hessian(model, jnp.asarray(z), data, jnp.asarray(ev.xhat)))
    t_jac = time.perf_counter() - t0
    names = [c.name for c in model.candidates] + [
        f"log noise scale {i}" for i in range(P - len(library))
    ]
    # Steps for the profiled second difference: a relative change of the
    # curvature-scaled parameter, checked at two sizes.
    l0, _ = log_marginal_at(model, data, z, ev.xhat)
    rows = []
    for i in range(P):
        h0 = 1.0 / np.sqrt(max(abs(ev.hessian[i, i]), 1e-12))
        prof = []
        for h in (1e-2 * h0, 1e-3 * h0):
            e = np.zeros(P)
            e[i] = h
            lp, _ = log_marginal_at(model, data, z + e, ev.xhat)
            lm, _ = log_marginal_at(model, data, z - e, ev.xhat)
            prof.append((lp - 2 * l0 + lm) / h**2)
        ref = prof[1]
        rows.append(
            dict(
                parameter=names[i],
                profiled=ref,
                profiled_step_agreement=abs(prof[0] - prof[1]) / abs(ref),
                difference=float(ev.hessian[i, i]),
                jacfwd=float(H[i, i]),
                difference_rel_err=abs(ev.hessian[i, i] - ref) / abs(ref),
                jacfwd_rel_err=abs(H[i, i] - ref) / abs(ref),
            )
        )
    table = markdown_table(
        [
            {k: (f"{v:.4g}" if isinstance(v, float) else v) for k, v in r.items()}
            for r in rows
        ],
        list(rows[0]),
    )
    print(table)
    summary = dict(
        median_difference_rel_err=float(
            np.median([r["difference_rel_err"] for r in rows])
        ),
        median_jacfwd_rel_err=float(np.median([r["jacfwd_rel_err"] for r in rows])),
        max_difference_rel_err=float(max(r["difference_rel_err"] for r in rows)),
        max_jacfwd_rel_err=float(max(r["jacfwd_rel_err"] for r in rows)),
        seconds_difference_all_columns=t_diff,
        seconds_jacfwd_first_call=t_jac,
    )
    print(summary)
    if a.json is not None:
        write_json(a.json, rows, dict(summary=summary))


if __name__ == "__main__":
    main()
