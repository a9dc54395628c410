"""Input checks at the public entry points of the discovery workflow."""

import hashlib

import numpy as np

from ._model import ChainModel, Sequences


def check_inputs(who: str, model: ChainModel, data: Sequences) -> None:
    """Raise `ValueError`/`TypeError` naming the argument if `model` and `data`
    cannot go together: types, at least one sequence of at least two steps,
    finite values, and state and measurement dimensions that agree."""
    if not isinstance(model, ChainModel):
        raise TypeError(
            f"{who}: model must be a ChainModel, got {type(model).__name__}"
        )
    if not isinstance(data, Sequences):
        raise TypeError(f"{who}: data must be Sequences, got {type(data).__name__}")
    B, T, m = data.measurements.shape
    if B < 1:
        raise ValueError(f"{who}: data has no sequences (B = 0)")
    if T < 2:
        raise ValueError(
            f"{who}: data has sequences of length T = {T}; the workflow needs at "
            "least 2 time steps (one transition)"
        )
    for field in ("measurements", "x0_mean", "inputs", "initial_states"):
        arr = np.asarray(getattr(data, field))
        if not np.all(np.isfinite(arr)):
            idx = tuple(int(i) for i in np.argwhere(~np.isfinite(arr))[0])
            raise ValueError(
                f"{who}: data.{field} has a non-finite value at index {idx} "
                "(missing measurements are not supported: drop or fill them)"
            )
    n = model.process_sigma.shape[0]
    if data.x0_mean.shape[1] != n:
        raise ValueError(
            f"{who}: data.x0_mean has state dimension {data.x0_mean.shape[1]} but "
            f"the model's process_sigma has {n} entries"
        )
    if model.measurement_sigma.shape[0] != m:
        raise ValueError(
            f"{who}: data.measurements has dimension m = {m} but the model's "
            f"measurement_sigma has {model.measurement_sigma.shape[0]} entries"
        )
    for field in ("process_sigma", "measurement_sigma", "prior_sigma"):
        sigma = np.asarray(getattr(model, field))
        if not np.all(np.isfinite(sigma) & (sigma > 0)):
            raise ValueError(
                f"{who}: model.{field} must be positive and finite, got {sigma}"
            )


def check_level(who: str, alpha: float) -> None:
    """Raise a `ValueError` naming `who` unless `0 < alpha < 1`."""
    if isinstance(alpha, bool) or not isinstance(alpha, (int, float, np.floating)):
        raise TypeError(f"{who}: alpha must be a number in (0, 1), got {alpha!r}")
    if not 0.0 < float(alpha) < 1.0:
        raise ValueError(
            f"{who}: alpha (the level of the workflow's alarms) must lie in (0, 1), "
            f"got {alpha} (0.05 is the usual choice)"
        )


def check_informative(who: str, data: Sequences) -> None:
    """Raise a `ValueError` naming the channel if a measurement channel never
    changes: its noise scale would be fitted to nothing (it ran to 1e-21)."""
    meas = np.asarray(data.measurements)
    flat = meas.reshape(-1, meas.shape[-1])
    constant = np.flatnonzero(np.ptp(flat, axis=0) == 0)
    if constant.size:
        raise ValueError(
            f"{who}: data.measurements channel(s) {constant.tolist()} hold the same "
            f"value ({flat[0, constant].tolist()}) in every sequence and step: a "
            "constant channel carries no information about the dynamics and its "
            "noise scale cannot be fitted (a disconnected or saturated sensor? "
            "drop the channel)"
        )


def fingerprint(data: Sequences) -> str:
    """A digest of the sequences (every array, its shape and dtype), so that a
    later step can tell whether it was given the data `find` analysed."""
    digest = hashlib.sha256()
    for field in ("measurements", "x0_mean", "inputs", "initial_states"):
        arr = np.ascontiguousarray(np.asarray(getattr(data, field)))
        digest.update(f"{field}{arr.shape}{arr.dtype}".encode())
        digest.update(arr.tobytes())
    return digest.hexdigest()
