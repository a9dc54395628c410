from collections.abc import Sequence

import jax
import numpy as np
from jaxtyping import ArrayLike


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

    **Arguments:**

    - `group`: the name of the variable group (a key of the values dict).
    - `ids`: one non-negative integer per factor row (a sequence or 1-D integer
        array; must be concrete, i.e. not a JAX tracer).
    """

    __slots__ = ("group", "_ids")

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

    @property
    def ids(self) -> np.ndarray:
        """The (read-only) variable indices, one per factor row."""
        return self._ids.array

    def __len__(self) -> int:
        return int(self._ids.array.shape[0])

    def __hash__(self) -> int:
        return hash((self.group, self._ids))

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Var)
            and self.group == other.group
            and self._ids == other._ids
        )

    def __repr__(self) -> str:
        ids = self.ids
        body = (
            str(ids.tolist())
            if ids.size <= 6
            else f"[{ids[0]}, {ids[1]}, ..., {ids[-1]}] ({ids.size} rows)"
        )
        return f"Var({self.group!r}, {body})"


jax.tree_util.register_pytree_node(
    Var,
    lambda v: ((), (v.group, v._ids)),
    lambda aux, _: _unflatten_var(*aux),
)


def _unflatten_var(group: str, ids: _Ids) -> Var:
    var = object.__new__(Var)
    var.group = group
    var._ids = ids
    return var
