"""Sub-buffer (jackknife) SURE: the covariance term of SURE from K independent sub-buffers of a
render, without Stein's Gaussian assumption and without derivatives.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.data.merge import combine_buffers  # noqa: F401  (the sure package's API)
from jaxden.errors import FrameError
from jaxden.frame import Frame, NonFinitePolicy
from jaxden.sure.stein import SureResult, check_output, checked_frame, sure_from_parts

# ------------------------------------------------------------- sub-buffer (jackknife) SURE
#
# Why: Stein's identity Cov(x_i, y_i) = var_i E[dy_i/dx_i] needs Gaussian noise of known
# variance. Monte Carlo pixel means are heavy-tailed (fireflies) and their variance is
# estimated from the same samples, so through a strongly nonlinear denoiser (OIDN) the
# divergence term can be off by 2x either way (measured: docs/results.md, "Sub-buffer SURE").
#
# With the N samples of each pixel split into K equal, independent sub-buffers x_1..x_K
# (x the mean of the x_k; x_-k the mean of all but x_k, independent of x_k):
#
#   E[(x_k - mu) y] = E[(x_k - mu) (y - F(x_-k))]                  (exactly: x_k indep. x_-k)
#
# so Cov(x_i, y_i) = E[(x_k,i - mu_i)(y_i - F(x_-k)_i)] for every k, with no assumption on the
# noise or on F. mu is unknown; with x_-k in its place the expectation picks up
# E[(x_-k - mu)(y - F(x_-k))], which for a linear F is exactly -Cov / (K - 1). Hence
#
#   cov_i = (K - 1) / K^2 * sum_k (x_k,i - x_-k,i) (y_i - F(x_-k)_i)
#
# is unbiased for any linear F and any noise distribution (property test), and for a
# nonlinear F its bias is the nonlinear part of that correction, which shrinks as K grows
# (measured on OIDN: docs/history.md, "Defaults of the code"). It needs no derivative and no
# probes, K + 1 denoiser calls, and a renderer that keeps sub-buffers (or K renders with
# different seeds at N / K spp each). For the identity it equals the batch-means variance estimate
# sum_k (x_k - x)^2 / (K (K - 1)) exactly.


def merge_buffer_pairs(buffers) -> np.ndarray:
    """(K, ...) sub-buffer colours -> (K / 2, ...): the mean of buffers 2i and 2i + 1."""
    xk = np.asarray(buffers, dtype=np.float64)
    if xk.shape[0] % 2:
        raise FrameError(f"merge_buffer_pairs: needs an even number of buffers, got {xk.shape[0]}")
    return 0.5 * (xk[0::2] + xk[1::2])


def check_sub_buffers(color, buffers, *, rtol: float = 2e-3, where: str = "sure_buffers",
                      names=None, spp=None, made_from=None,
                      frame_name: str = "the frame") -> np.ndarray:
    """The (K, ..., H, W, 3) sub-buffer colours ``buffers`` as float64, checked as the set of
    independent renders whose mean is the frame colour ``color`` (..., H, W, 3), in this order:
    K >= 2; as many as the frame records it was made from (``made_from``, a
    :class:`jaxden.data.merge.BufferList`, None: no record); each of the colour's shape; no
    image given twice (a buffer given twice is not independent: the covariance would be
    wrong); each among the recorded ones (by :func:`jaxden.data.merge.colour_digest`); all
    finite; equal sample counts where ``spp`` (one per buffer, None where unknown) says; and
    their mean equal to ``color`` to ``rtol`` of its largest value (see :func:`sure_buffers`).

    ``names``: how the messages name each buffer (e.g. its file; default "sub-buffer k"),
    ``frame_name`` the frame (e.g. its file). Raises FrameError prefixed with ``where`` (the
    parameter or function that took the buffers)."""
    from jaxden.data.merge import colour_digest

    x = np.asarray(color, dtype=np.float64)
    k = len(buffers)
    labels = [f"sub-buffer {i}" for i in range(k)] if names is None else [str(n) for n in names]
    if k < 2:
        raise FrameError(f"{where}: need K >= 2 sub-buffers, got {k}")
    if made_from is not None and len(made_from.digests) != k:
        raise FrameError(f"{where} names {k} files, but {frame_name} was made from "
                         f"{len(made_from.digests)} buffers ({', '.join(made_from.files)}): "
                         f"pass exactly those")
    seen: dict[str, int] = {}
    for i in range(k):
        shape = np.shape(buffers[i])
        if shape != x.shape:
            raise FrameError(f"{where}: {labels[i]} has shape {shape}, but {frame_name} has "
                             f"{x.shape}")
        digest = colour_digest(buffers[i])
        if digest in seen:
            pair = (f"sub-buffers {seen[digest]} and {i}" if names is None
                    else f"{labels[seen[digest]]} and {labels[i]}")
            raise FrameError(f"{where}: {pair} are identical (the same image); the buffers "
                             f"must be independent renders (other seeds)")
        seen[digest] = i
        if made_from is not None and digest not in made_from.digests:
            raise FrameError(f"{where}: {labels[i]} is not one of the {len(made_from.digests)} "
                             f"buffers {frame_name} was made from ({', '.join(made_from.files)}):"
                             f" its colour matches none of their sha256 digests")
    xk = np.stack([np.asarray(b, dtype=np.float64) for b in buffers])
    if not np.all(np.isfinite(xk)):
        raise FrameError(f"{where}: the sub-buffers have NaN or infinite values")
    counts = {float(n): i for i, n in enumerate(spp or ()) if n is not None}
    if len(counts) > 1:
        said = (f"{sorted(counts)}" if names is None else
                ", ".join(f"{c:g} ({labels[i]})" for c, i in sorted(counts.items())))
        raise FrameError(f"{where}: the sub-buffers must have equal spp, got {said}")
    scale = max(float(np.max(np.abs(x))), 1e-12)
    gap = float(np.max(np.abs(xk.mean(axis=0) - x)))
    if gap > rtol * scale:
        raise FrameError(f"{where}: the colour of {frame_name} is not the mean of the {k} "
                         f"buffers (max difference {gap:.3g}, colour scale {scale:.3g})")
    return xk


def sure_buffers(denoise: Callable[[Frame], Any], frame: Frame, buffers,
                 *, extrapolate: bool = False, rtol: float = 2e-3,
                 nonfinite: NonFinitePolicy = "error") -> SureResult:
    """Per-pixel SURE with the covariance term from K sub-buffers instead of Stein's identity.

    Args:
      denoise: ``denoise(frame) -> (..., H, W, 3)`` (NumPy or JAX; a :class:`Denoiser`, OIDN
        included); called K + 1 times, on x and on each leave-one-out mean x_-k (colour only
        changes; features stay).
      frame: the full image (colour x = the mean of the buffers, variance of the mean, the
        features the denoiser needs), e.g. :func:`combine_buffers` of the buffer frames.
      buffers: (K, ..., H, W, 3) colours of K >= 2 independent sub-buffers with equal sample
        counts, or a sequence of K Frames; their mean must equal ``frame.color`` (to
        ``rtol`` of the colour's largest value: the default 2e-3 allows files stored as
        half floats, relative rounding 4.9e-4), else FrameError. The leave-one-out means
        come from the buffers, y and (y - x)^2 from the frame's colour.
      extrapolate: Richardson extrapolation in 1/K: the covariance from the K buffers and
        from K/2 merged pairs (:func:`merge_buffer_pairs`), combined as 2 cov_K - cov_K/2,
        which cancels the O(1/K) bias of nonlinear denoisers (K even; K/2 more calls; measured:
        docs/history.md, "Defaults of the code").

    Returns:
      :class:`SureResult` (float32 NumPy) whose ``divergence_term`` is the sub-buffer
      covariance estimate (see the derivation above this function), ``sure = residual_sq -
      variance + 2 * divergence_term``.
    """
    frame = checked_frame(frame.numpy() if isinstance(frame, Frame) else frame, "sure_buffers",
                           nonfinite)
    spp = None
    if isinstance(buffers, (list, tuple)) and buffers and isinstance(buffers[0], Frame):
        spp = [None if b.spp is None else float(b.spp) for b in buffers]
        buffers = [np.asarray(b.color) for b in buffers]
    xk = check_sub_buffers(frame.color, buffers, rtol=rtol, spp=spp)
    x = np.asarray(frame.color, dtype=np.float64)
    k = xk.shape[0]

    def call(color: np.ndarray) -> np.ndarray:
        out = np.asarray(denoise(frame.replace(color=color.astype(np.float32))), np.float64)
        check_output(out.shape, x.shape, "sure_buffers")
        return out

    if extrapolate and (k % 2 or k < 4):
        raise FrameError(f"sure_buffers: extrapolate needs an even K >= 4, got {k}")
    y = call(x)

    def covariance_of(parts: np.ndarray) -> np.ndarray:
        count = parts.shape[0]
        total = np.zeros_like(x)
        xbar = parts.mean(axis=0)
        for kk in range(count):
            rest = (count * xbar - parts[kk]) / (count - 1)  # the mean of the other buffers
            total += (parts[kk] - rest) * (y - call(rest))
        return total * (count - 1) / count**2

    covariance = covariance_of(xk)
    if extrapolate:
        covariance = 2.0 * covariance - covariance_of(merge_buffer_pairs(xk))
    residual_sq = np.square(y - x)
    var = np.asarray(frame.variance, np.float64)
    result = SureResult(sure=residual_sq - var + 2.0 * covariance, residual_sq=residual_sq,
                        divergence_term=covariance, denoised=y)
    return SureResult(*(np.asarray(a, dtype=np.float32) for a in result))


def sure_buffers_jax(denoise_fn: Callable, frame: Frame, buffers) -> SureResult:
    """:func:`sure_buffers` for JAX denoisers, pure and jittable.

    ``denoise_fn(frame) -> (..., H, W, 3)`` must be a JAX function (e.g.
    ``Denoiser.function()``); ``buffers`` (K, ..., H, W, 3). The K leave-one-out passes run
    one after another (``lax.map``), so memory stays at one denoiser pass. Shapes are checked;
    values are not (call :func:`sure_buffers` for the checked NumPy path).
    """
    xk = jnp.asarray(buffers)
    x = jnp.asarray(frame.color)
    if frame.variance is None:
        raise FrameError("sure_buffers_jax: SURE needs the variance of the pixel mean "
                         "(Frame.variance)")
    if xk.ndim != x.ndim + 1 or xk.shape[1:] != x.shape or xk.shape[0] < 2:
        raise FrameError(f"sure_buffers_jax: buffers have shape {xk.shape}, expected (K >= 2, "
                         f"*{x.shape})")
    k = xk.shape[0]
    y = denoise_fn(frame)
    check_output(jnp.shape(y), x.shape, "sure_buffers_jax")
    rest = (k * jnp.mean(xk, axis=0) - xk) / (k - 1)
    y_rest = jax.lax.map(lambda colour: denoise_fn(frame.replace(color=colour)), rest)
    covariance = (k - 1) / k**2 * jnp.sum((xk - rest) * (y - y_rest), axis=0)
    return SureResult(sure=sure_from_parts(x, y, frame.variance, covariance),
                      residual_sq=jnp.square(y - x), divergence_term=covariance, denoised=y)
