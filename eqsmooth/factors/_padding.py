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
        return {
            name: _pad_rows(group, np.arange(counts[name]))
            for name, group in tree.items()
        }


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
