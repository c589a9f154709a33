"""Intel Open Image Denoise 2 (pyoidn, CPU, pretrained) registered as a black-box denoiser: NumPy
in, NumPy out, no derivatives.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from jaxden.config import bounded
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame


# ------------------------------------------------------------------------------------- OIDN
@dataclasses.dataclass(frozen=True)
class OIDNConfig:
    """Intel Open Image Denoise (pyoidn, CPU, built-in weights).

    ``use_albedo`` / ``use_normal`` pass the auxiliary features when the frame has them.
    ``clean_aux`` is OIDN's ``cleanAux`` flag (the features are noise-free): ``"yes"``
    (default), ``"no"``, or ``"auto"``: yes for frames of at least ``clean_aux_min_spp``
    samples per pixel (or of unknown spp), no below. Features average min(spp, feature_spp)
    samples, so at 2-4 spp they are noisy, but telling OIDN so is no reliable gain: on the 8
    crops of data/test "no" lowers OIDN's RMSE by 18 % at 2 spp and 9 % at 4 spp, while on
    the built-in scenes at 2-8 spp it ranges from 0.63x to 4.6x in relMSE (small-lights:
    far worse); from 16 spp up "yes" wins (docs/results.md, "OIDN's auxiliary features").
    """

    quality: Literal["high", "balanced", "fast"] = "high"
    use_albedo: bool = True
    use_normal: bool = True
    clean_aux: Literal["auto", "yes", "no"] = "yes"
    clean_aux_min_spp: int = bounded(8, low=1, high=4294967295)

    def __post_init__(self) -> None:
        if self.clean_aux not in ("auto", "yes", "no"):
            raise ConfigError(f"OIDN clean_aux must be auto, yes or no, got {self.clean_aux!r}")
        if self.clean_aux_min_spp < 1:
            raise ConfigError(f"OIDN clean_aux_min_spp must be >= 1, got "
                              f"{self.clean_aux_min_spp}")

    def features_are_clean(self, spp) -> bool:
        """Whether to pass cleanAux for a frame of ``spp`` samples per pixel (None: unknown)."""
        if self.clean_aux != "auto":
            return self.clean_aux == "yes"
        return spp is None or float(spp) >= self.clean_aux_min_spp


def _oidn_one(config: OIDNConfig, color, albedo, normal, clean: bool) -> np.ndarray:
    import pyoidn

    color = np.ascontiguousarray(np.maximum(np.asarray(color, np.float32), 0.0))
    if normal is not None and albedo is None:
        # OIDN's RT filter accepts normals only together with albedo.
        normal = None
    return pyoidn.denoise(
        color,
        None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32),
        None if normal is None else np.ascontiguousarray(np.clip(normal, -1, 1), np.float32),
        hdr=True,
        clean_aux=clean and albedo is not None,
        quality=config.quality,
    )


def oidn_apply(params: None, config: OIDNConfig, frame: Frame) -> np.ndarray:
    """Denoise with OIDN; NumPy in and out; batch dimensions are looped over."""
    color = np.asarray(frame.color, np.float32)
    if color.ndim < 3 or color.shape[-1] != 3:
        raise FrameError(f"OIDN needs colour of shape (..., H, W, 3), got {color.shape}")
    albedo = frame.albedo if config.use_albedo else None
    normal = frame.normal if config.use_normal else None
    batch = color.shape[:-3]
    flat = color.reshape((-1,) + color.shape[-3:])
    out = np.empty_like(flat)

    def flat_aux(aux):
        return None if aux is None else np.asarray(aux, np.float32).reshape(flat.shape)

    albedo, normal = flat_aux(albedo), flat_aux(normal)
    spp = (None,) * flat.shape[0] if frame.spp is None else np.broadcast_to(
        np.asarray(frame.spp, np.float64), batch).reshape(-1)
    for i in range(flat.shape[0]):
        out[i] = _oidn_one(
            config, flat[i], None if albedo is None else albedo[i],
            None if normal is None else normal[i], config.features_are_clean(spp[i]),
        )
    return out.reshape(batch + color.shape[-3:])


register(
    DenoiserDef(
        name="oidn",
        description="Intel Open Image Denoise 2 (pyoidn, CPU, pretrained; black box)",
        config_cls=OIDNConfig,
        required=lambda config: ("color",),
        apply=oidn_apply,
        differentiable=False,
    )
)
