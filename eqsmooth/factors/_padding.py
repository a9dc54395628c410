"""Structure as data: graphs padded to bucket sizes share one compiled solve.

The padding lives beside the graph it pads; its public names are
[`eqsmooth.solve.pad_graph`][], [`eqsmooth.solve.PaddedGraph`][] and
[`eqsmooth.solve.power_of_two`][], next to the solves that reuse one
compiled program. Each noise model pads its own rows
([`take_rows`][eqsmooth.factors.AbstractNoiseModel.take_rows],
[`mask_rows`][eqsmooth.factors.AbstractNoiseModel.mask_rows]).
"""

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PyTree

from ..manifold import tangent_dim
from ._builtin import PriorFactor
from ._factor import AbstractFactor, per_row_fields, with_rows
from ._graph import FactorGraph, group_count, Values
from ._noise import (
    AbstractNoiseModel,
    check_row_mask,
    device_mask,
    RowIndex,
    RowMask,
    take_leading,
)
from ._variables import Var


def power_of_two(n: int) -> int:
    """The default bucket: the next power of two, at least 8."""
    return max(8, 1 << max(0, math.ceil(math.log2(max(n, 1)))))


class _PaddingNoise(AbstractNoiseModel):
    """Unit noise on the rows of the padding prior that hold a padding
    variable (`active`), nothing on the others. Its normaliser is zero, so
    the padded graph's negative log-likelihood equals the original's."""

    active: Bool[Array, " n"]

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        keep = self.active.reshape(self.active.shape + (1,) * (r.ndim - 1))
        return jnp.where(keep, r, jnp.zeros((), r.dtype))

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        return jnp.asarray(0.0)  # weakly typed: keeps a float32 graph float32

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        return jnp.asarray(0.0)

    def rho(self, s):
        return s, jnp.ones_like(s)

    def active_rows(self) -> Bool[Array, " n"]:
        return self.active

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        check_row_mask(factor_name, "the padding mask", self.active, n)

    def curvature_model(self) -> "_PaddingNoise":
        return self

    def take_rows(self, index: RowIndex) -> "_PaddingNoise":
        return _PaddingNoise(take_leading(self.active, index))

    def mask_rows(self, active: RowMask) -> "_PaddingNoise":
        return _PaddingNoise(self.active & device_mask(active))


class PaddedGraph(eqx.Module):
    """A graph and its values padded to bucket sizes, from
    [`eqsmooth.solve.pad_graph`][].

    `graph` and `values` go to any solve that takes a graph with dynamic
    indices ([`eqsmooth.solve.least_squares`][] with its default or a dense
    or lineax linear solver); `unpad` returns the real variables of a result.

    **Fields:**

    - `graph`: the padded [`eqsmooth.factors.FactorGraph`][]: every factor
        stack with [`eqsmooth.factors.Var.dynamic`][] indices and its padding
        rows masked, then one padding prior per variable group.
    - `values`: the padded values (padding variables copy variable 0).
    - `counts`: `{group: number of real variables}` (static).
    """

    graph: FactorGraph
    values: Values
    counts: tuple[tuple[str, int], ...] = eqx.field(static=True)

    def pad(self, values: Values) -> Values:
        """Other values of the real variables (ground truth, another initial
        guess), padded as `values` is: the padding variables get the padding
        prior's means, so the padded graph's cost and negative log-likelihood
        at the result equal the original graph's at `values`."""
        counts = dict(self.counts)
        if sorted(values) != sorted(counts):
            raise ValueError(
                f"PaddedGraph.pad: values have groups {sorted(values)}, the graph "
                f"has {sorted(counts)}"
            )
        out = {}
        for name, group in values.items():
            n = group_count(name, group)
            if n != counts[name]:
                raise ValueError(
                    f"PaddedGraph.pad: group {name!r} has {n} variables, the padded "
                    f"graph was built for {counts[name]}"
                )
            out[name] = jax.tree_util.tree_map(
                lambda a, held: jnp.concatenate([jnp.asarray(a), held[n:]]),
                group,
                self.values[name],
            )
        return out

    def unpad(self, tree: dict[str, PyTree]) -> dict[str, PyTree]:
        """The real variables of a dict keyed by group whose leaves have the
        padded leading axis (solved values, tangents, marginal covariances)."""
        counts = dict(self.counts)
        unknown = set(tree) - set(counts)
        if unknown:
            raise ValueError(
                f"PaddedGraph.unpad: groups {sorted(unknown)} are not in the padded "
                f"graph (groups: {sorted(counts)})"
            )
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return {
                name: _pad_rows(group, np.arange(counts[name]))
                for name, group in tree.items()
            }
        # Concrete: one transfer to the host and one back, sliced in numpy
        # (an eager JAX slice would compile a program per shape).
        names = [
            name
            for name, group in tree.items()
            for _ in jax.tree_util.tree_leaves(group)
        ]
        host = jax.device_get(leaves)
        real = [np.asarray(h)[: counts[n]] for h, n in zip(host, names)]
        return jax.tree_util.tree_unflatten(treedef, jax.device_put(real))


def pad_graph(
    graph: FactorGraph,
    values: Values,
    bucket: Callable[[int], int] = power_of_two,
) -> PaddedGraph:
    """Pad a graph so that graphs of another size or connectivity reuse its
    compiled solve.

    A solve is compiled once per graph *structure*: factor types, stack
    sizes, variable counts and the static variable indices. `pad_graph`
    turns the last three into data: each factor stack is padded to
    `bucket(n)` rows (copies of row 0, masked out of the cost), each
    variable group to `bucket(N)` variables (copies of variable 0, held by a
    unit prior so the system stays non-singular), and the indices become
    [`eqsmooth.factors.Var.dynamic`][]. Two graphs whose sizes fall in the
    same buckets then share one compiled program if everything else that is
    structure agrees: the factor stacks (types and order), the noise models
    (types, shared or per-row parameters, a `MaskedNoise` or not, the kernel
    class), the dtypes and the groups of the values; with
    `bucket=lambda n: 64` every graph up to 64 rows and variables per stack
    and group does.

    The padded graph has the original's cost and negative log-likelihood at
    the padded values (and at any values padded by `PaddedGraph.pad`), and
    the solve's real variables equal the original solve's (the padding adds
    decoupled identity blocks to the normal matrix). The default linear solver for it is
    [`eqsmooth.solve.DenseCholesky`][]: `O(N³)` in the padded size, so this
    pays for small graphs (hundreds of coordinates); large graphs keep their
    static structure and the structured solvers. Gradients flow through the
    padding to the factors' data and parameters.

    **Arguments:**

    - `graph`: the graph (static indices; every stack needs at least one row).
    - `values`: its values `{group: stacked states}`.
    - `bucket`: the padded size for a real size `n` (at least `n`); by
        default the next power of two, at least 8.

    **Returns:** a [`eqsmooth.solve.PaddedGraph`][].
    """
    layout = graph.validate(values)
    counts = {g.name: g.count for g in layout}
    empty = [name for name, n in counts.items() if n == 0]
    if empty:
        raise ValueError(f"pad_graph: variable group {empty[0]!r} has no variables")
    sizes = {
        name: _bucket(bucket, n, f"variable group {name!r}")
        for name, n in counts.items()
    }
    factors = []
    for k, f in enumerate(graph.factors):
        where = f"{type(f).__name__} (factor stack {k})"
        n = f.num_rows
        if n == 0:
            raise ValueError(f"pad_graph: {where} has no rows")
        if any(v.is_dynamic for v in f.variables):
            raise ValueError(f"pad_graph: {where} already has dynamic indices")
        size = _bucket(bucket, n, where)
        factors.append(_pad_factor(f, size, where))
    padded = {
        name: _pad_rows(group, _first_then_zeros(counts[name], sizes[name]))
        for name, group in values.items()
    }
    for name in sorted(padded):
        active = np.arange(sizes[name]) >= counts[name]
        factors.append(
            PriorFactor(
                Var(name, np.arange(sizes[name])),
                padded[name],
                _PaddingNoise(jax.device_put(active)),
            )
        )
    return PaddedGraph(FactorGraph(factors), padded, tuple(sorted(counts.items())))


def _bucket(bucket: Callable[[int], int], n: int, where: str) -> int:
    size = int(bucket(n))
    if size < n:
        raise ValueError(
            f"pad_graph: bucket({n}) = {size} for {where}; a bucket must be at "
            "least the real size"
        )
    return size


def _first_then_zeros(n: int, size: int) -> np.ndarray:
    """`0, 1, …, n−1` then zeros up to `size`: real rows, then copies of row 0."""
    return np.concatenate([np.arange(n), np.zeros(size - n, dtype=np.int64)])


def _pad_rows(tree: PyTree, index: np.ndarray) -> PyTree:
    return jax.tree_util.tree_map(lambda a: take_leading(a, index), tree)


def _pad_factor(f: AbstractFactor, size: int, where: str) -> AbstractFactor:
    n = f.num_rows
    index = _first_then_zeros(n, size)
    active = np.arange(size) < n
    new = with_rows(f, {k: _pad_rows(v, index) for k, v in per_row_fields(f).items()})
    variables = tuple(Var.dynamic(v.group, v.ids[index]) for v in f.variables)
    object.__setattr__(new, "variables", variables)
    object.__setattr__(new, "noise", _padded_noise(f.noise, index, active, where))
    return new


def _padded_noise(
    noise: AbstractNoiseModel, index: np.ndarray, active: np.ndarray, where: str
) -> AbstractNoiseModel:
    """`noise` for the padded rows, with the padding rows switched off."""
    try:
        return noise.take_rows(index).mask_rows(active)
    except TypeError as err:
        raise TypeError(
            f"pad_graph: {where} has noise {noise.name}, whose padding rows "
            f"cannot be switched off: {err}"
        ) from None


def padding_size(graph: FactorGraph) -> tuple[Array | int, Array | int]:
    """`(variables, tangent coordinates)` of the padding variables of a graph
    from [`eqsmooth.solve.pad_graph`][] (zeros for any other graph): what
    counts of variables or coordinates leave out."""
    variables, coordinates = 0, 0
    for f in graph.factors:
        if isinstance(f.noise, _PaddingNoise):
            k = jnp.sum(f.noise.active)
            variables = variables + k
            coordinates = coordinates + k * tangent_dim(f.value, batch_ndim=1)
    return variables, coordinates


# ---------------------------------------------------------------------------
# The padding of one structure, learnt once: what `least_squares` pads with
# ---------------------------------------------------------------------------

# A padded graph's array leaves are row gathers of the original's leaves
# (`take_leading`) or constants of the structure (masks, dynamic indices).
# `pad_concrete` learns which, once per structure, by padding a copy whose
# leaves hold distinct codes, and then pads by numpy gathers and one
# transfer: a small fraction of `pad_graph`'s cost, which builds every
# Module and transfers every leaf again.

_PLANS: "dict[object, _Plan | None]" = {}
_MAX_PLANS = 256
_CODE_BASE = 1 << 20  # codes start here: constants (indices, 0, 1) stay below


class _Plan(NamedTuple):
    treedef: Any
    # Per output leaf: (input leaf, rows) for a gather (rows None: as is),
    # or (None, constant).
    recipes: tuple


def pad_concrete(
    graph: FactorGraph,
    values: Values,
    bucket: Callable[[int], int] = power_of_two,
    transfer: bool = True,
    accept: Callable[[FactorGraph, Values], bool] | None = None,
) -> PaddedGraph | None:
    """[`eqsmooth.solve.pad_graph`][]`(graph, values, bucket)` for concrete
    leaves, from a plan learnt once per structure (the treedef, the leaves'
    shapes and dtypes, the boolean leaves' contents, the bucket); `None`
    when the structure cannot be padded by gathers (then pad with
    `pad_graph`, which also names any error). `transfer=False` leaves the
    padded leaves as numpy arrays, for a `jax.jit` call that transfers its
    arguments itself (cheaper than `jax.device_put` from Python). `accept`,
    asked once per structure, can refuse it (`None` then, from the cache)."""
    leaves, treedef = jax.tree_util.tree_flatten((graph, values))
    if not all(isinstance(x, (np.ndarray, jax.Array)) for x in leaves):
        return None
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return None
    host = jax.device_get(leaves)
    host = [np.asarray(h) for h in host]
    key = (
        treedef,
        tuple((h.shape, h.dtype.str) for h in host),
        tuple(h.tobytes() for h in host if h.dtype == np.bool_),
        bucket,
        accept,
    )
    try:
        plan = _PLANS[key]
    except KeyError:
        plan = None
        if accept is None or accept(graph, values):
            plan = _learn_plan(graph, values, treedef, host, bucket)
        if len(_PLANS) >= _MAX_PLANS:
            _PLANS.pop(next(iter(_PLANS)))
        _PLANS[key] = plan
    except TypeError:  # an unhashable static field
        return None
    if plan is None:
        return None
    out = [_apply(recipe, leaves, host) for recipe in plan.recipes]
    if transfer:
        gathered = [k for k, x in enumerate(out) if isinstance(x, np.ndarray)]
        moved = jax.device_put([out[k] for k in gathered])
        for k, x in zip(gathered, moved):
            out[k] = x
    return jax.tree_util.tree_unflatten(plan.treedef, out)


def _apply(recipe, leaves, host):
    """An output leaf: a constant (on the device since the plan was learnt),
    an input leaf as it is, or a numpy gather of its rows."""
    j, rows = recipe
    if j is None:
        return rows
    return leaves[j] if rows is None else host[j][rows]


def _learn_plan(graph, values, treedef, host, bucket) -> _Plan | None:
    """The plan of one structure, learnt by padding a coded copy, then
    checked on a second coding (other codes, rows reversed): a leaf that
    any arithmetic of a padding routine made from the data (not a gather)
    differs between the two, and the structure is then not planned."""
    first = _padded_codes(treedef, host, bucket, _CODE_BASE, reverse=False)
    second = _padded_codes(treedef, host, bucket, 2 * _CODE_BASE, reverse=True)
    if first is None or second is None:
        return None
    (coded, ranges, (out_leaves, out_treedef)) = first
    (coded2, _, (out_leaves2, out_treedef2)) = second
    if out_treedef2 != out_treedef:
        return None
    recipes = []
    for leaf, leaf2 in zip(out_leaves, out_leaves2):
        recipe = _recipe(np.asarray(jax.device_get(leaf)), coded, ranges)
        if recipe is None:
            return None
        again = _apply(recipe, coded2, coded2)
        if not np.array_equal(np.asarray(again), np.asarray(jax.device_get(leaf2))):
            return None
        recipes.append(recipe)
    # Constants go to the device once, here, not on every call.
    recipes = [(None, jax.device_put(r)) if j is None else (j, r) for j, r in recipes]
    return _Plan(out_treedef, tuple(recipes))


_EXACT = {  # integers each dtype holds exactly
    np.dtype(np.float64): 2**53,
    np.dtype(np.int64): 2**62,
    np.dtype(np.float32): 2**24,
    np.dtype(np.int32): 2**31 - 1,
}


def _padded_codes(treedef, host, bucket, offset, reverse):
    """`pad_graph` of a copy whose numeric leaves hold distinct codes from
    `offset` (booleans kept): `(coded leaves, code ranges, (padded leaves,
    treedef))`, or `None` if a dtype cannot hold them or padding fails."""
    coded, ranges = [], []
    for h in host:
        if h.dtype == np.bool_:
            coded.append(h)
            ranges.append(None)
            continue
        if h.dtype not in _EXACT or offset + h.size >= _EXACT[h.dtype]:
            return None
        codes = offset + np.arange(h.size)
        if reverse and h.ndim:
            codes = codes.reshape(h.shape)[::-1].reshape(-1)
        coded.append(codes.reshape(h.shape).astype(h.dtype))
        ranges.append((offset, h.size))
        offset += h.size
    try:
        g, v = jax.tree_util.tree_unflatten(treedef, coded)
        padded = pad_graph(g, v, bucket)
    except Exception:  # a check the codes fail: the caller pads otherwise
        return None
    return coded, ranges, jax.tree_util.tree_flatten(padded)


def _recipe(out: np.ndarray, coded, ranges):
    """How `out` (a leaf of the coded padding) comes from the coded inputs:
    a gather of one input's rows, or a constant of the structure; `None` if
    neither (the plan is then not used)."""
    if out.dtype == np.bool_:
        return (None, out)
    flat = out.reshape(-1)
    for j, r in enumerate(ranges):
        if r is None or flat.size == 0:
            continue
        start, size = r
        inside = (flat >= start) & (flat < start + size)
        if not inside.any():
            continue
        if not inside.all():
            return None
        src = coded[j]
        if out.shape == src.shape and np.array_equal(out, src):
            return (j, None)
        if out.ndim == 0 or out.shape[1:] != src.shape[1:]:
            return None
        per_row = int(np.prod(src.shape[1:], dtype=np.int64))
        rows = (flat[:: max(per_row, 1)] - start).astype(np.int64) // max(per_row, 1)
        if rows.size != out.shape[0] or not np.array_equal(src[rows], out):
            return None
        return (j, rows)
    if flat.size and np.issubdtype(out.dtype, np.number):
        if np.any(np.abs(flat) >= _CODE_BASE):
            return None  # a constant that could be a code: do not guess
    return (None, out)
