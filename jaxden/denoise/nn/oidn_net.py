"""The U-Nets of Intel Open Image Denoise 2 (its ``rt`` filters), as a flax module whose layer
names are OIDN's own, so that the tensors of an OIDN weights blob load by name.

Every convolution is 3 x 3, stride 1, zero padding 1, with bias and ReLU (the last one too);
2 x 2 max-pooling; 2 x nearest upsampling; skips concatenated as [upsampled, skip], the last
skip being the network's input. Two sizes (from OIDN's source):

- base (``rt_hdr``, ``rt_hdr_alb``, ...): enc_conv0 32, enc_conv1 32 + pool, enc_conv2 48 +
  pool, enc_conv3 64 + pool, enc_conv4 80 + pool, enc_conv5a/b 96, decoder dec_conv4a/b 112,
  dec_conv3a/b 96, dec_conv2a/b 64, dec_conv1a 64, dec_conv1b 32, dec_conv0 3; receptive
  field 174 pixels;
- large (``*_large``): pairs enc_conv1a/b .. enc_conv5a/b of 64, 96, 128, 192, 256 (pools after
  1-4), decoder 192, 192, 128, 128, 96, 96, 64, 64, 3 (dec_conv4a .. dec_conv1c); 202 pixels.

The module takes the widths from the parameters it is given (``widths``), so the small
variants load too. Input (N, H, W, C) with H, W multiples of 16 (:mod:`jaxden.denoise.oidn_jax`
pads), already in OIDN's transformed domain.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

#: Layer order per size: (name, what follows it): "pool" saves the skip and pools, "up"
#: upsamples and concatenates the next skip (the deepest first, the input last).
BASE_LAYERS = (
    ("enc_conv0", ""), ("enc_conv1", "pool"), ("enc_conv2", "pool"), ("enc_conv3", "pool"),
    ("enc_conv4", "pool"), ("enc_conv5a", ""), ("enc_conv5b", "up"), ("dec_conv4a", ""),
    ("dec_conv4b", "up"), ("dec_conv3a", ""), ("dec_conv3b", "up"), ("dec_conv2a", ""),
    ("dec_conv2b", "up"), ("dec_conv1a", ""), ("dec_conv1b", ""), ("dec_conv0", ""),
)
LARGE_LAYERS = (
    ("enc_conv1a", ""), ("enc_conv1b", "pool"), ("enc_conv2a", ""), ("enc_conv2b", "pool"),
    ("enc_conv3a", ""), ("enc_conv3b", "pool"), ("enc_conv4a", ""), ("enc_conv4b", "pool"),
    ("enc_conv5a", ""), ("enc_conv5b", "up"), ("dec_conv4a", ""), ("dec_conv4b", "up"),
    ("dec_conv3a", ""), ("dec_conv3b", "up"), ("dec_conv2a", ""), ("dec_conv2b", "up"),
    ("dec_conv1a", ""), ("dec_conv1b", ""), ("dec_conv1c", ""),
)
#: Receptive field in pixels per size (OIDN's own figures).
RECEPTIVE_FIELD = {"base": 174, "large": 202}


def layers_of(size: str):
    return LARGE_LAYERS if size == "large" else BASE_LAYERS


def _pool(x):
    return nn.max_pool(x, (2, 2), strides=(2, 2))


def _upsample(x):
    return jnp.repeat(jnp.repeat(x, 2, axis=-3), 2, axis=-2)


class OIDNUNet(nn.Module):
    """OIDN's U-Net; ``widths``: output channels per layer in :func:`layers_of` order."""

    size: str  # "base" or "large"
    widths: tuple[int, ...]
    dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        layers = layers_of(self.size)
        if len(self.widths) != len(layers):
            raise ValueError(f"OIDNUNet {self.size}: {len(layers)} layer widths needed, got "
                             f"{len(self.widths)}")
        skips = [x]  # the input, then each pooled level; the deepest feeds the bottleneck
        bottleneck = True
        for (name, after), width in zip(layers, self.widths, strict=True):
            x = nn.relu(nn.Conv(width, (3, 3), padding=1, name=name, dtype=self.dtype)(x))
            if after == "pool":
                x = _pool(x)
                skips.append(x)
            elif after == "up":
                if bottleneck:
                    skips.pop()
                    bottleneck = False
                x = jnp.concatenate([_upsample(x), skips.pop()], axis=-1)
        return x
