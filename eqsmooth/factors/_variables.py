from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Int


class _Ids:
    """Read-only integer index array that hashes and compares by value."""

    __slots__ = ("array", "_hash")

    def __init__(self, array: np.ndarray):
        array = np.ascontiguousarray(array, dtype=np.int64)
        array.setflags(write=False)
        self.array = array
        self._hash = hash((array.shape, array.tobytes()))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, _Ids)
            and self._hash == other._hash
            and np.array_equal(self.array, other.array)
        )


class Var:
    """Static reference from the rows of a stacked factor to variables of a group.

    A graph's values are a dict `{group_name: stacked_states}` where every leaf
    of `stacked_states` has a leading axis indexing the variables of that group.
    `Var("x", ids)` says that row `i` of a factor touches variable `ids[i]` of
    group `"x"`.

    `Var` is a pytree with no array leaves: the indices are *structure*. They
    are hashed by value, so graphs with the same structure share compiled code
    while new measurements or parameters never trigger recompilation.
    [`eqsmooth.factors.Var.dynamic`][] builds the other kind, whose indices
    are data (an array leaf), so that graphs of another connectivity reuse a
    compiled program ([`eqsmooth.solve.pad_graph`][] builds such graphs).

    **Arguments:**

    - `group`: the name of the variable group (a key of the values dict).
    - `ids`: one non-negative integer per factor row (a sequence or 1-D integer
        array; must be concrete, i.e. not a JAX tracer).
    """

    __slots__ = ("group", "_ids")

    group: str
    _ids: "_Ids | Array"

    def __init__(self, group: str, ids: ArrayLike | Sequence[int] | int):
        if not isinstance(group, str):
            raise TypeError(f"Var group must be a string, got {type(group).__name__}")
        if isinstance(ids, jax.core.Tracer):
            raise TypeError(
                f"Var({group!r}, ids): ids must be concrete (numpy or a list), not a "
                "traced JAX array: graph structure is static"
            )
        arr = np.asarray(ids)
        if arr.ndim == 0:
            arr = arr[None]
        if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer) or arr.size == 0):
            raise ValueError(
                f"Var({group!r}, ids): ids must be a 1-D integer array, got dtype "
                f"{arr.dtype} and shape {arr.shape}"
            )
        if arr.size and arr.min() < 0:
            raise ValueError(f"Var({group!r}, ids): ids must be non-negative")
        self.group = group
        self._ids = _Ids(arr)

    @classmethod
    def dynamic(cls, group: str, ids: Int[ArrayLike, "*n"]) -> "Var":
        """A reference whose indices are data, not structure.

        The indices are an array leaf of the pytree (they may be traced,
        batched with `vmap`, or differ between calls of one compiled
        program), so two graphs that differ only in their connectivity share
        a compiled solve. Only what works for any connectivity accepts them:
        the residuals, the linearisation, the matrix-free normal operator
        (any lineax solver), `PCG` with its default block-Jacobi
        preconditioner and [`eqsmooth.solve.DenseCholesky`][], which the
        default solver picks for them; the structure-exploiting solvers
        (`BlockTridiagonal`, the sparse ones, `PCG(ChainPreconditioner())`),
        the filters and the file writers need static indices and say so.
        Indices out of range are named by `FactorGraph.validate` when they
        are concrete; traced ones gather NaN, so a solve reports non-finite
        residuals rather than a wrong answer.

        **Arguments:**

        - `group`: the name of the variable group.
        - `ids`: one integer per factor row (a 1-D integer array).
        """
        if not isinstance(group, str):
            raise TypeError(f"Var group must be a string, got {type(group).__name__}")
        if isinstance(ids, jax.Array):
            arr = ids
        else:  # on the host: jnp.asarray would compile a program per shape
            arr = jax.device_put(np.asarray(ids))
        if arr.ndim == 0:
            arr = arr[None]
        if arr.ndim != 1 or not jnp.issubdtype(arr.dtype, jnp.integer):
            raise ValueError(
                f"Var.dynamic({group!r}, ids): ids must be a 1-D integer array, got "
                f"dtype {arr.dtype} and shape {arr.shape}"
            )
        return _make_var(group, arr)

    @property
    def is_dynamic(self) -> bool:
        """Whether the indices are data ([`eqsmooth.factors.Var.dynamic`][])."""
        return not isinstance(self._ids, _Ids)

    @property
    def ids(self) -> np.ndarray:
        """The (read-only) static variable indices, one per factor row.

        Raises `TypeError` for a [`eqsmooth.factors.Var.dynamic`][] reference,
        whose indices are data: what reads `ids` needs the structure at
        trace time (use `index` where either kind works)."""
        if self.is_dynamic:
            raise TypeError(
                f"Var.dynamic({self.group!r}, ...): this operation needs static "
                "variable indices (the graph's structure at trace time), and these "
                "are data; build the graph with Var(group, ids) for it (for a "
                "solve: DenseCholesky, PCG and lineax solvers take dynamic indices)"
            )
        return self._ids.array

    @property
    def index(self) -> np.ndarray | Array:
        """The indices of either kind: a numpy array for static ones, a JAX
        array (possibly traced) for dynamic ones."""
        return self._ids if self.is_dynamic else self._ids.array

    def __len__(self) -> int:
        shape = getattr(self.index, "shape", None)  # None: a filtered-out leaf
        if shape is None:
            raise TypeError(f"Var.dynamic({self.group!r}) holds no index array")
        return int(shape[0])

    def __hash__(self) -> int:
        if self.is_dynamic:
            return hash((self.group, id(self._ids)))
        return hash((self.group, self._ids))

    def __eq__(self, other) -> bool:
        if not isinstance(other, Var) or self.group != other.group:
            return False
        if self.is_dynamic or other.is_dynamic:
            return self._ids is other._ids
        return self._ids == other._ids

    def __repr__(self) -> str:
        if self.is_dynamic:
            shape = getattr(self._ids, "shape", None)
            rows = "<no index>" if shape is None else f"{shape[0]} rows"
            return f"Var.dynamic({self.group!r}, {rows})"
        ids = self.ids
        body = (
            str(ids.tolist())
            if ids.size <= 6
            else f"[{ids[0]}, {ids[1]}, ..., {ids[-1]}] ({ids.size} rows)"
        )
        return f"Var({self.group!r}, {body})"


def _flatten_var(v: Var):
    if v.is_dynamic:
        return (v._ids,), (v.group, None)
    return (), (v.group, v._ids)


def _unflatten_var(aux, children) -> Var:
    group, ids = aux
    return _make_var(group, children[0] if ids is None else ids)


def _make_var(group: str, ids) -> Var:
    var = object.__new__(Var)
    var.group = group
    var._ids = ids
    return var


jax.tree_util.register_pytree_node(Var, _flatten_var, _unflatten_var)
