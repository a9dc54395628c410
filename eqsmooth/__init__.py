"""eqsmooth: learning smoothers with differentiable factor-graph optimisation.

The most used names are re-exported here; the subpackages are
[`eqsmooth.lie`][], [`eqsmooth.manifold`][], [`eqsmooth.factors`][] and
[`eqsmooth.solve`][].
"""

from . import (
    discover as discover,
    factors as factors,
    filters as filters,
    io as io,
    learn as learn,
    lie as lie,
    manifold as manifold,
    solve as solve,
)
from ._compilation_cache import (
    enable_compilation_cache as enable_compilation_cache,
)
from ._xla_flags import set_xla_cpu_flags as set_xla_cpu_flags
from .factors import (
    AbstractAnalyticFactor as AbstractAnalyticFactor,
    AbstractFactor as AbstractFactor,
    AbstractNoiseModel as AbstractNoiseModel,
    AbstractRobustNoise as AbstractRobustNoise,
    BearingFactor as BearingFactor,
    BearingRangeFactor as BearingRangeFactor,
    BetweenFactor as BetweenFactor,
    Cal3_S2 as Cal3_S2,
    Cal3_S2Stereo as Cal3_S2Stereo,
    Cal3DS2 as Cal3DS2,
    CauchyNoise as CauchyNoise,
    CombinedImuFactor as CombinedImuFactor,
    DCSNoise as DCSNoise,
    DiagonalNoise as DiagonalNoise,
    FactorGraph as FactorGraph,
    FairNoise as FairNoise,
    FunctionFactor as FunctionFactor,
    GemanMcClureNoise as GemanMcClureNoise,
    HuberNoise as HuberNoise,
    ImuFactor as ImuFactor,
    ImuParams as ImuParams,
    IsotropicNoise as IsotropicNoise,
    L2WithDeadZoneNoise as L2WithDeadZoneNoise,
    MaskedNoise as MaskedNoise,
    PoseToPointFactor as PoseToPointFactor,
    preintegrate as preintegrate,
    PreintegratedImuMeasurements as PreintegratedImuMeasurements,
    PriorFactor as PriorFactor,
    ProjectionFactor as ProjectionFactor,
    RangeFactor as RangeFactor,
    RobustNoise as RobustNoise,
    shared_field as shared_field,
    SqrtInformationNoise as SqrtInformationNoise,
    StereoProjectionFactor as StereoProjectionFactor,
    StudentTNoise as StudentTNoise,
    TranslationPriorFactor as TranslationPriorFactor,
    TruncatedQuadraticNoise as TruncatedQuadraticNoise,
    TukeyNoise as TukeyNoise,
    Var as Var,
    WelschNoise as WelschNoise,
)
from .filters import ekf as ekf, rts_smoother as rts_smoother
from .learn import (
    joint_nll as joint_nll,
    make_optimizer as make_optimizer,
    manifold_mse as manifold_mse,
    surrogate_loss as surrogate_loss,
    train as train,
)
from .lie import SE2 as SE2, SE3 as SE3, SO2 as SO2, SO3 as SO3
from .manifold import local as local, retract as retract
from .solve import (
    BlockTridiagonal as BlockTridiagonal,
    ChainPreconditioner as ChainPreconditioner,
    DenseCholesky as DenseCholesky,
    FixedStepGaussNewton as FixedStepGaussNewton,
    GaussNewton as GaussNewton,
    ImplicitAdjoint as ImplicitAdjoint,
    joint_marginal_covariance as joint_marginal_covariance,
    least_squares as least_squares,
    least_squares_batch as least_squares_batch,
    LevenbergMarquardt as LevenbergMarquardt,
    linearize as linearize,
    marginal_covariances as marginal_covariances,
    PCG as PCG,
    RESULTS as RESULTS,
    Solution as Solution,
    SparsaxCholesky as SparsaxCholesky,
    SparseCholesky as SparseCholesky,
    SparseLU as SparseLU,
    TruncatedAdjoint as TruncatedAdjoint,
    TwoLevelPreconditioner as TwoLevelPreconditioner,
    UnrolledAdjoint as UnrolledAdjoint,
)


__version__ = "0.2.0"
