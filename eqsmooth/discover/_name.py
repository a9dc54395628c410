"""Name: which candidates explain what find detected, and how stable the
choice is under resampling."""

import math

import equinox as eqx
import numpy as np

from .._stats import (
    chi2_quantile,
    chi2_sf,
    noncentral_chi2_sf,
    noncentrality_for_power,
)
from ._adequacy import adequacy_test, describe_region
from ._diagnostics import innovations_significant, safe_innovation_tests
from ._find import find
from ._fit import (
    covers,
    evaluate,
    EVALUATION_ERRORS,
    fit,
    fitted_model,
    with_hessian,
)
from ._model import (
    Sequences,
)
from ._report import FindState, NameState, StepReport
from ._structure import structure
from ._validate import fingerprint


_LN20 = float(np.log(20.0))
# The alarms a run can raise; each one's false-alarm rate on data with no
# (further) missing effect is reported on the discover page of the docs.
_ALARMS = (
    "detected",
    "unnamed_structure",
    "ambiguous",
    "leftover_structure",
    "partial",
)


def _forward_step(model, data, st, current, active, remaining, out):
    """Fit every remaining candidate beside the named ones; record the step in
    `out["steps"]` (with its runner-ups' gains) and return `(index, fit,
    runner-ups within ln 20)` of the best one if it passes the Bonferroni
    gate, else None."""
    names = [c.name for c in model.candidates]
    scales = st.scales
    # Every trial starts at `current`: one Hessian over all their parameters
    # serves them all (a column per parameter, not per parameter and trial),
    # and only the chosen fit gets a Hessian at its optimum (below).
    union = np.unique(np.concatenate([active, remaining, st.nuisance]).astype(int))
    start = None
    if covers(current, union):
        start = current
    else:
        try:
            start = evaluate(model, data, current.z, current.xhat, scales, union)
        except EVALUATION_ERRORS:
            start = None  # each fit then tries its own start (and flags it)
    trials = []
    for k in remaining:
        free = np.concatenate([np.asarray(active + [k], int), st.nuisance])
        trials.append(
            (
                k,
                fit(
                    model,
                    data,
                    free,
                    current.z,
                    current.xhat,
                    scales,
                    start=start,
                    final_hessian=False,
                ),
            )
        )
    unconverged = [names[k] for k, e in trials if not e.converged]
    if unconverged:
        out["flags"].append(
            f"step {len(out['steps']) + 1}: fit did not converge for "
            + ", ".join(unconverged)
        )
    trials.sort(key=lambda t: -t[1].log_marginal)
    best_k, best = trials[0]
    lr = 2.0 * (best.log_marginal - current.log_marginal)
    p = chi2_sf(lr, 1)
    gate = st.alpha / len(remaining)
    step = {
        "candidates": [
            {
                "name": names[k],
                "log_marginal_gain": e.log_marginal - current.log_marginal,
            }
            for k, e in trials
        ],
        "best": names[best_k],
        "likelihood_ratio": lr,
        "p_value": p,
        "gate": gate,
    }
    out["steps"].append(step)
    if p >= gate:
        return None
    free = np.concatenate([np.asarray(active + [best_k], int), st.nuisance])
    try:
        best = with_hessian(model, data, best, scales, free)
    except EVALUATION_ERRORS:
        best = eqx.tree_at(lambda e: e.converged, best, False)
        out["flags"].append(
            f"step {len(out['steps'])}: no information matrix at the fit of "
            f"{names[best_k]}"
        )
    family = _family(model, best_k)
    if family is not None:
        step["profile"] = _profile(model, trials, family, current.log_marginal)
    # Members of the named candidate's family are the same effect at another
    # value of its shape parameter: the profile reports them, not a set.
    rivals = [
        (k, e) for k, e in trials[1:] if family is None or _family(model, k) != family
    ]
    close = []
    if rivals:
        step["margin"] = best.log_marginal - rivals[0][1].log_marginal
        close = [k for k, e in rivals if best.log_marginal - e.log_marginal < _LN20]
    return best_k, best, close


def _family(model, k: int) -> str | None:
    profiled = model.candidates[k].profiled
    return None if profiled is None else profiled.family


# Half the 95% point of chi-square with one degree of freedom: the drop in
# log-likelihood that bounds a profile-likelihood 95% set of one parameter.
_PROFILE_DROP = 1.92


def _profile(model, trials, family: str, log_marginal0: float) -> dict:
    """The evidence gain of every member of `family` fitted at this step, in
    the order of the profiled parameter, and the values within
    `_PROFILE_DROP` of the best (a 95% profile set on the grid)."""
    members = [(model.candidates[k].profiled, e) for k, e in trials]
    members = [(pr, e) for pr, e in members if pr is not None and pr.family == family]
    rows = sorted((pr.value, e.log_marginal - log_marginal0) for pr, e in members)
    best = max(g for _, g in rows)
    kept = [v for v, g in rows if best - g < _PROFILE_DROP]
    return {
        "family": family,
        "parameter": members[0][0].parameter,
        "values": [v for v, _ in rows],
        "log_marginal_gains": [g for _, g in rows],
        "best": next(v for v, g in rows if g == best),
        "set_95": kept,
    }


def _separation(info, best_k, k, coefficient) -> float:
    """Expected log-evidence gap between `best_k` (true, with `coefficient`)
    and `k` fitted in its place, from the information after the noise
    scales: `½ c² I_bb (1 − ρ²)`, what `k` cannot mimic of `best_k`."""
    ibb, ikk, ibk = info[best_k, best_k], info[k, k], info[best_k, k]
    if not (ibb > 0 and ikk > 0):
        return 0.0
    rho2 = min(1.0, ibk * ibk / (ibb * ikk))
    return float(0.5 * coefficient * coefficient * ibb * (1.0 - rho2))


def _definite_pair(info, a: int, b: int) -> bool:
    """Whether the 2x2 block of `info` over `a` and `b` is positive
    semi-definite with positive diagonal."""
    iaa, ibb, iab = info[a, a], info[b, b], info[a, b]
    return bool(iaa > 0 and ibb > 0 and iab * iab <= iaa * ibb)


def _classify_rivals(
    out, names, best_k, close, info, equivalence_corr, best, data, same=None
) -> None:
    """Runner-ups within ln 20 of the named candidate, and its structural
    equivalents (`same`, whatever their evidence).

    A structural equivalent changes the data exactly as the named candidate
    does once the initial state is free (`eqsmooth.discover._structure`): no
    data of this kind separate the two, only the prior on the first state,
    so it always joins the equivalence set, whichever member that prior
    favours on a given data set. Another rival is kept in a set only when
    the data cannot separate the two: the expected gap (`_separation`, at
    the named coefficient) is below ln 20. It then forms an equivalence set
    when the information correlates the two beyond `equivalence_corr`, else
    an ambiguity; either way the step records how many sequences of this
    length would separate them. A rival the data could separate is recorded
    but does not make a set (its small observed margin is then the adequacy
    test's business).
    """
    B, T = data.num_sequences, data.length
    coefficient = float(best.z[best_k])
    equiv, amb, rivals = [names[best_k]], [names[best_k]], []
    step = out["steps"][-1]
    gains = {c["name"]: c["log_marginal_gain"] for c in step.get("candidates", [])}
    if same is None:  # no structural pairs
        same = np.zeros((len(names), len(names)), bool)
    for k in np.flatnonzero(same[best_k]):
        # The evidence margin between the two (what the first-state prior
        # made of it; None for a candidate not fitted at this step).
        both = names[best_k] in gains and names[k] in gains
        margin = gains[names[best_k]] - gains[names[k]] if both else None
        rivals.append(
            {
                "name": names[k],
                "structural": True,
                "evidence_margin": margin,
                "separable": False,
                "sequences_to_separate": None,
                "sequence_length": T,
            }
        )
        equiv.append(names[k])
    for k in close:
        if same[best_k, k]:
            continue  # recorded above
        ibb, ikk, ibk = info[best_k, best_k], info[k, k], info[best_k, k]
        # Where the pair's block of the (efficient) information is not
        # positive semi-definite, its correlation can exceed 1 (−1.04 for two
        # overflow candidates of the Cascaded Tanks library). The pair is
        # still classified as below (a correlation beyond the threshold is an
        # equivalence: an actuator gain and a sensor scale of a linear model
        # gain the same evidence to 0.1 nats and land here), but no data size
        # is claimed for it.
        indefinite = not _definite_pair(info, best_k, k)
        gap = _separation(info, best_k, k, coefficient)
        corr = ibk / np.sqrt(max(ibb * ikk, 1e-300))
        separable = gap >= _LN20 and not indefinite
        needed = math.inf if gap <= 0 or indefinite else B * _LN20 / gap
        rivals.append(
            {
                "name": names[k],
                "information_indefinite": indefinite,
                "expected_gap": gap,
                "information_correlation": float(corr),
                "separable": bool(separable),
                "sequences_to_separate": needed if math.isfinite(needed) else None,
                "sequence_length": T,
            }
        )
        if separable:
            continue
        if abs(corr) >= equivalence_corr:
            equiv.append(names[k])
        else:
            amb.append(names[k])
    step["rivals"] = rivals
    if len(equiv) > 1:
        out["equivalence_sets"].append(equiv)
    if len(amb) > 1:
        out["ambiguous"].append(amb)


def _structure_or_none(model, ev, data, scales, out) -> np.ndarray:
    """`structure` about the evaluation `ev`'s MAP; no pairs (and a flag)
    when the linearisation fails."""
    K = len(model.candidates)
    try:
        same = structure(model, ev.z, data, ev.xhat, scales)
    except EVALUATION_ERRORS as e:
        out["flags"].append(f"structural equivalence not decided: {e}")
        return np.zeros((K, K), bool)
    # Members of one family are one effect (the profile reports them).
    family = [_family(model, k) for k in range(K)]
    for i, j in zip(*np.nonzero(same)):
        if family[i] is not None and family[i] == family[j]:
            same[i, j] = False
    return same


def _needed(out: dict, nm: str) -> str:
    """ " (about N sequences of length T would separate them)" for the set
    around the named `nm`, from its step's rivals."""
    for step in out["steps"]:
        if step["best"] != nm:
            continue
        kept = [r for r in step.get("rivals", []) if not r["separable"]]
        sizes = [r["sequences_to_separate"] for r in kept]
        if not kept:
            return ""
        if all(r.get("structural") for r in kept):
            return (
                " (with the first state free they change the data in the same way: "
                "no amount of data of this kind separates them)"
            )
        if any(r.get("information_indefinite") for r in kept):
            return (
                " (the information is indefinite for some of them: no data size "
                "that would separate them can be given)"
            )
        if any(n is None for n in sizes):
            return " (no amount of data of this kind separates them)"
        return (
            f" (about {math.ceil(max(sizes))} sequences of length "
            f"{kept[0]['sequence_length']} would separate them)"
        )
    return ""


def _profile_note(out: dict, nm: str) -> str:
    """ " (level in 19.2 – 24.7 at 95%)" for a named family member: the grid
    values of its parameter within the profile's 95% set."""
    for step in out["steps"]:
        if step["best"] != nm or "profile" not in step:
            continue
        pr = step["profile"]
        kept = pr["set_95"]
        if len(kept) == len(pr["values"]) and len(kept) > 1:
            return f" ({pr['parameter']} not resolved by the grid)"
        if len(kept) == 1:
            return f" ({pr['parameter']} {kept[0]:.4g} of {len(pr['values'])} values)"
        return (
            f" ({pr['parameter']} in {kept[0]:.4g} – {kept[-1]:.4g} at 95%, "
            f"{len(pr['values'])} values)"
        )
    return ""


def _shape_check(out: dict, alpha: float, data, tolerance: float, power: float):
    """Whether the adequacy test could have seen the named terms' shapes be
    wrong by `tolerance` of their size: the `shape_check` report, or None
    when the test did not run or already failed (the verdict is then partial).

    A departure carrying the fraction `tolerance` of a named term's size
    carries about `tolerance²` of its evidence: noncentrality
    `tolerance² · LR` in the adequacy test, whose blocks' joint tests are
    `χ²` tests at `alpha / (2 · blocks)`. The term's shape is checked when
    that noncentrality reaches the one the test detects with probability
    `power`; a weaker term may be a smooth stand-in for an effect the library
    lacks (an input saturation fitted as a gain leaves a third of it
    unexplained) that no test at this data size can see, so its name is
    tentative. The likelihood ratio grows in proportion to the number of
    sequences, which gives the data size that would check it.
    """
    ad = out.get("adequacy", {})
    if not ad.get("tested") or ad.get("significant"):
        return None
    blocks = ad["blocks"]
    df = max(b["df"] for b in blocks)
    # Each block's p-value is twice the smaller of its joint and largest-
    # single p-values, Bonferroni-corrected over the blocks: the joint test
    # of one block rejects at `alpha / (2 · blocks)`.
    level = alpha / (2 * len(blocks))
    crit = chi2_quantile(1.0 - level, df)
    needed = noncentrality_for_power(crit, df, power) / tolerance**2
    terms = []
    for step in out["steps"][: len(out["named"])]:
        lr = float(step["likelihood_ratio"])
        terms.append(
            {
                "name": step["best"],
                "likelihood_ratio": lr,
                "power": noncentral_chi2_sf(crit, df, tolerance**2 * max(lr, 0.0)),
                "checked": bool(lr >= needed),
                "sequences_needed": int(
                    math.ceil(data.num_sequences * needed / max(lr, 1e-12))
                ),
            }
        )
    return {
        "tolerance": tolerance,
        "power": power,
        "needed_likelihood_ratio": needed,
        "sequence_length": int(data.length),
        "terms": terms,
        "checked": all(t["checked"] for t in terms),
    }


def _shape_note(out: dict) -> str:
    """ " (too weak for its shape to be checked: ...)" when a named term's
    shape was not checkable."""
    sc = out.get("shape_check")
    if not sc or sc["checked"]:
        return ""
    weak = [t for t in sc["terms"] if not t["checked"]]
    pct = round(100 * sc["tolerance"])
    names = ", ".join(t["name"] for t in weak)
    power = min(t["power"] for t in weak)
    need = max(t["sequences_needed"] for t in weak)
    return (
        f" ({names}: too weak for its shape to be checked; a departure of "
        f"{pct}% of it would be seen with probability "
        f"{math.floor(100 * power) / 100:.2f}; about "
        f"{need} sequences of length {sc['sequence_length']} would check it)"
    )


def _verdict(out: dict, leftover: bool) -> str:
    """The sentence that sums up a `name` report."""
    parts = []
    for nm in out["named"]:
        eq = [s for s in out["equivalence_sets"] if s[0] == nm]
        am = [s for s in out["ambiguous"] if s[0] == nm]
        if eq:
            parts.append(
                "not identifiable from this data: {"
                + " ≡ ".join(eq[0])
                + "}"
                + _needed(out, nm)
            )
        elif am:
            parts.append("ambiguous: {" + ", ".join(am[0]) + "}" + _needed(out, nm))
        else:
            parts.append(nm + _profile_note(out, nm))
    partial = out.get("adequacy", {})
    if partial.get("significant"):
        w = partial["where"]
        parts = [
            "partial: " + "; ".join(parts) + " explains part of the mismatch; "
            f"structure remains in {w['equation']} as a function of "
            f"{w['variable']}, in {describe_region(w['variable'], w['region'])} "
            f"(largest near {w['variable']} = {w['near']:.3g})"
        ]
    elif out["tentative"]:
        parts = ["tentative: " + "; ".join(parts) + _shape_note(out)]
    if leftover:
        parts.append("unnamed residual structure")
    elif not out["named"]:
        parts.append(
            "a missing effect is detected, but no candidate passes the naming "
            "test and the residual diagnostics are clean"
        )
    return "; ".join(parts)


def _leftover(out: dict, model, data, current, alpha: float) -> bool:
    """Whether the named model still fails its innovation diagnostics; records
    them and the alarms and flags that follow in `out`."""
    final = fitted_model(model, current.z)
    innov = safe_innovation_tests(final, data, current.xhat, out["flags"])
    leftover = innovations_significant(innov, alpha)
    out["leftover_diagnostics"] = {
        "nis_p_value": innov["nis_p_value"],
        "bias_p_values": [b["p_value"] for b in innov["bias"]],
        "whiteness_p_values": [w["p_value"] for w in innov["whiteness"]],
    }
    out["alarms"]["ambiguous"] = bool(out["ambiguous"])
    # "Unnamed residual structure" claims structure in the residuals, so it
    # needs the residual diagnostics, not only the decision test (whose
    # false rejections are already the "detected" alarm): counting a false
    # detection twice held the alarm at about 2α on null data.
    out["alarms"]["unnamed_structure"] = not out["named"] and leftover
    out["alarms"]["leftover_structure"] = bool(out["named"]) and leftover
    out["unnamed_residual_structure"] = bool(leftover)
    return leftover


def name(
    found: StepReport,
    data: Sequences,
    *,
    max_terms: int = 3,
    equivalence_corr: float = 0.95,
    adequacy: bool = True,
    shape_tolerance: float = 0.2,
    shape_power: float = 0.9,
) -> StepReport:
    """Name the missing effect(s) by forward selection on the Laplace evidence.

    Not significant in the decision test: "no missing effect detected" with
    the smallest detectable effect per candidate. Otherwise, at each step
    every remaining candidate is fitted (with the already named ones and the
    noise scales) by maximising the Laplace marginal likelihood; the best is
    named if its likelihood-ratio test passes a Bonferroni gate
    (`p < alpha / number of remaining candidates`). A runner-up within
    `ln 20` log-units makes the step "ambiguous"; when the two candidates'
    observed-information correlation exceeds `equivalence_corr` the
    data cannot tell them apart and they are reported as an equivalence set.
    Candidates that are *structurally* equivalent to the named one (their
    effects on the mean measurement path, linearised about the nominal MAP
    with each sequence's initial state free, are parallel: a constant force
    and a sensor bias with a spring) are always in its equivalence set,
    however far the prior on the first state puts their evidences apart, and
    leave the library once it is named.
    If the innovation diagnostics of the final model stay significant, the
    verdict includes "unnamed residual structure": with no name, something
    the library does not contain; with names, the names are reported as
    tentative (an effect outside the library must not get a confident name
    from its closest candidate). If the decision test fires but no candidate
    passes the gate and the diagnostics are clean, the verdict says so
    without claiming residual structure (the "detected" alarm is raised).

    **Adequacy.** A wrong smooth candidate can absorb much of an effect the
    library does not contain (a saturation fitted as a gain) and leave the
    innovations clean. So once something is named, a nonparametric
    alternative is score-tested at the named fit: piecewise-linear hat
    functions (knots at quantiles of the variable) of every state and input,
    on every equation a named candidate (or one in a set with it) acts on,
    one block per (variable,
    equation), Bonferroni over the blocks. If the named model fails it, the
    verdict says "partial: X explains part of the mismatch; structure
    remains in <equation> as a function of <variable> (largest near
    <value>)", the "partial" alarm is raised and `adequacy` reports every
    block. Equations are named `x{i}'` (the next value of state `i`) and
    `y{j}` (measurement channel `j`); variables `x{i}` and `u{k}` (input
    `k`).

    **Shape check.** Passing the adequacy test says little when the test
    could not have failed: a weak term's shape cannot be checked, and a
    smooth candidate standing in for an effect the library lacks (an input
    saturation fitted as an actuator gain leaves about a third of the
    effect unexplained) passes it at realistic data sizes. So a named term
    is confident only when the adequacy test would have detected a
    departure of `shape_tolerance` (20%) of its size with probability
    `shape_power` (0.9): taking such a departure to carry
    `shape_tolerance²` of the term's evidence, its likelihood ratio must
    reach `λ / shape_tolerance²`, with `λ` the noncentrality at which the
    adequacy test's largest block (its joint `χ²` test at
    `alpha / (2 · blocks)`) has that power. (At 30%, an input saturation
    whose remainder is a third of the effect was still named confidently in
    5 of 20 data sets of 48 sequences: the hats see roughly half the
    noncentrality this share gives it.) A weaker term is named
    tentatively, with the probability that such a departure would have been
    seen and the number of sequences (the likelihood ratio grows in
    proportion) that would check it (`shape_check`).

    Never raises on a numerical failure: a fit that did not converge is
    listed in `flags`, and a failed `find` gives the verdict "no decision".

    **Arguments:**

    - `found`: the output of [`eqsmooth.discover.find`][].
    - `data`: the same sequences.
    - `max_terms`: at most this many named terms.
    - `equivalence_corr`: information-correlation threshold for equivalence.
    - `adequacy`: run the adequacy test of the named model. Its hats are
        scored through the model's own score program, as additive terms
        linear in the state about the MAP (no extra compilation).
    - `shape_tolerance`: the fraction of a named term's size that a
        departure from its shape must reach to count (in `(0, 1]`).
    - `shape_power`: the probability with which the adequacy test must
        detect such a departure for the name to be confident (in `(0, 1)`).

    **Returns:** a [`eqsmooth.discover.StepReport`][] (its `state` a
    [`eqsmooth.discover.NameState`][]) with `verdict` (a
    sentence), `named` (list of names),
    `steps` (the selection table), `equivalence_sets`, `ambiguous`,
    `tentative`, `adequacy` (when something was named: `significant`,
    `p_value`, `where` and the per-block tests), `shape_check` (when the
    adequacy test passed: per named term its likelihood ratio, the power to
    see a departure of `shape_tolerance`, whether that was enough, and the
    sequences that would make it so), `flags` and `alarms`
    (which of "detected", "unnamed_structure", "ambiguous",
    "leftover_structure" and "partial" were raised).
    """
    if not 0.0 < shape_tolerance <= 1.0:
        raise ValueError(
            f"name: shape_tolerance must lie in (0, 1], got {shape_tolerance}"
        )
    if not 0.0 < shape_power < 1.0:
        raise ValueError(f"name: shape_power must lie in (0, 1), got {shape_power}")
    st = found.state if isinstance(found, StepReport) else None
    if not isinstance(st, FindState):
        raise TypeError(
            "name: found must be the report eqsmooth.discover.find returned, got "
            + (f"{type(found).__name__}" if st is None else "the report of name")
        )
    if st.fingerprint != fingerprint(data):
        raise ValueError(
            "name: data are not the sequences find analysed (their contents differ); "
            "name the effect on the data find was given, or run find on these"
        )
    out = {
        "named": [],
        "steps": [],
        "equivalence_sets": [],
        "ambiguous": [],
        "unnamed_residual_structure": False,
        "tentative": False,
        "shape_check": None,
        "flags": [],
        "alarms": dict.fromkeys(_ALARMS, False),
    }
    if st.failed:
        out["verdict"] = "no decision: " + "; ".join(found["flags"])
        return StepReport(out, NameState(None, ()))
    model, ev0 = st.model, st.evaluation
    alpha = st.alpha
    names = [c.name for c in model.candidates]
    out["alarms"]["detected"] = bool(found["detected"])
    if not found["detected"]:
        mde = {c["name"]: c["smallest_detectable"] for c in found["candidates"]}
        out["verdict"] = "no missing effect detected"
        if st.diagnostics_significant:
            # The innovations are not white / not consistent, yet no candidate
            # scores: something the library does not contain.
            out["verdict"] = "unnamed residual structure (no candidate explains it)"
            out["unnamed_residual_structure"] = True
            out["alarms"]["unnamed_structure"] = True
        out["smallest_detectable"] = mde
        return StepReport(out, NameState(ev0, ()))
    active: list[int] = []
    current = ev0
    # Structural equivalents (decided once, about the nominal MAP, from the
    # model and the inputs): computed at the first name.
    same = None
    for _ in range(max_terms):
        # A named family member takes its family out of the library, and a
        # named candidate its structural equivalents: beside it they could
        # only move the first states towards their prior.
        taken = {_family(model, k) for k in active} - {None}
        twins = set() if same is None else set(np.flatnonzero(same[active].any(0)))
        remaining = [
            k
            for k in range(len(names))
            if k not in active
            and k not in twins
            and st.identifiable[k]
            and _family(model, k) not in taken
        ]
        if not remaining:
            break
        chosen = _forward_step(model, data, st, current, active, remaining, out)
        if chosen is None:
            break
        best_k, current, close = chosen
        if same is None:
            same = _structure_or_none(model, ev0, data, st.scales, out)
        _classify_rivals(
            out,
            names,
            best_k,
            close,
            st.efficient_information,
            equivalence_corr,
            current,
            data,
            same,
        )
        active.append(best_k)
        out["named"].append(names[best_k])
    leftover = _leftover(out, model, data, current, alpha)
    if out["named"] and adequacy:
        # The equations of the named candidates and of those reported in a
        # set with them (the data could not tell which acts).
        rivals = out["equivalence_sets"] + out["ambiguous"]
        acting = set(active) | {model.index(nm) for group in rivals for nm in group}
        out["adequacy"] = adequacy_test(
            model, data, current.z, current.xhat, st.nuisance, alpha, sorted(acting)
        )
        out["alarms"]["partial"] = out["adequacy"]["significant"]
        out["shape_check"] = _shape_check(
            out, alpha, data, shape_tolerance, shape_power
        )
    # Names are tentative when the fitted model still fails its own
    # diagnostics (the effect may lie outside the library, and the closest
    # candidate would otherwise get a confident name), or when the named
    # terms are too weak for the adequacy test to check their shapes.
    unchecked = out["shape_check"] is not None and not out["shape_check"]["checked"]
    out["tentative"] = bool(out["named"]) and (leftover or unchecked)
    out["verdict"] = _verdict(out, leftover)
    return StepReport(out, NameState(current, tuple(active)))


def bootstrap(
    found: StepReport,
    data: Sequences,
    *,
    named: StepReport | None = None,
    num_resamples: int = 20,
    seed: int = 0,
    max_terms: int = 3,
) -> dict:
    """Stability of the naming under resampling of the sequences.

    Draws `num_resamples` bootstrap samples of the sequences (with
    replacement, same count, so compiled code is reused), reruns
    [`eqsmooth.discover.find`][] and [`eqsmooth.discover.name`][] on each
    with the settings of `found`, and counts how often each candidate is
    named, how often something is detected, and how often the verdict's
    named set equals the one on the full data. A name that appears in most
    resamples is stable; one that comes and goes rests on a few sequences.
    A candidate inside a reported equivalence or ambiguous set counts as
    included with the named one (the data could not separate them).

    **Arguments:**

    - `found`: the output of [`eqsmooth.discover.find`][] on `data`.
    - `data`: the same sequences.
    - `named`: the output of [`eqsmooth.discover.name`][] on `data`, if
        already computed (otherwise it is recomputed).
    - `num_resamples`: number of bootstrap samples.
    - `seed`: seed of the resampling.
    - `max_terms`: see [`eqsmooth.discover.name`][].

    **Returns:** a dict with `num_resamples`, `detected_rate`,
    `inclusion` (`{candidate name: fraction of resamples naming it, alone or
    inside a set}`), `named_alone` (`{name: fraction named as the single
    unambiguous choice}`), `same_named_set_rate` (fraction whose named set
    equals the full-data one) and `named_sets` (each resample's named set).
    """
    if num_resamples < 1:
        raise ValueError(f"bootstrap: num_resamples must be >= 1, got {num_resamples}")
    st = found.state
    model = st.model
    if named is None:
        named = name(found, data, max_terms=max_terms)
    reference = set(named["named"])
    rng = np.random.default_rng(seed)
    names = [c.name for c in model.candidates]
    inclusion = dict.fromkeys(names, 0)
    alone = dict.fromkeys(names, 0)
    detected = same = 0
    sets = []
    B = data.num_sequences
    for _ in range(num_resamples):
        sample = data.take(rng.integers(0, B, size=B))
        f = find(
            model,
            sample,
            alpha=st.alpha,
            fit_noise=st.fit_noise,
            covariance=st.covariance,
        )
        n = name(f, sample, max_terms=max_terms, adequacy=False)
        detected += int(f["detected"])
        chosen = set(n["named"])
        same += int(chosen == reference)
        sets.append(sorted(chosen))
        grouped = {nm: {nm} for nm in chosen}
        for group in n["equivalence_sets"] + n["ambiguous"]:
            grouped.setdefault(group[0], set()).update(group)
        for nm, members in grouped.items():
            for member in members:
                inclusion[member] += 1
            if members == {nm}:
                alone[nm] += 1
    return {
        "num_resamples": num_resamples,
        "seed": seed,
        "detected_rate": detected / num_resamples,
        "inclusion": {k: v / num_resamples for k, v in inclusion.items()},
        "named_alone": {k: v / num_resamples for k, v in alone.items()},
        "same_named_set_rate": same / num_resamples,
        "reference_named_set": sorted(reference),
        "named_sets": sets,
    }
