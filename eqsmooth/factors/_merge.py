"""Stacking factors that were built one at a time (a port of GTSAM code that
calls `graph.add` per edge) into one stack per kind of factor."""

import dataclasses
import warnings
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._factor import _is_per_row, AbstractFactor, check_row_leaves
from ._noise import AbstractNoiseModel
from ._variables import Var


MANY_STACKS = 64
"""`FactorGraph` warns when it is given more stacks than this, most of them
mergeable kinds: each stack is traced and compiled as its own piece of the
program, so a graph of hundreds of one-row stacks compiles for minutes."""


def merge_stacks(factors: Sequence[AbstractFactor]) -> tuple[AbstractFactor, ...]:
    """Stack factors of the same kind into one stack each.

    A graph built as GTSAM's is, one factor object per measurement, has as
    many stacks as factors, and the program that solves it grows with the
    number of stacks (each is linearised by its own code). This puts the
    rows of every set of compatible stacks into one stack, at the place of
    the first of them, rows in the order given: the cost, the solution and
    every derivative are those of the unmerged graph, only the program is
    smaller.

    Two stacks are compatible when they are of the same class, touch the
    same variable groups through static indices ([`eqsmooth.factors.Var`][],
    not `Var.dynamic`), have equal static fields and shared fields (the same
    array object, or equal concrete values), per-row fields of the same
    structure, and noise models of the same kind whose shared parameters are
    equal (per-row noise parameters and masks are concatenated). Anything
    else stays a stack of its own. A stack's position in the graph is what
    [`eqsmooth.solve.IncrementalSmoother`][]'s `update_rows` and the
    padding plans refer to, so merge before you hand a graph to them.

    **Arguments:**

    - `factors`: factor stacks, e.g. a list filled one factor per call.

    **Returns:** a tuple of factor stacks, for
    [`eqsmooth.factors.FactorGraph`][].

    ```python
    edges = [eqs.BetweenFactor(eqs.Var("x", [i]), eqs.Var("x", [j]), m, noise)
             for i, j, m in measurements]       # one object per edge
    graph = eqs.FactorGraph(eqs.factors.merge_stacks([prior, *edges]))
    ```
    """
    buckets: dict[tuple, list[list[AbstractFactor]]] = {}
    order: list[list[AbstractFactor]] = []
    rows: dict[int, list[bool] | None] = {}  # per noise object, probed once
    for position, factor in enumerate(factors):
        if not isinstance(factor, AbstractFactor):
            raise TypeError(
                f"merge_stacks: factors[{position}] is of type "
                f"{type(factor).__name__}, not an eqsmooth.factors.AbstractFactor"
            )
        key = _key(factor)
        for members in buckets.get(key, []) if key is not None else []:
            if _compatible(members[0], factor, rows):
                members.append(factor)
                break
        else:
            members = [factor]
            order.append(members)
            if key is not None:
                buckets.setdefault(key, []).append(members)
    return tuple(_concatenate(m, rows) if len(m) > 1 else m[0] for m in order)


def warn_if_unstacked(factors: tuple[AbstractFactor, ...]) -> None:
    """Warn (once per call site) when a graph has many stacks that
    `merge_stacks` would join: a cheap count by class and groups."""
    if len(factors) <= MANY_STACKS:
        return
    kinds = {_key(f) for f in factors} - {None}
    if len(factors) - len(kinds) > MANY_STACKS // 2:
        warnings.warn(
            f"FactorGraph: {len(factors)} factor stacks of {len(kinds)} kinds. "
            "Each stack is linearised by its own code, so the compiled solve "
            "grows with their number; stack the rows of each kind (one "
            "factor with index arrays, or eqsmooth.factors.merge_stacks("
            "factors) for factors built one at a time)",
            stacklevel=3,
        )


def _key(factor: AbstractFactor) -> tuple | None:
    """A cheap bucket key, `None` for a stack that never merges."""
    if any(v.is_dynamic for v in factor.variables):
        return None
    return (type(factor), tuple(v.group for v in factor.variables))


def _same(a, b) -> bool:
    """Equal leaves: the same object, or equal concrete values."""
    if a is b:
        return True
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return False
    if eqx.is_array_like(a) and eqx.is_array_like(b):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and bool(np.all(a == b))
    try:
        return bool(a == b)
    except Exception:  # an object without a usable equality: not merged
        return False


def _same_tree(a, b) -> bool:
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    return ta == tb and all(_same(x, y) for x, y in zip(la, lb))


def _rows_alike(a, b) -> bool:
    """Per-row leaves of one structure, trailing shapes and dtypes equal."""
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    if ta != tb:
        return False
    for x, y in zip(la, lb):
        if not (eqx.is_array(x) and eqx.is_array(y)):
            if not _same(x, y):
                return False
        elif x.shape[1:] != y.shape[1:] or x.dtype != y.dtype:
            return False
    return True


def _noise_rows(noise: AbstractNoiseModel, cache: dict) -> list[bool] | None:
    """Which leaves of `noise` are per row (indexed by `take_rows`); `None`
    if taking rows changes the model's structure. Kept in `cache` by object,
    as a stack's noise is compared with every candidate."""
    if id(noise) in cache:
        return cache[id(noise)]
    tree = jax.tree_util.tree_structure(noise)
    one, tree1 = jax.tree_util.tree_flatten(noise.take_rows(np.zeros(1, np.int32)))
    two, tree2 = jax.tree_util.tree_flatten(noise.take_rows(np.zeros(2, np.int32)))
    rows = None
    if tree == tree1 == tree2:
        rows = [jnp.shape(x) != jnp.shape(y) for x, y in zip(one, two)]
    cache[id(noise)] = rows
    return rows


def _noise_compatible(a: AbstractNoiseModel, b: AbstractNoiseModel, cache) -> bool:
    if type(a) is not type(b):
        return False
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    rows = _noise_rows(a, cache)
    if ta != tb or rows is None or rows != _noise_rows(b, cache):
        return False
    for x, y, per_row in zip(la, lb, rows):
        if per_row:
            if jnp.shape(x)[1:] != jnp.shape(y)[1:] or jnp.result_type(
                x
            ) != jnp.result_type(y):
                return False
        elif not _same(x, y):
            return False
    return True


def _compatible(a: AbstractFactor, b: AbstractFactor, cache: dict) -> bool:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "variables":
            continue  # groups compared by the key
        if f.name == "noise":
            if not _noise_compatible(x, y, cache):
                return False
        elif _is_per_row(f):
            if not _rows_alike(x, y):
                return False
        elif not _same_tree(x, y):
            return False
    return True


def _join(leaves: list):
    """Concatenate along the row axis, on the host while every part is."""
    if all(isinstance(x, np.ndarray) for x in leaves):
        return np.concatenate(leaves)
    return jnp.concatenate([jnp.asarray(x) for x in leaves])


def _concatenate(members: list[AbstractFactor], cache: dict) -> AbstractFactor:
    first = members[0]
    merged = object.__new__(type(first))
    for f in dataclasses.fields(first):
        value = getattr(first, f.name)
        if f.name == "variables":
            value = tuple(
                Var(v.group, np.concatenate([m.variables[k].ids for m in members]))
                for k, v in enumerate(value)
            )
        elif f.name == "noise":
            rows = _noise_rows(value, cache)
            parts = [jax.tree_util.tree_leaves(m.noise) for m in members]
            tree = jax.tree_util.tree_structure(value)
            value = jax.tree_util.tree_unflatten(
                tree,
                [
                    _join([p[i] for p in parts]) if per_row else parts[0][i]
                    for i, per_row in enumerate(rows or [])
                ],
            )
        elif _is_per_row(f):
            value = jax.tree_util.tree_map(
                lambda *xs: _join(list(xs)) if eqx.is_array(xs[0]) else xs[0],
                *[getattr(m, f.name) for m in members],
            )
        object.__setattr__(merged, f.name, value)
    check_row_leaves(merged)
    return merged
