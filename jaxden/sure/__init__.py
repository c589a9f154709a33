"""Stein's unbiased risk estimate (SURE) of a denoised image's per-pixel error.

- :mod:`~jaxden.sure.stein`: Monte Carlo SURE with the divergence by ``jax.jvp`` (exact J b per
  probe) or finite differences, and a NumPy black-box form;
- :mod:`~jaxden.sure.buffers`: sub-buffer SURE (no Gaussian assumption, no derivatives);
- :mod:`~jaxden.sure.denoiser`: SURE of a registered denoiser (jvp or finite differences by kind).
"""

from jaxden.sure.buffers import (
    combine_buffers,
    merge_buffer_pairs,
    sure_buffers,
    sure_buffers_jax,
)
from jaxden.sure.denoiser import (
    denoise_with_sure,
)
from jaxden.sure.stein import (
    PROBE_DISTS,
    SureResult,
    draw_probes,
    sure,
    sure_blackbox,
    sure_from_parts,
)

__all__ = [
    "PROBE_DISTS",
    "SureResult",
    "combine_buffers",
    "denoise_with_sure",
    "draw_probes",
    "merge_buffer_pairs",
    "sure",
    "sure_blackbox",
    "sure_buffers",
    "sure_buffers_jax",
    "sure_from_parts",
]
