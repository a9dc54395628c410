"""Atomic, resumable training checkpoints."""

import hashlib
import io
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
from jaxtyping import PyTree


_MAGIC = "eqsmooth-checkpoint"
# 2: the header holds the payload's length and SHA-256; 3: and what the
# checkpoint belongs to (`_structure`)
_VERSION = 3
_READABLE = (1, 2, 3)


class CheckpointError(ValueError):
    """A checkpoint file that cannot be trusted: truncated, corrupted, not
    written by [`eqsmooth.learn.save_checkpoint`][], or written for another
    model or optimiser."""


class CheckpointMismatch(CheckpointError):
    """A sound checkpoint of another run (raised, never skipped for the
    previous file: that one belongs to the same other run)."""


def _structure(state: "TrainState") -> str:
    """What a checkpoint belongs to: the model's and the optimiser state's
    classes, field names and static configuration, and each array's dtype
    and shape (no values). Two models whose leaves merely have the same
    shapes, or an Adam state read as another optimiser's, differ here.
    Object addresses that a repr may print are dropped (they change between
    processes); one token a line, so that a difference is named exactly."""
    described = jax.tree_util.tree_map(
        lambda x: f"{x.dtype}{list(x.shape)}" if eqx.is_array(x) else type(x).__name__,
        (state.model, state.opt_state),
    )
    return re.sub(r" at 0x[0-9a-fA-F]+", "", eqx.tree_pformat(described, width=1))


def _first_difference(saved: str, current: str) -> str:
    a, b = saved.splitlines(), current.splitlines()
    for i, (x, y) in enumerate(zip(a, b)):
        if x != y:
            context = " ".join(line.strip() for line in a[max(0, i - 3) : i])
            return (
                f"after `{context}` the checkpoint has `{x.strip()}` where this "
                f"run has `{y.strip()}`"
            )
    return f"the checkpoint's description has {len(a)} lines, this run's {len(b)}"


class TrainState(eqx.Module):
    """Everything a training run needs to continue exactly where it stopped.

    The data order is a function of `(seed, step)` only (see
    [`eqsmooth.learn.train`][]), so these fields fix the rest of the run.

    **Fields:**

    - `model`: the current model.
    - `opt_state`: the optimiser state (over the trainable leaves).
    - `step`: number of optimiser steps taken.
    - `seed`: the data-order seed of the run.
    - `best_model`: the model with the lowest validation loss so far (the
        current model when there is no validation data).
    - `best_metric`: that validation loss (`inf` before any evaluation).
    - `best_step`: the step at which `best_model` was taken (`-1`: none yet).
    """

    model: PyTree
    opt_state: PyTree
    step: int
    seed: int
    best_model: PyTree
    best_metric: float
    best_step: int


def _fsync_dir(directory: Path) -> None:
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:  # e.g. platforms without directory handles
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Any) -> None:
    """Write a file atomically: a temporary file in the same folder, then rename.

    `write(f)` fills the open binary file `f`; the data is flushed and
    fsync'ed before `os.replace` puts it in place, so a reader (or a run
    killed at any moment) sees either the old file or the complete new one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)


def previous_checkpoint(path: str | os.PathLike) -> Path:
    """Where [`eqsmooth.learn.save_checkpoint`][] keeps the checkpoint it replaced."""
    path = Path(path)
    return path.with_name(path.name + ".prev")


def save_checkpoint(
    path: str | os.PathLike, state: TrainState, metadata: dict | None = None
) -> None:
    """Write `state` to `path` atomically, keeping the previous file.

    The file starts with one line of JSON (format, step, seed, best metric,
    `metadata`, and the length and SHA-256 of the rest), readable with
    [`eqsmooth.learn.read_checkpoint_header`][], followed by the array leaves
    of `state` in `eqx.tree_serialise_leaves` format. The checkpoint it
    replaces is kept at `previous_checkpoint(path)`, so a damaged file never
    costs more than one checkpoint interval.

    **Arguments:**

    - `path`: the checkpoint file.
    - `state`: a [`eqsmooth.learn.TrainState`][].
    - `metadata`: extra JSON-serialisable information for the header.
    """
    buffer = io.BytesIO()
    eqx.tree_serialise_leaves(buffer, state)
    payload = buffer.getvalue()
    header = {
        "format": _MAGIC,
        "version": _VERSION,
        "step": int(state.step),
        "seed": int(state.seed),
        "best_step": int(state.best_step),
        "best_metric": float(state.best_metric),
        "metadata": metadata or {},
        "structure": _structure(state),
        "payload_bytes": len(payload),
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    line = (json.dumps(header, sort_keys=True) + "\n").encode()
    path = Path(path)
    if path.exists():
        # A hard link keeps the old file's contents under the second name
        # while the new file is renamed over the first.
        prev = previous_checkpoint(path)
        prev.unlink(missing_ok=True)
        try:
            os.link(path, prev)
        except OSError:  # file systems without hard links
            os.replace(path, prev)

    def write(f):
        f.write(line)
        f.write(payload)

    atomic_write(path, write)


def read_checkpoint_header(path: str | os.PathLike) -> dict:
    """The JSON header of a checkpoint (see [`eqsmooth.learn.save_checkpoint`][])."""
    with open(path, "rb") as f:
        return _read_header(f, path)


def _read_header(f, path) -> dict:
    line = f.readline()
    try:
        header = json.loads(line.decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        header = None
    if not isinstance(header, dict) or header.get("format") != _MAGIC:
        raise CheckpointError(f"{path} is not an eqsmooth checkpoint")
    if header.get("version") not in _READABLE:
        raise CheckpointError(
            f"{path}: checkpoint format version {header.get('version')} is not "
            f"supported (expected {_VERSION})"
        )
    return header


def load_checkpoint(path: str | os.PathLike, like: TrainState) -> TrainState:
    """Read a checkpoint written by [`eqsmooth.learn.save_checkpoint`][].

    **Arguments:**

    - `path`: the checkpoint file.
    - `like`: a [`eqsmooth.learn.TrainState`][] with the same structure,
        shapes and dtypes (e.g. the freshly initialised state of the run);
        it supplies every non-array part of the model.

    **Returns:** the stored `TrainState`.

    **Raises:** [`eqsmooth.learn.CheckpointError`][] (a `ValueError`) when the
    file is truncated, fails its checksum, or does not fit `like`: another
    model (other classes, fields or static configuration, even with leaves
    of the same shapes) or another optimiser's state. The message names the
    first difference.
    """
    with open(path, "rb") as f:
        header = _read_header(f, path)
        payload = f.read()
    if "structure" in header:  # version 3: refuse another run's checkpoint
        current = _structure(like)
        if header["structure"] != current:
            raise CheckpointMismatch(
                f"{path}: checkpoint was written for another model or optimiser "
                f"than this run's: {_first_difference(header['structure'], current)} "
                "(resume with the model and optimiser that wrote it, or start over: "
                "Checkpoints(..., resume=False) or another path)"
            )
    if "payload_bytes" in header:  # version 2: verify before trusting it
        expected = int(header["payload_bytes"])
        if len(payload) < expected:
            raise CheckpointError(
                f"{path}: checkpoint is truncated: {len(payload)} of {expected} "
                "bytes after the header (a copy cut short, or a full disk)"
            )
        if len(payload) > expected or (
            hashlib.sha256(payload).hexdigest() != header["sha256"]
        ):
            raise CheckpointError(
                f"{path}: checkpoint is corrupted: its contents do not match the "
                "SHA-256 recorded when it was written"
            )
    try:
        return eqx.tree_deserialise_leaves(io.BytesIO(payload), like)
    except (RuntimeError, ValueError, EOFError) as err:
        raise CheckpointError(
            f"{path}: checkpoint does not match the model/optimiser being "
            f"trained: {err}"
        ) from err
