"""Stein's unbiased risk estimate (SURE) of a denoised image's per-pixel error.

- :mod:`~jaxden.sure.settings`: :class:`SureSettings`, the one value SURE's options travel in;
- :mod:`~jaxden.sure.probes`: the probes (normal or Rademacher, per channel or from the colour
  covariance), the same for every path that draws them;
- :mod:`~jaxden.sure.stein`: Monte Carlo SURE with the divergence by ``jax.jvp`` (exact J b per
  probe) or finite differences, and the NumPy black-box forms;
- :mod:`~jaxden.sure.buffers`: sub-buffer SURE (no Gaussian assumption, no derivatives);
- :mod:`~jaxden.sure.denoiser`: SURE of a registered denoiser (jvp or finite differences by
  kind); :mod:`~jaxden.sure.tiled`: the same over tiles of a large frame.
"""

from jaxden.sure.buffers import (
    check_sub_buffers,
    combine_buffers,
    merge_buffer_pairs,
    sure_buffers,
    sure_buffers_jax,
)
from jaxden.sure.denoiser import default_eps, denoise_with_sure
from jaxden.sure.probes import draw_probes
from jaxden.sure.settings import PROBE_DISTS, SureSettings
from jaxden.sure.stein import SureResult, sure, sure_blackbox, sure_from_parts
from jaxden.sure.tiled import sure_frame

__all__ = [
    "PROBE_DISTS",
    "SureResult",
    "SureSettings",
    "check_sub_buffers",
    "combine_buffers",
    "default_eps",
    "denoise_with_sure",
    "draw_probes",
    "merge_buffer_pairs",
    "sure",
    "sure_blackbox",
    "sure_buffers",
    "sure_buffers_jax",
    "sure_frame",
    "sure_from_parts",
]
