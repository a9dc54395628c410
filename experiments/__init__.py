"""The paper's experiments and the pendulum study, run from a checkout.

This folder is not part of the installed package: it holds the applications
built on eqsmooth's public API, each a subpackage with a command-line entry,
run from the repository's root:

- `python -m experiments.disk_tracking`: visual disk tracking (Yi et al.,
  2021, Sec. V-A): the data generator and renderer, the virtual sensor, noise
  heads, EKF and LSTM baselines, the training stages, the resumable 10-fold
  protocol, its report and the fresh-data confirmation.
- `python -m experiments.kitti_vo`: visual odometry on rendered views of the
  KITTI ground-truth trajectories (Sec. V-B) and its pre-declared data
  variant.
- `python -m experiments.pendulum_friction`: the discrepancy workflow on a
  real pendulum recording.
- `python -m experiments.discovery_validation.<study>`: Monte Carlo
  studies of the discrepancy workflow's tests (size, power, naming,
  localisation) on simulated systems.

Real data is read from the path a script is given, else from
`$EQSMOOTH_DATA`, else from `../shared/data` beside the checkout
(`experiments/_data.py`). The code is tested (`tests/test_disk_tracking.py`,
`tests/test_kitti_vo.py`, `tests/test_pendulum_data.py`) but is research
code, not a stable API: it changes with the experiments it serves.
"""
