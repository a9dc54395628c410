"""Input checks at the public entry points of the discovery workflow."""

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
