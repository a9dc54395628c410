"""Speed runs of eqsmooth, each a module run from the repository root.

`python -m benchmarks.<name> --help` says what one measures; its docstring
gives the commands that wrote its results, `benchmarks/results/<workload>.json`
(and `.md`). The statistical studies of the discovery workflow (size, power,
localisation of its tests) are experiments, not speed runs:
`experiments/discovery_validation/`.
"""
