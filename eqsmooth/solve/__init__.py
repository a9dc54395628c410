"""Linearisation, linear solvers and nonlinear least-squares solvers."""

from ._incremental import (
    IncrementalSmoother as IncrementalSmoother,
    IncrementalState as IncrementalState,
)
from ._linear._block_tridiagonal import (
    block_tridiagonal_log_det as block_tridiagonal_log_det,
    BlockCyclicReduction as BlockCyclicReduction,
    BlockTridiagonal as BlockTridiagonal,
    BlockTridiagonalOperator as BlockTridiagonalOperator,
    ChainFactorization as ChainFactorization,
)
from ._linear._default_solver import (
    default_linear_solver as default_linear_solver,
    factorize as factorize,
)
from ._linear._dense import (
    DenseCholesky as DenseCholesky,
    DenseFactorization as DenseFactorization,
)
from ._linear._linear_solver import (
    AbstractFactorization as AbstractFactorization,
    AbstractNormalSolver as AbstractNormalSolver,
    NormalOperator as NormalOperator,
    solve_normal as solve_normal,
)
from ._linear._pcg import (
    AbstractPreconditioner as AbstractPreconditioner,
    BlockJacobi as BlockJacobi,
    ChainPreconditioner as ChainPreconditioner,
    PCG as PCG,
)
from ._linear._sparsax import (
    sparsax_blas as sparsax_blas,
    SparsaxCholesky as SparsaxCholesky,
    SparsaxFactorization as SparsaxFactorization,
)
from ._linear._sparse import SparseCholesky as SparseCholesky, SparseLU as SparseLU
from ._linear._two_level import TwoLevelPreconditioner as TwoLevelPreconditioner
from ._linearization import (
    FactorLinearization as FactorLinearization,
    Linearization as Linearization,
    linearize as linearize,
)
from ._nonlinear._adjoint import (
    AbstractAdjoint as AbstractAdjoint,
    ImplicitAdjoint as ImplicitAdjoint,
    TruncatedAdjoint as TruncatedAdjoint,
    UnrolledAdjoint as UnrolledAdjoint,
)
from ._nonlinear._batch import least_squares_batch as least_squares_batch
from ._nonlinear._descent import (
    AbstractDescent as AbstractDescent,
    DampedDescent as DampedDescent,
    UndampedDescent as UndampedDescent,
)
from ._nonlinear._gauss_newton import (
    AbstractGaussNewton as AbstractGaussNewton,
    FixedStepGaussNewton as FixedStepGaussNewton,
    GaussNewton as GaussNewton,
    GaussNewtonState as GaussNewtonState,
    LevenbergMarquardt as LevenbergMarquardt,
    LevenbergMarquardtState as LevenbergMarquardtState,
)
from ._nonlinear._graph_solver import AbstractGraphSolver as AbstractGraphSolver
from ._nonlinear._least_squares import least_squares as least_squares
from ._nonlinear._residuals import graph_residuals as graph_residuals
from ._nonlinear._stopping import (
    AbstractStopping as AbstractStopping,
    FixedSteps as FixedSteps,
    Tolerances as Tolerances,
)
from ._nonlinear._tangent import (
    tangent_least_squares as tangent_least_squares,
    TangentResiduals as TangentResiduals,
)
from ._padding import (
    pad_graph as pad_graph,
    PaddedGraph as PaddedGraph,
    power_of_two as power_of_two,
)
from ._posterior._joint_marginals import (
    joint_marginal_covariance as joint_marginal_covariance,
)
from ._posterior._logdet import normal_log_det as normal_log_det
from ._posterior._marginals import marginal_covariances as marginal_covariances
from ._solution import RESULTS as RESULTS, Solution as Solution
