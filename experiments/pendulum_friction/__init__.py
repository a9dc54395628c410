"""Bearing friction of a real pendulum, found by `eqsmooth.discover`.

The stages of `python -m experiments.pendulum_friction`: the recording and its
calibration (`data`), the nominal model and its candidate effects (`model`),
a model-free energy-balance check of the friction law (`energy`), the runs
of the workflow (`experiment`) and the printed and plotted report
(`report`). The story is in docs/tutorial/pendulum.md.
"""
