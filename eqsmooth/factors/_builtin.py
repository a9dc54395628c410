import warnings
import weakref
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import block_diag
from jaxtyping import Array, Float, PyTree

from .._precision import matmul as mm
from ..manifold import is_group, local, tangent_dim
from ._factor import AbstractAnalyticFactor, AbstractFactor, shared_field
from ._noise import AbstractNoiseModel
from ._variables import Var


class PriorFactor(AbstractAnalyticFactor):
    """Prior on any state: residual `x ⊖ value` (tangent coordinates).

    Its Jacobian is given in closed form: `Jr⁻¹(e)` for a group leaf with
    residual `e`, the identity for an array leaf.

    **Arguments:**

    - `variable`: a [`eqsmooth.factors.Var`][] with `n` rows.
    - `value`: the prior mean, the state pytree stacked with a leading axis `n`.
    - `noise`: noise model on the tangent residual.
    """

    variables: tuple[Var, ...]
    value: PyTree
    noise: AbstractNoiseModel

    def __init__(self, variable: Var, value: PyTree, noise: AbstractNoiseModel):
        self.variables = (variable,)
        self.value = value
        self.noise = noise

    def residual(self, x: PyTree) -> Float[Array, " m"]:
        check_like_state("PriorFactor", "value", self.value, x)
        return local(self.value, x)

    def residual_and_jacobians(
        self, x: PyTree
    ) -> tuple[Float[Array, " m"], tuple[Float[Array, "m d"]]]:
        check_like_state("PriorFactor", "value", self.value, x)
        pieces, jac = [], []
        for mean, leaf in zip(_leaves(self.value), _leaves(x)):
            if is_group(leaf):
                e = (mean.inverse() @ leaf).log()
                pieces.append(e)
                jac.append(type(leaf).right_jacobian_inv(e))
            else:
                e = (jnp.asarray(leaf) - jnp.asarray(mean)).reshape(-1)
                pieces.append(e)
                jac.append(jnp.eye(e.shape[0], dtype=e.dtype))
        return jnp.concatenate(pieces), (block_diag(*jac),)


def _leaves(x: PyTree) -> list:
    return jax.tree_util.tree_leaves(x, is_leaf=is_group)


def check_like_state(factor: str, field: str, given: PyTree, state: PyTree) -> None:
    """Raise `ValueError` unless one row of `given` has the structure, group
    types and leaf shapes of the state it is compared with.

    Called at trace time (inside the row `vmap`, so shapes are per row):
    without it a `(n, 1)` mean on `(n, 3)` states broadcasts silently.
    """
    gl, gdef = jax.tree_util.tree_flatten(given, is_leaf=is_group)
    sl, sdef = jax.tree_util.tree_flatten(state, is_leaf=is_group)
    if gdef != sdef:
        raise ValueError(
            f"{factor}.{field} has structure {gdef} but the state it is compared "
            f"with has structure {sdef}"
        )
    for k, (g, x) in enumerate(zip(gl, sl)):
        where = f" (leaf {k})" if len(gl) > 1 else ""
        if is_group(g) or is_group(x):
            if type(g) is not type(x):
                raise ValueError(
                    f"{factor}.{field}{where} is {_kind(g)} but the state it is "
                    f"compared with is {_kind(x)}"
                )
            continue
        if jnp.shape(g) != jnp.shape(x):
            raise ValueError(
                f"{factor}.{field}{where}: one row has shape {jnp.shape(g)} but the "
                f"state it is compared with has shape {jnp.shape(x)} (tangent "
                f"dimension {tangent_dim(x)}); give {field} the shape (n, "
                f"{', '.join(map(str, jnp.shape(x)))})"
            )


def _kind(leaf) -> str:
    return f"a {type(leaf).__name__}" if is_group(leaf) else "an array"


def _between(a: PyTree, b: PyTree) -> PyTree:
    def leaf(u, v):
        return u.inverse() @ v if is_group(u) else jnp.asarray(v) - jnp.asarray(u)

    return jax.tree_util.tree_map(leaf, a, b, is_leaf=is_group)


class BetweenFactor(AbstractAnalyticFactor):
    """Relative measurement between two states: residual `(a⁻¹ b) ⊖ measurement`.

    For group leaves `a⁻¹ b` is the relative transform; for array leaves it is
    the difference `b − a`. The classic pose-graph edge.

    Its Jacobians are given in closed form: for a group leaf with
    `X = a⁻¹ b` and residual `e = log(measurement⁻¹ X)`, `∂e/∂δ_b = Jr⁻¹(e)`
    and `∂e/∂δ_a = −Jr⁻¹(e) Ad(X⁻¹)`; for an array leaf, `−I` and `I`.

    **Arguments:**

    - `a`, `b`: [`eqsmooth.factors.Var`][]s with `n` rows each.
    - `measurement`: the measured relative state, stacked with leading axis `n`.
    - `noise`: noise model on the tangent residual.
    """

    variables: tuple[Var, ...]
    measurement: PyTree
    noise: AbstractNoiseModel

    def __init__(self, a: Var, b: Var, measurement: PyTree, noise: AbstractNoiseModel):
        self.variables = (a, b)
        self.measurement = measurement
        self.noise = noise

    def residual(self, a: PyTree, b: PyTree) -> Float[Array, " m"]:
        check_like_state("BetweenFactor", "variables", a, b)
        check_like_state("BetweenFactor", "measurement", self.measurement, a)
        return local(self.measurement, _between(a, b))

    def residual_and_jacobians(
        self, a: PyTree, b: PyTree
    ) -> tuple[Float[Array, " m"], tuple[Float[Array, "m d"], Float[Array, "m d"]]]:
        check_like_state("BetweenFactor", "variables", a, b)
        check_like_state("BetweenFactor", "measurement", self.measurement, a)
        pieces, ja, jb = [], [], []
        for mean, u, v in zip(_leaves(self.measurement), _leaves(a), _leaves(b)):
            if is_group(u):
                x = u.inverse() @ v
                e = (mean.inverse() @ x).log()
                jr_inv = type(u).right_jacobian_inv(e)
                pieces.append(e)
                ja.append(-mm(jr_inv, x.inverse().adjoint()))
                jb.append(jr_inv)
            else:
                e = (jnp.asarray(v) - jnp.asarray(u) - jnp.asarray(mean)).reshape(-1)
                eye = jnp.eye(e.shape[0], dtype=e.dtype)
                pieces.append(e)
                ja.append(-eye)
                jb.append(eye)
        return jnp.concatenate(pieces), (block_diag(*ja), block_diag(*jb))


# code object -> [weak reference to the last function seen with it, count of
# distinct function objects seen]; see `_note_function`.
_FUNCTIONS_SEEN: dict = {}
_NEW_FUNCTION_WARNING = (
    "FunctionFactor received a new function object {name!r} with the same code as "
    "one it has seen (e.g. a lambda or closure re-created before every solve). "
    "The function is part of the compiled graph's static structure, so each new "
    "object compiles the solve again (seconds). Define it once, at module level, "
    "and pass data through `data=` / `params=` instead."
)


def _note_function(fn: Callable) -> None:
    """Warn once per code object when new function objects with the same code
    keep arriving: the pattern of a lambda written inside a training or
    solving loop, which recompiles on every call."""
    code = getattr(fn, "__code__", None)
    if code is None:
        return
    entry = _FUNCTIONS_SEEN.get(code)
    if entry is None:
        _FUNCTIONS_SEEN[code] = [weakref.ref(fn), 1]
        return
    if entry[0]() is fn:
        return
    entry[0] = weakref.ref(fn)
    entry[1] += 1
    # At the second object: the first one has cost one compilation already,
    # and each further one costs another (it was the third; issue 36).
    if entry[1] == 2:
        warnings.warn(
            _NEW_FUNCTION_WARNING.format(name=getattr(fn, "__qualname__", fn)),
            UserWarning,
            stacklevel=4,
        )


class FunctionFactor(AbstractFactor):
    """A factor made from a user function `fn(*states, data, params) -> residual`.

    **Arguments:**

    - `fn`: returns the unwhitened 1-D residual of ONE row; receives the
        row's states (one per variable), that row's `data` and the shared
        `params`. It must be a hashable callable (a function, not a lambda
        re-created on every call, to avoid recompilation).
    - `variables`: tuple of [`eqsmooth.factors.Var`][].
    - `noise`: noise model.
    - `data`: per-row pytree (leaves with leading axis `n`), or `None`.
    - `params`: pytree shared by all rows (learnable), or `None`.
    - `residual_dim`: the residual's dimension `m`, if you declare it (a
        static int). A residual of another shape then raises naming `fn`.
        Without it a function that broadcasts (`x - data` with a state of
        dimension 2 and data of dimension 1) returns a residual of the wrong
        size that nothing can tell from a right one; noise models with a
        dimension (`DiagonalNoise`, `SqrtInformationNoise`) check `m` too.
    """

    fn: Callable = eqx.field(static=True)
    variables: tuple[Var, ...]
    noise: AbstractNoiseModel
    data: PyTree
    params: PyTree = shared_field()
    residual_dim: int | None = eqx.field(static=True, default=None)

    def __init__(
        self,
        fn: Callable,
        variables: tuple[Var, ...],
        noise: AbstractNoiseModel,
        data: PyTree = None,
        params: PyTree = None,
        *,
        residual_dim: int | None = None,
    ):
        if not callable(fn):
            raise TypeError(
                "FunctionFactor: fn must be a function fn(*states, data, params) -> "
                f"residual, got {type(fn).__name__}"
            )
        _note_function(fn)
        self.fn = fn
        self.variables = tuple(variables)
        self.noise = noise
        self.data = data
        self.params = params
        if residual_dim is not None and (
            isinstance(residual_dim, bool)
            or not isinstance(residual_dim, int)
            or residual_dim < 1
        ):
            raise ValueError(
                f"FunctionFactor.residual_dim must be a positive int, got "
                f"{residual_dim!r}"
            )
        self.residual_dim = residual_dim

    def residual(self, *states: PyTree) -> Float[Array, " m"]:
        r = jnp.asarray(self.fn(*states, self.data, self.params))
        if self.residual_dim is not None and r.shape != (self.residual_dim,):
            name = getattr(self.fn, "__qualname__", type(self.fn).__name__)
            shapes = [
                tuple(jnp.shape(leaf)) for leaf in jax.tree_util.tree_leaves(states)
            ]
            raise ValueError(
                f"FunctionFactor(fn={name}): one row's residual has shape {r.shape}, "
                f"but residual_dim={self.residual_dim} was declared (the row's state "
                f"leaves have shapes {shapes}; a residual such as x - data broadcasts "
                "a state against data of another size)"
            )
        return r
