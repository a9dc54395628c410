"""The experiments eqsmooth ships, as importable code.

Nothing here is imported by `import eqsmooth`; each experiment is a
subpackage that its example script drives:

- `eqsmooth.experiments.disk_tracking`: visual disk tracking (Yi et al.,
  2021, Sec. V-A): the data generator and renderer, the virtual sensor, noise
  heads, EKF and LSTM baselines, the training stages, the resumable 10-fold
  protocol, its report and the fresh-data confirmation
  (`examples/04_disk_tracking.py`).
- `eqsmooth.experiments.kitti_vo`: visual odometry on rendered views of the
  KITTI ground-truth trajectories (Sec. V-B) and its pre-declared data
  variant (`examples/07_kitti_vo.py`).
- `eqsmooth.experiments.pendulum_friction`: the discrepancy workflow on a real
  pendulum recording (`examples/06_discover_pendulum.py`).

They are research code with tests, not a stable API: their functions may
change with the experiments they serve.
"""
