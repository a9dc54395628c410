"""eqsmooth: learning smoothers with differentiable factor-graph optimisation.

The most used names are re-exported here; the subpackages are
[`eqsmooth.lie`][], [`eqsmooth.manifold`][], [`eqsmooth.factors`][] and
[`eqsmooth.solve`][].
"""

from . import factors as factors, lie as lie, manifold as manifold, solve as solve
from .factors import (
    AbstractFactor as AbstractFactor,
    AbstractNoiseModel as AbstractNoiseModel,
    BetweenFactor as BetweenFactor,
    CauchyNoise as CauchyNoise,
    DiagonalNoise as DiagonalNoise,
    FactorGraph as FactorGraph,
    FunctionFactor as FunctionFactor,
    HuberNoise as HuberNoise,
    IsotropicNoise as IsotropicNoise,
    PriorFactor as PriorFactor,
    SqrtInformationNoise as SqrtInformationNoise,
    Var as Var,
    shared_field as shared_field,
)
from .lie import SE2 as SE2, SE3 as SE3, SO2 as SO2, SO3 as SO3
from .manifold import local as local, retract as retract
from .solve import (
    PCG as PCG,
    RESULTS as RESULTS,
    BlockTridiagonal as BlockTridiagonal,
    DenseCholesky as DenseCholesky,
    FixedStepGaussNewton as FixedStepGaussNewton,
    GaussNewton as GaussNewton,
    LevenbergMarquardt as LevenbergMarquardt,
    Solution as Solution,
    least_squares as least_squares,
    marginal_covariances as marginal_covariances,
)


__version__ = "0.1.0"
