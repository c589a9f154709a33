"""Intel Open Image Denoise 2 (pyoidn, CPU, pretrained) registered as a black-box denoiser: NumPy
in, NumPy out, no derivatives.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
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
    OIDN's memory is a resource, not part of the denoiser: :func:`max_memory` sets it.
    Spec options (:data:`OIDN_OPTIONS`) set these from the command line, as on ``oidn-jax``:
    ``oidn:aux=albedo,clean_aux=no,quality=balanced``.
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


#: Spec options of ``oidn`` (``oidn:KEY=VALUE,...``), the first value the default; ``aux``:
#: the features passed when the frame has them (values as
#: :data:`jaxden.denoise.oidn_jax.AUX_INPUTS`).
OIDN_OPTIONS = (("aux", ("albedo+normal", "albedo", "none")), ("clean_aux", ("yes", "no", "auto")),
                ("quality", ("high", "balanced", "fast")))


def configure_oidn(config: OIDNConfig, options: dict[str, str]) -> OIDNConfig:
    """``config`` with spec options (:data:`OIDN_OPTIONS`, values already checked)."""
    changes: dict = {key: options[key] for key in ("quality", "clean_aux") if key in options}
    if "aux" in options:
        changes["use_albedo"] = options["aux"] != "none"
        changes["use_normal"] = options["aux"] == "albedo+normal"
    return dataclasses.replace(config, **changes)


def _oidn_one(config: OIDNConfig, color, albedo, normal, clean: bool) -> np.ndarray:
    import pyoidn

    color = np.ascontiguousarray(np.maximum(np.asarray(color, np.float32), 0.0))
    if normal is not None and albedo is None:
        # OIDN's RT filter accepts normals only together with albedo.
        normal = None
    albedo = None if albedo is None else np.ascontiguousarray(np.clip(albedo, 0, 1), np.float32)
    normal = None if normal is None else np.ascontiguousarray(np.clip(normal, -1, 1),
                                                              np.float32)
    if _MAX_MEMORY_MB[0] is not None:
        return _oidn_limited(config, color, albedo, normal, clean and albedo is not None,
                             _MAX_MEMORY_MB[0])
    return pyoidn.denoise(color, albedo, normal, hdr=True, clean_aux=clean and albedo is not None,
                          quality=config.quality)


_LIMITED: dict = {}  # OIDN's device and one filter per maxMemoryMB (pyoidn's denoise() hides it)
_LIMITED_LOCK = threading.Lock()
_MAX_MEMORY_MB: list = [None]
#: OIDN's scratch memory with its default maxMemoryMB, measured (pyoidn 2.5.1, 'high', CPU):
#: about 630 bytes a pixel up to its own tiling threshold, ~3.2 GB at 3840 x 2160 and above.
OIDN_DEFAULT_BYTES_PER_PIXEL, OIDN_DEFAULT_CAP = 630, 3_300 << 20


def default_memory(pixels: int) -> int:
    """OIDN's scratch bytes for a frame of ``pixels`` with its default maxMemoryMB."""
    return min(OIDN_DEFAULT_BYTES_PER_PIXEL * pixels, OIDN_DEFAULT_CAP)


@contextlib.contextmanager
def max_memory(megabytes: int | None):
    """Within the block, OIDN runs with ``maxMemoryMB = megabytes`` (None: its default, about
    3 GB at 3840 x 2160 and above): a smaller value makes OIDN split the frame into more
    overlapping tiles of its own (measured at 3840 x 2160: 512 MB holds its scratch to
    ~0.6 GB, from 3.2 GB). A resource, not part of the denoiser's identity (caches, mixers)."""
    previous = _MAX_MEMORY_MB[0]
    _MAX_MEMORY_MB[0] = None if megabytes is None else max(16, int(megabytes))
    try:
        yield
    finally:
        _MAX_MEMORY_MB[0] = previous


def _oidn_limited(config: OIDNConfig, color, albedo, normal, clean: bool,
                  megabytes: int) -> np.ndarray:
    """OIDN's RT filter with ``maxMemoryMB`` set, through pyoidn's Device and Filter (what
    ``pyoidn.denoise`` does, plus that parameter)."""
    import pyoidn

    qualities = {"high": pyoidn.OIDN_QUALITY_HIGH, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
                 "fast": pyoidn.OIDN_QUALITY_FAST}
    output = np.empty_like(color)
    with _LIMITED_LOCK:
        if "device" not in _LIMITED:
            device = pyoidn.Device()
            device.commit()
            _LIMITED["device"] = device
        device = _LIMITED["device"]
        flt = _LIMITED.get(megabytes)
        if flt is None:
            flt = _LIMITED[megabytes] = pyoidn.Filter(device, "RT")
            flt.set_int("maxMemoryMB", megabytes)
        images = {"color": color, "albedo": albedo, "normal": normal, "output": output}
        for name, image in images.items():
            if image is None:
                flt.unset_image(name)
            else:
                flt.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
        flt.set_bool("hdr", True)
        flt.set_bool("cleanAux", clean)
        flt.set_quality(qualities[config.quality])
        flt.commit()
        flt.execute()
        error = device.get_error()
        for name, image in images.items():
            if image is not None:  # OIDN shares our arrays: let go of them
                flt.unset_image(name)
    if error:
        raise RuntimeError(f"OIDN failed: {error}")
    return output


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
        optional=lambda config: (*(("albedo",) if config.use_albedo else ()),
                                 *(("normal",) if config.use_normal else ())),
        options=OIDN_OPTIONS,
        configure=configure_oidn,
    )
)
