"""Multi-resolution kernel prediction (MR-KP) as Meng et al. (EGSR 2020) modified KPCN.

Pipeline (BASELINES.md section 5):

1. inputs (10 channels): the demodulated colour (raw HDR in the authors' code, or tone-mapped),
   albedo, normal * 0.5 + 0.5, depth / max depth of the frame;
2. :class:`MRKPNet`, a U-Net: ``levels`` (5) encoder levels of conv 3x3 (48) + ReLU, each
   followed by a 2 x 2 average pool; as many decoder levels of transposed conv 3x3 stride 2
   (48) + ReLU, concatenated with the encoder activation (before its pool) of the same
   resolution; at the ``filter_levels`` (3) finest decoder levels (resolutions 1, 1/2, 1/4)
   a head conv 3x3 + ReLU predicts k*k (25: a 5 x 5 kernel) weights and one blend weight
   alpha. Glorot-uniform kernels, zero biases;
3. a pyramid of the demodulated colour, ``x_1 = x``, ``x_{l+1} = P(x_l)`` (P: 2 x 2 average),
   filtered at the ``F`` finest levels with their kernels by :func:`apply_kernels` (``d_l``)
   and combined from the coarsest up, from ``b = x_{F+1}``: ``b = d_l - alpha_l U(P(d_l)) +
   alpha_l U(b)`` for ``l = F .. 1`` (:func:`combine_levels`; U: the authors' x2 upsampling,
   :func:`upsample`), then multiplied by the albedo.

The transposed convolutions (:class:`UpConv`) read the same inputs as TensorFlow's
``conv2d_transpose`` (stride 2, 'SAME': even outputs from inputs ``m - 1`` and ``m``, odd ones
from ``m``) with the kernel flipped, which spans the same functions. Frames whose sides are not
multiples of 2^levels are edge-padded to them and cropped back (training crops of 64 or 128
pixels are not padded). Departures: docs/departures.md, "MR-KP".
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.denoise.nn.wskp import apply_per_pixel_kernels, downsample
from jaxden.errors import FrameError

#: Added to the kernel weights' sum (the authors' ``1e-8``).
KERNEL_EPS = 1e-8


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def apply_kernels(color, weights, kernel_size: int):
    """MR-KP's per-pixel kernel filter.

    Args:
      color: (..., H, W, C) the image to filter.
      weights: (..., H, W, k*k) non-negative kernel weights, row-major offsets (dy, dx).
      kernel_size: k, odd (static).

    Returns:
      (..., H, W, C): per channel ``sum_q w_q x(q) / (sum_q w_q + 1e-8)`` over the taps q
      inside the image whose value x(q) is > 0 (the others are skipped, in both sums).
    """
    if weights.shape != color.shape[:-1] + (kernel_size * kernel_size,):
        raise FrameError(f"apply_kernels: weights must be (..., H, W, {kernel_size ** 2}) for "
                         f"colour {color.shape}, got {weights.shape}")
    positive = color > 0
    channels = color.shape[-1]
    stacked = jnp.concatenate([jnp.where(positive, color, 0.0), positive.astype(color.dtype)],
                              axis=-1)
    sums = apply_per_pixel_kernels(stacked, weights, kernel_size)  # zero padding: skipped
    return sums[..., :channels] / (sums[..., channels:] + KERNEL_EPS)


@jax.jit
def upsample(x):
    """The authors' x2 upsampling of (..., h, w, C) -> (..., 2h, 2w, C): output row ``i``
    reads low-resolution rows ``floor(i / 2 + 0.05)`` and ``ceil(i / 2 - 0.05)`` (one row for
    even ``i``, two for odd ``i`` but the last, which has one), the same for columns, and
    averages the rows x columns it reads."""
    for axis in (-3, -2):
        last = jax.lax.slice_in_dim(x, x.shape[axis] - 1, x.shape[axis], axis=axis)
        following = jnp.concatenate(
            [jax.lax.slice_in_dim(x, 1, x.shape[axis], axis=axis), last], axis=axis)
        pair = jnp.stack([x, 0.5 * (x + following)], axis=axis)  # (..., n, 2, ...)
        shape = list(x.shape)
        shape[axis] *= 2
        x = pair.reshape(shape)
    return x


class UpConv(nn.Module):
    """``flax.linen.ConvTranspose(features, (3, 3), strides=(2, 2), padding="SAME")`` (same
    parameters, same outputs), computed at the input's resolution: output ``2m + a`` takes
    input ``m - 1`` with kernel row 0 and ``m`` with row 2 (a = 0), or ``m`` with row 1 (a = 1),
    the same along columns, so the four output phases are one 2 x 2 convolution with ``4 *
    features`` outputs, then interleaved. XLA's CPU gradient of the dilated-input convolution
    that ConvTranspose lowers to is slow: MR-KP's finest decoder level (batch 8 of 32 x 32 x 96
    -> 64 x 64 x 48), forward and backward, 1.48 s there and 0.15 s here (forward 0.053 and
    0.026 s); the whole network's training step 1.70 s -> 0.33 s.
    """

    features: int
    kernel_init: Callable[..., Any] = nn.initializers.glorot_uniform()

    @nn.compact
    def __call__(self, x):
        kernel = self.param("kernel", self.kernel_init, (3, 3, x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        rows_of_phase = ((0, 2), (None, 1))  # kernel row for the input at offset -1, 0
        zero = jnp.zeros_like(kernel[0, 0])

        def tap(a, b, r, c):
            i, j = rows_of_phase[a][r], rows_of_phase[b][c]
            return zero if i is None or j is None else kernel[i, j]

        phases = jnp.stack([jnp.stack([
            jnp.concatenate([tap(a, b, r, c) for a in (0, 1) for b in (0, 1)], axis=-1)
            for c in (0, 1)]) for r in (0, 1)])  # (2, 2, C_in, 4 F), channels (a, b, f)
        batch, (height, width, channels) = x.shape[:-3], x.shape[-3:]
        y = jax.lax.conv_general_dilated(
            x.reshape((-1, height, width, channels)), phases.astype(x.dtype), (1, 1),
            ((1, 0), (1, 0)), dimension_numbers=("NHWC", "HWIO", "NHWC"))
        y = y.reshape((-1, height, width, 2, 2, self.features)).transpose(0, 1, 3, 2, 4, 5)
        return y.reshape(batch + (2 * height, 2 * width, self.features)) + bias


class MRKPNet(nn.Module):
    """(..., H, W, 10) -> ``filter_levels`` outputs (..., H / 2^l, W / 2^l, k*k + 1), finest
    first (H, W multiples of 2^levels). Kernel weights and alpha are ReLU outputs (>= 0)."""

    levels: int = 5
    filter_levels: int = 3
    width: int = 48
    kernel_size: int = 5

    @nn.compact
    def __call__(self, x):
        init = nn.initializers.glorot_uniform()
        skips = []
        for level in range(self.levels):
            x = nn.relu(nn.Conv(self.width, (3, 3), padding="SAME", kernel_init=init,
                                name=f"encoder{level}")(x))
            skips.append(x)
            x = downsample(x)
        heads = [None] * self.filter_levels
        for level in reversed(range(self.levels)):
            x = nn.relu(UpConv(self.width, kernel_init=init, name=f"decoder{level}")(x))
            x = jnp.concatenate([x, skips[level]], axis=-1)
            if level < self.filter_levels:
                heads[level] = nn.relu(nn.Conv(self.kernel_size**2 + 1, (3, 3), padding="SAME",
                                               kernel_init=init, name=f"head{level}")(x))
        return heads


@jax.jit
def combine_levels(filtered, alphas, coarsest):
    """Coarse-to-fine blend: ``b = d_l - alpha_l U(P(d_l)) + alpha_l U(b)`` from ``b =
    coarsest`` (the pyramid's next level, half the coarsest filtered level's size) to the
    finest; ``filtered`` and ``alphas`` finest first, (..., H / 2^l, W / 2^l, C) and
    (..., H / 2^l, W / 2^l, 1)."""
    result = coarsest
    for fine, alpha in zip(reversed(filtered), reversed(alphas)):
        result = fine - alpha * upsample(downsample(fine)) + alpha * upsample(result)
    return result


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def mrkp_filter(heads, irradiance, kernel_size: int):
    """The reconstruction given the network's heads (finest first): pyramid, per-level
    :func:`apply_kernels`, :func:`combine_levels`. (..., H, W, C) -> (..., H, W, C)."""
    taps = kernel_size * kernel_size
    pyramid = [irradiance]
    for _ in heads:
        pyramid.append(downsample(pyramid[-1]))
    filtered = [apply_kernels(x, head[..., :taps], kernel_size)
                for x, head in zip(pyramid, heads)]
    return combine_levels(filtered, [head[..., taps:] for head in heads], pyramid[len(heads)])


def receptive_radius(levels: int, filter_levels: int, kernel_size: int) -> int:
    """Pixels (each side) of the input that an output pixel of :class:`MRKPNet` +
    :func:`mrkp_filter` can depend on, for origins on the pooling grid ``2^levels``.

    Interval arithmetic along one axis: a value at index ``i`` of scale ``s`` reads input
    pixels ``[s i + lo, s i + hi]`` (worst case over ``i``). A 3 x 3 conv adds ``s`` each side;
    a 2 x 2 pool (to scale 2s) adds ``s`` on the right; a stride-2 transposed conv (flax,
    'SAME': output j reads inputs ``ceil(j / 2) - 1 .. floor(j / 2)``) adds ``2s`` on the
    left; a k x k kernel reads ``k // 2`` pyramid pixels of ``s`` input pixels each side;
    ``U(P(d))`` reads ``d`` at ``i - 1 .. i + 2``, ``U(b)`` the coarser ``b`` at ``floor(i /
    2) .. ceil(i / 2)``."""
    lo, hi = 0, 0
    skips = []
    for level in range(levels):
        s = 2**level
        lo, hi = lo - s, hi + s  # conv 3 x 3
        skips.append((lo, hi))
        hi += s  # pool to scale 2s
    heads = {}
    for level in reversed(range(levels)):
        s = 2**level
        lo -= 2 * s  # transposed conv from scale 2s
        lo, hi = min(lo, skips[level][0]), max(hi, skips[level][1])
        if level < filter_levels:
            heads[level] = (lo - s, hi + s)
    r = kernel_size // 2
    s = 2**filter_levels
    b_lo, b_hi = 0, s - 1  # the pyramid's next level, x_{F+1}
    for level in reversed(range(filter_levels)):
        s = 2**level
        h_lo, h_hi = heads[level]
        d_lo, d_hi = min(h_lo, -r * s), max(h_hi, s - 1 + r * s)
        b_lo = min(d_lo - s, h_lo, b_lo - s)
        b_hi = max(d_hi + 2 * s, h_hi, b_hi + s)
    return max(-b_lo, b_hi)


__all__ = ["MRKPNet", "UpConv", "apply_kernels", "combine_levels", "mrkp_filter", "receptive_radius",
           "upsample"]
