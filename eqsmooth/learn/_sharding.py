"""Data parallelism: shard the batch axis over devices, replicate the model."""

from collections.abc import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import PyTree


BATCH_AXIS = "batch"


def initialize_distributed(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    auto: bool = False,
    **kwargs,
) -> bool:
    """Join a multi-host run through `jax.distributed.initialize`.

    Call it once per process, before any other JAX call, then build the mesh
    with [`eqsmooth.learn.make_mesh`][]: it spans the devices of every
    process, and [`eqsmooth.learn.shard_batch`][] assembles the global batch
    from each process's share. With every argument left out (and
    `auto=False`) it does nothing, so single-machine scripts can call it
    unconditionally.

    **Arguments:**

    - `coordinator_address`: `"host:port"` of process 0.
    - `num_processes`: total number of processes.
    - `process_id`: this process's index in `[0, num_processes)`.
    - `auto`: call `jax.distributed.initialize()` without arguments, letting
        JAX read the cluster environment (SLURM, Open MPI, Cloud TPU, ...).
    - `**kwargs`: passed on to `jax.distributed.initialize`.

    **Returns:** whether `jax.distributed.initialize` was called.
    """
    if auto:
        jax.distributed.initialize(**kwargs)
        return True
    if coordinator_address is None and num_processes in (None, 1) and not kwargs:
        return False
    jax.distributed.initialize(
        coordinator_address=coordinator_address,
        num_processes=num_processes,
        process_id=process_id,
        **kwargs,
    )
    return True


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis device mesh (axis name `"batch"`) for data parallelism.

    **Arguments:**

    - `devices`: the devices to use; default `jax.devices()` (every device of
        every process).

    **Returns:** a `jax.sharding.Mesh`.
    """
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("make_mesh: no devices")
    return Mesh(np.asarray(devices), (BATCH_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """The sharding that splits a leading batch axis over `mesh`'s devices."""
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """The sharding that keeps a full copy on every device of `mesh`."""
    return NamedSharding(mesh, PartitionSpec())


def _is_array(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray))


def shard_batch(batch: PyTree, mesh: Mesh) -> PyTree:
    """Place a batch with its leading axis split across the devices of `mesh`.

    On a single process `batch` is the global batch. On several processes
    (after [`eqsmooth.learn.initialize_distributed`][]) every process passes
    the SAME global batch (e.g. drawn with the same seed) and contributes
    only its own contiguous share of the rows, so no data moves between hosts.

    **Arguments:**

    - `batch`: a pytree of arrays with a common leading batch axis, whose
        length must be divisible by the number of devices.
    - `mesh`: from [`eqsmooth.learn.make_mesh`][].

    **Returns:** the batch as globally sharded `jax.Array`s.
    """
    sharding = batch_sharding(mesh)
    n_dev = mesh.devices.size
    leaves = [x for x in jax.tree_util.tree_leaves(batch) if _is_array(x)]
    for x in leaves:
        if np.ndim(x) == 0 or x.shape[0] % n_dev:
            raise ValueError(
                f"shard_batch: a leaf of shape {np.shape(x)} cannot be split over "
                f"{n_dev} devices; the batch size must be a multiple of the "
                "device count"
            )
    n_proc = jax.process_count()
    if n_proc == 1:
        return jax.tree_util.tree_map(
            lambda x: jax.device_put(x, sharding) if _is_array(x) else x, batch
        )
    pid = jax.process_index()

    def put(x):
        if not _is_array(x):
            return x
        rows = x.shape[0] // n_proc
        local = np.asarray(x[pid * rows : (pid + 1) * rows])
        return jax.make_array_from_process_local_data(sharding, local, x.shape)

    return jax.tree_util.tree_map(put, batch)


def replicate(tree: PyTree, mesh: Mesh) -> PyTree:
    """Copy every array leaf of `tree` (a model, an optimiser state) to all devices.

    **Arguments:**

    - `tree`: any pytree; non-array leaves are left as they are.
    - `mesh`: from [`eqsmooth.learn.make_mesh`][].

    **Returns:** the pytree with replicated `jax.Array` leaves.
    """
    sharding = replicated_sharding(mesh)
    if jax.process_count() == 1:
        return jax.tree_util.tree_map(
            lambda x: jax.device_put(x, sharding) if _is_array(x) else x, tree
        )

    def put(x):
        if not _is_array(x):
            return x
        return jax.make_array_from_process_local_data(sharding, np.asarray(x), x.shape)

    return jax.tree_util.tree_map(put, tree)
