"""The option groups of `eqsmooth.learn.train`: validation, checkpoints, logging."""

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
from jaxtyping import PyTree


def _check_every(owner: str, every: int) -> None:
    if isinstance(every, bool) or not isinstance(every, int) or every < 1:
        raise ValueError(f"{owner}: every must be an int >= 1, got {every!r}")


def _check_file(owner: str, path) -> None:
    """Refuse a path that can never be written: a directory, or one below an
    existing file (it failed with a bare `FileExistsError` at the first
    write, after the first interval of training)."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{owner}: path {path} is a directory; give a file path")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(
                    f"{owner}: path {path} cannot be written: {parent} is a file, "
                    "not a folder"
                )
            break


class Validation(eqx.Module):
    """Model selection on held-out data, for [`eqsmooth.learn.train`][].

    The validation loss is evaluated at step 0, every `every` steps and at the
    end; the model with the lowest one is kept as `best_model`.

    **Fields:**

    - `data`: a pytree of arrays with a leading example axis.
    - `loss_fn`: the validation loss, `loss_fn(model, batch) -> scalar`
        (averaged over the batch). `None`: the training loss (and its
        `has_aux`).
    - `every`: the evaluation interval in steps.
    """

    data: PyTree
    loss_fn: Callable[..., Any] | None = eqx.field(default=None, static=True)
    every: int = eqx.field(default=100, static=True)

    def __check_init__(self):
        _check_every("Validation", self.every)


class Checkpoints(eqx.Module):
    """Where and how often [`eqsmooth.learn.train`][] saves its state.

    A [`eqsmooth.learn.TrainState`][] is written atomically every `every`
    steps and at the end (the file before it is kept beside it, see
    [`eqsmooth.learn.previous_checkpoint`][]). In a multi-host run `path`
    must be on a file system every process sees; only process 0 writes it.

    **Fields:**

    - `path`: the checkpoint file.
    - `every`: the checkpoint interval in steps.
    - `resume`: continue from the checkpoint at `path` when it exists (a
        damaged one falls back to the previous file); `False` starts over.
    """

    path: str | os.PathLike = eqx.field(static=True)
    every: int = eqx.field(default=100, static=True)
    resume: bool = eqx.field(default=True, static=True)

    def __check_init__(self):
        _check_every("Checkpoints", self.every)
        _check_file("Checkpoints", self.path)


class Logging(eqx.Module):
    """What [`eqsmooth.learn.train`][] reports while it runs.

    **Fields:**

    - `path`: append one JSON record per logged step to this file (`step`,
        `epoch`, `loss`, `grad_norm`, aux metrics, `skipped`, `valid_loss`
        when evaluated, `time`); `None`: keep the records in memory only
        (`TrainResult.history`).
    - `every`: log every this many steps (evaluation steps always log).
    - `progress`: show a tqdm progress bar.
    - `callback`: called as `callback(step, record)` after every step.
    """

    path: str | os.PathLike | None = eqx.field(default=None, static=True)
    every: int = eqx.field(default=1, static=True)
    progress: bool = eqx.field(default=True, static=True)
    callback: Callable[[int, dict], None] | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        _check_every("Logging", self.every)
        _check_file("Logging", self.path)
