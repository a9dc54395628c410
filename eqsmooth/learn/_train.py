"""A small, resumable training loop on optax."""

import contextlib
import json
import math
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh
from jaxtyping import Array, Float, PRNGKeyArray, PyTree
from tqdm.auto import tqdm

from ._checkpoint import (
    atomic_write,
    CheckpointError,
    CheckpointMismatch,
    load_checkpoint,
    previous_checkpoint,
    read_checkpoint_header,
    save_checkpoint,
    TrainState,
)
from ._sharding import (
    batch_sharding,
    replicate,
    replicated_sharding,
    shard_batch,
)
from ._train_options import Checkpoints, Logging, Validation


def _split_loss(out, has_aux: bool):
    if has_aux:
        if not (isinstance(out, tuple) and len(out) == 2):
            raise TypeError(
                "with has_aux=True the loss function must return (loss, aux_dict)"
            )
        loss, aux = out
    else:
        loss, aux = out, {}
    # Checked at trace time, before `grad` would say it in its own words.
    shape, dtype = jnp.shape(loss), jnp.result_type(loss)
    if shape != () or not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            "the loss function must return a floating-point scalar"
            + (" (as the first element of (loss, aux_dict))" if has_aux else "")
            + f"; got shape {shape} and dtype {dtype} (reduce it with jnp.mean, "
            "and compute it from floating-point arrays)"
        )
    return loss, aux


def _global_norm(tree) -> Float[Array, ""]:
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.sqrt(sum(jnp.sum(jnp.square(x)) for x in leaves))


def make_train_step(
    loss_fn: Callable[..., Any],
    optimizer: optax.GradientTransformation,
    *,
    has_aux: bool = False,
    filter_spec: Any = eqx.is_inexact_array,
    mesh: Mesh | None = None,
) -> Callable[[PyTree, PyTree, PyTree], tuple[PyTree, PyTree, dict]]:
    """One jitted optimiser step: `step(model, opt_state, batch)`.

    Differentiates `loss_fn(model, batch)` with respect to the leaves of
    `model` selected by `filter_spec` and applies `optimizer`. With a `mesh`,
    the batch is constrained to be split along its leading axis over the
    mesh's devices and the model and optimiser state to be replicated, so XLA
    computes each device's share of the batch locally and all-reduces the
    gradients (data parallelism; with one device nothing changes).

    **Arguments:**

    - `loss_fn`: `loss_fn(model, batch) -> scalar`, or `-> (scalar, aux)` with
        `has_aux=True`, `aux` a dict of scalar metrics. It should average over
        the batch (e.g. `jnp.mean(jax.vmap(per_example)(batch))`).
    - `optimizer`: an `optax.GradientTransformation`; initialise its state
        with `optimizer.init(eqx.filter(model, filter_spec))`.
    - `has_aux`: whether `loss_fn` returns auxiliary metrics.
    - `filter_spec`: which leaves are trained (an `eqx.partition` filter);
        default every inexact array.
    - `mesh`: a mesh from [`eqsmooth.learn.make_mesh`][], or `None`.

    **Returns:** a function `step(model, opt_state, batch) -> (model,
    opt_state, metrics)` with `metrics` a dict holding `loss`, `grad_norm` and
    the aux metrics.
    """

    def step(model, opt_state, batch):
        if mesh is not None:
            batch = eqx.filter_shard(batch, batch_sharding(mesh))
            model = eqx.filter_shard(model, replicated_sharding(mesh))
            opt_state = eqx.filter_shard(opt_state, replicated_sharding(mesh))
        params, static = eqx.partition(model, filter_spec)

        def objective(p):
            return _split_loss(loss_fn(eqx.combine(p, static), batch), has_aux)

        (loss, aux), grads = jax.value_and_grad(objective, has_aux=True)(params)
        with jax.numpy_dtype_promotion("standard"):  # optax is not strict-clean
            updates, opt_state = optimizer.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        model = eqx.combine(params, static)
        if mesh is not None:
            model = eqx.filter_shard(model, replicated_sharding(mesh))
            opt_state = eqx.filter_shard(opt_state, replicated_sharding(mesh))
        metrics = {"loss": loss, "grad_norm": _global_norm(grads), **aux}
        return model, opt_state, metrics

    return eqx.filter_jit(step)


class TrainResult(eqx.Module):
    """What [`eqsmooth.learn.train`][] returns.

    **Fields:**

    - `model`: the model after the last step.
    - `best_model`: the model with the lowest validation loss among the
        evaluated ones (the initial model included); the last model when no
        validation data was given.
    - `best_step`: the step of `best_model`.
    - `best_valid_loss`: its validation loss (`inf` without validation data).
    - `opt_state`: the final optimiser state.
    - `step`: the number of steps taken in total.
    - `history`: the logged records (dicts), one per logged step; with a
        `log_path`, the records of an earlier run that this one resumed come
        first.
    """

    model: PyTree
    best_model: PyTree
    best_step: int
    best_valid_loss: float
    opt_state: PyTree
    step: int
    history: list


def epoch_order(seed: int, epoch: int, num_examples: int) -> np.ndarray:
    """The order in which epoch `epoch` visits the examples: a fixed permutation.

    A pure function of `(seed, epoch)`, so a resumed run sees the same batches
    as an uninterrupted one.
    """
    return np.random.default_rng([seed, epoch]).permutation(num_examples)


def _num_examples(data: PyTree, name: str) -> int:
    leaves = jax.tree_util.tree_leaves(data)
    if not leaves:
        raise ValueError(f"train: {name} has no array leaves")
    for path, leaf in jax.tree_util.tree_flatten_with_path(data)[0]:
        if np.asarray(leaf).dtype.kind not in "biuf":
            raise TypeError(
                f"train: {name}{jax.tree_util.keystr(path)} has dtype "
                f"{np.asarray(leaf).dtype}; every leaf must be a numeric array"
            )
    sizes = {np.shape(x)[0] if np.ndim(x) else -1 for x in leaves}
    if len(sizes) != 1 or -1 in sizes:
        raise ValueError(
            f"train: every leaf of {name} needs the same leading (example) axis; "
            f"got shapes {[np.shape(x) for x in leaves]}"
        )
    size = sizes.pop()
    if size == 0:
        raise ValueError(f"train: {name} has no examples")
    return size


def _to_host(data: PyTree) -> PyTree:
    return jax.tree_util.tree_map(np.asarray, data)


def _take(data: PyTree, idx: np.ndarray) -> PyTree:
    return jax.tree_util.tree_map(lambda x: x[idx], data)


def _floats(metrics: dict) -> dict:
    return {k: float(v) for k, v in metrics.items()}


def evaluate(
    model: PyTree,
    loss_fn: Callable[..., Any],
    data: PyTree,
    batch_size: int,
    *,
    has_aux: bool = False,
    mesh: Mesh | None = None,
) -> Float[Array, ""]:
    """The example-weighted mean of `loss_fn(model, batch)` over all of `data`.

    **Arguments:**

    - `model`, `loss_fn`, `has_aux`: as for [`eqsmooth.learn.train`][].
    - `data`: a pytree of arrays with a leading example axis.
    - `batch_size`: examples per evaluation batch (the last may be smaller).
    - `mesh`: shard the full batches over this mesh's devices.

    **Returns:** a scalar.
    """
    return _make_evaluator(loss_fn, has_aux, mesh)(model, _to_host(data), batch_size)


def _make_evaluator(loss_fn, has_aux, mesh):
    @eqx.filter_jit
    def batch_loss(model, batch):
        return _split_loss(loss_fn(model, batch), has_aux)[0]

    def run(model, data, batch_size):
        n = _num_examples(data, "the validation data")
        total, start, bad = 0.0, 0, []
        while start < n:
            stop = min(start + batch_size, n)
            batch = _take(data, np.arange(start, stop))
            if mesh is not None:
                divisible = (stop - start) % mesh.devices.size == 0
                batch = (
                    shard_batch(batch, mesh) if divisible else replicate(batch, mesh)
                )
            loss = batch_loss(model, batch)
            if not math.isfinite(float(loss)):
                bad.append(f"{start}..{stop - 1}")
            total = total + (stop - start) * loss
            start = stop
        if bad:
            # One non-finite example makes the mean non-finite, and a NaN
            # never compares lower: model selection would silently keep the
            # first model. Name the examples instead.
            raise FloatingPointError(
                f"the validation loss is {float(total) / n}: the validation batches of "
                f"examples {', '.join(bad)} (of {n}) gave a non-finite loss; fix "
                "or drop those examples of the validation data (evaluate them one "
                "at a time with batch_size=1 to find which)"
            )
        return total / n

    return run


def _rewrite_log(log_path: Path, upto_step: int) -> list[dict]:
    # Keep the records of steps the checkpoint covers; later ones (written by a
    # run killed after its last checkpoint) will be written again.
    if not log_path.exists():
        return []
    kept = []
    for line in log_path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut short by a kill
        if rec.get("step", math.inf) <= upto_step:
            kept.append(rec)
    text = "".join(json.dumps(r) + "\n" for r in kept)
    atomic_write(log_path, lambda f: f.write(text.encode()))
    return kept


def _resume(ckpt: Path, like: TrainState, seed: int, metadata: dict) -> TrainState:
    """The state in `ckpt`, or in the checkpoint before it if `ckpt` is damaged."""
    errors = []
    for path in (ckpt, previous_checkpoint(ckpt)):
        if not path.exists():
            continue
        try:
            header = read_checkpoint_header(path)
        except CheckpointError as err:
            errors.append(str(err))
            continue
        if header["seed"] != seed or header["metadata"] != metadata:
            raise ValueError(
                f"train: checkpoint {path} was written by a run with seed "
                f"{header['seed']} and {header['metadata']}; this run has seed "
                f"{seed} and {metadata} (delete it or pass resume=False)"
            )
        try:
            state = load_checkpoint(path, like)
        except CheckpointMismatch:
            raise
        except CheckpointError as err:
            errors.append(str(err))
            continue
        if errors:
            warnings.warn(
                f"train: {errors[0]}; resuming from the previous checkpoint "
                f"{path} (step {int(state.step)}) instead",
                stacklevel=3,
            )
        return state
    raise CheckpointError(
        "train: no usable checkpoint to resume from: " + "; ".join(errors)
    )


def _check_options(model, optimizer, filter_spec, on_nonfinite, num_steps, seed):
    """`train`'s argument checks, each naming the argument at fault."""
    if on_nonfinite not in ("raise", "skip"):
        raise ValueError(
            f"train: on_nonfinite must be 'raise' or 'skip', got {on_nonfinite!r}"
        )
    if num_steps < 0:
        raise ValueError(f"train: need num_steps >= 0, got {num_steps}")
    if not isinstance(optimizer, optax.GradientTransformation):
        raise TypeError(
            "train: optimizer must be an optax.GradientTransformation (e.g. "
            f"optax.adam(1e-3) or eqsmooth.learn.make_optimizer), got "
            f"{type(optimizer).__name__}"
        )
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"train: seed must be an int >= 0, got {seed!r}")
    if not jax.tree_util.tree_leaves(eqx.filter(model, filter_spec)):
        raise ValueError(
            "train: the model has no trainable leaves (none selected by "
            "filter_spec; by default floating-point JAX arrays: a Python float "
            "field is a constant, wrap it in jnp.asarray)"
        )


def _validation(validation, loss_fn, has_aux, mesh, train_data):
    """The validation data on the host and its evaluator (None, None without)."""
    if validation is None:
        return None, None
    valid = _to_host(validation.data)
    _num_examples(valid, "validation.data")
    own = validation.loss_fn is None
    if own and train_data is not None:
        _same_examples(valid, train_data)
    fn = loss_fn if own else validation.loss_fn
    return valid, _make_evaluator(fn, has_aux and own, mesh)


def _same_examples(valid, train) -> None:
    """Validation examples scored by the training loss must look like the
    training examples (it raised a `KeyError` from inside the user's loss)."""
    vs, ts = jax.tree_util.tree_structure(valid), jax.tree_util.tree_structure(train)
    if vs != ts:
        raise ValueError(
            "train: validation.data is scored by the training loss (Validation."
            "loss_fn is None) but its structure differs from train_data's: "
            f"{vs} against {ts} (give it the same keys and nesting, or a "
            "loss_fn of its own)"
        )
    for (path, v), t in zip(
        jax.tree_util.tree_flatten_with_path(valid)[0], jax.tree_util.tree_leaves(train)
    ):
        if np.shape(v)[1:] != np.shape(t)[1:]:
            raise ValueError(
                f"train: validation.data{jax.tree_util.keystr(path)} has examples "
                f"of shape {np.shape(v)[1:]} where train_data's have "
                f"{np.shape(t)[1:]}"
            )


def _check_batch(n: int, batch_size: int, mesh: Mesh | None) -> None:
    if batch_size < 1:
        raise ValueError(f"train: need batch_size >= 1, got {batch_size}")
    if n < batch_size:
        raise ValueError(f"train: batch_size {batch_size} exceeds the {n} examples")
    if mesh is not None and batch_size % mesh.devices.size:
        raise ValueError(
            f"train: batch_size {batch_size} is not a multiple of the "
            f"{mesh.devices.size} devices of the mesh"
        )


def _start(
    state: TrainState,
    checkpoints: Checkpoints | None,
    log: Path | None,
    metadata: dict,
    writer: bool,
) -> tuple[TrainState, list[dict]]:
    """The state to start from (resumed from a checkpoint when there is one)
    and the log records it covers; a fresh run starts a fresh log."""
    ckpt = None if checkpoints is None else Path(checkpoints.path)
    if (
        ckpt is not None
        and checkpoints.resume
        and (ckpt.exists() or previous_checkpoint(ckpt).exists())
    ):
        state = _resume(ckpt, state, state.seed, metadata)
        # Temporary files of a run killed while writing its checkpoint.
        for stale in ckpt.parent.glob(f".{ckpt.name}.*.tmp") if writer else ():
            stale.unlink(missing_ok=True)
        return state, ([] if log is None else _rewrite_log(log, state.step))
    if log is not None and log.exists():
        log.unlink()
    return state, []


class _RunConfig(eqx.Module):
    """One `train` call's settings, as its loop reads them.

    **Fields:**

    - `seed`, `batch_size`, `num_steps`, `mesh`, `validation`, `checkpoints`,
        `logging`, `on_nonfinite`: `train`'s arguments.
    - `num_examples`: the number of training examples.
    - `metadata`: what a checkpoint must match to be resumed.
    - `writer`: whether this process writes checkpoints and logs (process 0).
    - `step_fn`: the compiled optimiser step, `step_fn(model, opt_state,
        batch) -> (model, opt_state, metrics)`.
    - `augment`: the compiled augmentation, `augment(batch, key) -> batch`,
        or `None`.
    """

    seed: int = eqx.field(static=True)
    num_examples: int = eqx.field(static=True)
    batch_size: int = eqx.field(static=True)
    num_steps: int = eqx.field(static=True)
    metadata: dict[str, int] = eqx.field(static=True)
    writer: bool = eqx.field(static=True)
    mesh: Mesh | None = eqx.field(static=True)
    validation: Validation | None
    checkpoints: Checkpoints | None
    logging: Logging
    on_nonfinite: str = eqx.field(static=True)
    step_fn: Callable[..., tuple[PyTree, PyTree, dict]] = eqx.field(static=True)
    augment: Callable[[Any, PRNGKeyArray], Any] | None = eqx.field(static=True)


class _Run:
    """One `train` call's mutable state (current and best model, the log) and
    its loop over the steps."""

    def __init__(
        self, state, history, data, valid, evaluator, logfile, config: _RunConfig
    ):
        self.model, self.opt_state = state.model, state.opt_state
        self.best_model, self.best_metric = state.best_model, state.best_metric
        self.best_step, self.start = state.best_step, state.step
        self.history, self.data, self.valid = history, data, valid
        self.evaluator, self.logfile = evaluator, logfile
        self.config = config
        if config.mesh is not None:
            self.model, self.opt_state, self.best_model = replicate(
                (self.model, self.opt_state, self.best_model), config.mesh
            )
        self.t0 = time.perf_counter()

    def write(self, record: dict) -> None:
        self.history.append(record)
        if self.logfile is not None:
            self.logfile.write(json.dumps(record) + "\n")
            self.logfile.flush()

    def validate(self, step: int) -> float:
        v = float(self.evaluator(self.model, self.valid, self.config.batch_size))
        if step == 0 or v < self.best_metric:
            self.best_metric, self.best_model, self.best_step = v, self.model, step
        return v

    def checkpoint(self, step: int) -> None:
        validated = self.evaluator is not None
        state = TrainState(
            model=self.model,
            opt_state=self.opt_state,
            step=step,
            seed=self.config.seed,
            best_model=self.best_model if validated else self.model,
            best_metric=self.best_metric,
            best_step=self.best_step if validated else step,
        )
        save_checkpoint(Path(self.config.checkpoints.path), state, self.config.metadata)

    def batch(self, s: int, order: np.ndarray, pos: int):
        c = self.config
        examples = order[pos * c.batch_size : (pos + 1) * c.batch_size]
        batch = _take(self.data, examples)
        if c.augment is not None:
            key = jax.random.fold_in(jax.random.key(c.seed), s)
            batch = c.augment(batch, key)
        if c.mesh is None:
            return examples, jax.tree_util.tree_map(jnp.asarray, batch)
        return examples, shard_batch(batch, c.mesh)

    def loop(self, bar) -> None:
        c = self.config
        num_steps, n, logging = c.num_steps, c.num_examples, c.logging
        if self.evaluator is not None and self.start == 0:
            v = self.validate(0)
            self.write(
                {"step": 0, "valid_loss": v, "time": time.perf_counter() - self.t0}
            )
        epoch, order = -1, None
        skipped = 0  # non-finite steps dropped by this call (on_nonfinite="skip")
        for s in range(self.start, num_steps):
            e, pos = divmod(s, n // c.batch_size)
            if e != epoch:
                epoch, order = e, epoch_order(c.seed, e, n)
            assert order is not None
            examples, batch = self.batch(s, order, pos)
            model, opt_state, metrics = c.step_fn(self.model, self.opt_state, batch)
            if math.isfinite(float(metrics["loss"])) and math.isfinite(
                float(metrics["grad_norm"])
            ):
                self.model, self.opt_state = model, opt_state
            elif c.on_nonfinite == "raise":
                raise _nonfinite_error(s, e, metrics, examples)
            else:
                skipped += 1
            done = s + 1
            last = done == num_steps
            validate = self.evaluator is not None and (
                done % c.validation.every == 0 or last
            )
            record = None
            if done % logging.every == 0 or validate or last:
                record = {"step": done, "epoch": e, **_floats(metrics)}
                record["skipped"] = skipped
                if validate:
                    record["valid_loss"] = self.validate(done)
                record["time"] = time.perf_counter() - self.t0
                self.write(record)
                bar.set_postfix(loss=f"{record['loss']:.4g}")
            bar.update(1)
            ckpt = c.checkpoints
            if ckpt is not None and c.writer and (done % ckpt.every == 0 or last):
                self.checkpoint(done)
            if logging.callback is not None:
                logging.callback(done, _floats(metrics) if record is None else record)
        ran = num_steps - min(self.start, num_steps)
        if ran and skipped == ran:
            raise _all_skipped_error(ran)

    def result(self) -> "TrainResult":
        final_step = max(self.start, self.config.num_steps)
        if self.valid is None:
            self.best_model, self.best_step = self.model, final_step
        return TrainResult(
            model=self.model,
            best_model=self.best_model,
            best_step=self.best_step,
            best_valid_loss=self.best_metric,
            opt_state=self.opt_state,
            step=final_step,
            history=self.history,
        )


def _nonfinite_error(s: int, e: int, metrics: dict, examples) -> FloatingPointError:
    return FloatingPointError(
        f"train: step {s + 1} (epoch {e}) gave loss {float(metrics['loss'])} and "
        f"gradient norm {float(metrics['grad_norm'])}; the batch held examples "
        f"{examples.tolist()} of train_data. The model is left at step {s} (pass "
        "on_nonfinite='skip' to drop such batches)"
    )


def _all_skipped_error(ran: int) -> FloatingPointError:
    return FloatingPointError(
        f"train: every one of the {ran} steps of this call had a non-finite "
        "loss or gradient norm and was skipped (on_nonfinite='skip'), so "
        "nothing was trained; check the training data and the loss "
        "(on_nonfinite='raise' names the examples of the first such batch)"
    )


def train(
    model: PyTree,
    loss_fn: Callable[..., Any],
    train_data: PyTree,
    *,
    optimizer: optax.GradientTransformation,
    num_steps: int,
    batch_size: int,
    seed: int = 0,
    has_aux: bool = False,
    validation: Validation | None = None,
    checkpoints: Checkpoints | None = None,
    logging: Logging = Logging(),
    on_nonfinite: str = "raise",
    augment: Callable[[Any, PRNGKeyArray], Any] | None = None,
    filter_spec: Any = eqx.is_inexact_array,
    mesh: Mesh | None = None,
) -> TrainResult:
    """Train `model` by minimising `loss_fn` over mini-batches of `train_data`.

    Each epoch visits the examples in the order
    [`eqsmooth.learn.epoch_order`][]`(seed, epoch)`, in batches of
    `batch_size` (the incomplete last batch is dropped), so step `s` always
    sees the same batch. A run killed at any point and resumed from its
    [`eqsmooth.learn.Checkpoints`][] ends with bitwise the same parameters as
    an uninterrupted run (same machine, same software).

    **Arguments:**

    - `model`: an `eqx.Module` (or any pytree); its leaves selected by
        `filter_spec` are trained.
    - `loss_fn`: `loss_fn(model, batch) -> scalar` (or `(scalar, aux_dict)`
        with `has_aux=True`), averaged over the batch; the batch is
        `train_data` indexed along its leading axis.
    - `train_data`: a pytree of arrays with a leading example axis.
    - `optimizer`: an `optax.GradientTransformation`, e.g. from
        [`eqsmooth.learn.make_optimizer`][].
    - `num_steps`: total number of optimiser steps (counting resumed ones).
    - `batch_size`: examples per step (and per validation batch).
    - `seed`: fixes the data order (and `augment`'s keys).
    - `has_aux`: whether `loss_fn` returns auxiliary metrics to log.
    - `validation`: a [`eqsmooth.learn.Validation`][] (model selection), or
        `None`: `best_model` is then the last model.
    - `checkpoints`: a [`eqsmooth.learn.Checkpoints`][], or `None`: none.
    - `logging`: a [`eqsmooth.learn.Logging`][] (log file, interval,
        progress bar, callback).
    - `on_nonfinite`: what to do when a step's loss or gradient norm is NaN or
        infinite (a bad example, or a failed solve inside the loss): `"raise"`
        stops with a `FloatingPointError` naming the step, epoch and example
        indices of the batch, before the update is applied; `"skip"` drops that
        update (model and optimiser state stay as they were), counts it in the
        log record's `skipped` field and goes on. Either way the non-finite
        update never reaches the model.
    - `augment`: data augmentation, `augment(batch, key) -> batch`, applied
        (compiled once with `eqx.filter_jit`) to every training batch, never
        to validation data; `key` is
        `jax.random.fold_in(jax.random.key(seed), step)`, so a resumed run sees
        the same augmented batches as an uninterrupted one.
    - `filter_spec`: which leaves of `model` are trained.
    - `mesh`: data-parallel training over this mesh's devices (see
        [`eqsmooth.learn.make_train_step`][]); `batch_size` must be a
        multiple of the device count. Multi-host: see
        [`eqsmooth.learn.initialize_distributed`][] (only process 0 writes).

    **Returns:** a [`eqsmooth.learn.TrainResult`][].
    """
    _check_options(model, optimizer, filter_spec, on_nonfinite, num_steps, seed)
    data = _to_host(train_data)
    n = _num_examples(data, "train_data")
    _check_batch(n, batch_size, mesh)
    # (An augmentation may give the loss batches of another structure.)
    like = data if augment is None else None
    valid, evaluator = _validation(validation, loss_fn, has_aux, mesh, like)
    with jax.numpy_dtype_promotion("standard"):
        opt_state = optimizer.init(eqx.filter(model, filter_spec))
    seed = int(seed)
    metadata = {"num_examples": n, "batch_size": batch_size}
    # In a multi-host run every process reads the checkpoint (a shared file
    # system), and only process 0 writes checkpoints and logs.
    writer = jax.process_index() == 0
    log = None if logging.path is None or not writer else Path(logging.path)
    state = TrainState(model, opt_state, 0, seed, model, math.inf, -1)
    state, history = _start(state, checkpoints, log, metadata, writer)
    step_fn = make_train_step(
        loss_fn, optimizer, has_aux=has_aux, filter_spec=filter_spec, mesh=mesh
    )
    config = _RunConfig(
        seed=seed,
        num_examples=n,
        batch_size=batch_size,
        num_steps=num_steps,
        metadata=metadata,
        writer=writer,
        mesh=mesh,
        validation=validation,
        checkpoints=checkpoints,
        logging=logging,
        on_nonfinite=on_nonfinite,
        step_fn=step_fn,
        augment=None if augment is None else eqx.filter_jit(augment),
    )
    with open(log, "a") if log is not None else contextlib.nullcontext() as logfile:
        run = _Run(state, history, data, valid, evaluator, logfile, config)
        with tqdm(
            total=num_steps,
            initial=min(state.step, num_steps),
            disable=not (logging.progress and writer),
        ) as bar:
            run.loop(bar)
    return run.result()
