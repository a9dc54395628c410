"""Linearisation, linear solvers and nonlinear least-squares solvers."""

from ._adjoint import (
    AbstractAdjoint as AbstractAdjoint,
    ImplicitAdjoint as ImplicitAdjoint,
    TruncatedAdjoint as TruncatedAdjoint,
    UnrolledAdjoint as UnrolledAdjoint,
)
from ._block_tridiagonal import (
    BlockCyclicReduction as BlockCyclicReduction,
    BlockTridiagonal as BlockTridiagonal,
    BlockTridiagonalOperator as BlockTridiagonalOperator,
)
from ._dense import DenseCholesky as DenseCholesky
from ._gauss_newton import (
    FixedStepGaussNewton as FixedStepGaussNewton,
    GaussNewton as GaussNewton,
)
from ._least_squares import (
    AbstractFixedStepSolver as AbstractFixedStepSolver,
    AbstractLeastSquaresSolver as AbstractLeastSquaresSolver,
    least_squares as least_squares,
    LeastSquaresState as LeastSquaresState,
)
from ._levenberg_marquardt import LevenbergMarquardt as LevenbergMarquardt
from ._linear_solver import AbstractLinearSolver as AbstractLinearSolver
from ._linearization import (
    FactorLinearization as FactorLinearization,
    Linearization as Linearization,
    linearize as linearize,
)
from ._logdet import (
    block_tridiagonal_log_det as block_tridiagonal_log_det,
    normal_log_det as normal_log_det,
)
from ._marginals import marginal_covariances as marginal_covariances
from ._pcg import (
    AbstractPreconditioner as AbstractPreconditioner,
    BlockJacobi as BlockJacobi,
    ChainPreconditioner as ChainPreconditioner,
    PCG as PCG,
)
from ._solution import RESULTS as RESULTS, Solution as Solution
from ._sparse import SparseCholesky as SparseCholesky, SparseLU as SparseLU
