"""Data parallelism with jax.sharding: the batch is split along its first axis over the devices
of a 1-D mesh ("data"), parameters are replicated.

In one process the mesh holds (some of) the local devices and the host batch is placed whole.
In a multi-process job (:mod:`jaxden.distributed`) the mesh holds every device of every
process: each process holds only the rows of the global batch that its own devices take
(:func:`process_rows`) and :func:`shard_batch` assembles the global array from those.

Training batches must split evenly over the mesh (the loop picks a mesh that splits them);
validation batches are padded to a multiple of the devices (:func:`pad_to_devices`) and the
padding weighs nothing, so the validation numbers do not depend on the device count.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from jaxden.errors import ConfigError, JaxdenError


# --------------------------------------------------------------------------------- sharding
def data_mesh(devices=None) -> jax.sharding.Mesh:
    devices = np.asarray(devices if devices is not None else jax.devices())
    return jax.sharding.Mesh(devices, ("data",))


def process_rows(size: int, mesh: jax.sharding.Mesh) -> slice | None:
    """The rows of a global batch of ``size`` that this process's devices take (one block per
    device, in mesh order); None when ``size`` does not split evenly over the mesh."""
    count = mesh.devices.size
    if size % count:
        return None
    per_device = size // count
    me = jax.process_index()
    mine = [i for i, device in enumerate(mesh.devices.flat) if device.process_index == me]
    if not mine:
        raise JaxdenError(f"process {me} has no device in the training mesh")
    if mine != list(range(mine[0], mine[-1] + 1)):
        raise JaxdenError(f"the devices of process {me} are not contiguous in the mesh")
    return slice(mine[0] * per_device, (mine[-1] + 1) * per_device)


def pad_to_devices(rows: Sequence[Any], count: int) -> tuple[list[Any], np.ndarray]:
    """``rows`` padded with copies of its last entry to a multiple of ``count`` (the devices of
    the mesh), and the weights of the padded rows: 1.0 for each given row, 0.0 for each copy
    (float32, one per row). A copy is a real example, so whatever computes on it stays finite;
    weighing it 0 leaves every weighted sum as it is without it
    (:func:`jaxden.train.loop.evaluate`)."""
    if not rows:
        raise ValueError("pad_to_devices: no rows to pad")
    rows = list(rows)
    given = len(rows)
    padded = -(-given // count) * count
    weights = np.zeros(padded, np.float32)
    weights[:given] = 1.0
    return rows + [rows[-1]] * (padded - given), weights


def shard_batch(batch: Any, mesh: jax.sharding.Mesh, global_size: int | None = None) -> Any:
    """Place a host batch on the mesh, split along the first axis of every array.

    One process: ``batch`` is the whole batch. Several: ``batch`` holds this process's rows
    (:func:`process_rows`) of a global batch of ``global_size`` rows.
    """
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    count = mesh.devices.size
    several = jax.process_count() > 1

    def put(array):
        array = np.asarray(array)
        if array.ndim == 0:
            return replicate(array, mesh)
        rows = global_size if several and global_size is not None else array.shape[0]
        if rows % count:
            raise ConfigError(
                f"batch size {rows} must be a multiple of the number of devices ({count})"
            )
        if several:
            return jax.make_array_from_process_local_data(spec, array,
                                                          (rows, *array.shape[1:]))
        return jax.device_put(array, spec)

    return jax.tree_util.tree_map(put, batch)


def replicate(tree: Any, mesh: jax.sharding.Mesh) -> Any:
    """Every device of the mesh gets the whole tree (in a multi-process job every process must
    pass the same values: each places its own copy on its devices)."""
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)

    def put(leaf):
        host = host_value(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(put, tree)


def host_value(value: Any) -> np.ndarray:
    """A NumPy copy of a replicated (or local) value, also when the array spans devices of
    other processes (each process reads its own replica)."""
    if isinstance(value, jax.Array) and not value.is_fully_addressable:
        return np.asarray(value.addressable_data(0))
    return np.asarray(value)
