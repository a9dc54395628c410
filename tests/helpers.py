"""Tiny problems shared by the tests (import inside tests, after the hook)."""

import contextlib
import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def child_env(extra_xla_flags: str = "") -> dict[str, str]:
    """The environment of a test's child Python process: CPU only, compiled
    the way this suite compiles (tests/conftest.py): its `XLA_FLAGS` (XLA's
    earlier fusion emitters) plus `extra_xla_flags`, and LLVM's optimisation
    passes off (`JAX_DISABLE_MOST_OPTIMIZATIONS`)."""
    flags = f"{os.environ.get('XLA_FLAGS', '')} {extra_xla_flags}".strip()
    return dict(
        os.environ,
        JAX_PLATFORMS="cpu",
        XLA_FLAGS=flags,
        JAX_DISABLE_MOST_OPTIMIZATIONS="1",
    )


@contextlib.contextmanager
def compiled_programs():
    """Collect the names (`jit(f)`) of the XLA programs compiled inside the
    `with` block, in order."""
    from jax import monitoring

    names = []

    def on_duration(event, secs, **kwargs):
        if event.endswith("backend_compile_duration"):
            names.append(kwargs.get("fun_name"))

    monitoring.register_event_duration_secs_listener(on_duration)
    try:
        yield names
    finally:
        monitoring.unregister_event_duration_listener(on_duration)


def tree_allclose(x, y, *, rtol=1e-7, atol=1e-9):
    return eqx.tree_equal(x, y, typematch=True, rtol=rtol, atol=atol) is True


def _dyn(a, b, data, params):
    # Nonlinear 2-D transition with a shared learnable coefficient.
    return b - (a + 0.1 * jnp.sin(a) * params)


def _meas(x, data, params):
    return x - data


def random_chain(seed: int, T: int = 6, dim: int = 2, robust: bool = False):
    """A nonlinear Euclidean chain (graph, initial values, truth)."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    truth = jnp.asarray(np.cumsum(rng.normal(size=(T, dim)), axis=0))
    meas = truth + 0.1 * jnp.asarray(rng.normal(size=(T, dim)))
    t = np.arange(T)
    noise = eqs.IsotropicNoise.from_sigma(0.3)
    meas_noise = eqs.DiagonalNoise.from_sigmas(jnp.full((dim,), 0.2))
    if robust:
        meas_noise = eqs.HuberNoise(meas_noise, 1.0)
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _dyn,
                (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                noise,
                params=jnp.asarray(0.5),
            ),
            eqs.FunctionFactor(_meas, (eqs.Var("x", t),), meas_noise, data=meas),
        ]
    )
    init = {"x": meas + 0.5}
    return graph, init, truth


def prior_and_odometry(prior, prior_sigmas, a, b, odo, odo_sigmas):
    """A prior `prior` on pose 0 and between factors `odo` from poses `a` to
    poses `b` (variables "x"), each with diagonal noise of the sigmas given."""
    import eqsmooth as eqs

    return [
        eqs.PriorFactor(
            eqs.Var("x", [0]), prior, eqs.DiagonalNoise.from_sigmas(prior_sigmas)
        ),
        eqs.BetweenFactor(
            eqs.Var("x", a),
            eqs.Var("x", b),
            odo,
            eqs.DiagonalNoise.from_sigmas(odo_sigmas),
        ),
    ]


def loop_graph(truth, N: int, dof: int, rng, noise_scale: float, noise):
    """Odometry with noise model `noise` around the `N` poses `truth` and back
    to the first (measurements perturbed by `noise_scale` tangent draws from
    `rng`, `dof` a pose), and a tight prior on the first pose."""
    import eqsmooth as eqs

    a = np.concatenate([np.arange(N - 1), [N - 1]])
    b = np.concatenate([np.arange(1, N), [0]])
    rel = truth[a].inverse() @ truth[b]
    meas = rel @ type(truth).exp(jnp.asarray(noise_scale * rng.normal(size=(N, dof))))
    return eqs.FactorGraph(
        [
            eqs.BetweenFactor(eqs.Var("pose", a), eqs.Var("pose", b), meas, noise),
            eqs.PriorFactor(
                eqs.Var("pose", [0]),
                truth[np.array([0])],
                eqs.IsotropicNoise(sqrt_precision=1e3),
            ),
        ]
    )


def se2_loop(seed: int, N: int = 8, noise_scale: float = 0.05):
    """A noisy SE(2) loop with odometry and one loop closure; anchored."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 2 * np.pi, N, endpoint=False)
    xs = np.stack([np.cos(angles), np.sin(angles), angles + np.pi / 2], axis=1)
    truth = eqs.SE2.from_xy_theta(
        jnp.asarray(xs[:, 0]), jnp.asarray(xs[:, 1]), jnp.asarray(xs[:, 2])
    )
    noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 0.05]))
    graph = loop_graph(truth, N, 3, rng, noise_scale, noise)
    init = {"pose": truth @ eqs.SE2.exp(jnp.asarray(0.2 * rng.normal(size=(N, 3))))}
    return graph, init, truth


def oscillator_states(rng, accel, prior, q, batch: int, steps: int) -> np.ndarray:
    """True states `(batch, steps, 2)` of the discovery tests' 1-D oscillator:
    first states from N(0, diag(prior)²), then `p' = p + v`,
    `v' = v + accel(p)`, plus process noise of std `q`, all drawn from `rng`."""
    x = np.stack([rng.normal(0, prior[0], batch), rng.normal(0, prior[1], batch)], 1)
    xs = []
    for _ in range(steps):
        xs.append(x.copy())
        p, v = x[:, 0], x[:, 1]
        x = np.stack([p + v, v + accel(p)], 1) + rng.normal(size=(batch, 2)) * q
    return np.stack(xs, 1)


def key(seed: int = 0):
    return jax.random.key(seed)


def reduced_precision_products(fn, *args) -> list[str]:
    """The float32 matrix products in `fn(*args)`'s program (sub-programs of
    loops, conditionals and custom rules included) whose precision is not
    `HIGHEST` on both operands, as `"shape x shape"` strings.

    JAX's default precision lets GPUs and TPUs run a float32 product with
    TF32 or bfloat16 operands (about three significant digits); XLA:CPU
    ignores the setting, so this trace-time check is how a CPU run can tell
    whether a route is right on a GPU."""
    import jax.extend as jex

    found = []
    highest = jax.lax.Precision.HIGHEST

    def subjaxprs(value):
        if isinstance(value, jex.core.ClosedJaxpr):
            yield value.jaxpr
        elif isinstance(value, jex.core.Jaxpr):
            yield value
        elif isinstance(value, (tuple, list)):
            for v in value:
                yield from subjaxprs(v)

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                dtypes = {v.aval.dtype for v in eqn.invars}
                precision = eqn.params.get("precision")
                if jnp.dtype(jnp.float32) in dtypes and precision != (
                    highest,
                    highest,
                ):
                    shapes = " x ".join(str(v.aval.shape) for v in eqn.invars)
                    found.append(f"{shapes} ({precision})")
            for param in eqn.params.values():
                for sub in subjaxprs(param):
                    walk(sub)

    walk(jax.make_jaxpr(fn)(*args).jaxpr)
    return found
