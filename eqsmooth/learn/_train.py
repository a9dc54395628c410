"""A small, resumable training loop on optax."""

import json
import math
import os
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


def _check_options(
    model,
    optimizer,
    filter_spec,
    *,
    on_nonfinite,
    num_steps,
    batch_size,
    eval_every,
    checkpoint_every,
    log_every,
    seed,
    paths,
) -> None:
    """`train`'s argument checks, each naming the argument at fault."""
    if on_nonfinite not in ("raise", "skip"):
        raise ValueError(
            f"train: on_nonfinite must be 'raise' or 'skip', got {on_nonfinite!r}"
        )
    if num_steps < 0 or batch_size < 1 or eval_every < 1 or checkpoint_every < 1:
        raise ValueError(
            "train: need num_steps >= 0, batch_size >= 1, eval_every >= 1 and "
            f"checkpoint_every >= 1; got {num_steps}, {batch_size}, {eval_every}, "
            f"{checkpoint_every}"
        )
    if log_every < 1:
        raise ValueError(f"train: log_every must be >= 1, got {log_every}")
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
    for label, path in paths.items():
        if path is not None and Path(path).is_dir():
            raise ValueError(f"train: {label} {path} is a directory; give a file path")


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
    valid_data: PyTree | None = None,
    valid_loss_fn: Callable[..., Any] | None = None,
    eval_every: int = 100,
    checkpoint_path: str | os.PathLike | None = None,
    checkpoint_every: int = 100,
    resume: bool = True,
    log_path: str | os.PathLike | None = None,
    log_every: int = 1,
    progress: bool = True,
    mesh: Mesh | None = None,
    filter_spec: Any = eqx.is_inexact_array,
    callback: Callable[[int, dict], None] | None = None,
    on_nonfinite: str = "raise",
    augment: Callable[[Any, PRNGKeyArray], Any] | None = None,
) -> TrainResult:
    """Train `model` by minimising `loss_fn` over mini-batches of `train_data`.

    Each epoch visits the examples in the order
    [`eqsmooth.learn.epoch_order`][]`(seed, epoch)`, in batches of
    `batch_size` (the incomplete last batch is dropped), so step `s` always
    sees the same batch. With `checkpoint_path`, a
    [`eqsmooth.learn.TrainState`][] is written atomically every
    `checkpoint_every` steps and at the end; if the file exists and
    `resume=True`, training continues from it, and a run killed at any point
    and resumed ends with bitwise the same parameters as an uninterrupted run
    (same machine, same software).

    **Arguments:**

    - `model`: an `eqx.Module` (or any pytree); its leaves selected by
        `filter_spec` are trained.
    - `loss_fn`: `loss_fn(model, batch) -> scalar` (or `(scalar, aux_dict)`
        with `has_aux=True`), averaged over the batch; the batch is
        `train_data` indexed along its leading axis. Typically
        `jnp.mean(jax.vmap(lambda ex: surrogate_loss(build(model, ex),
        ex["truth"]))(batch))`.
    - `train_data`: a pytree of arrays with a leading example axis.
    - `optimizer`: an `optax.GradientTransformation`, e.g. from
        [`eqsmooth.learn.make_optimizer`][].
    - `num_steps`: total number of optimiser steps (counting resumed ones).
    - `batch_size`: examples per step.
    - `seed`: fixes the data order.
    - `has_aux`: whether `loss_fn` returns auxiliary metrics to log.
    - `valid_data`: optional validation data; evaluated at step 0, every
        `eval_every` steps and at the end. The model with the lowest
        validation loss is kept as `best_model`.
    - `valid_loss_fn`: the validation loss (default `loss_fn`).
    - `eval_every`: evaluation interval in steps.
    - `checkpoint_path`: where to keep the checkpoint (`None`: no
        checkpoints).
    - `checkpoint_every`: checkpoint interval in steps.
    - `resume`: continue from an existing checkpoint at `checkpoint_path`.
    - `log_path`: append one JSON record per logged step here (`step`,
        `epoch`, `loss`, `grad_norm`, aux metrics, `valid_loss` when
        evaluated, `time`).
    - `log_every`: log every this many steps (evaluation steps always log).
    - `progress`: show a tqdm progress bar.
    - `mesh`: data-parallel training over this mesh's devices (see
        [`eqsmooth.learn.make_train_step`][]); `batch_size` must be a
        multiple of the device count. In a multi-host run (see
        [`eqsmooth.learn.initialize_distributed`][]) every process calls
        `train` with the same arguments and data; the checkpoint must be on a
        file system all processes see, and only process 0 writes it and the
        log.
    - `filter_spec`: which leaves of `model` are trained.
    - `callback`: called as `callback(step, record)` after every step.
    - `on_nonfinite`: what to do when a step's loss or gradient norm is NaN or
        infinite (a bad example, or a failed solve inside the loss): `"raise"`
        stops with a `FloatingPointError` naming the step, epoch and example
        indices of the batch, before the update is applied; `"skip"` drops that
        update (model and optimiser state stay as they were), counts it in the
        log record's `skipped` field and goes on. Either way the non-finite
        update never reaches the model.
    - `augment`: data augmentation, `augment(batch, key) -> batch`, applied
        (compiled once with `eqx.filter_jit`) to every training batch before
        the step, never to `valid_data`. `key` is
        `jax.random.fold_in(jax.random.key(seed), step)`: it depends only on
        the seed and the step, so a resumed run sees the same augmented
        batches as an uninterrupted one.

    **Returns:** a [`eqsmooth.learn.TrainResult`][].
    """
    _check_options(
        model,
        optimizer,
        filter_spec,
        on_nonfinite=on_nonfinite,
        num_steps=num_steps,
        batch_size=batch_size,
        eval_every=eval_every,
        checkpoint_every=checkpoint_every,
        log_every=log_every,
        seed=seed,
        paths={"checkpoint_path": checkpoint_path, "log_path": log_path},
    )
    data = _to_host(train_data)
    n = _num_examples(data, "train_data")
    if n < batch_size:
        raise ValueError(f"train: batch_size {batch_size} exceeds the {n} examples")
    if mesh is not None and batch_size % mesh.devices.size:
        raise ValueError(
            f"train: batch_size {batch_size} is not a multiple of the "
            f"{mesh.devices.size} devices of the mesh"
        )
    steps_per_epoch = n // batch_size
    valid = None if valid_data is None else _to_host(valid_data)
    if valid is not None:
        _num_examples(valid, "valid_data")

    with jax.numpy_dtype_promotion("standard"):
        opt_state = optimizer.init(eqx.filter(model, filter_spec))
    state = TrainState(
        model=model,
        opt_state=opt_state,
        step=0,
        seed=int(seed),
        best_model=model,
        best_metric=math.inf,
        best_step=-1,
    )
    metadata = {"num_examples": n, "batch_size": batch_size}
    ckpt = None if checkpoint_path is None else Path(checkpoint_path)
    log = None if log_path is None else Path(log_path)
    # In a multi-host run every process reads the checkpoint (a shared file
    # system), and only process 0 writes checkpoints and logs.
    writer = jax.process_index() == 0
    if not writer:
        log = None
    history: list[dict] = []
    if (
        ckpt is not None
        and resume
        and (ckpt.exists() or previous_checkpoint(ckpt).exists())
    ):
        state = _resume(ckpt, state, seed, metadata)
        # Temporary files of a run killed while writing its checkpoint.
        for stale in ckpt.parent.glob(f".{ckpt.name}.*.tmp") if writer else ():
            stale.unlink(missing_ok=True)
        if log is not None:
            history = _rewrite_log(log, state.step)
    elif log is not None and log.exists():
        log.unlink()

    model, opt_state = state.model, state.opt_state
    best_model, best_metric, best_step = (
        state.best_model,
        state.best_metric,
        state.best_step,
    )
    if mesh is not None:
        model, opt_state, best_model = replicate((model, opt_state, best_model), mesh)

    step_fn = make_train_step(
        loss_fn, optimizer, has_aux=has_aux, filter_spec=filter_spec, mesh=mesh
    )
    augment_fn = None if augment is None else eqx.filter_jit(augment)
    augment_key = jax.random.key(int(seed))
    evaluator = None
    if valid is not None:
        evaluator = _make_evaluator(
            loss_fn if valid_loss_fn is None else valid_loss_fn,
            has_aux if valid_loss_fn is None else False,
            mesh,
        )

    def checkpoint(step):
        if ckpt is None or not writer:
            return
        save_checkpoint(
            ckpt,
            TrainState(
                model=model,
                opt_state=opt_state,
                step=step,
                seed=int(seed),
                best_model=best_model if valid is not None else model,
                best_metric=best_metric,
                best_step=best_step if valid is not None else step,
            ),
            metadata,
        )

    logfile = None if log is None else open(log, "a")
    t0 = time.perf_counter()

    def write(record):
        history.append(record)
        if logfile is not None:
            logfile.write(json.dumps(record) + "\n")
            logfile.flush()

    bar = tqdm(
        total=num_steps,
        initial=min(state.step, num_steps),
        disable=not (progress and writer),
    )
    try:
        if evaluator is not None and state.step == 0:
            v = float(evaluator(model, valid, batch_size))
            best_metric, best_model, best_step = v, model, 0
            write({"step": 0, "valid_loss": v, "time": time.perf_counter() - t0})
        epoch, order = -1, None
        skipped = 0  # non-finite steps dropped by this call (on_nonfinite="skip")
        for s in range(state.step, num_steps):
            e, pos = divmod(s, steps_per_epoch)
            if e != epoch:
                epoch, order = e, epoch_order(seed, e, n)
            assert order is not None
            batch = _take(data, order[pos * batch_size : (pos + 1) * batch_size])
            if augment_fn is not None:
                batch = augment_fn(batch, jax.random.fold_in(augment_key, s))
            batch = (
                jax.tree_util.tree_map(jnp.asarray, batch)
                if mesh is None
                else (shard_batch(batch, mesh))
            )
            new_model, new_opt_state, metrics = step_fn(model, opt_state, batch)
            if not (
                math.isfinite(float(metrics["loss"]))
                and math.isfinite(float(metrics["grad_norm"]))
            ):
                examples = order[pos * batch_size : (pos + 1) * batch_size]
                if on_nonfinite == "raise":
                    raise FloatingPointError(
                        f"train: step {s + 1} (epoch {e}) gave loss "
                        f"{float(metrics['loss'])} and gradient norm "
                        f"{float(metrics['grad_norm'])}; the batch held examples "
                        f"{examples.tolist()} of train_data. The model is left at "
                        f"step {s} (pass on_nonfinite='skip' to drop such batches)"
                    )
                skipped += 1
            else:
                model, opt_state = new_model, new_opt_state
            done = s + 1
            evaluate_now = evaluator is not None and (
                done % eval_every == 0 or done == num_steps
            )
            record = None
            if done % log_every == 0 or evaluate_now or done == num_steps:
                record = {
                    "step": done,
                    "epoch": e,
                    **_floats(metrics),
                    "skipped": skipped,
                }
                if evaluate_now:
                    assert evaluator is not None
                    v = float(evaluator(model, valid, batch_size))
                    record["valid_loss"] = v
                    if v < best_metric:
                        best_metric, best_model, best_step = v, model, done
                record["time"] = time.perf_counter() - t0
                write(record)
                bar.set_postfix(loss=f"{record['loss']:.4g}")
            bar.update(1)
            if done % checkpoint_every == 0 or done == num_steps:
                checkpoint(done)
            if callback is not None:
                callback(done, record if record is not None else _floats(metrics))
        ran = num_steps - min(state.step, num_steps)
        if ran and skipped == ran:
            raise FloatingPointError(
                f"train: every one of the {ran} steps of this call had a non-finite "
                "loss or gradient norm and was skipped (on_nonfinite='skip'), so "
                "nothing was trained; check the training data and the loss "
                "(on_nonfinite='raise' names the examples of the first such batch)"
            )
    finally:
        bar.close()
        if logfile is not None:
            logfile.close()
    final_step = max(state.step, num_steps)
    if valid is None:
        best_model, best_step = model, final_step
    return TrainResult(
        model=model,
        best_model=best_model,
        best_step=best_step,
        best_valid_loss=best_metric,
        opt_state=opt_state,
        step=final_step,
        history=history,
    )
