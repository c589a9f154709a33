"""Denoisers: the kernel decoder, the networks, the registry and temporal accumulation.

``make_denoiser(name, key=...)`` and ``load_denoiser(spec)`` give a :class:`Denoiser`
(``denoise(params, frame) -> (..., H, W, 3)``); importing this package registers every
built-in denoiser (OIDN, the U-Net, WSKP / KP and their variants).
"""

from jaxden.denoise import models, oidn  # noqa: F401  (registration)
from jaxden.denoise.registry import (
    REGISTRY,
    WEIGHTS_DIR,
    Denoiser,
    DenoiserDef,
    get_definition,
    load_denoiser,
    make_denoiser,
    register,
)

__all__ = [
    "REGISTRY",
    "WEIGHTS_DIR",
    "Denoiser",
    "DenoiserDef",
    "get_definition",
    "load_denoiser",
    "make_denoiser",
    "register",
]
