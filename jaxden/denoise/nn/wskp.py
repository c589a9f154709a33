"""Weight-sharing kernel prediction (Fan et al. 2021): ImportanceNet, KPCN baselines, and the
multi-resolution variant.

Pipeline (paper Sec. 4, Fig. 1):

1. inputs (10 channels): tone-mapped colour, albedo, normal * 0.5 + 0.5, depth / max depth of
   the frame (paper Sec. 5.1; REFERENCE-NOTES);
2. ImportanceNet: RepVGG blocks (5x5 + 3x3 + 1x1 [+ identity], LeakyReLU 0.1), width 14,
   6 or 3 layers, ending in 2 M channels: M importance maps and M fusion logits;
3. albedo demodulation: the noisy radiance is divided by the albedo and the *irradiance* is
   filtered with each importance map's kernels of sizes k_i (3, 5, ..., 13), fused per pixel
   by a softmax over the logits, and multiplied by the albedo again.

Departures, each a config option:
- ``tonemap``: the authors gamma-correct the clipped colour (their BMFR data is nearly LDR);
  our scenes have bright emitters, so the default is ``reinhard_gamma`` (x / (1 + x)) ** (1/2.2),
  which keeps highlights distinguishable; ``gamma`` is the authors' choice.
- demodulation: the radiance is divided by a *safe* albedo (:func:`safe_albedo`): the albedo
  itself from ``albedo_floor`` up, and below it a linear ramp to 1 at albedo 0 (misses, black or
  specular surfaces: Mitsuba's albedo AOV is 0 there, where the radiance is filtered as it is).
  The ramp is continuous and never below the floor, so no pixel's irradiance is amplified by
  more than 1 / albedo_floor. A hard switch at 1e-3 (our first form) amplified anti-aliased edge
  pixels of albedo ~0.001 beside mirrors ~1000x and smeared them into their neighbours.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Literal

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.config import bounded
from jaxden.denoise import kernels
from jaxden.denoise.nn.layers import RepVGGBlock, RepVGGDeployBlock
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

WSKP_FEATURES = ("color", "albedo", "normal", "depth")


def _gamma(t: jax.Array) -> jax.Array:
    """t ** (1/2.2) for t >= 0, with a zero derivative at t = 0 (the true one is infinite,
    which made jvp SURE NaN, inf * 0, at black pixels with zero variance). Values are
    unchanged: the inner ``where`` only keeps the power's derivative finite."""
    positive = t > 0
    return jnp.where(positive, jnp.where(positive, t, 1.0) ** (1 / 2.2), 0.0)


def tonemap(color: jax.Array, kind: str) -> jax.Array:
    color = jnp.maximum(color, 0.0)
    if kind == "gamma":
        return _gamma(jnp.clip(color, 0.0, 1.0))
    if kind == "reinhard_gamma":
        return _gamma(color / (1.0 + color))
    raise FrameError(f"unknown tonemap {kind!r}; choose 'gamma' or 'reinhard_gamma'")


def frame_depth_max(frame: Frame) -> jax.Array:
    """The depth normalisation of :func:`network_inputs`: max depth per image, (..., 1, 1, 1)."""
    return jnp.max(jnp.asarray(frame.depth, jnp.float32), axis=(-3, -2, -1), keepdims=True)


def network_inputs(frame: Frame, tonemap_kind: str, depth_max=None) -> jax.Array:
    """(..., H, W, 10): tone-mapped colour, albedo, normal * 0.5 + 0.5, depth / frame max
    (``depth_max``: :func:`frame_depth_max` of the whole frame when ``frame`` is a tile)."""
    depth = jnp.asarray(frame.depth, jnp.float32)
    if depth_max is None:
        depth_max = frame_depth_max(frame)
    return jnp.concatenate(
        [
            tonemap(jnp.asarray(frame.color, jnp.float32), tonemap_kind),
            jnp.clip(frame.albedo, 0.0, 1.0),
            frame.normal * 0.5 + 0.5,
            depth / jnp.maximum(depth_max, 1e-6),
        ],
        axis=-1,
    )


def safe_albedo(albedo: jax.Array, floor: float) -> jax.Array:
    """The albedo used for (de)modulation, per channel: ``albedo`` where it is at least
    ``floor``; below, ``1 - (1 - floor) * albedo / floor`` (1 at albedo 0, where the albedo
    carries no information, down to ``floor``). Continuous and >= min(floor, 1)."""
    ramp = 1.0 - (1.0 - floor) * jnp.clip(albedo, 0.0, None) / floor
    return jnp.where(albedo >= floor, albedo, ramp)


class RepVGGStack(nn.Module):
    """``num_layers`` RepVGG blocks of ``width`` channels; the last outputs ``out_channels``
    without activation (it produces logits). ``deploy``: single 5x5 convs (parameters from
    :func:`jaxden.denoise.nn.layers.reparameterize` of the training form; same outputs, faster)."""

    num_layers: int
    width: int
    out_channels: int
    deploy: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        block = RepVGGDeployBlock if self.deploy else RepVGGBlock
        for index in range(self.num_layers):
            last = index == self.num_layers - 1
            x = block(
                features=self.out_channels if last else self.width,
                activation=not last,
                name=f"block{index}",
            )(x)
        return x


def _check_config_kernels(field: str, sizes) -> None:
    if not sizes or any(not isinstance(k, int) or k < 1 or k % 2 == 0 for k in sizes):
        raise ConfigError(f"{field}: kernel sizes must be odd integers >= 1, got {sizes!r}")


@dataclasses.dataclass(frozen=True)
class WSKPConfig:
    """ImportanceNet + weight-sharing kernel decoder (paper Sec. 4)."""

    num_layers: int = bounded(6, low=1, high=64)  # 6 (quality) or 3 (speed) in the paper
    width: int = bounded(14, low=1, high=1024)
    kernel_sizes: tuple[int, ...] = bounded((3, 5, 7, 9, 11, 13), low=1, high=63)
    tonemap: Literal["gamma", "reinhard_gamma"] = "reinhard_gamma"
    albedo_floor: float = bounded(0.05, low=0, low_open=True, high=1)
    decoder: Literal["box", "unfold"] = "box"
    deploy: bool = False  # re-parameterised single-conv blocks (inference)

    def __post_init__(self):
        _check_config_kernels("WSKPConfig.kernel_sizes", self.kernel_sizes)


def wskp_denoise(params, config: WSKPConfig, frame: Frame, depth_max=None) -> jax.Array:
    """(..., H, W, 3) denoised radiance (``depth_max``: see :func:`network_inputs`)."""
    count = len(config.kernel_sizes)
    net = RepVGGStack(config.num_layers, config.width, 2 * count, config.deploy)
    out = net.apply(params, network_inputs(frame, config.tonemap, depth_max))
    albedo = safe_albedo(jnp.asarray(frame.albedo, jnp.float32), config.albedo_floor)
    irradiance = jnp.asarray(frame.color, jnp.float32) / albedo
    filtered = kernels.decode(
        irradiance, out[..., :count], out[..., count:], config.kernel_sizes, form=config.decoder
    )
    return filtered * albedo


def wskp_init(key: jax.Array, config: WSKPConfig):
    net = RepVGGStack(config.num_layers, config.width, 2 * len(config.kernel_sizes), config.deploy)
    return net.init(key, jnp.zeros((1, 16, 16, 10), jnp.float32))


# ------------------------------------------------------------------------------------- KPCN
@dataclasses.dataclass(frozen=True)
class KPConfig:
    """Direct kernel prediction: the network outputs k * k weights per pixel (softmax).

    The paper's variants: KP (6 layers, k = 13: the WSKP backbone), KP-1 (2 layers, k = 13),
    KP-2 (5 layers, k = 7).
    """

    num_layers: int = bounded(6, low=1, high=64)
    width: int = bounded(14, low=1, high=1024)
    kernel_size: int = bounded(13, low=1, high=63)
    tonemap: Literal["gamma", "reinhard_gamma"] = "reinhard_gamma"
    albedo_floor: float = bounded(0.05, low=0, low_open=True, high=1)
    deploy: bool = False

    def __post_init__(self):
        _check_config_kernels("KPConfig.kernel_size", (self.kernel_size,))


def apply_per_pixel_kernels(color: jax.Array, weights: jax.Array, kernel_size: int) -> jax.Array:
    """sum_q w_p(q) color(p + q) with weights (..., H, W, k*k) (row-major offsets), zero padding.

    Loops over the k*k offsets with shifted slices, so the (H, W, k*k, C) unfolded colour is
    never built.
    """
    radius = kernel_size // 2
    height, width = color.shape[-3], color.shape[-2]
    pad = [(0, 0)] * (color.ndim - 3) + [(radius, radius), (radius, radius), (0, 0)]
    padded = jnp.pad(color, pad)
    out = jnp.zeros_like(color)
    for dy in range(kernel_size):
        for dx in range(kernel_size):
            shifted = padded[..., dy : dy + height, dx : dx + width, :]
            out = out + weights[..., dy * kernel_size + dx, None] * shifted
    return out


def kp_denoise(params, config: KPConfig, frame: Frame, depth_max=None) -> jax.Array:
    taps = config.kernel_size**2
    net = RepVGGStack(config.num_layers, config.width, taps, config.deploy)
    logits = net.apply(params, network_inputs(frame, config.tonemap, depth_max))
    weights = jax.nn.softmax(logits, axis=-1)
    albedo = safe_albedo(jnp.asarray(frame.albedo, jnp.float32), config.albedo_floor)
    irradiance = jnp.asarray(frame.color, jnp.float32) / albedo
    return apply_per_pixel_kernels(irradiance, weights, config.kernel_size) * albedo


def kp_init(key: jax.Array, config: KPConfig):
    net = RepVGGStack(config.num_layers, config.width, config.kernel_size**2, config.deploy)
    return net.init(key, jnp.zeros((1, 16, 16, 10), jnp.float32))


# ------------------------------------------------------------------------- multi-resolution
@dataclasses.dataclass(frozen=True)
class WSKPMRConfig:
    """Multi-resolution WSKP (paper Sec. 5.2, Eq. 7): ``levels`` resolutions, each filtered with
    weight-sharing kernels of ``kernel_sizes`` and fused; adjacent levels are combined from the
    coarsest up with a predicted per-pixel weight alpha:
    o = i_f - alpha * U(D(i_f)) + alpha * U(i_c),  D = 2x2 average, U = nearest x2.

    The paper's network is a U-Net whose details are in its supplement; ours is a RepVGG stack
    per level on the downsampled inputs (with the finer level's features), sharing nothing
    across levels. Frames of any size are edge-padded to a multiple of 2^(levels-1).
    """

    levels: int = bounded(3, low=1, high=8)
    num_layers: int = bounded(4, low=1, high=64)
    width: int = bounded(16, low=1, high=1024)
    kernel_sizes: tuple[int, ...] = bounded((3, 5), low=1, high=63)
    tonemap: Literal["gamma", "reinhard_gamma"] = "reinhard_gamma"
    albedo_floor: float = bounded(0.05, low=0, low_open=True, high=1)
    deploy: bool = False

    def __post_init__(self):
        _check_config_kernels("WSKPMRConfig.kernel_sizes", self.kernel_sizes)


def downsample(x: jax.Array) -> jax.Array:
    """2x2 average (H and W must be even)."""
    shape = x.shape[:-3] + (x.shape[-3] // 2, 2, x.shape[-2] // 2, 2, x.shape[-1])
    return x.reshape(shape).mean(axis=(-4, -2))


def upsample(x: jax.Array) -> jax.Array:
    return jnp.repeat(jnp.repeat(x, 2, axis=-3), 2, axis=-2)


def _mr_nets(config: WSKPMRConfig):
    count = len(config.kernel_sizes)
    # Each level predicts M importance maps + M fusion logits (+ 1 blend weight, except the
    # coarsest level which has nothing coarser to blend with).
    return [
        RepVGGStack(config.num_layers, config.width,
                    2 * count + (1 if level < config.levels - 1 else 0), config.deploy,
                    name=f"level{level}")
        for level in range(config.levels)
    ]


class _MRNet(nn.Module):
    config: WSKPMRConfig

    @nn.compact
    def __call__(self, inputs: list[jax.Array]) -> list[jax.Array]:
        return [net(x) for net, x in zip(_mr_nets(self.config), inputs)]


def wskp_mr_denoise(params, config: WSKPMRConfig, frame: Frame) -> jax.Array:
    multiple = 2 ** (config.levels - 1)
    height, width = frame.color.shape[-3], frame.color.shape[-2]
    pad_h, pad_w = (-height) % multiple, (-width) % multiple

    def pad(x):
        x = jnp.asarray(x, jnp.float32)
        if pad_h or pad_w:
            x = jnp.pad(x, [(0, 0)] * (x.ndim - 3) + [(0, pad_h), (0, pad_w), (0, 0)], mode="edge")
        return x

    frame = Frame(color=pad(frame.color), albedo=pad(frame.albedo), normal=pad(frame.normal),
                  depth=pad(frame.depth))
    albedo = safe_albedo(frame.albedo, config.albedo_floor)
    irradiance = [frame.color / albedo]
    features = [network_inputs(frame, config.tonemap)]
    for _ in range(config.levels - 1):
        irradiance.append(downsample(irradiance[-1]))
        features.append(downsample(features[-1]))
    outputs = _MRNet(config).apply(params, features)
    count = len(config.kernel_sizes)
    filtered = [
        kernels.decode(irr, out[..., :count], out[..., count : 2 * count], config.kernel_sizes)
        for irr, out in zip(irradiance, outputs)
    ]
    result = filtered[-1]
    for level in range(config.levels - 2, -1, -1):
        fine = filtered[level]
        alpha = jax.nn.sigmoid(outputs[level][..., 2 * count :])
        result = fine - alpha * upsample(downsample(fine)) + alpha * upsample(result)
    return (result * albedo)[..., :height, :width, :]


def wskp_mr_init(key: jax.Array, config: WSKPMRConfig):
    if config.levels < 1:
        raise FrameError(f"levels must be >= 1, got {config.levels}")
    size = 8 * 2 ** (config.levels - 1)
    inputs = [jnp.zeros((1, size // 2**level, size // 2**level, 10)) for level in range(config.levels)]
    return _MRNet(config).init(key, inputs)


def check_kernel_sizes(sizes: Sequence[int]) -> None:
    for size in sizes:
        if size < 1 or size % 2 == 0:
            raise FrameError(f"kernel sizes must be odd and >= 1, got {tuple(sizes)}")
