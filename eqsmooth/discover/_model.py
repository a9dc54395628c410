"""A chain (state-space) model with candidate terms, and its likelihoods."""

import dataclasses
import functools
import hashlib
import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import ClosedJaxpr, Jaxpr
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._compilation_cache import stored_program
from ..factors import (
    AbstractNoiseModel,
    DiagonalNoise,
    FactorGraph,
    FunctionFactor,
    StudentTNoise,
    Var,
)
from ..filters import ekf
from ..solve import BlockTridiagonal, GaussNewton, least_squares
from ._candidates import Candidate
from ._integrator import Integrator
from ._laplace import laplace_at_map


def _stacked(field: str, value, dtype=None) -> Array:
    # A list of sequences of different lengths would otherwise fail inside
    # NumPy with "inhomogeneous shape"; name the lengths instead.
    if isinstance(value, (list, tuple)):
        shapes = [np.shape(v) for v in value]
        if len(set(shapes)) > 1:
            raise ValueError(
                f"Sequences.{field} is ragged: its {len(shapes)} entries have shapes "
                f"{shapes}. discover needs sequences of one length T; cut them to "
                "a common length or split them into batches of equal length"
            )
    return jnp.asarray(value, dtype=dtype)


class Sequences(eqx.Module):
    """A batch of measured sequences of equal length.

    **Arguments:**

    - `measurements`: `(B, T, m)` measurements `y_t`.
    - `x0_mean`: `(B, n)` mean of the prior on each sequence's first state.
    - `inputs`: `(B, T, k)` known inputs `u_t`, or `None` (then `k = 1`, zeros).
    - `initial_states`: `(B, T, n)` initial guess for the MAP solves, or
        `None` (the prior mean repeated over time).
    """

    measurements: Float[Array, "B T m"]
    x0_mean: Float[Array, "B n"]
    inputs: Float[Array, "B T k"]
    initial_states: Float[Array, "B T n"]

    def __init__(
        self,
        measurements: Float[ArrayLike, "B T m"],
        x0_mean: Float[ArrayLike, "B n"],
        inputs: Float[ArrayLike, "B T k"] | None = None,
        initial_states: Float[ArrayLike, "B T n"] | None = None,
    ):
        y = _stacked("measurements", measurements)
        x0 = _stacked("x0_mean", x0_mean, y.dtype)
        if y.ndim != 3:
            raise ValueError(f"Sequences.measurements must be (B, T, m), got {y.shape}")
        if x0.ndim != 2 or x0.shape[0] != y.shape[0]:
            raise ValueError(
                f"Sequences.x0_mean must be (B, n) with B = {y.shape[0]}, got "
                f"{x0.shape}"
            )
        B, T, _ = y.shape
        if inputs is None:
            u = jnp.zeros((B, T, 1), y.dtype)
        else:
            u = _stacked("inputs", inputs, y.dtype)
            if u.ndim != 3 or u.shape[:2] != (B, T):
                raise ValueError(
                    f"Sequences.inputs must be (B, T, k) = ({B}, {T}, k), got {u.shape}"
                )
        if initial_states is None:
            xi = jnp.broadcast_to(x0[:, None, :], (B, T, x0.shape[1]))
        else:
            xi = _stacked("initial_states", initial_states, y.dtype)
            if xi.shape != (B, T, x0.shape[1]):
                raise ValueError(
                    f"Sequences.initial_states must be {(B, T, x0.shape[1])}, got "
                    f"{xi.shape}"
                )
        self.measurements = y
        self.x0_mean = x0
        self.inputs = u
        self.initial_states = xi

    @property
    def num_sequences(self) -> int:
        return int(self.measurements.shape[0])

    @property
    def length(self) -> int:
        return int(self.measurements.shape[1])

    def take(self, index: Sequence[int] | np.ndarray) -> "Sequences":
        """The sequences at `index` (a new batch)."""
        idx = np.asarray(index)
        return Sequences(
            self.measurements[idx],
            self.x0_mean[idx],
            self.inputs[idx],
            self.initial_states[idx],
        )


class ChainModel(eqx.Module):
    """A nominal state-space model plus scalar coefficients of candidate effects.

        x_{t+1} = f(x_t, u_t, params) + Σ_k c_k φ_k(x_t, u_t) + w_t,  w ~ N(0, diag(q²))
        y_t     = h(x_t, params)      + Σ_j c_j ψ_j(x_t, u_t) + v_t,  v ~ N(0, diag(r²))
        x_0     ~ N(x0_mean, diag(prior_sigma²))

    With `measurement_dof = ν`, the measurement noise is heavy-tailed
    instead: `v_t` is a Student-t with `ν` degrees of freedom and scale
    `diag(r)` ([`eqsmooth.factors.StudentTNoise`][]), a robust model whose
    Laplace evidence is still that of a normalised density. The diagnostics
    (innovation tests, k-step errors) then use the moment-matched Gaussian,
    of standard deviation `measurement_std = r √(ν/(ν − 2))`.

    The coefficients `c` of all candidates are stored (zero = absent), so that
    models with different active sets share compiled code.

    **Arguments:**

    - `dynamics`: `f(x, u, params) -> (n,)` (module-level function), or an
        [`eqsmooth.discover.Integrator`][] of a continuous-time vector field
        (needed by candidates with `target="rate"`).
    - `measurement`: `h(x, params) -> (m,)`.
    - `params`: nominal parameters (a pytree; held fixed by the workflow).
    - `process_sigma`: `(n,)` process noise standard deviations `q` (positive).
    - `measurement_sigma`: `(m,)` measurement noise standard deviations `r`.
    - `prior_sigma`: `(n,)` standard deviations of the first-state prior.
    - `candidates`: tuple of [`eqsmooth.discover.Candidate`][].
    - `coefficients`: `(K,)` coefficients (default zeros).
    - `measurement_dof`: `None` (Gaussian measurement noise) or the degrees
        of freedom `ν > 2` of Student-t measurement noise.
    - `noise_scale_prior`: `None` (the default: noise multipliers are fitted
        by the Laplace evidence alone) or the standard deviation `s` of a
        weak zero-mean normal prior on each log noise multiplier (`0` is the
        nominal sigma). The workflow's fits then maximise the evidence plus
        `-½ Σ (log multiplier / s)²`, so a multiplier the data cannot
        identify stays near its nominal value instead of running off towards
        zero or infinity; with `s = 5` a multiplier of `e^{±5}` (×150) costs
        half a nat. Reported evidences stay those of the data. The prior
        acts in the fits only, outside compiled code: models that differ
        in it share the compiled MAP, evidence and score programs.
    """

    dynamics: Callable = eqx.field(static=True)
    measurement: Callable = eqx.field(static=True)
    params: PyTree
    process_sigma: Float[Array, " n"]
    measurement_sigma: Float[Array, " m"]
    prior_sigma: Float[Array, " n"]
    candidates: tuple[Candidate, ...] = eqx.field(static=True)
    coefficients: Float[Array, " K"]
    measurement_dof: float | None = eqx.field(static=True)
    noise_scale_prior: float | None = eqx.field(static=True)

    def __init__(
        self,
        dynamics: Callable,
        measurement: Callable,
        params: PyTree,
        process_sigma: Float[ArrayLike, " n"],
        measurement_sigma: Float[ArrayLike, " m"],
        prior_sigma: Float[ArrayLike, " n"],
        candidates: Sequence[Candidate] = (),
        coefficients: Float[ArrayLike, " K"] | None = None,
        measurement_dof: float | None = None,
        noise_scale_prior: float | None = None,
    ):
        self.dynamics = dynamics
        self.measurement = measurement
        self.params = params
        self.process_sigma = jnp.asarray(process_sigma, dtype=float)
        self.measurement_sigma = jnp.asarray(measurement_sigma, dtype=float)
        self.prior_sigma = jnp.asarray(prior_sigma, dtype=float)
        self.candidates = tuple(candidates)
        if coefficients is None:
            coefficients = np.zeros(len(self.candidates))
        self.coefficients = jnp.asarray(coefficients, dtype=float)
        self.measurement_dof = (
            None if measurement_dof is None else float(measurement_dof)
        )
        self.noise_scale_prior = (
            None if noise_scale_prior is None else float(noise_scale_prior)
        )

    def __check_init__(self):
        dof = self.measurement_dof
        if dof is not None and not (np.isfinite(dof) and dof > 2):
            raise ValueError(
                "ChainModel.measurement_dof must be None (Gaussian) or degrees of "
                f"freedom ν > 2 (the diagnostics need a finite variance), got {dof}"
            )
        s = self.noise_scale_prior
        if s is not None and not (np.isfinite(s) and s > 0):
            raise ValueError(
                "ChainModel.noise_scale_prior must be None or a positive, finite "
                f"standard deviation of the log noise multipliers, got {s}"
            )
        for c in self.candidates:
            if not isinstance(c, Candidate):
                raise TypeError(
                    f"ChainModel.candidates must be Candidate, got {type(c).__name__}"
                )
        names = [c.name for c in self.candidates]
        if len(set(names)) != len(names):
            raise ValueError(f"ChainModel: duplicate candidate names {names}")
        rates = [c.name for c in self.candidates if c.target == "rate"]
        if rates and not isinstance(self.dynamics, Integrator):
            raise ValueError(
                f"ChainModel: candidates {rates} have target 'rate' (terms of a "
                "continuous-time vector field), which needs dynamics given as an "
                "eqsmooth.discover.Integrator; got "
                f"{getattr(self.dynamics, '__name__', type(self.dynamics).__name__)}"
            )
        if self.coefficients.shape != (len(self.candidates),):
            raise ValueError(
                f"ChainModel.coefficients must have shape ({len(self.candidates)},), "
                f"got {self.coefficients.shape}"
            )
        n = self.process_sigma.shape
        if self.process_sigma.ndim != 1 or self.prior_sigma.shape != n:
            raise ValueError(
                "ChainModel: process_sigma and prior_sigma must both be (n,), got "
                f"{self.process_sigma.shape} and {self.prior_sigma.shape}"
            )
        if self.measurement_sigma.ndim != 1:
            raise ValueError(
                "ChainModel.measurement_sigma must be (m,), got "
                f"{self.measurement_sigma.shape}"
            )
        for field in ("process_sigma", "measurement_sigma", "prior_sigma"):
            sigma = getattr(self, field)
            if isinstance(sigma, jax.core.Tracer):
                continue  # learned scales are built positive (exp) under jit
            sigma = np.asarray(sigma)
            if not np.all(np.isfinite(sigma) & (sigma > 0)):
                raise ValueError(
                    f"ChainModel.{field} must be positive and finite standard "
                    f"deviations, got {sigma}"
                )

    @property
    def measurement_std(self) -> Float[Array, " m"]:
        """Standard deviation of the measurement noise: `r`, or `r √(ν/(ν − 2))`
        for Student-t noise."""
        if self.measurement_dof is None:
            return self.measurement_sigma
        nu = self.measurement_dof
        return self.measurement_sigma * math.sqrt(nu / (nu - 2.0))

    def moment_matched(self, scale: float = 1.0) -> "ChainModel":
        """The Gaussian model with measurement standard deviation
        `scale · measurement_std` (the model itself if Gaussian and `scale`
        is 1)."""
        if self.measurement_dof is None and scale == 1.0:
            return self
        return dataclasses.replace(
            self,
            measurement_sigma=self.measurement_std * scale,
            measurement_dof=None,
        )

    def measurement_noise(self) -> AbstractNoiseModel:
        """The measurement factor's noise model (Gaussian or Student-t)."""
        gaussian = _diagonal_noise(self.measurement_sigma)
        if self.measurement_dof is None:
            return gaussian
        m = self.measurement_sigma.shape[0]
        return StudentTNoise(gaussian, self.measurement_dof, dim=m)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.candidates)

    def index(self, name: str) -> int:
        """Position of the candidate called `name`."""
        if name not in self.names:
            raise ValueError(f"no candidate named {name!r}; candidates: {self.names}")
        return self.names.index(name)

    def with_coefficients(self, coefficients: Float[ArrayLike, " K"]) -> "ChainModel":
        return eqx.tree_at(lambda m: m.coefficients, self, jnp.asarray(coefficients))

    def with_noise_scales(
        self,
        log_q: Float[ArrayLike, ""],
        log_r: Float[ArrayLike, ""],
        log_p0: Float[ArrayLike, ""] = 0.0,
    ) -> "ChainModel":
        """Multiply the process, measurement and prior sigmas by `exp(·)`."""
        return eqx.tree_at(
            lambda m: (m.process_sigma, m.measurement_sigma, m.prior_sigma),
            self,
            (
                self.process_sigma * jnp.exp(log_q),
                self.measurement_sigma * jnp.exp(log_r),
                self.prior_sigma * jnp.exp(log_p0),
            ),
        )

    def transition(
        self, x: Float[Array, " n"], u: Float[Array, " k"]
    ) -> Float[Array, " n"]:
        """Mean of `x_{t+1}` given `x_t = x`, `u_t = u` (candidates included)."""
        rates = [
            (c, coef)
            for c, coef in zip(self.candidates, self.coefficients)
            if c.target == "rate"
        ]
        if isinstance(self.dynamics, Integrator):

            def extra(z, v):
                return sum(coef * c.feature(z, v) for c, coef in rates)

            out = self.dynamics.step(x, u, self.params, extra if rates else None)
        else:
            out = self.dynamics(x, u, self.params)
        for c, coef in zip(self.candidates, self.coefficients):
            if c.target == "dynamics":
                out = out + coef * c.feature(x, u)
        return out

    def observe(
        self, x: Float[Array, " n"], u: Float[Array, " k"]
    ) -> Float[Array, " m"]:
        """Mean of `y_t` given `x_t = x` (candidates included)."""
        out = self.measurement(x, self.params)
        for c, coef in zip(self.candidates, self.coefficients):
            if c.target == "measurement":
                out = out + coef * c.feature(x, u)
        return out

    def graph(
        self,
        measurements: Float[Array, "T m"],
        inputs: Float[Array, "T k"],
        x0_mean: Float[Array, " n"],
    ) -> FactorGraph:
        """The factor graph of ONE sequence (prior, transitions, measurements)."""
        return _graph(self, measurements, inputs, x0_mean)


def _diagonal_noise(sigma: Float[Array, " d"]) -> DiagonalNoise:
    """`DiagonalNoise(sqrt_precision=1/sigma)` without the noise model's
    run-time positivity check.

    Under `jit` that check is an `eqx.error_if`, a host callback, and JAX's
    persistent cache does not store programs with host callbacks: every
    process compiled the workflow's programs again (`benchmarks/
    discover_speed.py`). Here the check is redundant: `ChainModel` checks its
    sigmas positive and finite where it is built, and the workflow only
    multiplies them by `exp(·)` of bounded log scales.
    """
    template = DiagonalNoise(sqrt_precision=np.ones(sigma.shape))  # concrete
    return eqx.tree_at(lambda n: n.sqrt_precision, template, 1.0 / sigma)


class Offsets(eqx.Module):
    """Additive terms on the equations of a batch of sequences, linear in the
    state about reference states `x_ref` (the MAP):

        x_{t+1} = f(x_t, u_t) + … + d[t] + D[t] (x_t − x_ref[t])
        y_t     = h(x_t)      + … + e[t] + E[t] (x_t − x_ref[t])

    (`d`, `D`, `e`, `E` = `dynamics`, `dynamics_jacobian`, `measurement`,
    `measurement_jacobian`; `…` the model's candidate terms).

    A term `c φ(x, u)` of a small coefficient enters the Laplace evidence at
    `x_ref` only through its value and its Jacobian there (and its second
    derivative, which a piecewise-linear `φ` does not have): the gradient of
    the evidence with respect to these offsets, contracted with `φ` and `∂φ/∂x`
    at the reference states, is the score of `c`. One compiled program then
    scores any number of such terms (the adequacy test's hats) on the
    nominal model, instead of a program per augmented model.
    """

    dynamics: Float[Array, "B T1 n"]
    dynamics_jacobian: Float[Array, "B T1 n n"]
    measurement: Float[Array, "B T m"]
    measurement_jacobian: Float[Array, "B T m n"]

    @staticmethod
    def zeros(data: "Sequences", n: int) -> "Offsets":
        B, T, m = data.measurements.shape
        return _zero_offsets(B, T, m, n, np.dtype(data.measurements.dtype).str)


@functools.lru_cache(maxsize=8)
def _zero_offsets(B: int, T: int, m: int, n: int, dtype: str) -> Offsets:
    # Cached: every score evaluation without offsets passes zeros, and four
    # eager `jnp.zeros` per call cost about a fifth of a `name` call's time.
    # (Arrays are immutable, so one set serves every call; built eagerly
    # even under a trace, so no tracer is cached.)
    # NumPy zeros put on the device: `jnp.zeros` (or `jnp.asarray`) would
    # compile a program per shape on a first call.
    shapes = ((B, T - 1, n), (B, T - 1, n, n), (B, T, m), (B, T, m, n))
    with jax.ensure_compile_time_eval():
        return Offsets(*(jax.device_put(np.zeros(s, dtype)) for s in shapes))


def _graph(model, measurements, inputs, x0_mean, offsets=None, x_ref=None):
    """The factor graph of one sequence; with `offsets` (of this sequence)
    and `x_ref`, their linear terms on the transitions and measurements."""
    T = measurements.shape[0]
    t = np.arange(T)
    if offsets is None:
        transition = (_transition_residual, inputs[:-1])
        measurement = (_measurement_residual, (measurements, inputs))
    else:
        transition = (
            _offset_transition_residual,
            (inputs[:-1], offsets.dynamics, offsets.dynamics_jacobian, x_ref[:-1]),
        )
        measurement = (
            _offset_measurement_residual,
            (
                measurements,
                inputs,
                offsets.measurement,
                offsets.measurement_jacobian,
                x_ref,
            ),
        )
    return FactorGraph(
        [
            FunctionFactor(
                _prior_residual,
                (Var("x", [0]),),
                _diagonal_noise(model.prior_sigma),
                data=x0_mean[None],
            ),
            FunctionFactor(
                transition[0],
                (Var("x", t[:-1]), Var("x", t[1:])),
                _diagonal_noise(model.process_sigma),
                data=transition[1],
                params=model,
            ),
            FunctionFactor(
                measurement[0],
                (Var("x", t),),
                model.measurement_noise(),
                data=measurement[1],
                params=model,
            ),
        ]
    )


def _prior_residual(x, data, params):
    return x - data


def _transition_residual(a, b, u, model: ChainModel):
    return b - model.transition(a, u)


def _measurement_residual(x, data, model: ChainModel):
    y, u = data
    return y - model.observe(x, u)


def _offset_transition_residual(a, b, data, model: ChainModel):
    u, d, jac, a_ref = data
    return b - (model.transition(a, u) + d + jac @ (a - a_ref))


def _offset_measurement_residual(x, data, model: ChainModel):
    y, u, d, jac, x_ref = data
    return y - (model.observe(x, u) + d + jac @ (x - x_ref))


# ---------------------------------------------------------------------------
# Likelihoods of a batch; z = [coefficients (K), log q-, r- and prior scales]
# ---------------------------------------------------------------------------


NUM_SCALES = 3  # process, measurement and prior noise scales


def apply_z(model: ChainModel, z: Float[Array, " P"]) -> ChainModel:
    K = len(model.candidates)
    return model.with_coefficients(z[:K]).with_noise_scales(z[K], z[K + 1], z[K + 2])


def z_of(model: ChainModel) -> np.ndarray:
    return np.concatenate([np.asarray(model.coefficients), np.zeros(NUM_SCALES)])


_SOLVER = GaussNewton(BlockTridiagonal())


def _compiled(fn: Callable) -> Callable:
    """`eqx.filter_jit(fn)` for functions of a `ChainModel`, called with the
    model's `noise_scale_prior` cleared.

    That (static) setting only steers the fits, which run outside compiled
    code, so models that differ in it share one compiled program; otherwise
    each new prior width compiled the MAP, evidence and score programs again.
    """
    jitted = stored_program(fn, eqx.filter_jit(fn), _fingerprint)

    @functools.wraps(fn)
    def call(model: ChainModel, *args, **kwargs):
        if model.noise_scale_prior is not None:
            model = dataclasses.replace(model, noise_scale_prior=None)
        return jitted(model, *args, **kwargs)

    return call


def _fingerprint(arguments: dict) -> str:
    """What the model's functions compute, for the key of a stored program
    (`eqsmooth.enable_compilation_cache`): the jaxpr of its transition and
    measurement means (candidates included) at a state and an input of the
    call's shapes, with the values of its constants. Every use of the
    model's callables in the compiled programs goes through these two."""
    model = arguments["model"]
    u = arguments["data"].inputs if "data" in arguments else arguments["inputs"]
    dynamic, static = eqx.partition(model, eqx.is_array)

    def means(dynamic, x, u):
        m = eqx.combine(dynamic, static)
        return m.transition(x, u), m.observe(x, u)

    u = u if hasattr(u, "dtype") else np.asarray(u)
    n, k, dtype = model.process_sigma.shape[0], u.shape[-1], u.dtype
    x, u = jax.ShapeDtypeStruct((n,), dtype), jax.ShapeDtypeStruct((k,), dtype)
    closed = jax.make_jaxpr(means)(dynamic, x, u)
    digest = hashlib.sha256()
    for c in _constants(closed):
        digest.update(repr((np.shape(c), str(np.result_type(c)))).encode())
        digest.update(np.ascontiguousarray(c).tobytes())
    return f"{closed.jaxpr}\nconstants {digest.hexdigest()}"


def _constants(closed) -> list:
    """The constants of a closed jaxpr and of every jaxpr nested in it."""
    out = list(closed.consts)
    for eqn in closed.jaxpr.eqns:
        for p in eqn.params.values():
            for sub in p if isinstance(p, (tuple, list)) else (p,):
                if isinstance(sub, ClosedJaxpr):
                    out += _constants(sub)
                elif isinstance(sub, Jaxpr):
                    out += _constants(ClosedJaxpr(sub, ()))
    return out


def _map_one(model, y, u, x0, xinit, max_steps):
    graph = model.graph(y, u, x0)
    sol = least_squares(graph, {"x": xinit}, _SOLVER, max_steps=max_steps, throw=False)
    return sol.value["x"]


@_compiled
def map_states(
    model: ChainModel,
    z: Float[Array, " P"],
    data: Sequences,
    init: Float[Array, "B T n"],
    max_steps: int = 30,
) -> Float[Array, "B T n"]:
    """MAP (smoothed) states of every sequence, starting the solves at `init`."""
    m = apply_z(model, z)
    return jax.vmap(_map_one, in_axes=(None, 0, 0, 0, 0, None))(
        m, data.measurements, data.inputs, data.x0_mean, init, max_steps
    )


def _laplace_one(model, y, u, x0, xhat):
    return laplace_at_map(model.graph(y, u, x0), {"x": xhat}, _SOLVER.linear_solver)


def sequence_log_marginals(
    model: ChainModel,
    z: Float[Array, " P"],
    data: Sequences,
    xhat: Float[Array, "B T n"],
) -> Float[Array, " B"]:
    """Laplace log marginal likelihood of every sequence at the MAP `xhat`."""
    m = apply_z(model, z)
    return jax.vmap(_laplace_one, in_axes=(None, 0, 0, 0, 0))(
        m, data.measurements, data.inputs, data.x0_mean, xhat
    )


@_compiled
def batch_log_marginal(model, z, data, xhat):
    return sequence_log_marginals(model, z, data, xhat)


def _one_z(zz, offsets, model, y, u, x0, xh):
    graph = _graph(apply_z(model, zz), y, u, x0, offsets, xh)
    return laplace_at_map(graph, {"x": xh}, _SOLVER.linear_solver)


@_compiled
def _batch_scores(model, z, data, xhat, offsets):
    fn = jax.vmap(
        jax.value_and_grad(_one_z, argnums=(0, 1)),
        in_axes=(None, 0, None, 0, 0, 0, 0),
    )
    vals, (gz, goff) = fn(
        z, offsets, model, data.measurements, data.inputs, data.x0_mean, xhat
    )
    return vals, gz, goff


def batch_scores(
    model: ChainModel,
    z: Float[Array, " P"],
    data: Sequences,
    xhat: Float[Array, "B T n"],
    offsets: Offsets | None = None,
) -> tuple[Float[Array, " B"], Float[Array, "B P"], Offsets]:
    """Per-sequence Laplace evidences `(B,)`, their scores `(B, P)` in `z`
    (reverse mode, vmapped) and their gradients with respect to `offsets`
    (zero offsets when `None`) at the MAP `xhat`.

    One compiled program per model structure serves both uses: scores of
    the candidates, and (through the offsets) of terms the model does not
    hold (see `Offsets`)."""
    if offsets is None:
        offsets = Offsets.zeros(data, xhat.shape[-1])
    return _batch_scores(model, z, data, xhat, offsets)


# ---------------------------------------------------------------------------
# Diagnostic filter: the model linearised at the smoothed states
# ---------------------------------------------------------------------------


def _linear_transition_residual(a, b, data, model: ChainModel):
    u, x_ref = data
    f_ref, df = jax.jvp(lambda x: model.transition(x, u), (x_ref,), (a - x_ref,))
    return b - (f_ref + df)


def _linear_measurement_residual(x, data, model: ChainModel):
    y, u, x_ref = data
    h_ref, dh = jax.jvp(lambda s: model.observe(s, u), (x_ref,), (x - x_ref,))
    return y - (h_ref + dh)


def _diagnostic_filter_one(model: ChainModel, y, u, x0, xhat):
    T = y.shape[0]
    t = np.arange(T)
    transition = FunctionFactor(
        _linear_transition_residual,
        (Var("x", t[:-1]), Var("x", t[1:])),
        _diagonal_noise(model.process_sigma),
        data=(u[:-1], xhat[:-1]),
        params=model,
    )
    measurement = FunctionFactor(
        _linear_measurement_residual,
        (Var("x", t),),
        _diagonal_noise(model.measurement_std),
        data=(y, u, xhat),
        params=model,
    )
    sol = ekf(
        transition,
        (measurement,),
        x0,
        jnp.diag(model.prior_sigma**2),
        throw=False,
    )
    # The filter's innovations are whitened by the measurement noise and
    # signed as −R r = R (ŷ − y); turn them back into y − ŷ and S into
    # measurement units.
    r = model.measurement_std
    nu = -sol.innovations[0] * r[None, :]
    S = sol.innovation_covariances[0] * jnp.outer(r, r)[None]
    return nu, S, sol.mean


@_compiled
def diagnostic_innovations(
    model: ChainModel, data: Sequences, xhat: Float[Array, "B T n"]
):
    """Innovations `(B, T, m)`, their covariances `(B, T, m, m)`, filtered means.

    The Kalman filter ([`eqsmooth.filters.ekf`][]) of the model linearised
    about the smoothed (MAP) states `xhat`: the exact filter of the Gaussian
    that the Laplace evidence approximates the model by. For a
    linear-Gaussian model it is the Kalman filter. An EKF that linearises at
    its own predictions is not used: its first-order error grows with the
    prediction covariance and rejected the true model of a system with
    Coulomb friction at the true noise levels, while the smoothed states
    are accurate enough for the linearisation to be consistent. With
    Student-t measurement noise (`measurement_dof`) the filter uses the
    moment-matched Gaussian, of standard deviation `model.measurement_std`.
    """
    return jax.vmap(_diagnostic_filter_one, in_axes=(None, 0, 0, 0, 0))(
        model, data.measurements, data.inputs, data.x0_mean, xhat
    )


@_compiled
def simulate(
    model: ChainModel, x0: Float[ArrayLike, "B n"], inputs: Float[ArrayLike, "B T k"]
):
    """Noise-free open-loop states `(B, T, n)` from `x0`, and measurements."""

    def one(x0, u):
        def step(x, ut):
            return model.transition(x, ut), x

        _, xs = jax.lax.scan(step, x0, u)
        ys = jax.vmap(model.observe)(xs, u)
        return xs, ys

    return jax.vmap(one)(x0, inputs)


@_compiled
def trajectory_checks(
    model: ChainModel, xhat: Float[Array, "B T n"], inputs: Float[Array, "B T k"]
):
    """What `find` checks about the smoothed states `xhat`, in one program:
    the noise-free open-loop measurements from `xhat[:, 0]` `(B, T, m)`, and
    every state's one-step means `f(x̂_t, u_t)` `(B, T, n)` and `h(x̂_t, u_t)`
    `(B, T, m)`. (Evaluated eagerly, the model's functions compiled a small
    program per operation on a first call: about twenty.)"""
    _, ys = simulate.__wrapped__(model, xhat[:, 0], inputs)
    step = jax.vmap(jax.vmap(model.transition))(xhat, inputs)
    return ys, step, jax.vmap(jax.vmap(model.observe))(xhat, inputs)


@_compiled
def k_step_errors(
    model: ChainModel,
    data: Sequences,
    xhat: Float[Array, "B T n"],
    horizon: int,
    burn_in: int = 0,
):
    """Squared k-step open-loop prediction errors from filtered states.

    Returns `(horizon, m)` mean squared errors of `y_{t+k} − ĥ(x̂_{t+k|t})` for
    `k = 1..horizon`, averaged over sequences and start times
    `t = burn_in .. T − horizon − 1` (a burn-in leaves out starts whose
    filtered state still rests on few measurements). Filtered states come
    from [`diagnostic_innovations`][] about the smoothed states `xhat`.
    """
    y, u = data.measurements, data.inputs
    T = y.shape[1]
    if horizon < 1 or not 0 <= burn_in < T - horizon:
        raise ValueError(
            f"k_step_errors: need horizon >= 1 and 0 <= burn_in < T - horizon "
            f"(T = {T}) so that some start is left; got horizon={horizon}, "
            f"burn_in={burn_in}"
        )
    _, _, xf = diagnostic_innovations(model, data, xhat)
    starts = np.arange(burn_in, T - horizon)

    def from_start(xf_b, y_b, u_b):
        def one(t):
            x = xf_b[t]

            def step(x, k):
                xn = model.transition(x, u_b[t + k])
                return xn, model.observe(xn, u_b[t + k + 1]) - y_b[t + k + 1]

            _, errs = jax.lax.scan(step, x, jnp.arange(horizon))
            return errs**2

        return jax.vmap(one)(jnp.asarray(starts))

    errs = jax.vmap(from_start)(xf, y, u)  # (B, starts, horizon, m)
    return jnp.mean(errs, axis=(0, 1))
