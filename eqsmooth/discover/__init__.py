"""The model-discrepancy workflow: find, name, add, show.

See the [API page](../api/discover.md) for the statistics behind each step.
"""

from ._add import add as add
from ._candidates import (
    Candidate as Candidate,
    mechanical_library as mechanical_library,
    Profiled as Profiled,
)
from ._design import propose as propose
from ._find import find as find
from ._integrator import Integrator as Integrator
from ._laplace import (
    laplace_at_map as laplace_at_map,
    laplace_log_marginal as laplace_log_marginal,
)
from ._model import ChainModel as ChainModel, Sequences as Sequences
from ._name import bootstrap as bootstrap, name as name
from ._report import (
    FindState as FindState,
    NameState as NameState,
    StepReport as StepReport,
)
from ._score import score_test as score_test
from ._show import discover as discover, show as show, to_json as to_json
