"""Differentiable online estimators built from factors: the extended Kalman
filter, the RTS smoother and the fixed-lag smoother.

The baseline of Yi et al. (IROS 2021): the same transition and measurement
factor stacks that define a smoothing graph define the filter.
"""

from ._ekf import ekf as ekf, EKFSolution as EKFSolution
from ._fixed_lag import (
    fixed_lag_smoother as fixed_lag_smoother,
    FixedLagSolution as FixedLagSolution,
    lag_from_seconds as lag_from_seconds,
)
from ._fixed_lag_update import (
    FixedLagSmoother as FixedLagSmoother,
    FixedLagState as FixedLagState,
)
from ._losses import (
    ekf_innovation_nll as ekf_innovation_nll,
    ekf_marginal_nll as ekf_marginal_nll,
    ekf_mse_loss as ekf_mse_loss,
)
from ._rts import rts_smoother as rts_smoother, RTSSolution as RTSSolution
