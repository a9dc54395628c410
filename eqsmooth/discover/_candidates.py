"""Named candidate effects: the library the discrepancy workflow searches."""

import dataclasses
from collections.abc import Callable, Hashable, Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._integrator import Integrator


_TARGETS = ("dynamics", "rate", "measurement")


class Candidate(eqx.Module):
    """One named effect that may be missing from a model.

    A candidate adds `coefficient · feature(x, u)` to the model: to the
    predicted next state for `target="dynamics"`
    (`x_{t+1} = f(x_t, u_t) + c φ(x_t, u_t) + w_t`), to the continuous-time
    vector field for `target="rate"` (`ẋ = f(x, u) + c φ(x, u)`, integrated
    with the model's own scheme; the model's dynamics must then be an
    [`eqsmooth.discover.Integrator`][]), or to the predicted measurement for
    `target="measurement"` (`y_t = h(x_t) + c ψ(x_t, u_t) + v_t`).
    The coefficient is a scalar; its value 0 is the nominal model.

    **Arguments:**

    - `name`: the name reported when the effect is found, e.g. `"quadratic drag"`.
    - `feature`: `feature(x, u) -> array`, with `x` ONE state `(n,)` and `u`
        one input `(k,)`; returns `(n,)` for dynamics and rate candidates and
        `(m,)` for measurement candidates. Must be a hashable callable that compares by
        value or identity (a module-level function or a frozen dataclass), so
        that compiled code is reused.
    - `target`: `"dynamics"`, `"rate"` or `"measurement"`.
    - `sign`: `+1` if physics says the coefficient is non-negative, `-1` if
        non-positive, `0` if either (only reported, not enforced).
    - `unit`: unit of the coefficient, for reports.
    - `description`: one line for reports, e.g. `"v' -= c v|v| dt"`.
    - `profiled`: set by [`eqsmooth.discover.Candidate.family`][] on the
        members of a family of one effect over a shape parameter (a
        threshold); `None` for a candidate of its own.
    """

    name: str = eqx.field(static=True)
    feature: Callable = eqx.field(static=True)
    target: str = eqx.field(static=True, default="dynamics")
    sign: int = eqx.field(static=True, default=0)
    unit: str = eqx.field(static=True, default="")
    description: str = eqx.field(static=True, default="")
    profiled: "Profiled | None" = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("Candidate.name must be a non-empty string")
        if self.target not in _TARGETS:
            raise ValueError(
                f"Candidate {self.name!r}: target must be one of {_TARGETS}, got "
                f"{self.target!r}"
            )
        if self.sign not in (-1, 0, 1):
            raise ValueError(
                f"Candidate {self.name!r}: sign must be -1, 0 or 1, got {self.sign}"
            )
        if not callable(self.feature):
            raise TypeError(f"Candidate {self.name!r}: feature must be callable")
        if self.profiled is not None and not isinstance(self.profiled, Profiled):
            raise TypeError(
                f"Candidate {self.name!r}: profiled must be a Profiled or None"
            )

    @classmethod
    def from_function(
        cls,
        name: str,
        fn: Callable,
        *,
        target: str = "dynamics",
        sign: int = 0,
        unit: str = "",
        description: str = "",
        **constants: Hashable,
    ) -> "Candidate":
        """A user-defined candidate from a plain function and its constants.

        `fn(x, u, **constants)` returns the feature of ONE state `x` `(n,)`
        and input `u` `(k,)`: `(n,)` for a dynamics candidate, `(m,)` for a
        measurement candidate. The constants fix the shape of a
        non-polynomial effect (a saturation level, a dead-zone width, a
        threshold); the workflow fits the candidate's one scalar coefficient.
        The feature compares by `fn` and the constants, so candidates built
        twice with the same arguments share compiled code. For example, a
        dead zone of the input acting on the velocity:

            def dead_zone(x, u, width, dt):
                push = jnp.sign(u[0]) * jnp.maximum(jnp.abs(u[0]) - width, 0.0)
                return jnp.stack([0.0 * push, dt * push])

            Candidate.from_function("dead zone", dead_zone, width=0.2, dt=0.1)

        `fn` must be a module-level function (hashable, compared by identity).
        """
        for key, value in constants.items():
            try:
                hash(value)
            except TypeError:
                raise TypeError(
                    f"Candidate {name!r}: constant {key!r} must be hashable (a "
                    f"number or a tuple), got {type(value).__name__}"
                ) from None
        feature = _BoundFeature(fn, tuple(sorted(constants.items())))
        return cls(name, feature, target, sign, unit, description)

    def feature_at(self, value: float | Array) -> Callable:
        """This family member's feature with its profiled parameter set to
        `value` instead of the grid value: `feature_at(v)(x, u)`. `value`
        may be a traced array, so a refit can fit the parameter itself (as
        the cascaded tanks example fits the overflow level). Raises for a
        candidate not made by [`eqsmooth.discover.Candidate.family`][]."""
        if self.profiled is None or not isinstance(self.feature, _BoundFeature):
            raise ValueError(
                f"Candidate {self.name!r} is not a member of a family "
                "(Candidate.family): it has no profiled parameter"
            )
        constants = dict(self.feature.constants)
        constants[self.profiled.parameter] = value
        fn = self.feature.fn

        def feature(x, u):
            return fn(x, u, **constants)

        return feature

    @classmethod
    def family(
        cls,
        name: str,
        fn: Callable,
        *,
        over: str,
        values: Sequence[float | int] | np.ndarray,
        target: str = "dynamics",
        sign: int = 0,
        unit: str = "",
        description: str = "",
        **constants: Hashable,
    ) -> tuple["Candidate", ...]:
        """One effect whose shape parameter (a threshold, a level, a width)
        is not known: a candidate per value of `over`, profiled by the
        workflow.

        Each member is `Candidate.from_function(f"{name}, {over} = {v}", fn,
        **constants, **{over: v})`. [`eqsmooth.discover.name`][] treats the
        members as one effect: their coefficients are fitted in turn, the
        value with the largest evidence is the one named, and the step
        reports the profile (the gain at every value) and the values within
        1.92 log-units of the best (the grid's 95% profile-likelihood set for
        the parameter). Members of the family never form an equivalence or
        ambiguity set with each other (that the data tell neighbouring
        thresholds apart only roughly is what the profile says), and once one
        is named the others leave the library. The naming gate still counts
        every member (Bonferroni over the grid, conservative for a profiled
        parameter). For example, an upper tank that spills above an unknown
        level:

            def overflow(x, u, level, ts):
                e = jax.nn.relu(x[0] - level)
                return jnp.stack([-ts * e, ts * e])

            Candidate.family(
                "upper overflow", overflow, over="level",
                values=(16.0, 20.0, 24.0), ts=4.0, sign=1,
            )

        The grid is the user's: a few values spread over the range the
        parameter could take in the data (quantiles of the state it acts on
        under the nominal model, say). A finer value is then fitted where
        the model is refitted, as in the cascaded tanks example.
        """
        if over in constants:
            raise ValueError(
                f"Candidate family {name!r}: {over!r} is the profiled parameter; "
                "do not also pass it as a constant"
            )
        values = tuple(float(v) for v in values)
        if len(values) < 1 or len(set(values)) != len(values):
            raise ValueError(
                f"Candidate family {name!r}: values of {over!r} must be one or "
                f"more distinct numbers, got {values}"
            )
        if not all(np.isfinite(values)):
            raise ValueError(
                f"Candidate family {name!r}: values of {over!r} must be finite, "
                f"got {values}"
            )
        members = []
        for v in values:
            member = cls.from_function(
                f"{name}, {over} = {v:.4g}",
                fn,
                target=target,
                sign=sign,
                unit=unit,
                description=description,
                **constants,
                **{over: v},
            )
            members.append(
                dataclasses.replace(member, profiled=Profiled(name, over, v))
            )
        return tuple(members)


@dataclasses.dataclass(frozen=True)
class Profiled:
    """Where a candidate sits in a family (see
    [`eqsmooth.discover.Candidate.family`][]): the family's name, the
    profiled parameter and this member's value of it."""

    family: str
    parameter: str
    value: float


@dataclasses.dataclass(frozen=True)
class _BoundFeature:
    """`fn(x, u, **constants)` as a hashable feature (see `from_function`)."""

    fn: Callable
    constants: tuple[tuple[str, Hashable], ...]

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " k"]) -> Array:
        return self.fn(x, u, **dict(self.constants))


def check_features(
    candidates: Sequence[Candidate], x: Array, u: Array, meas_dim: int
) -> None:
    """Raise a clear error if a candidate's feature fails or has the wrong shape.

    `x` and `u` are one state `(n,)` and one input `(k,)` (only their shapes
    and dtypes are used).
    """
    import jax

    state_dim, input_dim = x.shape[0], u.shape[0]
    x = jax.ShapeDtypeStruct(x.shape, x.dtype)
    u = jax.ShapeDtypeStruct(u.shape, u.dtype)
    for c in candidates:
        want = (meas_dim,) if c.target == "measurement" else (state_dim,)
        try:
            out = jax.eval_shape(c.feature, x, u)
        except Exception as e:
            raise ValueError(
                f"Candidate {c.name!r}: its feature fails on a state of shape "
                f"{(state_dim,)} and an input of shape {(input_dim,)}: "
                f"{type(e).__name__}: {e}"
            ) from e
        shape = out.shape if isinstance(out, jax.ShapeDtypeStruct) else type(out)
        if shape != want:
            raise ValueError(
                f"Candidate {c.name!r} ({c.target}): its feature must return shape "
                f"{want}, got {shape}"
            )


# Features are frozen dataclasses (hash and compare by value), so two libraries
# built with the same arguments share compiled code.


@dataclasses.dataclass(frozen=True)
class _Acceleration:
    kind: str
    positions: tuple[int, ...]
    velocities: tuple[int, ...]
    state_dim: int
    dt: float
    eps: float = 1.0
    axis: int | None = None
    input_index: int = 0
    vector_field: Callable | None = None
    rate: bool = False

    def _select(self, index: tuple[int, ...]) -> np.ndarray:
        sel = np.zeros((self.state_dim, len(index)))
        sel[np.asarray(index), np.arange(len(index))] = 1.0
        return sel

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " k"]) -> Array:
        # Constant selection matrices instead of gathers/scatters: smaller
        # programs to compile once differentiated twice.
        sel_p = jnp.asarray(self._select(self.positions), x.dtype)
        sel_v = jnp.asarray(self._select(self.velocities), x.dtype)
        if self.vector_field is not None and not self.rate:
            # The kick of a continuous acceleration over one step, evaluated
            # at the nominal half-step state (midpoint rule).
            x = x + 0.5 * self.dt * self.vector_field(x, u)
        p, v = x @ sel_p, x @ sel_v
        if self.kind in ("constant", "actuator"):
            unit = np.zeros(len(self.velocities))
            unit[self.axis] = 1.0
            a = jnp.asarray(unit, x.dtype)
            if self.kind == "actuator":
                a = a * u[self.input_index]
        elif self.kind == "viscous":
            a = -v
        elif self.kind == "drag":
            a = -v * jnp.abs(v)
        elif self.kind == "coulomb":
            a = -jnp.tanh(v / self.eps)
        elif self.kind == "cubic_damping":
            a = -(v**3)
        elif self.kind == "spring":
            a = -p
        elif self.kind == "cubic_stiffness":
            a = -(p**3)
        else:  # pragma: no cover - guarded by the library builder
            raise ValueError(f"unknown acceleration feature {self.kind!r}")
        # A rate candidate is the acceleration itself (a term of ẋ); a
        # dynamics candidate is its kick over one step.
        return sel_v @ (a if self.rate else self.dt * a)


@dataclasses.dataclass(frozen=True)
class _Sensor:
    kind: str
    channel: int
    measurement_dim: int
    position: int = 0
    velocity: int = 0

    def __call__(self, x: Float[Array, " n"], u: Float[Array, " k"]) -> Array:
        unit = np.zeros(self.measurement_dim)
        unit[self.channel] = 1.0
        if self.kind == "bias":
            value = jnp.ones((), x.dtype)
        elif self.kind == "scale":
            value = x[self.position]
        elif self.kind == "delay":
            # y(t − τ) ≈ p(t) − τ ṗ(t): a delay τ (time units of the velocity).
            value = -x[self.velocity]
        else:  # pragma: no cover - guarded by the library builder
            raise ValueError(f"unknown sensor feature {self.kind!r}")
        return value * jnp.asarray(unit, x.dtype)


_MECHANICAL = (
    ("constant force", "constant", 0, "per-axis constant acceleration: v' += c dt"),
    ("viscous damping", "viscous", 1, "v' -= c v dt"),
    ("quadratic drag", "drag", 1, "v' -= c v|v| dt"),
    ("Coulomb friction", "coulomb", 1, "v' -= c tanh(v/eps) dt (smoothed sign)"),
    ("cubic damping", "cubic_damping", 1, "v' -= c v^3 dt"),
    ("spring error", "spring", 0, "v' -= c p dt"),
    ("cubic stiffness", "cubic_stiffness", 0, "v' -= c p^3 dt"),
    ("actuator gain", "actuator", 0, "v' += c u dt (per axis)"),
)


def _check_vector_field(vector_field, state_dim: int, num_inputs: int) -> None:
    """Raise a clear error unless `vector_field(x, u)` is a hashable callable
    returning `(state_dim,)` (see `mechanical_library`)."""
    if not callable(vector_field):
        raise TypeError(
            "mechanical_library: vector_field must be a callable f(x, u) -> "
            f"dx/dt, got {type(vector_field).__name__}"
        )
    try:
        hash(vector_field)
    except TypeError:
        raise TypeError(
            "mechanical_library: vector_field must be hashable (a module-level "
            "function or a frozen dataclass), so that compiled code is reused"
        ) from None
    import jax

    x = jax.ShapeDtypeStruct((state_dim,), jnp.float32)
    u = jax.ShapeDtypeStruct((max(num_inputs, 1),), jnp.float32)
    try:
        out = jax.eval_shape(vector_field, x, u)
    except Exception as e:
        raise ValueError(
            f"mechanical_library: vector_field fails on a state of shape "
            f"{(state_dim,)} and an input of shape {(max(num_inputs, 1),)}: "
            f"{type(e).__name__}: {e}"
        ) from e
    if getattr(out, "shape", None) != (state_dim,):
        raise ValueError(
            f"mechanical_library: vector_field must return dx/dt of shape "
            f"{(state_dim,)}, got {getattr(out, 'shape', type(out).__name__)}"
        )


def _check_mechanical(
    positions, velocities, state_dim, coulomb_eps, vector_field, rate
) -> None:
    if len(positions) != len(velocities) or not positions:
        raise ValueError(
            "mechanical_library: positions and velocities must be non-empty and of "
            f"equal length, got {positions} and {velocities}"
        )
    for i in positions + velocities:
        if not 0 <= i < state_dim:
            raise ValueError(
                f"mechanical_library: state index {i} out of range for state_dim "
                f"{state_dim}"
            )
    if coulomb_eps <= 0:
        raise ValueError("mechanical_library: coulomb_eps must be positive")
    if vector_field is not None and rate:
        raise ValueError(
            "mechanical_library: give vector_field (midpoint kicks) or rate=True "
            "(terms integrated by the model's Integrator), not both"
        )


def _acceleration_candidates(template, axis_names, num_inputs, coulomb_eps, wanted):
    """The library's acceleration terms, per axis where they act on one
    (`template`: an `_Acceleration` with the system's geometry)."""
    rate, naxes = template.rate, len(template.positions)
    target = "rate" if rate else "dynamics"
    if axis_names is None:
        axis_names = [f"x{i}" for i in range(naxes)]
    if len(axis_names) != naxes:
        raise ValueError("mechanical_library: one axis name per axis")

    def suffix(i):
        return "" if naxes == 1 else f" [{axis_names[i]}]"

    out = []
    for name, kind, sign, desc in _MECHANICAL:
        if wanted is not None and name not in wanted:
            continue
        if rate:
            desc = desc.replace("v' ", "v̇ ").replace(" dt", "")
        if kind == "constant":
            for i in range(naxes):
                feat = dataclasses.replace(template, kind=kind, axis=i)
                out.append(Candidate(name + suffix(i), feat, target, 0, "", desc))
        elif kind == "actuator":
            for i in range(min(num_inputs, naxes)):
                feat = dataclasses.replace(template, kind=kind, axis=i, input_index=i)
                out.append(Candidate(name + suffix(i), feat, target, 0, "", desc))
        else:
            eps = coulomb_eps if kind == "coulomb" else 1.0
            feat = dataclasses.replace(template, kind=kind, eps=eps)
            out.append(Candidate(name, feat, target, sign, "", desc))
    return out


def _sensor_candidates(measured_positions, positions, velocities, wanted) -> list:
    """Bias, scale and delay of each measured position's sensor."""
    out = []
    measured_positions = tuple(measured_positions)
    m = len(measured_positions)
    for j, pos in enumerate(measured_positions):
        if pos not in positions:
            raise ValueError(
                f"mechanical_library: measured position {pos} is not one of the "
                f"positions {positions}"
            )
        vel = velocities[positions.index(pos)]
        sfx = "" if m == 1 else f" [y{j}]"
        for name, kind, desc in (
            ("sensor bias", "bias", "y += c"),
            ("sensor scale", "scale", "y += c p"),
            ("sensor delay", "delay", "y += -c v  (delay c)"),
        ):
            if wanted is not None and name not in wanted:
                continue
            feat = _Sensor(kind, j, m, pos, vel)
            out.append(Candidate(name + sfx, feat, "measurement", 0, "", desc))
    return out


def mechanical_library(
    positions: Sequence[int],
    velocities: Sequence[int],
    state_dim: int,
    *,
    dt: float | None = None,
    coulomb_eps: float = 0.1,
    measured_positions: Sequence[int] | None = None,
    num_inputs: int = 0,
    axis_names: Sequence[str] | None = None,
    include: Sequence[str] | None = None,
    vector_field: Callable | None = None,
    rate: bool | None = None,
    dynamics: Callable | None = None,
) -> tuple[Candidate, ...]:
    """The standard candidate effects of a second-order mechanical system.

    The state holds positions `p` and velocities `v` of one or more axes
    (`positions[i]` and `velocities[i]` are the indices of axis `i`). Every
    dynamics candidate is an extra acceleration `a(p, v, u)` entering the
    velocities as `v' += c · a · dt` (the discretisation of `v̇ = … + c a`).
    By default `a` is evaluated at the start of the step (`x_t`). Given the
    nominal model's continuous-time `vector_field`, it is evaluated at the
    nominal half-step state `x_t + dt/2 · f(x_t, u_t)` (a midpoint kick),
    and a fitted coefficient is then a continuous-time quantity. For viscous
    damping of an oscillator of frequency `ω₀`, the start-of-step kick reads
    the damping rate high by `1/cos(ω₀ dt)`; the midpoint kick removes that
    factor (see the tests). With `rate=True` every acceleration is instead a
    term of the continuous-time vector field (`target="rate"`,
    `v̇ = … + c a`), integrated by the model's own scheme: the nominal model's
    dynamics must then be an [`eqsmooth.discover.Integrator`][], and the
    coefficients are continuous-time quantities with no discretisation
    error, at a somewhat higher compile cost.

    Pass the model's `dynamics` to get the library that fits it: for an
    [`eqsmooth.discover.Integrator`][] the acceleration candidates are then
    vector-field terms (`rate=True`, the default for a continuous-time
    model) and `dt` is the integrator's. An effect that acts inside the
    ODE then gets one name: as kicks at a coarse sample time it also picks
    up stiffness-like terms and the sensor scale
    (`results/discovery_validation/continuous.md`).
    Dissipative and stiffness terms share one coefficient over all axes
    (isotropic); constant force, actuator gain and the sensor effects get one
    candidate per axis or channel.

    | name | acceleration / measurement term |
    |---|---|
    | constant force | `+1` on one axis |
    | viscous damping | `−v` |
    | quadratic drag | `−v|v|` |
    | Coulomb friction | `−tanh(v/ε)`, a smoothed `−sign(v)` (`ε = coulomb_eps`) |
    | cubic damping | `−v³` |
    | spring error | `−p` |
    | cubic stiffness | `−p³` |
    | actuator gain | `+u_i` (only with `num_inputs > 0`) |
    | sensor bias | `y_j += c` |
    | sensor scale | `y_j += c p` |
    | sensor delay | `y_j += −c v` (`y(t − τ) ≈ p(t) − τ v(t)`) |

    Sensor candidates are built when `measured_positions` is given: channel
    `j` of the measurement measures position `measured_positions[j]`.

    **Arguments:**

    - `positions`, `velocities`: state indices, one per axis.
    - `state_dim`: the state dimension `n`.
    - `dt`: time step of the discrete model (default 1, or the
        integrator's when `dynamics` is an `Integrator`).
    - `coulomb_eps`: smoothing velocity `ε` of the Coulomb term (velocity
        units); small compared with typical speeds.
    - `measured_positions`: for sensor candidates (see above), or `None`.
    - `num_inputs`: number of inputs; actuator-gain candidates map input `i`
        to axis `i`.
    - `axis_names`: names of the axes for per-axis candidates (default
        `x0, x1, …`; with one axis no suffix is used).
    - `include`: restrict to these candidate names (before axis suffixes).
    - `vector_field`: the nominal continuous-time dynamics `f(x, u) -> ẋ`
        `(n,)` for midpoint kicks, or `None` (kicks at the start of the
        step). It takes no `params`: bake the nominal parameters in (a
        frozen dataclass holding them), and build the library again if they
        change. Like a feature it must be hashable and compare by value or
        identity (a module-level function or a frozen dataclass; a lambda
        works but compiles again every time it is created).
    - `rate`: build the acceleration candidates as vector-field terms (see
        above; then `dt` and `vector_field` are not used by them). `None`
        (default): `True` when `dynamics` is an `Integrator`, else `False`.
    - `dynamics`: the nominal model's dynamics (what is passed to
        [`eqsmooth.discover.ChainModel`][]), or `None`. An `Integrator`
        makes rate candidates the default and supplies `dt`.

    **Returns:** a tuple of [`eqsmooth.discover.Candidate`][].
    """
    positions, velocities = tuple(positions), tuple(velocities)
    if isinstance(dynamics, Integrator):
        if dt is not None and dt != dynamics.dt:
            raise ValueError(
                f"mechanical_library: dt={dt} differs from the integrator's dt="
                f"{dynamics.dt}; leave dt out when dynamics is given"
            )
        dt = dynamics.dt
        if rate is None:
            rate = vector_field is None
    elif dynamics is not None and not callable(dynamics):
        raise TypeError(
            "mechanical_library: dynamics must be the model's dynamics (a callable "
            f"or an eqsmooth.discover.Integrator), got {type(dynamics).__name__}"
        )
    rate, dt = bool(rate), 1.0 if dt is None else float(dt)
    _check_mechanical(positions, velocities, state_dim, coulomb_eps, vector_field, rate)
    if vector_field is not None:
        _check_vector_field(vector_field, state_dim, num_inputs)
    wanted = None if include is None else set(include)
    geometry = (positions, velocities, state_dim, dt)
    template = _Acceleration(
        "constant", *geometry, vector_field=vector_field, rate=rate
    )
    out = _acceleration_candidates(
        template, axis_names, num_inputs, coulomb_eps, wanted
    )
    if measured_positions is not None:
        out += _sensor_candidates(measured_positions, positions, velocities, wanted)
    names = [c.name for c in out]
    if len(set(names)) != len(names):
        raise ValueError(f"mechanical_library: duplicate candidate names {names}")
    return tuple(out)
