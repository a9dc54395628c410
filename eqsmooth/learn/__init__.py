"""Learning through the solver: losses, training loop, data parallelism."""

from .._stack import stack_trees as stack_trees
from ..manifold import (
    manifold_errors as manifold_errors,
    manifold_mse as manifold_mse,
)
from ._calibration import (
    chi2_quantile as chi2_quantile,
    gaussian_calibration as gaussian_calibration,
    GaussianCalibration as GaussianCalibration,
    nees_band as nees_band,
)
from ._checkpoint import (
    atomic_write as atomic_write,
    CheckpointError as CheckpointError,
    load_checkpoint as load_checkpoint,
    previous_checkpoint as previous_checkpoint,
    read_checkpoint_header as read_checkpoint_header,
    save_checkpoint as save_checkpoint,
    TrainState as TrainState,
)
from ._losses import joint_nll as joint_nll, surrogate_loss as surrogate_loss
from ._noise_heads import (
    AbstractNoiseHead as AbstractNoiseHead,
    ConstantNoiseHead as ConstantNoiseHead,
    HeteroscedasticNoiseHead as HeteroscedasticNoiseHead,
)
from ._optim import (
    make_optimizer as make_optimizer,
    standard_promotion as standard_promotion,
)
from ._sharding import (
    batch_sharding as batch_sharding,
    initialize_distributed as initialize_distributed,
    make_mesh as make_mesh,
    replicate as replicate,
    replicated_sharding as replicated_sharding,
    shard_batch as shard_batch,
)
from ._train import (
    epoch_order as epoch_order,
    evaluate as evaluate,
    make_train_step as make_train_step,
    train as train,
    TrainResult as TrainResult,
)
from ._train_options import (
    Checkpoints as Checkpoints,
    Logging as Logging,
    Validation as Validation,
)
