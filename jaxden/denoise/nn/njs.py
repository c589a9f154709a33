"""The network of the Neural James-Stein combiner (Gu, Iglesias-Guitian, Moon, SIGGRAPH Asia
2022; the authors' ``model.py``, BASELINES.md section 8.2).

A small U-Net of 3 x 3 convolutions, each followed by a ReLU ('SAME' zero padding, Glorot-
uniform kernels and zero biases, TensorFlow's Keras defaults as the authors build it):

    32, 32 | max-pool 2 | 64, 64 | max-pool 2 | 128, 128 | nearest x2, concat the 64s | 64, 64
    | nearest x2, concat the 32s | 32, 32 | 3 x 3 convolution to k * k + 1 (no activation)

The ``k * k`` = 225 first outputs are the weights of the variance average (``relu + 1e-4``,
so every weight is positive), row-major over the ``k x k`` window (channel ``i`` for the offset
``divmod(i, k) - (k // 2, k // 2)``, as :mod:`jaxden.denoise.njs` reads them); the last one is
the blend ``alpha`` of the two cross-regressed images (``sigmoid``, in (0, 1)).

Input: 12 channels per pixel (:func:`njs_inputs`): the noisy colour ``y``, its variance of the
mean, ``olsA``, ``olsB``, all linear radiance as they are (the authors feed them untransformed).

Sizes: the two pools need sides that are multiples of 4 (the authors' 'valid' pooling would
otherwise drop a row that the concatenation then misses). Other sizes are edge-padded at the
bottom and right to the next multiple of 4 and the outputs cropped back, as
:mod:`jaxden.denoise.nn.unet` does for its multiple of 16; training crops (128 x 128) and
1280 x 720 need no padding.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.errors import FrameError

#: The authors' combination window (``KERNEL_SIZE = 15``).
KERNEL_SIZE = 15
#: Widths of the encoder's three levels (the decoder's are the first two, reversed).
WIDTHS: tuple[int, ...] = (32, 64, 128)
#: Input channels: noisy colour 3, its variance 3, olsA 3, olsB 3.
INPUT_CHANNELS = 12
#: Added to the ReLU of the weight outputs: every weight is > 0.
WEIGHT_FLOOR = 1e-4
#: The sides the network runs on are multiples of this (two 2 x 2 pools).
SIZE_MULTIPLE = 4


def njs_inputs(noisy, variance, ols_a, ols_b) -> jax.Array:
    """(..., H, W, 12): the noisy colour, its variance of the mean, olsA, olsB (each
    (..., H, W, 3), linear radiance, concatenated in that order as the authors')."""
    parts = {"noisy": noisy, "variance": variance, "ols_a": ols_a, "ols_b": ols_b}
    shape = jnp.shape(noisy)
    for name, value in parts.items():
        if jnp.shape(value) != shape or len(shape) < 3 or shape[-1] != 3:
            raise FrameError(f"njs_inputs: {name} must have shape (..., H, W, 3) = {shape}, "
                             f"got {jnp.shape(value)}")
    return jnp.concatenate([jnp.asarray(v, jnp.float32) for v in parts.values()], axis=-1)


def _pad_to_multiple(x: jax.Array, multiple: int) -> jax.Array:
    pad_h, pad_w = (-x.shape[-3]) % multiple, (-x.shape[-2]) % multiple
    if not (pad_h or pad_w):
        return x
    return jnp.pad(x, [(0, 0)] * (x.ndim - 3) + [(0, pad_h), (0, pad_w), (0, 0)], mode="edge")


class NJSNet(nn.Module):
    """(..., H, W, 12) -> ``(weights (..., H, W, k * k), alpha (..., H, W, 1))``: the variance
    weights (> 0, row-major over the window) and the blend of olsA and olsB (in (0, 1)).
    Any H, W >= 1 (padded to a multiple of 4 inside and cropped back).

    Attributes: ``widths`` of the three levels (the authors: 32, 64, 128), ``kernel_size`` of
    the combination window (15).
    """

    widths: Sequence[int] = WIDTHS
    kernel_size: int = KERNEL_SIZE

    @nn.compact
    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        if x.ndim < 3:
            raise FrameError(f"NJSNet: input must have shape (..., H, W, C), got {x.shape}")
        height, width = x.shape[-3], x.shape[-2]
        w1, w2, w3 = self.widths

        def conv(features, name, y):
            return nn.Conv(features, (3, 3), padding="SAME",
                           kernel_init=nn.initializers.xavier_uniform(),
                           bias_init=nn.initializers.zeros, name=name)(y)

        def block(features, prefix, y):
            y = nn.relu(conv(features, f"{prefix}a", y))
            return nn.relu(conv(features, f"{prefix}b", y))

        def pool(y):
            return nn.max_pool(y, (2, 2), strides=(2, 2))

        def up(y):
            return jnp.repeat(jnp.repeat(y, 2, axis=-3), 2, axis=-2)

        y = _pad_to_multiple(jnp.asarray(x, jnp.float32), SIZE_MULTIPLE)
        level1 = block(w1, "enc1", y)
        level2 = block(w2, "enc2", pool(level1))
        y = block(w3, "enc3", pool(level2))
        y = block(w2, "dec2", jnp.concatenate([up(y), level2], axis=-1))
        y = block(w1, "dec1", jnp.concatenate([up(y), level1], axis=-1))
        taps = self.kernel_size * self.kernel_size
        out = conv(taps + 1, "out", y)[..., :height, :width, :]
        weights = nn.relu(out[..., :taps]) + WEIGHT_FLOOR
        alpha = nn.sigmoid(out[..., taps:])
        return weights, alpha


__all__ = [
    "INPUT_CHANNELS",
    "KERNEL_SIZE",
    "SIZE_MULTIPLE",
    "WEIGHT_FLOOR",
    "WIDTHS",
    "NJSNet",
    "njs_inputs",
]
