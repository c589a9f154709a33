"""Neural bilateral grid denoiser (Meng et al., EGSR 2020): guide network and bilateral grids.

Pipeline (BASELINES.md section 3; the authors' released "2-layer 3-grid" configuration):

1. inputs (10 channels): tone-mapped colour, albedo, normal * 0.5 + 0.5, depth / max depth of
   the frame (:func:`jaxden.denoise.nn.wskp.network_inputs`, the real-time family's inputs);
2. :class:`GuideNet`: conv 5x5 10 -> 20 + LeakyReLU(0.2), conv 5x5 20 -> 2 N - 1 + sigmoid,
   with N grids: N guides ``g_k = 255 out_k`` and N - 1 fusion weights (the last weight is
   ``1 - sum`` of the others, unclamped, as released);
3. per grid ``k`` with cell size ``(s_k, r_k)`` (spatial pixels, guide units; (4, 4), (8, 8),
   (16, 16)): :func:`splat` the demodulated HDR colour (radiance / albedo) into a grid of
   ``ceil(H / s) x ceil(W / s) x 256 / r`` cells indexed by ``(x / s, y / s, g / r)``, then
   :func:`slice_grid` it back with the same guide;
4. fuse ``sum_k w_k slice_k`` and multiply the albedo back.

Cell ``(i, j, d)`` has its centre at pixel ``((i + 0.5) s, (j + 0.5) s)`` and guide value
``(d + 0.5) r``; a pixel ``(y, x)`` with guide ``g`` sits at the continuous cell coordinate
``((y + 0.5) / s - 0.5, (x + 0.5) / s - 0.5, (g + 0.5) / r - 0.5)`` and its weight for a cell is
the product of three tents ``max(0, 1 - |t|)`` of the coordinate differences, with
``|t| = sqrt(t^2 + 1e-8)`` (smooth at 0, so the guide's gradient is defined at cell centres):
each pixel touches the 2 x 2 x 2 cells around it.

* splat: each cell holds the *normalised* weighted mean ``sum w c / sum w`` of the pixels it
  receives (0 where it receives none), by one scatter-add (``segment_sum``) of ``(w c, w)``;
* slice: each pixel takes the weighted mean of its 8 cells, per channel over the cells whose
  value is > 0 (empty cells are skipped), renormalised by the weights used (0 if none).

Both are pure JAX, jittable, and differentiable (forward and reverse mode) in the values, the
grid and the guide; the tents' floor indices carry no gradient, and a cell enters or leaves a
pixel's set only where its weight is 0, so both are continuous in the guide.

Departures (docs/departures.md, "NBGD"): the grid's spatial size is ``ceil(H / s)`` (the
authors' integer division drops a partial last cell; the same for sizes that are multiples of
``s``, as all training crops are); no gradient guard (the authors' custom op zeroes gradient
entries above 100; here the exact gradients of JAX, see the departures page); demodulation by
the safe albedo of the real-time family.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError

#: Guides are ``GUIDE_SCALE * sigmoid``: the authors' 8-bit range [0, 255].
GUIDE_SCALE = 255.0
#: The guide axis of a grid spans ``RANGE_EXTENT / r`` cells (256 / r, integer division).
RANGE_EXTENT = 256
#: The smoothing of ``|t|`` in the tents: ``sqrt(t^2 + ABS_EPS)``.
ABS_EPS = 1e-8


def _tent(t):
    return jnp.maximum(0.0, 1.0 - jnp.sqrt(t * t + ABS_EPS))


def grid_shape(height: int, width: int, spatial: int, range_size: int) -> tuple[int, int, int]:
    """(rows, columns, guide bins) of a grid with cells of ``spatial`` pixels and
    ``range_size`` guide units over a ``height`` x ``width`` image."""
    if spatial < 1 or range_size < 1 or range_size > RANGE_EXTENT:
        raise ConfigError(f"bilateral grid: cell sizes must be spatial >= 1 and 1 <= range <= "
                          f"{RANGE_EXTENT}, got ({spatial}, {range_size})")
    return -(-height // spatial), -(-width // spatial), RANGE_EXTENT // range_size


def _spatial_taps(length: int, spatial: int, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel along one axis: the two cell indices around it (clamped into the grid) and
    their tent weights (0 for a cell outside the grid); shapes (2, length). Constants."""
    coord = (np.arange(length) + 0.5) / spatial - 0.5
    low = np.floor(coord)
    index, weight = [], []
    for cell in (low, low + 1):
        inside = (cell >= 0) & (cell <= cells - 1)
        tent = np.maximum(0.0, 1.0 - np.sqrt((coord - cell) ** 2 + ABS_EPS))
        weight.append(np.where(inside, tent, 0.0))
        index.append(np.clip(cell, 0, cells - 1).astype(np.int32))
    return np.stack(index), np.stack(weight)


def _taps(guide, spatial: int, range_size: int, cells: tuple[int, int, int]):
    """The 8 cells of every pixel: flat cell indices within one image and weights, each
    (8, N, H, W) for a guide (N, H, W). Only the guide axis is traced (and differentiated)."""
    rows, cols, bins = cells
    height, width = guide.shape[-2:]
    y_index, y_weight = _spatial_taps(height, spatial, rows)
    x_index, x_weight = _spatial_taps(width, spatial, cols)
    y_weight, x_weight = (jnp.asarray(w, guide.dtype) for w in (y_weight, x_weight))
    coord = (guide + 0.5) / range_size - 0.5
    low = jax.lax.stop_gradient(jnp.floor(coord))
    indices, weights = [], []
    for dz in (0, 1):
        cell = low + dz
        inside = (cell >= 0) & (cell <= bins - 1)
        z_weight = jnp.where(inside, _tent(coord - cell), 0.0)
        z_index = jnp.clip(cell, 0, bins - 1).astype(jnp.int32)
        for dy in (0, 1):
            for dx in (0, 1):
                yx = (y_index[dy][:, None] * cols + x_index[dx][None, :]) * bins  # (H, W)
                indices.append(yx + z_index)
                weights.append(y_weight[dy][:, None] * x_weight[dx][None, :] * z_weight)
    return jnp.stack(indices), jnp.stack(weights)


def _check(values, guide, where: str) -> None:
    if values.ndim < 3 or guide.shape != values.shape[:-1]:
        raise FrameError(f"{where}: values must be (..., H, W, C) and the guide (..., H, W), "
                         f"got {values.shape} and {guide.shape}")


def _safe_divide(numerator, denominator):
    """``numerator / denominator`` where the denominator is > 0, else 0 (finite gradients)."""
    positive = denominator > 0
    return jnp.where(positive, numerator / jnp.where(positive, denominator, 1.0), 0.0)


@functools.partial(jax.jit, static_argnames=("spatial", "range_size"))
def splat(values, guide, spatial: int, range_size: int):
    """Splat an image into a bilateral grid of normalised cell means.

    Args:
      values: (..., H, W, C) the image (NBGD: demodulated linear radiance).
      guide: (..., H, W) guide in [0, 255] (any real value: cells outside [0, 256 / r) drop).
      spatial, range_size: cell size in pixels and in guide units (static).

    Returns:
      (..., ceil(H / s), ceil(W / s), 256 // r, C): per cell ``sum w c / sum w`` over the
      pixels with weight w > 0 for it (trilinear tents; module docstring), 0 where none.
    """
    values, guide = jnp.asarray(values), jnp.asarray(guide, jnp.asarray(values).dtype)
    _check(values, guide, "splat")
    batch, (height, width, channels) = values.shape[:-3], values.shape[-3:]
    cells = grid_shape(height, width, spatial, range_size)
    values = values.reshape((-1, height, width, channels))
    count = values.shape[0]
    indices, weights = _taps(guide.reshape((-1, height, width)), spatial, range_size, cells)
    per_image = cells[0] * cells[1] * cells[2]
    indices = indices + (np.arange(count, dtype=np.int32) * per_image)[None, :, None, None]
    data = jnp.concatenate([weights[..., None] * values[None], weights[..., None]], axis=-1)
    sums = jax.ops.segment_sum(data.reshape((-1, channels + 1)), indices.reshape(-1),
                               num_segments=count * per_image)
    grid = _safe_divide(sums[:, :channels], sums[:, channels:])
    return grid.reshape(batch + cells + (channels,))


@functools.partial(jax.jit, static_argnames=("spatial", "range_size"))
def slice_grid(grid, guide, spatial: int, range_size: int):
    """Read a bilateral grid back at every pixel (trilinear, empty cells skipped).

    Args:
      grid: (..., rows, cols, bins, C) from :func:`splat` of an H x W image.
      guide: (..., H, W) the pixels' guide.
      spatial, range_size: the grid's cell sizes (static).

    Returns:
      (..., H, W, C): per channel, ``sum w v / sum w`` over the pixel's 8 cells whose value v
      is > 0 (w its tent weight), 0 if there are none.
    """
    grid, guide = jnp.asarray(grid), jnp.asarray(guide, jnp.asarray(grid).dtype)
    height, width = guide.shape[-2:]
    cells = grid_shape(height, width, spatial, range_size)
    if grid.shape[-4:-1] != cells or grid.shape[:-4] != guide.shape[:-2]:
        raise FrameError(f"slice_grid: a guide {guide.shape} with cells ({spatial}, "
                         f"{range_size}) needs a grid (..., {', '.join(map(str, cells))}, C) "
                         f"with the guide's leading shape, got {grid.shape}")
    batch, channels = guide.shape[:-2], grid.shape[-1]
    flat = grid.reshape((-1, cells[0] * cells[1] * cells[2], channels))
    indices, weights = _taps(guide.reshape((-1, height, width)), spatial, range_size, cells)
    gather = jax.vmap(lambda cells_of_image, index: cells_of_image[index], in_axes=(0, 1),
                      out_axes=1)  # (8, N, H, W) indices into each image's cells
    cell_values = gather(flat, indices)  # (8, N, H, W, C)
    used = weights[..., None] * (cell_values > 0)
    out = _safe_divide(jnp.sum(used * cell_values, axis=0), jnp.sum(used, axis=0))
    return out.reshape(batch + (height, width, channels))


@functools.partial(jax.jit, static_argnames=("spatial", "range_size"))
def bilateral_filter(values, guide, spatial: int, range_size: int):
    """:func:`slice_grid` of :func:`splat`: (..., H, W, C) -> (..., H, W, C)."""
    return slice_grid(splat(values, guide, spatial, range_size), guide, spatial, range_size)


class GuideNet(nn.Module):
    """The released NBGD guide network: (..., H, W, 10) -> (..., H, W, 2 grids - 1) in (0, 1).

    conv k x k (``width``, bias) + LeakyReLU(``negative_slope``), conv k x k (2 grids - 1,
    bias) + sigmoid; 'SAME' zero padding; Glorot-uniform kernels, zero biases (TensorFlow's
    default initialisers).
    """

    grids: int = 3
    width: int = 20
    kernel_size: int = 5
    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, x):
        init = nn.initializers.glorot_uniform()
        size = (self.kernel_size, self.kernel_size)
        x = nn.Conv(self.width, size, padding="SAME", kernel_init=init, name="conv0")(x)
        x = nn.leaky_relu(x, self.negative_slope)
        x = nn.Conv(2 * self.grids - 1, size, padding="SAME", kernel_init=init, name="conv1")(x)
        return nn.sigmoid(x)


@functools.partial(jax.jit, static_argnames=("cells",))
def fuse_grids(guide_out, irradiance, cells: Sequence[tuple[int, int]]):
    """NBGD's filter given the guide network's output.

    Args:
      guide_out: (..., H, W, 2 N - 1) :class:`GuideNet` output: N guides / 255, N - 1 weights.
      irradiance: (..., H, W, C) the demodulated colour to filter.
      cells: N pairs (spatial, range) of cell sizes (static).

    Returns:
      (..., H, W, C): ``sum_k w_k slice_k`` with ``w_N = 1 - sum_{k<N} w_k`` (not clamped).
    """
    count = len(cells)
    if guide_out.shape[-1] != 2 * count - 1:
        raise FrameError(f"fuse_grids: {count} grids need 2 * {count} - 1 guide channels, got "
                         f"{guide_out.shape[-1]}")
    weights = [guide_out[..., count + k, None] for k in range(count - 1)]
    weights.append(1.0 - sum(weights, jnp.zeros_like(guide_out[..., :1])))
    out = None
    for k, (spatial, range_size) in enumerate(cells):
        sliced = bilateral_filter(irradiance, GUIDE_SCALE * guide_out[..., k], spatial,
                                  range_size)
        out = weights[k] * sliced if out is None else out + weights[k] * sliced
    return out


__all__ = ["GUIDE_SCALE", "GuideNet", "bilateral_filter", "fuse_grids", "grid_shape",
           "slice_grid", "splat"]
