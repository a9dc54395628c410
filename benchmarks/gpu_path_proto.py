"""Prototype: block-band ("super-block tridiagonal") preconditioners, CG counts."""
import sys, time, json
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import scipy.sparse as sp, scipy.sparse.linalg as spl
import gtsam
from pathlib import Path
import eqsmooth as eqs
from eqsmooth.io import load_g2o
from eqsmooth.solve._linear._linear_solver import NormalOperator
from eqsmooth.solve._linear._sparse import assemble_sparse, _host_csc
from eqsmooth.solve._linearization import gradient, flatten_tangent
from benchmarks.gpu_path_study import RecordingSparsax, SYSTEMS, lm_run

def spans(pg):
    out = []
    for f in pg.graph.factors if hasattr(pg.graph, "factors") else []:
        pass
    return out

def pcg_curve(H, b, Minv, n, m_star):
    x = np.zeros_like(b); r = b.copy(); z = Minv(r); p = z.copy(); rz = r @ z
    bb = np.sqrt(b @ b); rel = []; left = []
    for k in range(n):
        ap = H @ p; a = rz / (p @ ap); x += a * p; r -= a * ap
        z = Minv(r); rzn = r @ z; p = z + (rzn / rz) * p; rz = rzn
        rel.append(np.linalg.norm(r) / bb); left.append(1 - (-0.5 * (b @ x + r @ x)) / m_star)
    return np.array(rel), np.array(left)

def first(a, t):
    i = np.flatnonzero(a <= t); return int(i[0]) + 1 if len(i) else -1

def main(fname, steps, Bs, n):
    data = Path(gtsam.__file__).parent / "Data"
    pg = load_g2o(data / fname, skip_unsupported=True, se3_information="gtsam")
    lm_kw = {"damping_update": "fixed"} if "sphere_smallnoise" in fname else {}
    SYSTEMS.clear()
    sol, _ = lm_run(pg, lm_kw, RecordingSparsax(), 300 if lm_kw else 100)
    systems = list(SYSTEMS)
    print(fname, "systems", len(systems), "final", float(sol.stats["final_cost"]), flush=True)
    res = {}
    for s in steps:
        idx = s if s >= 0 else len(systems) + s
        lin, damping = systems[idx]
        st = assemble_sparse(NormalOperator(lin, damping))
        H = _host_csc(st.pattern, st.data).tocsr()
        b = -np.asarray(flatten_tangent(lin, gradient(lin)))
        d = lin.layout[0].dim
        assert len(lin.layout) == 1
        xs = spl.splu(H.tocsc()).solve(b); m_star = -0.5 * b @ xs
        Hc = H.tocoo(); pi, pj = Hc.row // d, Hc.col // d
        # span histogram of off-diagonal blocks
        sp_ = np.abs(pi - pj); sp_ = sp_[sp_ > 0]
        hist = {q: float(np.quantile(sp_, q)) for q in (0.5, 0.9, 0.99)}
        out = {"cost": float(lin.cost), "span_quantiles": hist, "frac_span_le": {B: float(np.mean(sp_ <= B)) for B in Bs}}
        for B in Bs:
            sb_i, sb_j = pi // B, pj // B
            keep = np.abs(sb_i - sb_j) <= (0 if B == "jacobi" else 1)
            M = sp.csc_matrix((Hc.data[keep], (Hc.row[keep], Hc.col[keep])), shape=H.shape)
            t = time.perf_counter(); lu = spl.splu(M); tf = time.perf_counter() - t
            rel, left = pcg_curve(H, b, lu.solve, n, m_star)
            rec = {f"rel_{t:g}": first(rel, t) for t in (1e-2, 1e-4, 1e-6, 1e-10)}
            rec |= {f"model_{t:g}": first(left, t) for t in (1e-1, 1e-2, 1e-4, 1e-6)}
            rec["rel_at_n"] = float(rel[-1]); rec["model_left_at_n"] = float(left[-1])
            out[f"B={B}"] = rec
            print(fname, idx, B, rec, flush=True)
        res[idx] = out
        print(fname, idx, hist, out["frac_span_le"], flush=True)
    return res

if __name__ == "__main__":
    fname = sys.argv[1]; n = int(sys.argv[2]); Bs = [int(x) for x in sys.argv[3].split(",")]
    steps = [int(x) for x in sys.argv[4].split(",")]
    r = main(fname, steps, Bs, n)
    Path(f"proto_{fname}.json").write_text(json.dumps(r, indent=1, default=str))
