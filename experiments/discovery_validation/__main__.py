"""The discovery workflow's validation studies and how to run them (results in
`results/discovery_validation/`)."""

STUDIES = {
    "oscillator": "1-D oscillator: hidden effects, null data, data size",
    "systems": "two coupled axes; a driven oscillator",
    "nonsmooth": "effects outside every library must not get a confident name",
    "localise": "where find(..., localise=True) says an effect acts",
    "continuous": "effects inside a continuous-time model",
    "equivalence": "a non-identifiable pair is always reported as the pair",
    "physics": "physical parameters before and after the named effect",
    "design": "following propose: sequences to a confident correct name",
}

if __name__ == "__main__":
    print(__doc__.replace("\n", " ").replace("`", ""), "\n")
    for name, what in STUDIES.items():
        print(f"{name}: {what}\n    python -m experiments.discovery_validation.{name}")
