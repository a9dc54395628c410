"""Propose: the experiment that would settle a tentative verdict or a set."""

import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._add import add
from ._find import find
from ._model import ChainModel, Sequences, simulate
from ._name import name
from ._report import FindState, StepReport


def _unresolved(named: StepReport) -> list[dict]:
    """What a `name` report leaves open: each named term in a set or an
    ambiguity (with its rivals), and each term whose shape was too weak to
    check."""
    out = []
    for group in named["equivalence_sets"] + named["ambiguous"]:
        out.append({"kind": "rivals", "named": group[0], "rivals": list(group[1:])})
    sc = named.get("shape_check")
    if sc:
        for t in sc["terms"]:
            if not t["checked"]:
                out.append({"kind": "shape", "named": t["name"]})
    return out


def _needed(item: dict, report: StepReport, size: int) -> float:
    """Sequences (of the simulated data's length) that would settle `item`,
    read from `report`, the `name` report on `size` simulated sequences of
    a design; `inf` where none would (structural equivalents, indefinite
    information, or the term not named there). A rival that is not within
    ln 20 of the named term there is separated by `size` sequences, which
    is then the figure (an upper bound)."""
    if item["kind"] == "shape":
        sc = report.get("shape_check")
        terms = [t for t in (sc or {}).get("terms", []) if t["name"] == item["named"]]
        return float(terms[0]["sequences_needed"]) if terms else math.inf
    step = next((s for s in report["steps"] if s.get("best") == item["named"]), None)
    if step is None:
        return math.inf
    rivals = {r["name"]: r for r in step.get("rivals", [])}
    worst = 0.0
    for rival in item["rivals"]:
        r = rivals.get(rival)
        if r is None:
            worst = max(worst, float(size))
            continue
        need = r.get("sequences_to_separate")
        worst = max(worst, math.inf if need is None else float(need))
    return worst


def _simulated(model: ChainModel, design: Sequences, rng) -> Sequences:
    """Sequences of `design`'s inputs and size, measured from `model` (its
    fitted coefficients and noise scales): first states drawn from the
    model's prior about the design's `x0_mean`, process and measurement
    noise added."""
    x0_mean = np.asarray(design.x0_mean)
    u = np.asarray(design.inputs)
    B, T, _ = u.shape
    q, r = np.asarray(model.process_sigma), np.asarray(model.measurement_sigma)
    x = x0_mean + np.asarray(model.prior_sigma) * rng.normal(size=x0_mean.shape)
    step = jax.jit(jax.vmap(model.transition))
    observe = jax.jit(jax.vmap(model.observe))
    xs, ys = [], []
    for t in range(T):
        xs.append(x)
        ys.append(np.asarray(observe(jnp.asarray(x), jnp.asarray(u[:, t]))))
        x = np.asarray(step(jnp.asarray(x), jnp.asarray(u[:, t])))
        x = x + q * rng.normal(size=x.shape)
    y = np.stack(ys, 1) + r * rng.normal(size=(B, T, r.shape[0]))
    # The MAP solves start from the fitted model's noise-free path from the
    # prior mean (what the experimenter can compute before measuring).
    guess, _ = simulate(model, jnp.asarray(x0_mean), jnp.asarray(u))
    return Sequences(y, x0_mean, inputs=u, initial_states=np.asarray(guess))


def propose(
    found: StepReport,
    named: StepReport,
    data: Sequences,
    designs: Mapping[str, Sequences],
    *,
    seed: int = 0,
    max_terms: int = 3,
    shape_tolerance: float = 0.2,
    shape_power: float = 0.9,
) -> dict:
    """Which of the experiments the user can run would settle what `name`
    left open, and with how many sequences.

    What is open: each named term in an equivalence set or an ambiguity
    (separating it from its rivals) and each term too weak for its shape to
    be checked. For each design, sequences with the design's inputs and
    first-state means are simulated from the current fit
    ([`eqsmooth.discover.add`][]'s model: the named coefficients and the
    fitted noise scales), and `find` and `name` run on them as on the
    data; their report gives, per open item, the number of sequences of
    that design that would settle it (the sequences that would separate the
    rivals, from their expected evidence gap, or that the shape check
    needs). A design's figure is the largest over the open items, in
    sequences of that design alone (the data already measured would add
    to them); the proposal is the design with the smallest. Structural equivalents are
    settled by no design of this model (their effects on the data are the
    same once the first state is free), and the figure is then infinite.

    **Arguments:**

    - `found`, `named`, `data`: the workflow's reports and its data.
    - `designs`: `{name: Sequences}`, the experiments the user allows: each
        gives the inputs `(B, T, k)` and first-state means `(B, n)` of one
        batch of sequences (its measurements are not read; give zeros). A
        design of the data's `B` and `T` reuses the compiled programs.
    - `seed`: the simulations' random seed.
    - `max_terms`, `shape_tolerance`, `shape_power`: as for
        [`eqsmooth.discover.name`][] (use the values the data were named
        with).

    **Returns:** a dict with `open` (the open items), `designs` (per
    design: `sequences_needed` in all, `per_item`, the verdict `name`
    reached on the simulated batch), `proposal` (the design's name, or
    `None` when nothing is open or no design settles it), `sequences` (the
    proposal's figure, rounded up) and `statement`.
    """
    st = found.state if isinstance(found, StepReport) else None
    if not isinstance(st, FindState) or not isinstance(named, StepReport):
        raise TypeError(
            "propose: found and named must be the reports of eqsmooth.discover.find "
            "and eqsmooth.discover.name, in that order"
        )
    if not isinstance(designs, Mapping) or not designs:
        raise ValueError("propose: designs must be a non-empty {name: Sequences}")
    for key, d in designs.items():
        if not isinstance(d, Sequences):
            raise TypeError(
                f"propose: design {key!r} must be a Sequences, got {type(d).__name__}"
            )
        if d.x0_mean.shape[1:] != data.x0_mean.shape[1:] or (
            d.inputs.shape[2] != data.inputs.shape[2]
        ):
            raise ValueError(
                f"propose: design {key!r} has states of {d.x0_mean.shape[1:]} and "
                f"{d.inputs.shape[2]} inputs per step; the data have "
                f"{data.x0_mean.shape[1:]} and {data.inputs.shape[2]}"
            )
    items = _unresolved(named)
    out: dict = {"open": items, "designs": {}, "proposal": None, "sequences": None}
    if not items:
        out["statement"] = "nothing is open: the verdict is confident"
        return out
    fitted = add(found, named, data)["model"]
    for key, design in designs.items():
        # The same random numbers for every design, so that their figures
        # differ by the design and not by the draw.
        sim = _simulated(fitted, design, np.random.default_rng(seed))
        f = find(
            st.model,
            sim,
            alpha=st.alpha,
            fit_noise=st.fit_noise,
            covariance=st.covariance,
        )
        n = name(
            f,
            sim,
            max_terms=max_terms,
            shape_tolerance=shape_tolerance,
            shape_power=shape_power,
        )
        per_item = [_needed(item, n, sim.num_sequences) for item in items]
        out["designs"][key] = {
            "sequences_needed": max(per_item),
            "per_item": per_item,
            "simulated_verdict": n["verdict"],
            "sequence_length": sim.length,
        }
    best = min(out["designs"], key=lambda k: out["designs"][k]["sequences_needed"])
    need = out["designs"][best]["sequences_needed"]
    if math.isinf(need):
        out["statement"] = (
            "no design given settles it: the open items stay open for every one "
            "(structural equivalents, or information that does not grow)"
        )
        return out
    out["proposal"], out["sequences"] = best, int(math.ceil(need))
    out["statement"] = (
        f"measure about {out['sequences']} sequences of design {best!r} "
        f"(length {out['designs'][best]['sequence_length']})"
    )
    return out
