import warnings
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import PyTree


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
            "(check the measurements and initial values for NaN/inf, and that no "
            "landmark starts at the position of its observer)."
        )
        linear_solve_failed = (
            "The linear system was singular or not positive definite (is every gauge "
            "freedom fixed by a prior? In float32, noise scales that differ by "
            "several orders of magnitude can also make it numerically singular: "
            "use float64)."
        )
        fn_not_graph_residuals = (
            "The solver's fn returned other residuals than the factor graph passed as "
            "args, at the initial values or at a perturbation of them. An eqsmooth "
            "solver linearises the graph itself, so its fn must be "
            "eqsmooth.solve.graph_residuals (use optimistix's solvers, or "
            "eqsmooth.solve.tangent_least_squares, for another residual function)."
        )


# The codes of optimistix's result enumeration, in its order; the first seven
# are lineax's (optimistix's enumeration extends lineax's, eqsmooth's
# extends optimistix's). `tests/test_lineax_optimistix.py` checks that the
# lists still cover both libraries.
LINEAX_CODES = (
    "successful",
    "max_steps_reached",
    "singular",
    "breakdown",
    "stagnation",
    "conlim",
    "nonfinite_input",
)
OPTX_CODES = LINEAX_CODES + (
    "nonlinear_max_steps_reached",
    "nonlinear_divergence",
    "nonfinite",
)


def promote_result(result: lx.RESULTS | optx.RESULTS) -> RESULTS:
    """A lineax or optimistix result code as the eqsmooth code of the same name.

    What `RESULTS.promote` does, written as comparisons with each parent
    code: equinox's `promote` builds its lookup table eagerly inside the
    trace, which compiles two tiny XLA programs in every fresh process.
    """
    parent = lx.RESULTS if isinstance(result, lx.RESULTS) else optx.RESULTS
    names = LINEAX_CODES if parent is lx.RESULTS else OPTX_CODES
    out = RESULTS.successful
    for name in names[1:]:
        out = RESULTS.where(
            result == getattr(parent, name), getattr(RESULTS, name), out
        )
    return out


class Solution(eqx.Module):
    """What [`eqsmooth.solve.least_squares`][] returns.

    **Fields:**

    - `value`: the solution values dict `{group: stacked states}`.
    - `result`: a [`eqsmooth.solve.RESULTS`][] code.
    - `stats`: dict with `num_steps`, `num_accepted`, `initial_cost`,
        `final_cost`, `cost_history` (cost after each step, padded with the
        final cost).
    - `state`: the solver's final state; its `lin` is the linearisation at
        `value` (what [`eqsmooth.solve.marginal_covariances`][] and
        [`eqsmooth.solve.joint_marginal_covariance`][] use), differentiable
        with every adjoint. Its other fields are diagnostics, not
        differentiable.
    - `padding`: `None`, or the real variable counts `((group, count), …)`
        when the solve ran on a padded copy of the graph (see
        [`eqsmooth.solve.least_squares`][]): `state` then belongs to the
        padded graph, whose groups hold the real variables first.

    Derivatives: `value`, `stats["final_cost"]`, `stats["initial_cost"]` and
    `state.lin` are differentiable with every adjoint;
    `stats["cost_history"]` only with the unrolled and truncated adjoints
    (under [`eqsmooth.solve.ImplicitAdjoint`][] differentiating it raises).
    """

    value: PyTree
    result: RESULTS
    stats: dict[str, Any]
    state: PyTree
    padding: tuple[tuple[str, int], ...] | None = eqx.field(static=True, default=None)


def raise_unless_successful(
    sol: Solution, detail: Callable[[RESULTS], str] | None = None
) -> Solution:
    """`throw=True` of the solve entry points, applied after the compiled solve
    rather than inside it.

    Called outside any JAX transformation, the result code is a concrete
    array and is checked here on the host. Under `jit`, `vmap` or `grad` (the
    arguments traced, or closed over by a traced function) it is a tracer,
    and an `eqx.error_if` on the solution joins the caller's program. The
    solve's own program is then the same with and without `throw`, and has
    no host callback: JAX neither writes a program with host callbacks to
    its persistent compilation cache nor reads one from it, so a second
    process would compile the whole solve again.
    """
    # The code as a host array, compared in numpy: an `==` of the codes would
    # be an eager JAX operation (one more compilation, and dispatch on every
    # solve), and `EnumerationItem.is_traced` is slower still.
    code = result_index(sol.result)
    try:
        code = np.asarray(code)
    except jax.errors.TracerArrayConversionError:
        value = sol.result.error_if(sol.value, sol.result != RESULTS.successful)
        return eqx.tree_at(lambda s: s.value, sol, value)
    if not np.all(code == _SUCCESS):
        message = RESULTS[sol.result]
        # On the host, the failure is narrowed down (which rows, which cause).
        more = "" if detail is None else detail(sol.result)
        raise eqx.EquinoxRuntimeError(f"{message} {more}" if more else message)
    return sol


def result_index(result: RESULTS) -> Any:
    """The index of an eqsmooth result code in [`eqsmooth.solve.RESULTS`][]: an
    integer array (a tracer under a transformation), for host-side tests.

    Only for reading a code; codes are made and converted as codes
    (`RESULTS.where`, `promote_result`), never rebuilt from an index. An
    equinox enumeration item is a Module whose one pytree leaf is its index.
    """
    if not isinstance(result, RESULTS):
        raise TypeError(
            f"result_index: expected an eqsmooth RESULTS code, got {result!r}"
        )
    (index,) = jax.tree_util.tree_leaves(result)
    return index


_SUCCESS = result_index(RESULTS.successful)
