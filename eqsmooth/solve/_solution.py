import warnings
from typing import Any

import equinox as eqx
import optimistix as optx
from jaxtyping import Array, Float, Int, PyTree


with warnings.catch_warnings():
    # Giving `successful` a message (optimistix leaves it empty, so a good
    # result printed as `RESULTS<>`) makes equinox warn that the inherited
    # entry is redefined; the index, and so promotion from optimistix's
    # codes, is unchanged.
    warnings.simplefilter("ignore", UserWarning)

    class RESULTS(optx.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
        """Result codes of eqsmooth solves (extends `optimistix.RESULTS`)."""

        successful = "successful"

        nonfinite_problem = (
            "A factor produced a non-finite residual or Jacobian at the initial values "
            "(check the measurements and initial values for NaN/inf)."
        )
        linear_solve_failed = (
            "The linear system was singular or not positive definite (is every gauge "
            "freedom fixed by a prior?)."
        )


class Solution(eqx.Module):
    """What [`eqsmooth.solve.least_squares`][] returns.

    **Fields:**

    - `value`: the solution values dict `{group: stacked states}`.
    - `result`: a [`eqsmooth.solve.RESULTS`][] code.
    - `stats`: dict with `num_steps`, `num_accepted`, `initial_cost`,
        `final_cost`, `cost_history` (cost after each step, padded with the
        final cost).
    - `state`: the solver's final state.
    """

    value: PyTree
    result: RESULTS
    stats: dict[str, Any]
    state: PyTree


class Stats(eqx.Module):
    num_steps: Int[Array, ""]
    num_accepted: Int[Array, ""]
    cost_history: Float[Array, " max_steps_plus_one"]
