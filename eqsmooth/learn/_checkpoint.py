"""Atomic, resumable training checkpoints."""

import hashlib
import io
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import equinox as eqx
from jaxtyping import PyTree


_MAGIC = "eqsmooth-checkpoint"
_VERSION = 2  # 2: the header holds the payload's length and SHA-256
_READABLE = (1, 2)


class CheckpointError(ValueError):
    """A checkpoint file that cannot be trusted: truncated, corrupted, or not
    written by [`eqsmooth.learn.save_checkpoint`][]."""


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
    file is truncated, fails its checksum, or does not fit `like`.
    """
    with open(path, "rb") as f:
        header = _read_header(f, path)
        payload = f.read()
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
