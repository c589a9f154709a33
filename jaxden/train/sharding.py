"""Data parallelism over all local devices with jax.sharding: the batch is split along its first
axis, parameters are replicated.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from jaxden.errors import ConfigError


# --------------------------------------------------------------------------------- sharding
def data_mesh(devices=None) -> jax.sharding.Mesh:
    devices = np.asarray(devices if devices is not None else jax.devices())
    return jax.sharding.Mesh(devices, ("data",))


def shard_batch(batch: Any, mesh: jax.sharding.Mesh) -> Any:
    """Place a host batch on the mesh, split along the first axis of every array."""
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    count = mesh.devices.size

    def put(array):
        array = np.asarray(array)
        if array.ndim == 0:
            return jax.device_put(array, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
        if array.shape[0] % count:
            raise ConfigError(
                f"batch size {array.shape[0]} must be a multiple of the number of devices ({count})"
            )
        return jax.device_put(array, spec)

    return jax.tree_util.tree_map(put, batch)


def replicate(tree: Any, mesh: jax.sharding.Mesh) -> Any:
    return jax.device_put(tree, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
