"""Denoisers: the kernel decoder, the networks, the registry and temporal accumulation.

``make_denoiser(name, key=...)`` and ``load_denoiser(spec)`` give a :class:`Denoiser`
(``denoise(params, frame) -> (..., H, W, 3)``); importing this package registers every
built-in denoiser (OIDN, the U-Net, WSKP / KP and their variants, the training-free
baselines SVGF, BMFR and StatMC). Any of them keeps the
directly visible emission out of the filter with the spec option ``:emission=separate``
(:mod:`jaxden.denoise.emission`).
"""

from jaxden.denoise import (  # noqa: F401  (registration)
    bmfr,
    deep_combiner,
    models,
    oidn,
    oidn_jax,
    rt_baselines,
    statmc,
    svgf,
)
from jaxden.denoise.emission import EMISSION_MODES, separate_emission
from jaxden.denoise.registry import (
    DENOISER_OPTIONS,
    REGISTRY,
    WEIGHTS_DIR,
    Denoiser,
    DenoiserDef,
    emission_separated,
    get_definition,
    load_denoiser,
    make_denoiser,
    register,
    split_spec,
    with_options,
)

__all__ = [
    "DENOISER_OPTIONS",
    "EMISSION_MODES",
    "REGISTRY",
    "WEIGHTS_DIR",
    "Denoiser",
    "DenoiserDef",
    "emission_separated",
    "get_definition",
    "load_denoiser",
    "make_denoiser",
    "register",
    "separate_emission",
    "split_spec",
    "with_options",
]
