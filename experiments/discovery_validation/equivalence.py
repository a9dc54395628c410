"""A non-identifiable pair must always be reported as the pair.

With a spring, a constant force `c` on the velocity and a sensor bias `c / k`
change the data in the same way once the first state is free: the
equilibrium moves, and only the prior on the first state (mean 0, std 20
here) tells the two apart, by a few nats. `eqsmooth.discover.name` groups
them by a structural test (their effects on the mean measurement path,
linearised about the MAP, are parallel once each sequence's initial state
is profiled out; `eqsmooth/discover/_structure.py`), whatever their
evidence gap. Before that test a pair was grouped only when the runner-up
came within ln 20 of the named candidate, so the prior's few nats gave the
force (or the bias) alone in some data sets.

Each data set is named twice from the same `find`: `before`, with the
structural test switched off (no pair found, which is the earlier code
path exactly), and `after`. The data are those of `nonsmooth.py`'s
constant-force cells (the same streams): the driven oscillator and the
undriven one, B = 24 sequences × T = 40 steps, SNR 1.

    python -m experiments.discovery_validation.equivalence --seeds 20 \\
        --json results/discovery_validation/equivalence.json
"""

import argparse
import time

import numpy as np

import eqsmooth.discover as dc
from benchmarks._common import write_json
from eqsmooth.discover import _name

from ._run import log, run_info, stream
from .nonsmooth import _TAGS, B, plants


PAIR = ("constant force", "sensor bias")


def outcome(named) -> str:
    """`pair` (one member named, both in its equivalence set), `alone` (one
    named without the other beside it), `both named`, or `other`."""
    chosen = [nm for nm in named["named"] if nm in PAIR]
    if len(chosen) == 2:
        return "both named"
    if not chosen:
        return "other"
    sets = [set(s) for s in named["equivalence_sets"] if s[0] == chosen[0]]
    return "pair" if any(set(PAIR) <= s for s in sets) else "alone"


def run(system: str, seeds: int) -> dict:
    plant = plants()[system]
    effect, level = "constant force", 1.0
    coef = plant.coefficient(effect, level)
    key = stream(plant.tag, _TAGS.get(effect, 0), level, 1.0, B)
    structure = _name.structure
    K = len(plant.model.candidates)
    rows = []
    for s in range(seeds):
        rng = np.random.default_rng(np.random.SeedSequence(key + [s]))
        data, _ = plant.simulate(rng, effect, coef)
        found = dc.find(plant.model, data)
        row = {"seed": s, "detected": bool(found["detected"])}
        for label, fn in (
            ("before", lambda *a: np.zeros((K, K), bool)),
            ("after", structure),
        ):
            _name.structure = fn
            try:
                t0 = time.perf_counter()
                named = dc.name(found, data)
                row[label] = {
                    "outcome": outcome(named),
                    "named": list(named["named"]),
                    "equivalence_sets": list(named["equivalence_sets"]),
                    "verdict": named["verdict"],
                    "name_s": time.perf_counter() - t0,
                }
            finally:
                _name.structure = structure
        # The first step's evidence gain of each member (the same fits in
        # both runs): how far apart the first-state prior put them.
        steps = named["steps"]
        first = steps[0]["candidates"] if steps else []
        gains = {c["name"]: c["log_marginal_gain"] for c in first}
        both = all(nm in gains for nm in PAIR)
        row["evidence_gap"] = abs(gains[PAIR[0]] - gains[PAIR[1]]) if both else None
        before, after = row["before"]["outcome"], row["after"]["outcome"]
        log(f"{system} seed {s}: {before} -> {after}")
        rows.append(row)
    counts = {
        label: {
            k: sum(r[label]["outcome"] == k for r in rows)
            for k in ("pair", "alone", "both named", "other")
        }
        for label in ("before", "after")
    }
    return {
        "system": system,
        "effect": effect,
        "snr": level,
        "coefficient": coef,
        "sequences": B,
        "n": seeds,
        "counts": counts,
        "runs": rows,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--systems", nargs="+", default=["driven", "oscillator"])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    info = run_info()
    records = []
    for system in args.systems:
        records.append(run(system, args.seeds))
        log(f"{system}: {records[-1]['counts']}")
        info["total_s"] = time.perf_counter() - t0
        if args.json:
            write_json(args.json, records, {"info": info})


if __name__ == "__main__":
    main()
