"""Incremental smoothing of a growing graph: GTSAM's `ISAM2` loop (add
factors and new variables, get the estimate back) as one compiled program
per update, with buffers that grow by doubling.

The graph lives in preallocated stacks (each factor stack and each variable
group has a capacity, its unused rows masked and its unused variables held
by a unit prior, as [`eqsmooth.solve.pad_graph`][] pads them, with dynamic
indices). An update writes the new rows and variables at the end of their
buffers inside the compiled program and solves the whole graph again from
the last estimate, so updates compile nothing new until a buffer is full;
then that buffer doubles (one new program, `log2` of the growth in all).
"""

import functools as ft
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Bool, Int, PyTree

from ..factors import (
    AbstractFactor,
    FactorGraph,
    MaskedNoise,
    per_row_fields,
    PriorFactor,
    Var,
    with_rows,
)
from ..factors._graph import group_count, Values
from ..factors._noise import take_leading
from ..factors._padding import _PaddingNoise, pad_graph, power_of_two
from ._nonlinear._gauss_newton import LevenbergMarquardt
from ._nonlinear._graph_solver import AbstractGraphSolver
from ._nonlinear._least_squares import least_squares
from ._solution import result_index, RESULTS


_SUCCESS = result_index(RESULTS.successful)


class IncrementalState(eqx.Module):
    """The state of an [`eqsmooth.solve.IncrementalSmoother`][].

    **Fields:**

    - `graph`: the graph in its buffers: the user's factor stacks, each
        padded to its capacity with dynamic indices and its unused rows
        masked, then one padding prior per variable group.
    - `values`: the estimate of every variable, padded to each group's
        capacity (unused slots copy variable 0).
    - `result`: the [`eqsmooth.solve.RESULTS`][] code of the last solve.
    - `num_rows`: the real rows of each factor stack (static, on the host).
    - `num_variables`: `{group: real variables}` as sorted pairs (static).
    - `row_leaves`: per factor stack, which of its array leaves are per-row.
    - `templates`: one row of each of init's stacks and one variable of each
        group, on the host: what an update writes to a buffer that gets
        nothing new (masked), so that every update runs one program.
    """

    graph: FactorGraph
    values: Values
    result: RESULTS
    num_rows: tuple[int, ...] = eqx.field(static=True)
    num_variables: tuple[tuple[str, int], ...] = eqx.field(static=True)
    row_leaves: tuple[tuple[bool, ...], ...] = eqx.field(static=True)
    templates: tuple = ()

    @property
    def capacity(self) -> tuple[tuple[int, ...], tuple[tuple[str, int], ...]]:
        """`(rows per factor stack, {group: variables})` the buffers hold."""
        stacks = tuple(f.num_rows for f in self.graph.factors[: len(self.num_rows)])
        groups = tuple(
            (name, group_count(name, self.values[name]))
            for name, _ in self.num_variables
        )
        return stacks, groups

    def estimate(self) -> dict[str, PyTree]:
        """The real variables' estimates, copied to the host (numpy leaves;
        host slicing compiles nothing)."""
        counts = dict(self.num_variables)
        return {
            name: jax.tree_util.tree_map(lambda a: np.asarray(a)[: counts[name]], group)
            for name, group in self.values.items()
        }


class IncrementalSmoother(eqx.Module):
    """Smoothing of a graph that grows: add factors and variables, get the
    estimate of everything after each update (GTSAM's `ISAM2` loop).

    `init` puts a first graph into buffers with room to grow; `update` adds
    new factor stacks (loop closures anywhere, any of the kinds `init` was
    given) and new variables, and solves the whole graph again, warm-started
    from the last estimate. Each update is one compiled program: the new
    rows and variables are written at the end of their buffers on the
    device, so a sequence of updates with the same kinds and row counts
    compiles once; a buffer that would overflow doubles first (a new
    program per capacity). The answer after each update is the batch
    solution of the graph so far (the solve runs to convergence; tested
    against [`eqsmooth.solve.least_squares`][] on the unpadded graph).
    `update_rows` takes an update's rows as arrays instead of factor
    objects: one `jax.jit` call per update and little Python around it
    (2.4-4x faster than `update` on GTSAM's Pose2ISAM2Example shape, where
    `update`'s factor objects and host blocks cost more than its solve).

    Unlike iSAM2 it relinearises and refactors the whole graph at every
    update (a dense Cholesky factorisation of the padded normal matrix, the
    solver dynamic indices take): `O(N³)` in the capacity's coordinates,
    which suits graphs of up to a few thousand coordinates; iSAM2's Bayes
    tree refactors only the cliques an update touches.

    **Arguments:**

    - `solver`: the graph solver of each update, by default
        [`eqsmooth.solve.LevenbergMarquardt`][] (its linear solver must take
        dynamic indices: the default, `DenseCholesky`, `PCG` or a lineax
        solver).
    - `max_steps`: the iteration limit of each update's solve.
    - `throw`: whether a failed solve raises (the default) or is reported in
        `state.result`.
    - `bucket`: the initial capacity of a stack or group from its size
        (default: the next power of two, at least 8); a full buffer doubles.
    """

    solver: AbstractGraphSolver = LevenbergMarquardt()
    max_steps: int = eqx.field(static=True, default=100)
    throw: bool = eqx.field(static=True, default=True)
    bucket: Callable[[int], int] = eqx.field(static=True, default=power_of_two)
    rows_per_update: int = eqx.field(static=True, default=4)

    def init(self, graph: FactorGraph, values: Values) -> IncrementalState:
        """Put `graph` (static indices) and its initial `values` into
        buffers and solve it.

        Every factor kind that later updates add must be in this graph (a
        stack of it, at least one row); the same holds for variable groups.
        """
        if not isinstance(graph, FactorGraph):
            raise TypeError(
                "IncrementalSmoother.init: graph must be a FactorGraph, got "
                f"{type(graph).__name__}"
            )
        padded = pad_graph(graph, values, self.bucket)
        n = len(graph.factors)
        flags = tuple(
            _row_leaves(padded.graph.factors[k], graph.factors[k]) for k in range(n)
        )
        templates = (
            tuple(_first_row(f) for f in graph.factors),
            {
                g: jax.tree_util.tree_map(lambda a: np.asarray(a)[:1], v)
                for g, v in values.items()
            },
        )
        state = IncrementalState(
            padded.graph,
            padded.values,
            RESULTS.successful,
            tuple(f.num_rows for f in graph.factors),
            padded.counts,
            flags,
            templates,
        )
        # The update's own program (every buffer gets a masked block), so
        # that the first update compiles nothing new.
        return self._advance(state, {}, {})

    def update(
        self,
        state: IncrementalState,
        new_factors: AbstractFactor | Sequence[AbstractFactor] = (),
        new_values: Values | None = None,
    ) -> IncrementalState:
        """Add factor stacks and variables, and solve the grown graph.

        **Arguments:**

        - `state`: from `init` or the previous `update`.
        - `new_factors`: factor stacks of kinds `init` was given (same
            factor type, noise type and variable groups), with static
            indices into the grown graph. Each goes to the first stack of
            `init`'s graph of its kind.
        - `new_values`: `{group: stacked initial values}` of the new
            variables, which take the next indices of their groups (GTSAM's
            new keys, numbered in order).

        **Returns:** the new state; `state.values` holds the estimate of
        every variable (padded), `state.estimate()` the real ones on the
        host.
        """
        who = "IncrementalSmoother.update"
        if not isinstance(state, IncrementalState):
            raise TypeError(f"{who}: state must be an IncrementalState from init")
        if isinstance(new_factors, AbstractFactor):
            new_factors = (new_factors,)
        new_factors = tuple(new_factors)
        new_values = dict(new_values or {})
        counts, grown = _grown_counts(who, state, new_values)
        kinds = [_kind(f) for f in state.graph.factors[: len(state.num_rows)]]
        by_stack: dict[int, list[AbstractFactor]] = {}
        for j, f in enumerate(new_factors):
            if not isinstance(f, AbstractFactor):
                raise TypeError(
                    f"{who}: new_factors[{j}] must be an AbstractFactor stack, got "
                    f"{type(f).__name__}"
                )
            name = f"new_factors[{j}] ({type(f).__name__})"
            if _kind(f) not in kinds:
                raise ValueError(
                    f"{who}: {name} with noise {type(f.noise).__name__} on groups "
                    f"{[v.group for v in f.variables]} is of no kind init's graph "
                    "has; give init a stack of every kind the updates add"
                )
            if f.num_rows == 0:
                continue
            for k, v in enumerate(f.variables):
                if v.is_dynamic:
                    raise ValueError(f"{who}: {name} has dynamic indices; give ids")
                ids = v.ids
                if ids.max() >= grown[v.group]:
                    raise ValueError(
                        f"{who}: {name} variable {k} (group {v.group!r}) refers to "
                        f"index {int(ids.max())}, but the group has {grown[v.group]} "
                        "variables after this update (give new variables in "
                        "new_values)"
                    )
            by_stack.setdefault(kinds.index(_kind(f)), []).append(f)
        return self._advance(state, by_stack, new_values)

    def update_rows(
        self,
        state: IncrementalState,
        rows: Sequence[dict[str, PyTree[ArrayLike]] | None],
        ids: Sequence[Sequence[Int[ArrayLike, " k"]] | None],
        active: Sequence[Bool[ArrayLike, " k"] | None] | None = None,
        new_values: Values | None = None,
    ) -> IncrementalState:
        """`update` with the new rows as arrays: one compiled call per update,
        no factor objects built.

        The new rows of each of `init`'s stacks are that stack's first row
        with its per-row data replaced by these arrays, so their noise and
        shared fields are `init`'s (a row with other noise takes `update`).
        A sequence of updates whose arrays keep their shapes runs one
        compiled program until a buffer doubles; give a fixed number of rows
        per stack and mask the absent ones with `active` (e.g. room for one
        loop closure every update). On the same rows it gives `update`'s
        estimates (tested to 1e-10). Shapes, dtypes and fields are checked
        when the program is traced (a new shape traces again), the indices
        on the host: give them as NumPy arrays (JAX arrays are read back).

        **Arguments:**

        - `state`: from `init` or the previous update.
        - `rows`: one entry per stack of `init`'s graph, in order: `None`
            (nothing new) or a dict `{field: value with a leading axis of k
            rows}` of that stack's per-row fields as
            [`eqsmooth.factors.per_row_fields`][] gives them (e.g.
            `{"measured": SE2}` for a `BetweenFactor`); a field left out
            copies the stack's first row.
        - `ids`: per stack, `None` or one `(k,)` integer array per variable
            of the factor (static indices into the grown graph, as `Var`'s
            `ids`).
        - `active`: `None` (every row counts) or, per stack, `None` or a
            `(k,)` boolean array, false for a row that adds nothing (its data
            must still be finite; a masked row at the end of the block frees
            its slot for the next update when the mask is a NumPy array).
        - `new_values`: `{group: stacked initial values}` of the new
            variables, which take the next indices of their groups.

        **Returns:** the new state, as `update` returns it. With
        `throw=True` a failed solve raises after the call (the result code
        is read back, which waits for the solve); with `throw=False` nothing
        is read and `state.result` says.
        """
        who = "IncrementalSmoother.update_rows"
        if not isinstance(state, IncrementalState):
            raise TypeError(f"{who}: state must be an IncrementalState from init")
        n = len(state.num_rows)
        if active is None:
            active = (None,) * n
        for name, arg in (("rows", rows), ("ids", ids), ("active", active)):
            if not isinstance(arg, (tuple, list)) or len(arg) != n:
                raise TypeError(
                    f"{who}: {name} must be a sequence of one entry per stack of "
                    f"init's graph ({n}), got {type(arg).__name__}"
                    + (f" of {len(arg)}" if isinstance(arg, (tuple, list)) else "")
                )
        new_values = new_values or {}
        counts, grown = _grown_counts(who, state, new_values)
        factors = state.graph.factors
        blocks, used, ends, offsets = [], list(state.num_rows), [], []
        for s in range(n):
            offsets.append(used[s])
            if rows[s] is None:
                if ids[s] is not None or active[s] is not None:
                    raise ValueError(
                        f"{who}: stack {s} has ids or active but no rows (give "
                        "rows[s], or None in all three)"
                    )
                blocks.append(None)
                ends.append(used[s])
                continue
            block, k, advance = _host_rows(
                who, s, factors[s], rows[s], ids[s], active[s], grown
            )
            blocks.append(block)
            ends.append(used[s] + k)
            used[s] += advance
        for g in sorted(counts):
            offsets.append(counts[g])
        real = [*used, *(grown[g] for g in sorted(counts))]
        value_ends = dict(grown)
        state = self._grown(state, ends, value_ends, real)
        graph, values, result = _rows_step(
            self.solver,
            state.graph,
            state.values,
            tuple(blocks),
            {g: new_values[g] for g in sorted(new_values)},
            np.asarray(offsets, np.int32),
            max_steps=self.max_steps,
            row_leaves=state.row_leaves,
        )
        if self.throw:
            if _is_traced(jax.tree_util.tree_leaves(result)):  # a caller's jit/grad
                values = result.error_if(values, result != RESULTS.successful)
            elif np.asarray(result_index(result)) != _SUCCESS:
                raise eqx.EquinoxRuntimeError(f"{who}: {RESULTS[result]}")
        return IncrementalState(
            graph,
            values,
            result,
            tuple(used),
            tuple(sorted(grown.items())),
            state.row_leaves,
            state.templates,
        )

    def _advance(self, state, by_stack, new_values) -> IncrementalState:
        """Write each stack's new rows and each group's new variables as one
        block padded to a bucket (at least `rows_per_update`; a masked
        template block where nothing is new), built on the host, and solve:
        the compiled update depends on the blocks' sizes only."""
        counts = dict(state.num_variables)
        templates, value_templates = state.templates
        rows, ends = list(state.num_rows), list(state.num_rows)
        blocks, offsets = [], []
        for s_ in range(len(rows)):
            fs = by_stack.get(s_)
            k = sum(f.num_rows for f in fs) if fs else 0
            size = self._block(k)
            block, active = _block(fs or [templates[s_]], size)
            blocks.append((block, active if fs else jnp.zeros_like(active)))
            offsets.append(rows[s_])
            rows[s_] += k
            ends[s_] = offsets[-1] + size
        value_blocks, value_ends, grown = {}, {}, {}
        for g in sorted(counts):
            m = group_count(g, new_values[g]) if g in new_values else 0
            size = self._block(m)
            value_blocks[g] = _value_block(
                new_values.get(g, value_templates[g]), m, size
            )
            value_ends[g] = counts[g] + size
            grown[g] = counts[g] + m
            offsets.append(counts[g])
        state = self._grown(state, ends, value_ends, [*rows, *grown.values()])
        graph, values, result = _step(
            self,
            state.graph,
            state.values,
            tuple(blocks),
            value_blocks,
            jax.device_put(np.asarray(offsets, np.int32)),
            tuple(range(len(rows))),
            state.row_leaves,
        )
        return IncrementalState(
            graph,
            values,
            result,
            tuple(rows),
            tuple(sorted(grown.items())),
            state.row_leaves,
            state.templates,
        )

    def _block(self, k: int) -> int:
        return max(self.rows_per_update, 1 << max(0, (k - 1).bit_length()))

    def _grown(self, state, rows, grown, real) -> IncrementalState:
        """`state` with every buffer that `rows`/`grown` overflow doubled;
        when one grows, so does every factor stack more than half full and
        every variable group more than three quarters full (they tend to
        fill together), so that a growth costs one compile, not one per
        buffer. Groups wait longer: their capacity sets the dense
        factorisation's size (`O(N³)` in every update), a stack's only a
        linear cost. Built on the host (numpy), so growing compiles nothing
        but the next update's program."""
        (stacks, groups), n = state.capacity, len(state.num_rows)
        needed = [*rows, *(grown[g] for g in sorted(dict(groups)))]
        have = [*stacks, *(c for _, c in groups)]
        if all(a <= c for a, c in zip(needed, have)):
            return state
        full = [2] * n + [4 / 3] * len(groups)  # co-grow above 1/2 and 3/4
        sizes = [
            _doubled(c, a) if a > c else (2 * c if f * r > c else c)
            for a, c, r, f in zip(needed, have, real, full)
        ]
        factors = list(state.graph.factors)
        values = dict(state.values)
        for s in range(n):
            if sizes[s] != have[s]:
                factors[s] = _host_grown(factors[s], state.row_leaves[s], sizes[s])
        for k, name in enumerate(sorted(values)):
            size, c = sizes[n + k], have[n + k]
            if size == c:
                continue
            values[name] = jax.tree_util.tree_map(
                lambda a: _rows_of([np.asarray(a)], size), values[name]
            )
            active = np.concatenate(
                [np.asarray(factors[n + k].noise.active), np.ones(size - c, bool)]
            )
            factors[n + k] = PriorFactor(
                Var(name, np.arange(size)),
                values[name],
                _PaddingNoise(jax.device_put(active)),
            )
        return IncrementalState(
            FactorGraph(factors),
            values,
            state.result,
            state.num_rows,
            state.num_variables,
            state.row_leaves,
            state.templates,
        )


def _host_grown(f: AbstractFactor, per_row: tuple[bool, ...], size: int):
    """Buffer stack `f` grown to `size` rows on the host: per-row leaves
    padded with copies of row 0, except the row mask (the one boolean per-row
    leaf), padded with False."""
    arrays, rest = eqx.partition(f, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    out = []
    for a, r in zip(leaves, per_row):
        if r:
            a = np.asarray(a)
            fill = (
                np.zeros((size - a.shape[0], *a.shape[1:]), bool)
                if a.dtype == np.bool_
                else np.broadcast_to(a[:1], (size - a.shape[0], *a.shape[1:]))
            )
            a = jax.device_put(np.concatenate([a, fill]))
        out.append(a)
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, out), rest)


def _kind(f: AbstractFactor) -> tuple:
    noise = f.noise
    while isinstance(noise, MaskedNoise):
        noise = noise.base
    return (type(f), type(noise), tuple(v.group for v in f.variables))


def _doubled(capacity: int, needed: int) -> int:
    while capacity < needed:
        capacity *= 2
    return capacity


def _index(n: int, size: int) -> np.ndarray:
    """`0 … n−1`, then copies of row 0 up to `size`."""
    return np.concatenate([np.arange(n), np.zeros(size - n, np.int64)])


def _take(f: AbstractFactor, n: int, size: int) -> AbstractFactor:
    """Stack `f` (`n` rows) grown to `size` rows: new rows copy row 0 and
    are masked out."""
    index = _index(n, size)
    new = with_rows(
        f,
        {
            k: jax.tree_util.tree_map(lambda a: take_leading(a, index), v)
            for k, v in per_row_fields(f).items()
        },
    )
    variables = tuple(Var.dynamic(v.group, v.index[index]) for v in f.variables)
    object.__setattr__(new, "variables", variables)
    noise = f.noise.take_rows(index).mask_rows(np.arange(size) < n)
    object.__setattr__(new, "noise", noise)
    return new


def _row_leaves(buffer: AbstractFactor, original: AbstractFactor) -> tuple[bool, ...]:
    """Which array leaves of a buffer stack have one entry per row: those
    whose length changes when the stack is padded one row further."""
    n = buffer.num_rows
    more = jax.eval_shape(lambda: _take(buffer, n, n + 1))
    a = jax.tree_util.tree_leaves(eqx.filter(buffer, eqx.is_array))
    b = jax.tree_util.tree_leaves(
        eqx.filter(more, lambda x: isinstance(x, jax.ShapeDtypeStruct))
    )
    if len(a) != len(b):
        raise TypeError(
            f"IncrementalSmoother.init: {type(original).__name__}'s stack changes "
            "structure when it grows; its noise cannot be padded"
        )
    return tuple(x.shape != y.shape for x, y in zip(a, b))


# One compiled program per update: write the new rows and variables into the
# buffers, then solve the whole graph from the last estimate.
@eqx.filter_jit
def _step(smoother, graph, values, blocks, value_blocks, offsets, targets, flags):
    graph, values = _write(graph, values, blocks, value_blocks, offsets, targets, flags)
    sol = least_squares(
        graph,
        values,
        smoother.solver,
        max_steps=smoother.max_steps,
        throw=smoother.throw,
    )
    return graph, sol.value, sol.result


def _write(graph, values, blocks, value_blocks, offsets, targets, row_leaves):
    """The grown graph and values: each block of new rows written into its
    target stack at its offset (its padding rows masked), each group's new
    variables at the end of the group (the real ones released from the
    padding prior)."""
    factors = list(graph.factors)
    n = len(row_leaves)
    for j, ((f, active), s) in enumerate(zip(blocks, targets)):
        k = f.num_rows
        padded = _take(f, k, k)  # the buffer's form: masked noise
        padded = eqx.tree_at(lambda p: p.noise, padded, padded.noise.mask_rows(active))
        buf = factors[s]
        treedef = jax.tree_util.tree_structure(eqx.filter(buf, eqx.is_array))
        new_leaves, new_def = jax.tree_util.tree_flatten(
            eqx.filter(padded, eqx.is_array)
        )
        if new_def != treedef:
            raise TypeError(
                f"IncrementalSmoother.update: the new {type(f).__name__} rows differ "
                f"in structure from init's stack {s} (fields or noise parameters "
                "of another form)"
            )
        factors[s] = _write_rows(buf, new_leaves, row_leaves[s], offsets[j])
    values = dict(values)
    base = len(blocks)
    for k, name in enumerate(sorted(values)):
        if name not in value_blocks:
            continue
        start = offsets[base + k]
        new, real = value_blocks[name]
        values[name] = jax.tree_util.tree_map(
            lambda a, b: jax.lax.dynamic_update_slice_in_dim(
                a, jnp.asarray(b, a.dtype), start, 0
            ),
            values[name],
            new,
        )
        prior = factors[n + k]
        held = jax.lax.dynamic_slice_in_dim(prior.noise.active, start, real.shape[0])
        active = jax.lax.dynamic_update_slice_in_dim(
            prior.noise.active, held & ~real, start, 0
        )
        factors[n + k] = eqx.tree_at(
            lambda p: (p.noise, p.value), prior, (_PaddingNoise(active), values[name])
        )
    return FactorGraph(factors), values


def _is_traced(leaves) -> bool:
    return any(isinstance(a, jax.core.Tracer) for a in leaves)


def _rows_of(arrays: list, size: int):
    """Arrays with a leading row axis, concatenated and padded to `size` rows
    with copies of the first: on the host (numpy, then one transfer: no
    compile) unless traced (a caller's `grad` or `jit`)."""
    if _is_traced(arrays):
        a = jnp.concatenate([jnp.asarray(x) for x in arrays])
        fill = jnp.broadcast_to(a[:1], (size - a.shape[0], *a.shape[1:]))
        return jnp.concatenate([a, fill])
    a = np.concatenate([np.asarray(x) for x in arrays])
    fill = np.broadcast_to(a[:1], (size - a.shape[0], *a.shape[1:]))
    return jax.device_put(np.concatenate([a, fill]))


_NOISE_ROWS: dict = {}


def _noise_row_leaves(noise, k: int) -> tuple[bool, ...]:
    """Which array leaves of a stack's noise have one entry per row (their
    length changes when the rows are taken one more time)."""
    leaves, treedef = jax.tree_util.tree_flatten(eqx.filter(noise, eqx.is_array))
    key = (treedef, k, tuple((a.shape, a.dtype) for a in leaves))
    if key not in _NOISE_ROWS:
        more = jax.eval_shape(lambda n: n.take_rows(np.zeros(k + 1, np.int64)), noise)
        shapes = [
            a.shape
            for a in jax.tree_util.tree_leaves(
                eqx.filter(more, lambda x: isinstance(x, jax.ShapeDtypeStruct))
            )
        ]
        _NOISE_ROWS[key] = tuple(a.shape != b for a, b in zip(leaves, shapes))
    return _NOISE_ROWS[key]


def _block(fs: list[AbstractFactor], size: int):
    """The rows of the stacks `fs` (one kind) as one stack of `size` rows with
    dynamic indices, padded with copies of the first row, and the `(size,)`
    mask of the real rows."""
    first = fs[0]
    k = sum(f.num_rows for f in fs)
    fields = {
        name: jax.tree_util.tree_map(
            lambda *a: _rows_of(list(a), size), *(per_row_fields(f)[name] for f in fs)
        )
        for name in per_row_fields(first)
    }
    block = with_rows(first, fields)
    variables = tuple(
        Var.dynamic(v.group, _rows_of([f.variables[i].ids for f in fs], size))
        for i, v in enumerate(first.variables)
    )
    object.__setattr__(block, "variables", variables)
    arrays, rest = eqx.partition(first.noise, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    per_row = _noise_row_leaves(first.noise, first.num_rows)
    per_factor = [
        jax.tree_util.tree_leaves(eqx.filter(f.noise, eqx.is_array)) for f in fs
    ]
    out = [
        _rows_of([p[i] for p in per_factor], size) if per_row[i] else leaves[i]
        for i in range(len(leaves))
    ]
    noise = eqx.combine(jax.tree_util.tree_unflatten(treedef, out), rest)
    object.__setattr__(block, "noise", noise)
    return block, jax.device_put(np.arange(size) < k)


def _first_row(f: AbstractFactor) -> AbstractFactor:
    """Row 0 of a stack, built on the host (no compile)."""
    first = with_rows(
        f,
        {
            k: jax.tree_util.tree_map(lambda a: jax.device_put(np.asarray(a)[:1]), v)
            for k, v in per_row_fields(f).items()
        },
    )
    object.__setattr__(
        first, "variables", tuple(Var(v.group, v.ids[:1]) for v in f.variables)
    )
    arrays, rest = eqx.partition(f.noise, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    per_row = _noise_row_leaves(f.noise, f.num_rows)
    leaves = [
        jax.device_put(np.asarray(a)[:1]) if r else a for a, r in zip(leaves, per_row)
    ]
    object.__setattr__(
        first, "noise", eqx.combine(jax.tree_util.tree_unflatten(treedef, leaves), rest)
    )
    return first


def _value_block(group: PyTree, m: int, size: int):
    """New variables padded to `size` with copies of the first, and the mask
    of the real ones."""
    padded = jax.tree_util.tree_map(lambda a: _rows_of([a], size), group)
    return padded, jax.device_put(np.arange(size) < m)


def _host_rows(who, s, buffer, rows, ids, active, grown):
    """Stack `s`'s new rows checked on the host (cheap: lengths, index
    bounds), as the compiled update takes them: `((rows, ids, active), k,
    rows to advance)`."""
    name = f"stack {s} ({type(buffer).__name__})"
    if not isinstance(rows, dict):
        raise TypeError(
            f"{who}: rows[{s}] for {name} must be a dict of per-row fields, got "
            f"{type(rows).__name__}"
        )
    variables = buffer.variables
    if not isinstance(ids, (tuple, list)) or len(ids) != len(variables):
        raise TypeError(
            f"{who}: ids[{s}] for {name} must be a sequence of {len(variables)} "
            "index arrays (one per variable of the factor)"
        )
    k = None
    checked = []
    for i, (v, a) in enumerate(zip(variables, ids)):
        if isinstance(a, jax.core.Tracer):
            shape = a.shape
        else:
            a = np.asarray(a)
            shape = a.shape
            if not np.issubdtype(a.dtype, np.integer):
                raise TypeError(
                    f"{who}: ids[{s}][{i}] for {name} must be integers, got "
                    f"dtype {a.dtype}"
                )
            if a.size and (a.min() < 0 or a.max() >= grown[v.group]):
                bad = int(a.max()) if a.max() >= grown[v.group] else int(a.min())
                raise ValueError(
                    f"{who}: {name} variable {i} (group {v.group!r}) refers to "
                    f"index {bad}, but the group has {grown[v.group]} variables "
                    "after this update (give new variables in new_values)"
                )
        if len(shape) != 1 or (k is not None and shape[0] != k):
            raise ValueError(
                f"{who}: ids[{s}][{i}] for {name} has shape {shape}; every index "
                f"array of a stack must be 1-D of the same length"
                + (f" ({k})" if k is not None else "")
            )
        k = shape[0]
        checked.append(a)
    advance = k
    if active is not None:
        shape = np.shape(active)
        if shape != (k,):
            raise ValueError(
                f"{who}: active[{s}] for {name} has shape {shape}, expected ({k},)"
            )
        if isinstance(active, np.ndarray):
            # Masked rows at the end of the block: the next update writes
            # over them (they count for nothing until then).
            on = np.flatnonzero(active)
            advance = int(on[-1]) + 1 if on.size else 0
    return (rows, tuple(checked), active), k, advance


def _set_active(noise, active):
    """`noise` (a buffer stack's: a `MaskedNoise`, perhaps inside a robust
    kernel) with its row mask replaced by `active`."""
    if isinstance(noise, MaskedNoise):
        return eqx.tree_at(lambda m: m.active, noise, active)
    return eqx.tree_at(lambda m: m.base, noise, _set_active(noise.base, active))


# The arrays-in update: one `jax.jit` program (its static arguments hashed
# by the C++ dispatch; every other leaf an array), which writes the rows and
# variables into the buffers and solves, without error checks inside (the
# result code is returned; `throw` is applied on the host after the call).
@ft.partial(jax.jit, static_argnames=("max_steps", "row_leaves"))
def _rows_step(
    solver, graph, values, blocks, new_values, offsets, *, max_steps, row_leaves
):
    who = "IncrementalSmoother.update_rows"
    factors = list(graph.factors)
    for s, block in enumerate(blocks):
        if block is None:
            continue
        rows, ids, active = block
        buf = factors[s]
        name = f"stack {s} ({type(buf).__name__})"
        k = ids[0].shape[0]
        template = _take(buf, 1, k)  # k copies of the stack's first row
        fields = per_row_fields(template)
        unknown = sorted(set(rows) - set(fields))
        if unknown:
            raise ValueError(
                f"{who}: rows[{s}] for {name} has field {unknown[0]!r}; its per-row "
                f"fields are {sorted(fields)}"
            )
        for field, value in rows.items():
            ref = fields[field]
            a, ta = jax.tree_util.tree_flatten(value)
            b, tb = jax.tree_util.tree_flatten(ref)
            if ta != tb:
                raise TypeError(
                    f"{who}: rows[{s}][{field!r}] for {name} is {ta}, the stack's "
                    f"field is {tb}"
                )
            for x, y in zip(a, b):
                if jnp.shape(x) != y.shape:
                    raise ValueError(
                        f"{who}: rows[{s}][{field!r}] for {name} has shape "
                        f"{jnp.shape(x)}, expected {y.shape} ({k} rows, as ids)"
                    )
            fields[field] = jax.tree_util.tree_map(
                lambda x, y: jnp.asarray(x, y.dtype), value, ref
            )
        new = with_rows(template, fields)
        variables = tuple(
            Var.dynamic(v.group, jnp.asarray(i, v.index.dtype))
            for v, i in zip(buf.variables, ids)
        )
        object.__setattr__(new, "variables", variables)
        mask = jnp.ones(k, bool) if active is None else jnp.asarray(active, bool)
        object.__setattr__(new, "noise", _set_active(new.noise, mask))
        new_leaves = jax.tree_util.tree_leaves(eqx.filter(new, eqx.is_array))
        factors[s] = _write_rows(buf, new_leaves, row_leaves[s], offsets[s])
    values = dict(values)
    n = len(blocks)
    for g, name in enumerate(sorted(values)):
        if name not in new_values:
            continue
        start = offsets[n + g]
        a, ta = jax.tree_util.tree_flatten(new_values[name])
        b, tb = jax.tree_util.tree_flatten(values[name])
        if ta != tb or any(jnp.shape(x)[1:] != y.shape[1:] for x, y in zip(a, b)):
            raise ValueError(
                f"{who}: new_values[{name!r}] has leaves "
                f"{[jnp.shape(x) for x in a]} ({ta}); the group's values have "
                f"{[y.shape[1:] for y in b]} after the leading axis ({tb})"
            )
        m = jnp.shape(a[0])[0]
        values[name] = jax.tree_util.tree_map(
            lambda x, y: jax.lax.dynamic_update_slice_in_dim(
                y, jnp.asarray(x, y.dtype), start, 0
            ),
            new_values[name],
            values[name],
        )
        prior = factors[n + g]
        held = jax.lax.dynamic_update_slice_in_dim(
            prior.noise.active, jnp.zeros(m, bool), start, 0
        )
        factors[n + g] = eqx.tree_at(
            lambda p: (p.noise, p.value), prior, (_PaddingNoise(held), values[name])
        )
    sol = least_squares(
        FactorGraph(factors), values, solver, max_steps=max_steps, throw=False
    )
    return FactorGraph(factors), sol.value, sol.result


def _grown_counts(
    who: str, state: IncrementalState, new_values: dict
) -> tuple[dict[str, int], dict[str, int]]:
    """`({group: variables before}, {group: variables after})` of an update
    adding `new_values`; a group that init's graph lacks is refused."""
    counts = dict(state.num_variables)
    unknown = sorted(set(new_values) - set(counts))
    if unknown:
        raise ValueError(
            f"{who}: new_values has group {unknown[0]!r}, which init's graph "
            f"does not have (groups: {sorted(counts)})"
        )
    added = {g: group_count(g, v) for g, v in new_values.items()}
    return counts, {g: counts[g] + added.get(g, 0) for g in counts}


def _write_rows(buf, new_leaves, per_row, offset):
    """The factor stack `buf` with the per-row array leaves of new rows
    (`new_leaves`, in `buf`'s array-leaf order) written at row `offset`."""
    arrays, rest = eqx.partition(buf, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(arrays)
    out = [
        jax.lax.dynamic_update_slice_in_dim(
            leaf, jnp.asarray(new, leaf.dtype), offset, 0
        )
        if row
        else leaf
        for leaf, new, row in zip(leaves, new_leaves, per_row)
    ]
    return eqx.combine(jax.tree_util.tree_unflatten(treedef, out), rest)
