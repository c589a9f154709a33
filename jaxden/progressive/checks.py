"""Argument checks shared by the progressive-denoising functions: shapes, matching sizes, variance
values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jaxden.frame
from jaxden.errors import FrameError


def check_image(name: str, array, where: str, channels: tuple[int, ...] = (3,)) -> tuple:
    shape = np.shape(array)
    if len(shape) < 3 or shape[-1] not in channels:
        raise FrameError(
            f"{where}: '{name}' must have shape (..., H, W, {' or '.join(map(str, channels))}), "
            f"got {shape}"
        )
    return shape


def check_same(where: str, **arrays) -> tuple:
    """All arrays (..., H, W, 3) with the same shape; returns it."""
    shapes = {name: check_image(name, a, where) for name, a in arrays.items()}
    first_name, first = next(iter(shapes.items()))
    for name, shape in shapes.items():
        if shape != first:
            raise FrameError(f"{where}: '{name}' has shape {shape} but '{first_name}' has {first}")
    return first


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


@jax.jit
def _variance_passes(var) -> jax.Array:
    return jnp.all(jnp.isfinite(var) & (var >= 0))


def check_variance_values(var, where: str) -> None:
    """Variance must be finite and >= 0 (only checked on concrete arrays; a JAX array on an
    accelerator is checked where it lives, and copied to the host only to word a failure)."""
    if not _is_concrete(var):
        return
    if (isinstance(var, jax.Array)
            and all(d.platform in jaxden.frame.DEVICE_CHECK_PLATFORMS for d in var.devices())
            and bool(_variance_passes(var))):
        return
    values = np.asarray(var)
    bad = ~np.isfinite(values) | (values < 0)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise FrameError(
            f"{where}: variance must be finite and >= 0 but {int(bad.sum())} value(s) are not "
            f"(first at index {index}: {values[index]})"
        )


def check_spp(spp, lead: tuple, where: str):
    """None, or the sample count as a float32 array broadcastable to the leading dims."""
    if spp is None:
        return None
    spp = np.asarray(spp, np.float64)
    if not np.all(np.isfinite(spp)) or np.any(spp <= 0):
        raise FrameError(f"{where}: spp must be finite and > 0, got {spp}")
    try:
        np.broadcast_to(spp, lead)
    except ValueError:
        raise FrameError(f"{where}: spp of shape {spp.shape} does not match the leading "
                         f"(batch) dims {lead} of the images") from None
    return jnp.asarray(spp, jnp.float32)
