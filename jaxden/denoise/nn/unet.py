"""The U-Net denoiser of OIDN / Chaitanya et al. 2017, as trained in the progressive-denoising paper.

Architecture (REFERENCE-NOTES, OIDN): 3x3 convolutions with ReLU, 2x2 max-pooling, nearest
x2 upsampling and skip concatenation; encoder widths 32/48/64/80/96 and decoder widths
112/96/64/64/32 by default, four pooling stages, linear 3-channel output.

Inputs are selected from HDR, VAR, ALB, NRM (the paper's feature sets ``hdr``, ``hdr var``,
``hdr alb nrm``, ``hdr alb nrm var``) with the paper's transforms (Sec. 5.1): ``log(1 + x)`` for
radiance and albedo, ``arctan(x)`` for the variance of the mean, normals as they are (in
[-1, 1]). The network predicts ``log(1 + y)``; the output is ``expm1`` of it clamped at 0, so
the whole map from linear radiance to linear radiance is what SURE differentiates (as in the
authors' code, where F includes the transfer functions and the clamp).

Departure: OIDN's default HDR transfer is a perceptual (PU) curve; we follow the progressive-
denoising paper's log(1 + x). Images of any size are handled by edge-padding to a multiple of
16 and cropping the output back.
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.errors import FrameError
from jaxden.frame import Frame

FEATURE_CHANNELS = {"hdr": 3, "var": 3, "alb": 3, "nrm": 3}
FEATURE_FIELDS = {"hdr": "color", "var": "variance", "alb": "albedo", "nrm": "normal"}
POOLING_STAGES = 4


def check_features(features: Sequence[str]) -> tuple[str, ...]:
    features = tuple(features)
    unknown = [f for f in features if f not in FEATURE_CHANNELS]
    if unknown or "hdr" not in features or len(set(features)) != len(features):
        raise FrameError(
            f"U-Net input features must include 'hdr', without repeats, from "
            f"{', '.join(FEATURE_CHANNELS)}; got {features}"
        )
    return features


def unet_inputs(frame: Frame, features: Sequence[str]) -> jax.Array:
    """Transformed, concatenated network inputs (..., H, W, 3 * len(features))."""
    features = check_features(features)
    frame.require(*(FEATURE_FIELDS[f] for f in features), who=f"the U-Net with inputs {features}")
    parts = []
    for feature in features:
        value = jnp.asarray(getattr(frame, FEATURE_FIELDS[feature]), jnp.float32)
        if feature in ("hdr", "alb"):
            value = jnp.log1p(jnp.maximum(value, 0.0))
        elif feature == "var":
            value = jnp.arctan(value)
        parts.append(value)
    return jnp.concatenate(parts, axis=-1)


def _pad_to_multiple(x: jax.Array, multiple: int) -> tuple[jax.Array, int, int]:
    height, width = x.shape[-3], x.shape[-2]
    pad_h = (-height) % multiple
    pad_w = (-width) % multiple
    if pad_h or pad_w:
        pad = [(0, 0)] * (x.ndim - 3) + [(0, pad_h), (0, pad_w), (0, 0)]
        x = jnp.pad(x, pad, mode="edge")
    return x, height, width


class UNet(nn.Module):
    """Maps (..., H, W, C_in) transformed inputs to (..., H, W, 3) in the log(1 + x) domain."""

    encoder_widths: Sequence[int] = (32, 48, 64, 80, 96)
    decoder_widths: Sequence[int] = (112, 96, 64, 64, 32)
    out_channels: int = 3

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        e0, e1, e2, e3, e4 = self.encoder_widths
        d4, d3, d2, d1a, d1b = self.decoder_widths

        def conv(features, name):
            return nn.Conv(features, (3, 3), padding="SAME", name=name)

        def pool(y):
            return nn.max_pool(y, (2, 2), strides=(2, 2))

        def up(y):
            return jnp.repeat(jnp.repeat(y, 2, axis=-3), 2, axis=-2)

        skip0 = x
        y = nn.relu(conv(e0, "enc_conv0")(x))
        y = pool(nn.relu(conv(e0, "enc_conv1")(y)))
        skip1 = y
        y = pool(nn.relu(conv(e1, "enc_conv2")(y)))
        skip2 = y
        y = pool(nn.relu(conv(e2, "enc_conv3")(y)))
        skip3 = y
        y = pool(nn.relu(conv(e3, "enc_conv4")(y)))
        y = nn.relu(conv(e4, "enc_conv5a")(y))
        y = nn.relu(conv(e4, "enc_conv5b")(y))
        y = jnp.concatenate([up(y), skip3], axis=-1)
        y = nn.relu(conv(d4, "dec_conv4a")(y))
        y = nn.relu(conv(d4, "dec_conv4b")(y))
        y = jnp.concatenate([up(y), skip2], axis=-1)
        y = nn.relu(conv(d3, "dec_conv3a")(y))
        y = nn.relu(conv(d3, "dec_conv3b")(y))
        y = jnp.concatenate([up(y), skip1], axis=-1)
        y = nn.relu(conv(d2, "dec_conv2a")(y))
        y = nn.relu(conv(d2, "dec_conv2b")(y))
        y = jnp.concatenate([up(y), skip0], axis=-1)
        y = nn.relu(conv(d1a, "dec_conv1a")(y))
        y = nn.relu(conv(d1b, "dec_conv1b")(y))
        return conv(self.out_channels, "dec_conv0")(y)


def unet_denoise(module: UNet, params, frame: Frame, features: Sequence[str]) -> jax.Array:
    """Denoise: linear radiance in, linear radiance out (..., H, W, 3), clamped at 0."""
    x = unet_inputs(frame, features)
    padded, height, width = _pad_to_multiple(x, 2**POOLING_STAGES)
    log_y = module.apply(params, padded)[..., :height, :width, :]
    return jnp.maximum(jnp.expm1(log_y), 0.0)
