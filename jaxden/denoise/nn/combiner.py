"""Deep Combiner, single-buffer variant (Back, Hua, Hachisuka, Moon, SIGGRAPH Asia 2020):
the kernel network and the kernel combination.

Given a *correlated* estimate ``corr`` (a denoiser's output) and the *independent* unbiased
Monte Carlo estimate ``rand`` of the same pixels, the network reads 13 channels per pixel
(:func:`combiner_inputs`: corr, rand, normal, albedo, depth) and predicts one non-negative
weight per offset of a ``k x k`` window (k = 15); the combination is

    W_pq   = relu_out_pq / max(sum_q' relu_out_pq', 1e-10)                   (normalisation)
    out(p) = corr(p) + sum_{q in k x k(p)} W_pq (rand(q) - corr(q))            (combination)

so where every weight is 0 the output is ``corr`` itself, and where ``corr = rand`` it is
``rand`` (= ``corr``).

Weight ordering (the authors' windowed sum is a compiled op, its order is not visible):
**row-major** over the window. Channel ``i`` of the network's output weighs the neighbour at
offset ``(dy, dx) = divmod(i, k) - (k // 2, k // 2)``: ``i = 0`` is the top-left neighbour
``(-7, -7)``, ``i = 7`` is ``(-7, 0)``, ``i = 112`` the pixel itself, ``i = 224`` ``(+7, +7)``
(``dy`` down the rows, ``dx`` along a row). Neighbours outside the image contribute nothing
(``rand - corr`` is zero-padded); the weights are *not* renormalised over the in-image part,
since the normalisation above is over all ``k * k`` outputs, as the authors normalise them.

Network (:class:`CombinerNet`): six 5 x 5 convolutions, 'SAME' zero padding, Xavier (Glorot
uniform) kernels and zero biases, each followed by a ReLU, the last one included; widths
100, 100, 100, 100, 100, then ``k * k`` = 225.

:func:`combine` never materialises the ``(..., H, W, k*k, C)`` window tensor: a
``lax.scan`` over the ``k`` window rows adds one row of ``k`` shifted neighbours per step
(``(..., H, W, k, C)`` at a time), its body rematerialised in reverse mode so the backward pass
stores the ``k`` running sums only. It is jit-able, differentiable in every argument and takes
leading batch dimensions.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.errors import ConfigError, FrameError

#: The authors' window (``half_kernel_size = 7``).
KERNEL_SIZE = 15
#: Widths of the first five convolutions (the sixth has ``KERNEL_SIZE ** 2`` outputs).
HIDDEN_WIDTHS: tuple[int, ...] = (100, 100, 100, 100, 100)
#: Side of every convolution.
CONV_SIZE = 5
#: The floor of the weight sum in the normalisation.
WEIGHT_SUM_FLOOR = 1e-10
#: Input channels of the single-buffer network: corr 3, rand 3, normal 3, albedo 3, depth 1.
INPUT_CHANNELS = 13
#: Depth inputs: ``minmax`` (min-max normalised over each image, what the authors' loader
#: does) or ``zero`` (what their network's "local" re-normalisation over a 1-channel axis
#: makes of it: identically 0).
DEPTH_MODES: tuple[str, ...] = ("minmax", "zero")


def _check_kernel_size(kernel_size) -> int:
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size < 1 \
            or kernel_size % 2 == 0:
        raise ConfigError(f"combiner: kernel size must be an odd int >= 1, got {kernel_size!r}")
    return kernel_size


def window_offset(index: int, kernel_size: int = KERNEL_SIZE) -> tuple[int, int]:
    """``(dy, dx)`` of weight channel ``index`` in the row-major ``kernel_size`` window."""
    radius = _check_kernel_size(kernel_size) // 2
    if not 0 <= index < kernel_size * kernel_size:
        raise ConfigError(f"window_offset: index must be in [0, {kernel_size ** 2}), got {index}")
    dy, dx = divmod(index, kernel_size)
    return dy - radius, dx - radius


# ------------------------------------------------------------------------------ network
class CombinerNet(nn.Module):
    """(..., H, W, C_in) -> (..., H, W, kernel_size**2) non-negative raw weights.

    Attributes: ``hidden_widths`` of the first convolutions (the authors: five of 100),
    ``kernel_size`` of the combination window (15).
    """

    hidden_widths: Sequence[int] = HIDDEN_WIDTHS
    kernel_size: int = KERNEL_SIZE

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        widths = (*self.hidden_widths, self.kernel_size * self.kernel_size)
        for index, width in enumerate(widths):
            x = nn.Conv(width, (CONV_SIZE, CONV_SIZE), padding="SAME",
                        kernel_init=nn.initializers.xavier_uniform(),
                        bias_init=nn.initializers.zeros, name=f"conv{index}")(x)
            x = nn.relu(x)  # the last layer's too: the weights are >= 0
        return x


def receptive_radius(num_convs: int = len(HIDDEN_WIDTHS) + 1,
                     kernel_size: int = KERNEL_SIZE) -> int:
    """Pixels each side that one output depends on, given corr and rand: the weights of p
    see the convolutions' field (2 pixels per 5 x 5 convolution), the window reaches
    ``kernel_size // 2``; the larger of the two (12 for the authors' network)."""
    return max(num_convs * (CONV_SIZE // 2), kernel_size // 2)


# ------------------------------------------------------------------------------- inputs
def normalized_depth(depth: jax.Array, mode: str = "minmax") -> jax.Array:
    """(..., H, W, 1): ``(d - min) / (max - min)`` over each image (a constant image: 0), or
    zeros (``mode = "zero"``, the authors' network as released)."""
    depth = jnp.asarray(depth, jnp.float32)
    if mode == "zero":
        return jnp.zeros_like(depth)
    if mode != "minmax":
        raise ConfigError(f"combiner: depth must be one of {', '.join(DEPTH_MODES)}, got {mode!r}")
    low = jnp.min(depth, axis=(-3, -2, -1), keepdims=True)
    high = jnp.max(depth, axis=(-3, -2, -1), keepdims=True)
    span = high - low
    return jnp.where(span > 0, (depth - low) / jnp.where(span > 0, span, 1.0), 0.0)


def combiner_inputs(corr, rand, normal, albedo, depth, depth_mode: str = "minmax") -> jax.Array:
    """(..., H, W, 13): corr, rand (linear radiance, as they are), normal, albedo, the depth
    of :func:`normalized_depth`; every part (..., H, W, 3) but depth (..., H, W, 1)."""
    parts = {"corr": corr, "rand": rand, "normal": normal, "albedo": albedo}
    shape = jnp.shape(corr)
    for name, value in parts.items():
        if jnp.shape(value) != shape or shape[-1:] != (3,):
            raise FrameError(f"combiner_inputs: {name} must have shape (..., H, W, 3) = "
                             f"{shape}, got {jnp.shape(value)}")
    if jnp.shape(depth) != (*shape[:-1], 1):
        raise FrameError(f"combiner_inputs: depth must have shape {(*shape[:-1], 1)}, got "
                         f"{jnp.shape(depth)}")
    return jnp.concatenate([jnp.asarray(v, jnp.float32) for v in parts.values()]
                           + [normalized_depth(depth, depth_mode)], axis=-1)


# -------------------------------------------------------------------------- combination
def normalize_weights(raw: jax.Array) -> jax.Array:
    """``relu(raw) / max(sum relu(raw), 1e-10)`` over the last axis: (..., K) -> (..., K).
    Sums to 1 wherever some weight is positive, all 0 where none is."""
    raw = jax.nn.relu(jnp.asarray(raw, jnp.float32))
    return raw / jnp.maximum(jnp.sum(raw, axis=-1, keepdims=True), WEIGHT_SUM_FLOOR)


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _window_sum(values, weights, kernel_size: int):
    """sum_i weights[..., i] * values[p + offset(i)], zero outside: (..., H, W, C)."""
    radius = kernel_size // 2
    height, width = values.shape[-3], values.shape[-2]
    batch = values.ndim - 3
    pad = [(0, 0)] * batch + [(radius, radius), (radius, radius), (0, 0)]
    padded = jnp.pad(values, pad)
    rows = weights.reshape(*weights.shape[:-1], kernel_size, kernel_size)
    rows = jnp.moveaxis(rows, -2, 0)  # (k rows, ..., H, W, k): the scan's slices

    @jax.checkpoint
    def step(total, xs):
        dy, row_weights = xs
        band = jax.lax.dynamic_slice_in_dim(padded, dy, height, axis=batch)  # (..., H, W+2r, C)
        shifted = jnp.stack([band[..., dx : dx + width, :] for dx in range(kernel_size)], -2)
        return total + jnp.einsum("...k,...kc->...c", row_weights, shifted), None

    total = jnp.zeros(values.shape, jnp.result_type(values, weights))
    total, _ = jax.lax.scan(step, total, (jnp.arange(kernel_size), rows))
    return total


def combine(corr, rand, weights, kernel_size: int = KERNEL_SIZE) -> jax.Array:
    """``corr(p) + sum_q W_pq (rand(q) - corr(q))`` over the row-major ``kernel_size`` window.

    Args:
      corr: (..., H, W, C) correlated estimate (a denoiser's output), linear radiance.
      rand: (..., H, W, C) independent unbiased estimate of the same pixels.
      weights: (..., H, W, kernel_size**2) normalised weights ``W`` (:func:`normalize_weights`),
        channel ``i`` for the neighbour at :func:`window_offset` ``(i)``.
      kernel_size: odd window side (static; 15).

    Returns:
      (..., H, W, C) the combined estimate; neighbours outside the image add nothing.

    Raises:
      FrameError: mismatched shapes. ConfigError: a bad kernel size.
    """
    kernel_size = _check_kernel_size(kernel_size)
    corr, rand, weights = (jnp.asarray(a, jnp.float32) for a in (corr, rand, weights))
    if corr.ndim < 3 or corr.shape != rand.shape:
        raise FrameError(f"combine: corr and rand must have one shape (..., H, W, C), got "
                         f"{corr.shape} and {rand.shape}")
    if weights.shape != (*corr.shape[:-1], kernel_size * kernel_size):
        raise FrameError(f"combine: weights must have shape (..., H, W, {kernel_size ** 2}) = "
                         f"{(*corr.shape[:-1], kernel_size ** 2)}, got {weights.shape}")
    return corr + _window_sum(rand - corr, weights, kernel_size)


def combiner_output(net: CombinerNet, params, corr, rand, normal, albedo, depth,
                    depth_mode: str = "minmax") -> jax.Array:
    """The whole single-buffer combiner: inputs, network, normalisation, combination.
    (..., H, W, 3) each (depth (..., H, W, 1)) -> (..., H, W, 3)."""
    x = combiner_inputs(corr, rand, normal, albedo, depth, depth_mode)
    weights = normalize_weights(net.apply(params, x))
    return combine(corr, rand, weights, net.kernel_size)


__all__ = [
    "CONV_SIZE",
    "DEPTH_MODES",
    "HIDDEN_WIDTHS",
    "INPUT_CHANNELS",
    "KERNEL_SIZE",
    "WEIGHT_SUM_FLOOR",
    "CombinerNet",
    "combine",
    "combiner_inputs",
    "combiner_output",
    "normalize_weights",
    "normalized_depth",
    "receptive_radius",
    "window_offset",
]
