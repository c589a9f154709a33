"""An outside plugin for jaxden's tests: a cross-bilateral filter (a registered function), a
small trainable convolutional denoiser (a registered model), a loss and a mixer network. It lives outside the
package and is never on sys.path: the tests name it by --plugin, JAXDEN_PLUGINS or a config's
plugins."""

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxden.denoise import Denoiser, DenoiserDef, register
from jaxden.progressive.network import MixerNetwork, register_mixer_network
from jaxden.train.losses import register_loss

RADIUS = 2


def cross_bilateral(frame):
    """Cross-bilateral filter guided by albedo and normal, 5 x 5 window."""
    color, albedo, normal = frame.color, frame.albedo, frame.normal
    total = jnp.zeros_like(color)
    weights = jnp.zeros(color.shape[:-1] + (1,), color.dtype)
    for dy in range(-RADIUS, RADIUS + 1):
        for dx in range(-RADIUS, RADIUS + 1):
            def shift(a, dy=dy, dx=dx):
                return jnp.roll(a, (dy, dx), axis=(-3, -2))

            distance = (dy * dy + dx * dx) / (2 * 1.5**2)
            feature = (jnp.sum((shift(albedo) - albedo) ** 2, -1, keepdims=True) / 0.02
                       + jnp.sum((shift(normal) - normal) ** 2, -1, keepdims=True) / 0.1)
            weight = jnp.exp(-distance - feature)
            total = total + weight * shift(color)
            weights = weights + weight
    return total / weights


Denoiser.from_function(cross_bilateral, name="lab-xbilateral", needs=("albedo", "normal"),
                       radius=RADIUS, register=True)


@dataclasses.dataclass(frozen=True)
class TinyConvConfig:
    width: int = 8


def tiny_init(key, config):
    k1, k2 = jax.random.split(key)
    return {"w1": 0.1 * jax.random.normal(k1, (3, 3, 6, config.width)),
            "w2": 0.1 * jax.random.normal(k2, (3, 3, config.width, 3))}


def tiny_apply(params, config, frame):
    """A residual two-layer CNN on colour and albedo."""
    x = jnp.concatenate([frame.color, frame.albedo], -1)
    batched = x[None] if x.ndim == 3 else x
    conv = lambda a, w: jax.lax.conv_general_dilated(
        a, w, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    out = batched[..., :3] + conv(jax.nn.relu(conv(batched, params["w1"])), params["w2"])
    return out[0] if x.ndim == 3 else out


register(DenoiserDef(name="lab-tinyconv", description="residual two-layer CNN (test plugin)",
                     config_cls=TinyConvConfig, required=lambda config: ("albedo",),
                     apply=tiny_apply, init=tiny_init))


def charbonnier(prediction, target):
    """Per-image Charbonnier loss (a smooth L1)."""
    return jnp.mean(jnp.sqrt((prediction - target) ** 2 + 1e-6), axis=(-3, -2, -1))


register_loss("lab-charbonnier", charbonnier)


class LabMixNet(nn.Module):
    """A one-layer mixer network: a 3 x 3 convolution of the mixer inputs."""

    out_channels: int

    @nn.compact
    def __call__(self, x):
        return nn.Conv(self.out_channels, (3, 3), padding="SAME", name="conv_out")(x)


register_mixer_network(MixerNetwork("lab-mixnet", lambda config: LabMixNet(config.out_channels),
                                    radius=1, description="one 3x3 convolution (test plugin)"))
