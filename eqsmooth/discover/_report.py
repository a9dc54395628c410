"""What the workflow's steps return: a report and the state later steps reuse."""

from collections.abc import Iterator, Mapping
from typing import Any

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float, Int

from ._fit import Evaluation
from ._model import ChainModel


class FindState(eqx.Module):
    """What [`eqsmooth.discover.find`][] hands on to the later steps.

    **Fields:**

    - `fingerprint`: a digest of the sequences find analysed (the later
        steps refuse other data).
    - `model`: the nominal [`eqsmooth.discover.ChainModel`][], candidate
        coefficients zero.
    - `alpha`, `fit_noise`, `covariance`: find's settings (a bootstrap
        resample reruns find with them).
    - `failed`: the evidence could not be evaluated; the fields below are
        then `None` (or false).
    - `evaluation`: the evidence at the nominal fit, with its scores and
        information over every candidate and the nuisance parameters.
    - `scales`: the candidates' feature scales (their step sizes).
    - `nuisance`: the indices of the noise scales in the parameter vector
        (empty without `fit_noise`).
    - `efficient_information`: the candidates' information after the
        nuisance parameters.
    - `identifiable`: per candidate, whether that information is not (almost)
        all explained by the nuisance parameters.
    - `diagnostics_significant`: whether the innovation diagnostics of the
        nominal fit raise an alarm.
    """

    fingerprint: str
    model: ChainModel
    alpha: float = eqx.field(static=True)
    fit_noise: bool = eqx.field(static=True)
    covariance: str = eqx.field(static=True)
    failed: bool = eqx.field(static=True, default=False)
    evaluation: Evaluation | None = None
    scales: Float[np.ndarray, " K"] | None = None
    nuisance: Int[np.ndarray, " n"] | None = None
    efficient_information: Float[np.ndarray, "K K"] | None = None
    identifiable: Bool[np.ndarray, " K"] | None = None
    diagnostics_significant: bool = False


class NameState(eqx.Module):
    """What [`eqsmooth.discover.name`][] hands on to
    [`eqsmooth.discover.add`][].

    **Fields:**

    - `evaluation`: the evidence at the fit of the named candidates (`None`
        after a failed find).
    - `active`: the named candidates' indices in the model's library, in the
        order they were named.
    """

    evaluation: Evaluation | None
    active: tuple[int, ...]


class StepReport(eqx.Module, Mapping[str, Any]):
    """The result of [`eqsmooth.discover.find`][] or
    [`eqsmooth.discover.name`][].

    It reads as the report, a read-only mapping of plain values (what
    [`eqsmooth.discover.to_json`][] writes): `named["verdict"]`,
    `dict(found)`. What the later steps reuse (the model, the evaluation at
    the fit, the feature scales, ...) is its `state`, which is not part of
    the mapping, so the report has no private entries and
    `json.dumps(to_json(report))` needs no filtering.

    **Fields:**

    - `report`: the report, a dict of JSON-serialisable values.
    - `state`: a [`eqsmooth.discover.FindState`][] (from `find`) or a
        [`eqsmooth.discover.NameState`][] (from `name`).
    """

    report: dict[str, Any]
    state: FindState | NameState

    def __getitem__(self, key: str) -> Any:
        return self.report[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.report)

    def __len__(self) -> int:
        return len(self.report)
