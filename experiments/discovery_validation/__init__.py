"""How well the discrepancy workflow's tests work: size, power, naming and
localisation, measured by Monte Carlo on simulated systems.

These studies validate a method (`eqsmooth.discover`'s `find` → `name` →
`add`); they do not time code (its speed run is `benchmarks/discover_speed.py`).
Each is a module run from the repository's root, which saves its records and
report as it goes:

- `oscillator`: the 1-D oscillator with hidden effects in and outside the
  library, null data with several noises (size of every alarm), data size.
- `systems`: two coupled axes with two sensors; an oscillator driven by a
  known input.
- `nonsmooth`: effects outside every library (saturation, dead zone,
  backlash, stiction) must not get a confident name; effects inside keep
  theirs.
- `localise`: where `find(..., localise=True)` says a regional effect acts,
  against where it does.
- `continuous`: effects inside a continuous-time (`Integrator`) model, the
  rate library against the discrete-time one.
- `equivalence`: a non-identifiable pair (a constant force and a sensor
  bias with a spring) is reported as the pair, with and without `name`'s
  structural test.
- `physics`: the physical parameters (spring, damping, gain) fitted before
  and after the named effect is added, beside a flexible residual model:
  bias, interval width and coverage.
- `design`: following `propose`'s experiment against the default
  excitation: sequences to a confident correct name.

    python -m experiments.discovery_validation              # the list
    python -m experiments.discovery_validation.oscillator --quick

Their committed results are in `results/discovery_validation/`, named
`<study>[_<variant>].{json,md}`; each module's docstring gives the commands
that wrote them. The machine record and output helpers are the benchmarks'
(`benchmarks/_common.py`).
"""
