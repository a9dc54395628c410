"""Factors and noise models."""

from ._builtin import (
    BetweenFactor as BetweenFactor,
    FunctionFactor as FunctionFactor,
    PriorFactor as PriorFactor,
)
from ._camera import (
    AbstractCalibration as AbstractCalibration,
    Cal3_S2 as Cal3_S2,
    Cal3_S2Stereo as Cal3_S2Stereo,
    Cal3DS2 as Cal3DS2,
    check_cheirality as check_cheirality,
    project as project,
    project_stereo as project_stereo,
    ProjectionFactor as ProjectionFactor,
    StereoProjectionFactor as StereoProjectionFactor,
)
from ._factor import (
    AbstractAnalyticFactor as AbstractAnalyticFactor,
    AbstractFactor as AbstractFactor,
    per_row_fields as per_row_fields,
    shared_field as shared_field,
    with_rows as with_rows,
)
from ._graph import FactorGraph as FactorGraph, GroupLayout as GroupLayout
from ._imu import (
    CombinedImuFactor as CombinedImuFactor,
    ImuFactor as ImuFactor,
    ImuTransitionFactor as ImuTransitionFactor,
    navigation_error as navigation_error,
)
from ._imu_chain import bias_walk_sigmas as bias_walk_sigmas, imu_chain as imu_chain
from ._imu_preintegration import (
    ImuParams as ImuParams,
    preintegrate as preintegrate,
    PreintegratedImuMeasurements as PreintegratedImuMeasurements,
)
from ._landmark import (
    BearingFactor as BearingFactor,
    BearingRangeFactor as BearingRangeFactor,
    PoseToPointFactor as PoseToPointFactor,
    RangeFactor as RangeFactor,
    TranslationPriorFactor as TranslationPriorFactor,
)
from ._masked_noise import MaskedNoise as MaskedNoise
from ._merge import merge_stacks as merge_stacks
from ._noise import (
    AbstractNoiseModel as AbstractNoiseModel,
    AbstractRobustNoise as AbstractRobustNoise,
    DiagonalNoise as DiagonalNoise,
    gaussian_log_normalizer as gaussian_log_normalizer,
    IsotropicNoise as IsotropicNoise,
    SqrtInformationNoise as SqrtInformationNoise,
)
from ._robust_kernels import (
    AbstractKernel as AbstractKernel,
    Cauchy as Cauchy,
    CauchyNoise as CauchyNoise,
    DCS as DCS,
    DCSNoise as DCSNoise,
    Fair as Fair,
    FairNoise as FairNoise,
    GemanMcClure as GemanMcClure,
    GemanMcClureNoise as GemanMcClureNoise,
    Huber as Huber,
    HuberNoise as HuberNoise,
    KernelChoice as KernelChoice,
    L2WithDeadZone as L2WithDeadZone,
    L2WithDeadZoneNoise as L2WithDeadZoneNoise,
    RobustNoise as RobustNoise,
    TruncatedQuadratic as TruncatedQuadratic,
    TruncatedQuadraticNoise as TruncatedQuadraticNoise,
    Tukey as Tukey,
    TukeyNoise as TukeyNoise,
    Welsch as Welsch,
    WelschNoise as WelschNoise,
)
from ._student_t import StudentTNoise as StudentTNoise
from ._variables import Var as Var
from ._vehicle import (
    vehicle_motion as vehicle_motion,
    VehicleDynamicsFactor as VehicleDynamicsFactor,
    VehicleState as VehicleState,
    VelocityMeasurementFactor as VelocityMeasurementFactor,
)
