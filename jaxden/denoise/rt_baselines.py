"""Registers the real-time baselines that WSKP and NBGD compare to, as trainable denoisers:
``nbgd`` (neural bilateral grid denoiser, Meng et al. EGSR 2020; :mod:`jaxden.denoise.nn.nbgd`)
and ``mrkp`` (multi-resolution kernel prediction as Meng et al. modified KPCN;
:mod:`jaxden.denoise.nn.mrkp`).

Both read the real-time family's frame fields (colour, albedo, normal, depth), filter the
colour demodulated by the safe albedo (:func:`jaxden.denoise.nn.wskp.safe_albedo`) and
multiply it back; the config defaults are the authors' released models (BASELINES.md sections
3 and 5) except where docs/departures.md says otherwise. Train them with
``jaxden train experiments/configs/train-nbgd.toml`` / ``train-mrkp.toml``.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp

from jaxden.config import bounded, check_fields
from jaxden.denoise.nn import mrkp, nbgd, wskp
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.tiling import TileSpec

FEATURES = ("color", "albedo", "normal", "depth")


def _features(config) -> tuple[str, ...]:
    return FEATURES


def _depth_max(config, frame: Frame):
    return wskp.frame_depth_max(frame)


def _tile_apply(apply):
    """``apply`` on a tile with the whole frame's depth normalisation (TileSpec.constants)."""
    return lambda packed, config, frame: apply(packed["params"], config, frame,
                                                depth_max=packed["constants"])


def _demodulate(frame: Frame, floor: float):
    albedo = wskp.safe_albedo(jnp.asarray(frame.albedo, jnp.float32), floor)
    return jnp.asarray(frame.color, jnp.float32) / albedo, albedo


# ------------------------------------------------------------------------------------- NBGD
@dataclasses.dataclass(frozen=True)
class NBGDConfig:
    """NBGD, the released "2-layer 3-grid" model: grid ``k`` has cells of ``grid_spatial[k]``
    pixels and ``grid_range[k]`` guide units (of 0..255); the guide network is two
    ``guide_kernel`` convolutions with ``guide_width`` hidden channels. ``tonemap``: of the
    guide network's colour input (the authors': ``gamma``; default ``reinhard_gamma`` as
    every real-time model here, docs/departures.md); ``albedo_floor``: of the safe albedo."""

    grid_spatial: tuple[int, ...] = bounded((4, 8, 16), low=1, high=256)
    grid_range: tuple[int, ...] = bounded((4, 8, 16), low=1, high=256)
    guide_width: int = bounded(20, low=1, high=1024)
    guide_kernel: int = bounded(5, low=1, high=31)
    tonemap: Literal["gamma", "reinhard_gamma"] = "reinhard_gamma"
    albedo_floor: float = bounded(0.05, low=0, low_open=True, high=1)

    def __post_init__(self):
        check_fields(self)
        if not self.grid_spatial or len(self.grid_spatial) != len(self.grid_range):
            raise ConfigError(f"NBGDConfig: grid_spatial and grid_range need one value per "
                              f"grid (at least one), got {self.grid_spatial} and "
                              f"{self.grid_range}")
        if self.guide_kernel % 2 == 0:
            raise ConfigError(f"NBGDConfig: guide_kernel must be odd, got {self.guide_kernel}")

    @property
    def cells(self) -> tuple[tuple[int, int], ...]:
        return tuple(zip(self.grid_spatial, self.grid_range))


def _guide_net(config: NBGDConfig) -> nbgd.GuideNet:
    return nbgd.GuideNet(grids=len(config.grid_spatial), width=config.guide_width,
                         kernel_size=config.guide_kernel)


def nbgd_init(key: jax.Array, config: NBGDConfig):
    return _guide_net(config).init(key, jnp.zeros((1, 16, 16, 10), jnp.float32))


def nbgd_denoise(params, config: NBGDConfig, frame: Frame, depth_max=None) -> jax.Array:
    """(..., H, W, 3) denoised radiance (``depth_max``: of the whole frame, for tiles)."""
    guide_out = _guide_net(config).apply(params, wskp.network_inputs(frame, config.tonemap,
                                                                      depth_max))
    irradiance, albedo = _demodulate(frame, config.albedo_floor)
    return nbgd.fuse_grids(guide_out, irradiance, config.cells) * albedo


def nbgd_tiling(config: NBGDConfig) -> TileSpec:
    """A cell of s pixels gathers the pixels less than s from its centre and a pixel reads
    the cells less than s from it: pixels less than 2 s apart interact (2 s - 1), each also
    through its guide (two k x k convolutions: k - 1 more). Tiles start on the largest cell
    grid, so that every tile's cells are the whole frame's."""
    largest = max(config.grid_spatial)
    return TileSpec(radius=2 * largest - 1 + config.guide_kernel - 1, multiple=largest,
                    constants=_depth_max, apply=_tile_apply(nbgd_denoise))


register(DenoiserDef(
    name="nbgd",
    description="neural bilateral grid denoiser (Meng et al. 2020): guide net + 3 grids",
    config_cls=NBGDConfig, required=_features, apply=nbgd_denoise, init=nbgd_init,
    tiling=nbgd_tiling))


# ------------------------------------------------------------------------------------ MR-KP
@dataclasses.dataclass(frozen=True)
class MRKPConfig:
    """MR-KP (Meng et al.'s KPCN variant): a U-Net of ``levels`` levels of ``width`` channels
    predicting ``kernel_size`` x ``kernel_size`` kernels and a blend weight at the
    ``filter_levels`` finest resolutions. ``color_input``: the network's colour channels,
    ``hdr`` the raw demodulated colour (the authors'), or the tone-mapped radiance of WSKP's
    inputs (``gamma``, ``reinhard_gamma``); ``albedo_floor``: of the safe albedo."""

    levels: int = bounded(5, low=1, high=10)
    filter_levels: int = bounded(3, low=1, high=10)
    width: int = bounded(48, low=1, high=1024)
    kernel_size: int = bounded(5, low=1, high=31)
    color_input: Literal["hdr", "gamma", "reinhard_gamma"] = "hdr"
    albedo_floor: float = bounded(0.05, low=0, low_open=True, high=1)

    def __post_init__(self):
        check_fields(self)
        if self.filter_levels > self.levels:
            raise ConfigError(f"MRKPConfig: filter_levels ({self.filter_levels}) must not "
                              f"exceed levels ({self.levels})")
        if self.kernel_size % 2 == 0:
            raise ConfigError(f"MRKPConfig: kernel_size must be odd, got {self.kernel_size}")


def _mrkp_net(config: MRKPConfig) -> mrkp.MRKPNet:
    return mrkp.MRKPNet(levels=config.levels, filter_levels=config.filter_levels,
                        width=config.width, kernel_size=config.kernel_size)


def mrkp_init(key: jax.Array, config: MRKPConfig):
    size = 2**config.levels
    return _mrkp_net(config).init(key, jnp.zeros((1, size, size, 10), jnp.float32))


def _pad_to(x, multiple: int):
    height, width = x.shape[-3], x.shape[-2]
    pad = [(0, 0)] * (x.ndim - 3) + [(0, (-height) % multiple), (0, (-width) % multiple), (0, 0)]
    return jnp.pad(x, pad, mode="edge") if any(p[1] for p in pad) else x


def mrkp_denoise(params, config: MRKPConfig, frame: Frame, depth_max=None) -> jax.Array:
    """(..., H, W, 3) denoised radiance (``depth_max``: of the whole frame, for tiles)."""
    height, width = frame.color.shape[-3], frame.color.shape[-2]
    irradiance, albedo = _demodulate(frame, config.albedo_floor)
    hdr = config.color_input == "hdr"
    inputs = wskp.network_inputs(frame, "gamma" if hdr else config.color_input, depth_max)
    if hdr:  # the authors' input: the raw demodulated colour in place of the tone-mapped one
        inputs = jnp.concatenate([irradiance, inputs[..., 3:]], axis=-1)
    multiple = 2**config.levels
    heads = _mrkp_net(config).apply(params, _pad_to(inputs, multiple))
    out = mrkp.mrkp_filter(heads, _pad_to(irradiance, multiple), config.kernel_size)
    return out[..., :height, :width, :] * albedo


def mrkp_tiling(config: MRKPConfig) -> TileSpec:
    """The U-Net's and the pyramid's receptive field (:func:`mrkp.receptive_radius`: 98
    pixels for the default network); tiles start on the pooling grid ``2^levels``."""
    return TileSpec(radius=mrkp.receptive_radius(config.levels, config.filter_levels,
                                                 config.kernel_size),
                    multiple=2**config.levels, constants=_depth_max,
                    apply=_tile_apply(mrkp_denoise))


register(DenoiserDef(
    name="mrkp",
    description="multi-resolution kernel prediction (Meng et al. 2020's KPCN variant, 5x5 at 3 scales)",
    config_cls=MRKPConfig, required=_features, apply=mrkp_denoise, init=mrkp_init,
    tiling=mrkp_tiling))
