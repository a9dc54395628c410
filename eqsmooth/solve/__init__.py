"""Linearisation, linear solvers and nonlinear least-squares solvers."""

from ._adjoint import (
    AbstractAdjoint as AbstractAdjoint,
    ImplicitAdjoint as ImplicitAdjoint,
    TruncatedAdjoint as TruncatedAdjoint,
    UnrolledAdjoint as UnrolledAdjoint,
)
from ._block_tridiagonal import (
    block_tridiagonal_log_det as block_tridiagonal_log_det,
    BlockCyclicReduction as BlockCyclicReduction,
    BlockTridiagonal as BlockTridiagonal,
    BlockTridiagonalOperator as BlockTridiagonalOperator,
    ChainFactorization as ChainFactorization,
)
from ._default_solver import (
    default_linear_solver as default_linear_solver,
    factorize as factorize,
)
from ._dense import (
    DenseCholesky as DenseCholesky,
    DenseFactorization as DenseFactorization,
)
from ._gauss_newton import (
    FixedStepGaussNewton as FixedStepGaussNewton,
    GaussNewton as GaussNewton,
    GaussNewtonState as GaussNewtonState,
)
from ._graph_solver import (
    AbstractConvergingSolver as AbstractConvergingSolver,
    AbstractFixedStepSolver as AbstractFixedStepSolver,
    AbstractGraphSolver as AbstractGraphSolver,
    graph_residuals as graph_residuals,
)
from ._joint_marginals import joint_marginal_covariance as joint_marginal_covariance
from ._least_squares import least_squares as least_squares
from ._levenberg_marquardt import (
    LevenbergMarquardt as LevenbergMarquardt,
    LevenbergMarquardtState as LevenbergMarquardtState,
)
from ._linear_solver import (
    AbstractFactorization as AbstractFactorization,
    AbstractNormalSolver as AbstractNormalSolver,
    NormalOperator as NormalOperator,
    solve_normal as solve_normal,
)
from ._linearization import (
    FactorLinearization as FactorLinearization,
    Linearization as Linearization,
    linearize as linearize,
)
from ._logdet import normal_log_det as normal_log_det
from ._marginals import marginal_covariances as marginal_covariances
from ._pcg import (
    AbstractPreconditioner as AbstractPreconditioner,
    BlockJacobi as BlockJacobi,
    ChainPreconditioner as ChainPreconditioner,
    PCG as PCG,
)
from ._solution import RESULTS as RESULTS, Solution as Solution
from ._sparsax import (
    sparsax_blas as sparsax_blas,
    SparsaxCholesky as SparsaxCholesky,
    SparsaxFactorization as SparsaxFactorization,
)
from ._sparse import SparseCholesky as SparseCholesky, SparseLU as SparseLU
from ._tangent import (
    tangent_least_squares as tangent_least_squares,
    TangentResiduals as TangentResiduals,
)
