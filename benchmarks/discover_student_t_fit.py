"""Why Student-t evidence fits stop unconverged: curvature at the stopped point.

Runs the workflow of `benchmarks/discover.py` with the Student-t(4)
measurement model on one viscous-damping data set (SNR 0.4, seed 1) and, at
the first candidate fit that ends unconverged, compares along each free
parameter: the score against a central difference of the evidence (the MAP
re-solved at each point), and the fit's Hessian (differences of scores at the
fixed MAP) against second differences of the evidence; then the evidence
along the fit's own Newton step against the quadratic model's prediction.

    cd benchmarks && python discover_student_t_fit.py \
        > results/discover_student_t_fit.log
"""

import sys
from pathlib import Path

import numpy as np


sys.path.insert(0, str(Path(__file__).resolve().parent))

import discover as B  # noqa: E402

import eqsmooth.discover._add as A  # noqa: E402
import eqsmooth.discover._find as Fi  # noqa: E402
import eqsmooth.discover._fit as F  # noqa: E402
import eqsmooth.discover._name as N  # noqa: E402


def inspect(model, data, free, ev):
    g = np.sum(ev.scores, axis=0)[free]
    neg_h = -ev.hessian[np.ix_(free, free)]
    base, _ = F.log_marginal_at(model, data, ev.z, ev.xhat)
    print(f"stopped fit over z{list(map(int, free))} = {ev.z[free]}")
    for i, fi in enumerate(free):
        for h in (1e-3, 1e-4):
            e = h * np.eye(len(ev.z))[fi]
            lp, _ = F.log_marginal_at(model, data, ev.z + e, ev.xhat)
            lm, _ = F.log_marginal_at(model, data, ev.z - e, ev.xhat)
            print(
                f"  z[{fi}] h={h:g}: score {g[i]:.5g}, evidence difference "
                f"{(lp - lm) / (2 * h):.5g}; fit Hessian {-neg_h[i, i]:.5g}, evidence "
                f"second difference {(lp - 2 * base + lm) / h**2:.5g}"
            )
    step = np.linalg.solve(neg_h, g)
    for t in (0.25, 0.5, 1.0):
        zt = ev.z.copy()
        zt[free] += t * step
        lt, _ = F.log_marginal_at(model, data, zt, ev.xhat)
        predicted = t * g @ step - 0.5 * t * t * step @ neg_h @ step
        print(f"  Newton step x {t}: gain {lt - base:.3e}, predicted {predicted:.3e}")


def main():
    fit, seen = F.fit, []

    def traced(model, data, free, z0, init, scales, **kw):
        ev = fit(model, data, free, z0, init, scales, **kw)
        if not ev.converged and len(seen) < 2:  # sensor bias, sensor delay
            seen.append(True)
            inspect(model, data, free, ev)
        return ev

    for step in (Fi, N, A):
        step.fit = traced  # the workflow's own fits, observed
    model = B.make_model(4.0)
    coef = B.calibrate((0.4,))["viscous"][0.4]
    tag = list(B.EFFECTS).index("viscous") + 1
    _, y, _ = B.simulate(B.rng_for(tag, 0.4, 1), "viscous", coef)
    out = B.run_workflow(B.sequences(y), model)
    print("flags:", out["flags"])
    print("named:", out["named"])


if __name__ == "__main__":
    main()
