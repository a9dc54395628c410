"""What the workflow's steps return: a report and the state later steps reuse."""

from typing import Any


class StepReport(dict):
    """The result of [`eqsmooth.discover.find`][] or
    [`eqsmooth.discover.name`][]: the report, a plain dict (what
    [`eqsmooth.discover.to_json`][] writes), and, as the attribute `state`,
    what the later steps reuse (the model, the evaluation at the fit, the
    feature scales, ...). The state is not part of the dict, so the report
    has no private entries and `json.dumps(to_json(report))` needs no
    filtering; `dict(report)` is the report alone.
    """

    def __init__(self, report: dict[str, Any], state: dict[str, Any]):
        super().__init__(report)
        self.state = state
