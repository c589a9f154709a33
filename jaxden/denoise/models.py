"""Registers the trainable denoisers: the U-Net and the kernel-prediction family.

``unet`` (OIDN's U-Net, the progressive-denoising paper's base; feature sets hdr, var, alb,
nrm), ``wskp`` (6 RepVGG layers), ``wskp3`` (3 layers), ``wskp_mr`` (multi-resolution, Eq. 7),
``kp`` (direct 13x13 kernels, WSKP backbone), ``kp1`` (2 layers, k = 13), ``kp2``
(5 layers, k = 7).
"""

from __future__ import annotations

import dataclasses

import jax

from jaxden.config import bounded
from jaxden.denoise.nn import wskp
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.frame import Frame
from jaxden.tiling import TileSpec

_FEATURES = lambda config: wskp.WSKP_FEATURES  # noqa: E731


def _depth_constants(config, frame: Frame):
    return wskp.frame_depth_max(frame)


def _with_depth_max(apply):
    """``apply`` on a tile, with the whole frame's depth normalisation (see TileSpec)."""
    return lambda packed, config, frame: apply(packed["params"], config, frame,
                                                depth_max=packed["constants"])


def _kernel_tiling(apply):
    """RepVGG stacks (5 x 5 blocks: 2 pixels each) and per-pixel kernels (k // 2 pixels).
    WSKP's kernels weigh each neighbour q by its own importance exp(I(q)), computed by the
    network around q: the fields add up. Direct kernel prediction (kp) weighs the
    neighbours by the kernel predicted at p: the larger of the two."""
    def tiling(config):
        sizes = getattr(config, "kernel_sizes", None)
        network = 2 * config.num_layers
        radius = (network + max(sizes) // 2 if sizes is not None
                  else max(network, config.kernel_size // 2))
        return TileSpec(radius=radius, constants=_depth_constants, apply=_with_depth_max(apply))
    return tiling


def _variant(cls, **defaults):
    """A config class with other defaults (so `wskp3` is its own registered name)."""
    fields = [(f.name, f.type, dataclasses.field(default=defaults.get(f.name, f.default)))
              for f in dataclasses.fields(cls)]
    # __module__: the string annotations (Literal[...]) resolve in the original module
    return dataclasses.make_dataclass(cls.__name__, fields, frozen=True, namespace={
        "__doc__": cls.__doc__, "__module__": cls.__module__})


for name, description, cls, init, apply, tiling in (
    ("wskp", "weight-sharing kernel prediction, 6 RepVGG layers, kernels 3..13", wskp.WSKPConfig,
     wskp.wskp_init, wskp.wskp_denoise, _kernel_tiling(wskp.wskp_denoise)),
    ("wskp3", "weight-sharing kernel prediction, 3 RepVGG layers", _variant(wskp.WSKPConfig, num_layers=3),
     wskp.wskp_init, wskp.wskp_denoise, _kernel_tiling(wskp.wskp_denoise)),
    ("wskp_mr", "multi-resolution WSKP (3 scales, kernels 3 and 5, paper Eq. 7)", wskp.WSKPMRConfig,
     wskp.wskp_mr_init, wskp.wskp_mr_denoise, None),
    ("kp", "direct kernel prediction, 13x13, WSKP backbone (6 layers)", wskp.KPConfig,
     wskp.kp_init, wskp.kp_denoise, _kernel_tiling(wskp.kp_denoise)),
    ("kp1", "direct kernel prediction, 2 layers, 13x13", _variant(wskp.KPConfig, num_layers=2),
     wskp.kp_init, wskp.kp_denoise, _kernel_tiling(wskp.kp_denoise)),
    ("kp2", "direct kernel prediction, 5 layers, 7x7", _variant(wskp.KPConfig, num_layers=5, kernel_size=7),
     wskp.kp_init, wskp.kp_denoise, _kernel_tiling(wskp.kp_denoise)),
):
    register(DenoiserDef(name=name, description=description, config_cls=cls, required=_FEATURES,
                         apply=apply, init=init, tiling=tiling))


# ------------------------------------------------------------------------------------ U-Net
@dataclasses.dataclass(frozen=True)
class UNetConfig:
    """The progressive-denoising paper's U-Net; ``features`` from hdr, var, alb, nrm."""

    features: tuple[str, ...] = ("hdr", "alb", "nrm", "var")
    encoder_widths: tuple[int, ...] = bounded((32, 48, 64, 80, 96), low=1, high=4096)
    decoder_widths: tuple[int, ...] = bounded((112, 96, 64, 64, 32), low=1, high=4096)

    def __post_init__(self):
        from jaxden.errors import ConfigError

        if len(self.encoder_widths) != 5 or len(self.decoder_widths) != 5:
            raise ConfigError(
                f"UNetConfig: encoder_widths and decoder_widths need 5 values each (the "
                f"network has 5 levels), got {len(self.encoder_widths)} and "
                f"{len(self.decoder_widths)}")


def _unet_module(config: UNetConfig):
    from jaxden.denoise.nn.unet import UNet

    return UNet(tuple(config.encoder_widths), tuple(config.decoder_widths))


def _unet_init(key, config: UNetConfig):
    from jaxden.denoise.nn.unet import check_features

    features = check_features(config.features)
    sample = jax.numpy.zeros((1, 16, 16, 3 * len(features)), jax.numpy.float32)
    return _unet_module(config).init(key, sample)


def _unet_apply(params, config: UNetConfig, frame: Frame):
    from jaxden.denoise.nn.unet import unet_denoise

    return unet_denoise(_unet_module(config), params, frame, config.features)


def _unet_required(config: UNetConfig) -> tuple[str, ...]:
    from jaxden.denoise.nn.unet import FEATURE_FIELDS, check_features

    return tuple(FEATURE_FIELDS[f] for f in check_features(config.features))


#: The U-Net's receptive field (pixels, each side): its 3 x 3 convolutions at scales 1, 2, 4,
#: 8, 16 (two at 1, one each at 2, 4, 8 and two at 16 going down; two each at 8, 4, 2 and
#: three at 1 coming up: 79 pixels), plus up to one pixel of the current scale per 2 x 2 pool
#: and per upsampling (15 + 15). Tiles start on its pooling grid (16).
UNET_RADIUS = 79 + 15 + 15


def _unet_tiling(config: UNetConfig):
    from jaxden.denoise.nn.unet import POOLING_STAGES

    return TileSpec(radius=UNET_RADIUS, multiple=2**POOLING_STAGES)


register(
    DenoiserDef(
        name="unet",
        description="U-Net of OIDN / the progressive-denoising paper (trainable, JAX)",
        config_cls=UNetConfig,
        required=_unet_required,
        apply=_unet_apply,
        init=_unet_init,
        tiling=_unet_tiling,
    )
)
