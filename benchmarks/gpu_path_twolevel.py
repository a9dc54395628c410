# One-off prototype (scipy): the two-level preconditioner with rigid-body
# coarse space, before it was built in the library. Usage (2026-11-29):
#   OPENBLAS_NUM_THREADS=1 python benchmarks/gpu_path_twolevel.py FILE KS NCG SIZES KINDS FIRST
#   e.g. w10000.graph 3,10 300 10,20 const,rigid 0
import sys, numpy as np, jax, jax.numpy as jnp, time
jax.config.update("jax_enable_x64", True)
exec(open(__file__.replace("gpu_path_twolevel", "gpu_path_proto")).read().split('if __name__')[0])
from eqsmooth.solve._nonlinear._descent import marquardt_damping
SIZES = [int(x) for x in sys.argv[4].split(",")]; KINDS = sys.argv[5].split(",")
fname = sys.argv[1]; ks = [int(k) for k in sys.argv[2].split(",")]; n = int(sys.argv[3])
data = Path(gtsam.__file__).parent / "Data"
pg = load_g2o(data / fname, skip_unsupported=True, se3_information="gtsam")
lm_kw = {"damping_update": "fixed"} if "sphere_smallnoise" in fname else {}
for k in ks:
    SYSTEMS.clear()
    sol, _ = lm_run(pg, lm_kw, RecordingSparsax(), k)
    lin, damping = SYSTEMS[-1]
    key = lin.layout[0].name
    X = sol.value[key]
    st = assemble_sparse(NormalOperator(lin, damping))
    H = _host_csc(st.pattern, st.data).tocsr()
    b = -np.asarray(flatten_tangent(lin, gradient(lin)))
    d = lin.layout[0].dim; N = H.shape[0] // d
    xs = spl.splu(H.tocsc()).solve(b); m_star = -0.5 * b @ xs
    Hc = H.tocoo(); pi, pj = Hc.row // d, Hc.col // d
    keep = np.abs(pi - pj) <= 1
    lu = spl.splu(sp.csc_matrix((Hc.data[keep], (Hc.row[keep], Hc.col[keep])), shape=H.shape))
    print(fname, "k", k, "cost", float(lin.cost), "N", N, flush=True)
    for s in SIZES:
        na = -(-N // s); agg = np.arange(N) // s
        for kind in KINDS:
            blocks = np.broadcast_to(np.eye(d), (N, d, d)).copy()
            if kind == "rigid":
                Xa = jax.tree_util.tree_map(lambda a: a[agg * s], X)
                rel_ = jax.vmap(lambda xi, xa: (xi.inverse().compose(xa)).adjoint())(X, Xa)
                blocks = np.asarray(rel_)  # (N, d, d)
            rows = np.repeat(np.arange(N * d), d)
            cols = (agg[:, None, None] * d + np.arange(d)[None, None, :]).repeat(d, 1).reshape(-1)
            P = sp.csr_matrix((blocks.reshape(-1), (rows, cols)), shape=(N * d, na * d))
            Ac = (P.T @ H @ P).toarray()
            Acinv = np.linalg.inv(Ac)
            coarse = lambda r: P @ (Acinv @ (P.T @ r))
            additive = lambda r: lu.solve(r) + coarse(r)
            def mult(r):
                z1 = coarse(r); z2 = z1 + lu.solve(r - H @ z1); return z2 + coarse(r - H @ z2)
            for name, Minv in (("additive", additive), ("symmetric", mult))[int(sys.argv[6]):]:
                rel, left = pcg_curve(H, b, Minv, n, m_star)
                print(" ", s, kind, name, {f"rel_{t:g}": first(rel, t) for t in (1e-2, 1e-4, 1e-6, 1e-10)}, {f"model_{t:g}": first(left, t) for t in (1e-2, 1e-4, 1e-6)}, f"{rel[-1]:.2e} {left[-1]:.2e}", flush=True)
    rel, left = pcg_curve(H, b, lu.solve, n, m_star)
    print("  chain only", {f"rel_{t:g}": first(rel, t) for t in (1e-2, 1e-4, 1e-6, 1e-10)}, {f"model_{t:g}": first(left, t) for t in (1e-2, 1e-4, 1e-6)}, f"{rel[-1]:.2e} {left[-1]:.2e}", flush=True)
