"""The closed-form mixer: Eq. 9's per-pixel optimal alpha with the expectations replaced by local
Gaussian means, optionally restricted to neighbours of similar brightness (range strata):
:func:`closed_form_alpha`. Its spec and config (``--mixer closed-form``) are
:func:`jaxden.progressive.mixer_config.closed_form_mixer`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_same


def gaussian_taps(sigma: float) -> np.ndarray:
    radius = max(1, math.ceil(3.0 * sigma))
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-np.square(offsets) / (2.0 * sigma * sigma)).astype(np.float32)


def blur_shifted(image, taps, axis: int):
    """Zero-padded correlation of (H, W, C) along ``axis`` with odd-length ``taps`` as a loop of
    shifted, weighted adds: on XLA:CPU far faster than a depthwise convolution for the closed
    form's wide kernels (measured: docs/history.md, "Defaults of the code"), the same result
    to float32 rounding."""
    radius = taps.shape[0] // 2
    size = image.shape[axis]
    padding = [(0, 0)] * image.ndim
    padding[axis] = (radius, radius)
    padded = jnp.pad(image, padding)

    def add(k, total):
        return total + taps[k] * jax.lax.dynamic_slice_in_dim(padded, k, size, axis=axis)

    return jax.lax.fori_loop(0, taps.shape[0], add, jnp.zeros_like(image))


#: Range-aware closed form (``closed_form_stops``): the proxy of a pixel's brightness is the
#: channel mean of (x + y) / 2 under a Gaussian blur of this width (pixels), so that one
#: noisy sample does not move a pixel to another stratum; (x + y) / 2 keeps the closed form
#: swap-symmetric.
CLOSED_FORM_PROXY_SIGMA = 2.0
#: Proxy values are clamped to [FLOOR, CEIL] (radiance) before their log2: everything darker
#: than FLOOR shares the lowest stratum, everything brighter than CEIL the highest.
CLOSED_FORM_RANGE_FLOOR = 1e-3
CLOSED_FORM_RANGE_CEIL = 1e4


def blur_2d(image, taps):
    return blur_shifted(blur_shifted(image, taps, 0), taps, 1)


def strata_local_sums(terms, level, lo: int, hi: int, taps):
    """Gaussian local sums of ``terms`` (H, W, C) over neighbours in the same strata: tent bins
    of ``level`` (H, W, 1), in bin units, for the integer bins lo..hi. For each bin b the terms
    of its members (weight s_b) are blurred, and a pixel collects sum_b s_b(p) blur(s_b
    terms)(p), so neighbours more than two bins apart do not contribute. A loop over the bins
    (one compiled body), empty bins skipped at run time."""

    def add(b, total):
        weight = jnp.clip(1.0 - jnp.abs(level - b.astype(level.dtype)), 0.0, 1.0)
        return jax.lax.cond(
            jnp.any(weight > 0),
            lambda t: t + weight * blur_2d(terms * weight, taps),
            lambda t: t,
            total,
        )

    return jax.lax.fori_loop(lo, hi + 1, add, jnp.zeros_like(terms))


def _range_local_means(terms, x, y, taps, stops: float):
    """Gaussian local sums of ``terms`` (H, W, C) restricted to pixels of similar brightness.

    A bilateral grid along log2 brightness with tent bins ``stops`` wide
    (:func:`strata_local_sums`): neighbours more than two bins apart in brightness do not
    contribute, so a bright emitter does not set the alpha of the dim wall beside it.
    """
    proxy = jnp.mean((x + y) * 0.5, axis=-1, keepdims=True)
    proxy = blur_2d(proxy, jnp.asarray(gaussian_taps(CLOSED_FORM_PROXY_SIGMA), x.dtype))
    proxy = jnp.clip(proxy, CLOSED_FORM_RANGE_FLOOR, CLOSED_FORM_RANGE_CEIL)
    level = jnp.log2(proxy) / stops
    lo = math.floor(math.log2(CLOSED_FORM_RANGE_FLOOR) / stops)
    hi = math.ceil(math.log2(CLOSED_FORM_RANGE_CEIL) / stops)
    return strata_local_sums(terms, level, lo, hi, taps)


def _closed_form_single(x, y, var, sure, taps, per_channel: bool, stops: float | None = None):
    residual = jnp.square(y - x)
    # E[(y - x)^2 + var - SURE] = 2 (var - var E f'(x)): Eq. 9's numerator, twice.
    numerator = residual + var - sure
    denominator = 2.0 * residual
    if not per_channel:
        numerator = jnp.sum(numerator, axis=-1, keepdims=True)
        denominator = jnp.sum(denominator, axis=-1, keepdims=True)
    # Zero-padded sums with the same weights in both: the ratio of local weighted means over
    # the in-image pixels of the window.
    both = jnp.concatenate([numerator, denominator], axis=-1)
    if stops is None:
        sums = blur_2d(both, taps)
    else:
        sums = _range_local_means(both, x, y, taps, stops)
    numerator, denominator = jnp.split(sums, 2, axis=-1)
    positive = denominator > 0
    # y == x on the whole window: every alpha gives the same z; take y.
    alpha = jnp.where(positive, numerator / jnp.where(positive, denominator, 1.0), 1.0)
    return jnp.broadcast_to(jnp.clip(alpha, 0.0, 1.0), x.shape)


@functools.partial(jax.jit, static_argnames=("sigma", "per_channel", "stops"))
def closed_form_alpha_unchecked(x, y, var, sure, sigma: float, per_channel: bool,
                                stops: float | None = None):
    taps = jnp.asarray(gaussian_taps(sigma), x.dtype)
    lead = x.shape[:-3]
    flat = [a.reshape((-1,) + a.shape[-3:]) for a in (x, y, var, sure)]
    single = lambda args: _closed_form_single(*args, taps, per_channel, stops)
    # With strata, lax.map (not vmap) keeps the skipping of empty bins a real branch.
    alpha = jax.vmap(single)(flat) if stops is None else jax.lax.map(single, flat)
    return alpha.reshape(lead + alpha.shape[1:])


def closed_form_alpha(x, y, var, sure, *, sigma: float = 12.0, per_channel: bool = False,
                      stops: float | None = None):
    """The paper's Eq. 9 with Gaussian local means: a mixer without a network (our addition).

    For z = x + alpha (y - x), the alpha that minimises E[(z - mu)^2] is (paper Eq. 9)
    ``alpha = (var - var E f'(x)) / E[(y - x)^2]``; with SURE = (y - x)^2 - var + 2 var f'(x)
    its numerator is ``((y - x)^2 + var - SURE) / 2``. Per pixel these estimates are far too
    noisy to use (paper Sec. 4.1; measured: docs/history.md, "Defaults of the code"), so both
    numerator and denominator are replaced by local means, Gaussian weights of standard
    deviation ``sigma`` pixels (truncated at 3 sigma, only in-image pixels), summed over the
    colour channels unless ``per_channel``, and the ratio is clipped to [0, 1].

    Properties: swap-symmetric by construction (exchanging (x, var) with (y, SURE) gives
    1 - alpha before clipping); consistent on its own (as var -> 0 with y's bias fixed, the
    numerator -> 0 and the denominator -> 2 bias^2, so alpha -> 0), and the t-statistic
    scaling still applies on top in :func:`jaxden.progressive.progressive_denoise`. Where
    y == x on a whole window alpha is 1 (any value gives the same z).

    ``stops`` (None: off) makes the local means range-aware (our addition): only neighbours of
    similar brightness count, through tent bins ``stops`` wide in log2 of the channel mean of
    (x + y) / 2 (blurred by :data:`CLOSED_FORM_PROXY_SIGMA` px; see
    :func:`_range_local_means`). Without it, a window holding an emitter or a bright
    highlight is ruled by that spot's errors, which are orders of magnitude larger than those
    of the dim surfaces around it, and its alpha is forced on them. The proxy is symmetric in
    x and y, so swap symmetry and consistency hold as above.

    Inputs (..., H, W, 3) as in :func:`jaxden.progressive.mixer_alpha`; returns alpha
    (..., H, W, 3) in [0, 1]. Pure and jitted (``sigma``, ``per_channel`` and ``stops``
    static). FrameError for missing ``sure`` or mismatched shapes, ConfigError for a width
    that is not a finite number > 0.
    """
    for name, value in (("sigma", sigma), ("stops", stops)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ConfigError(f"closed_form_alpha: {name} must be a finite number > 0, got "
                              f"{value!r}")
    if sure is None:
        raise FrameError("closed_form_alpha: the closed form reads SURE: need 'sure'")
    check_same("closed_form_alpha", x=x, y=y, var=var, sure=sure)
    x, y, var, sure = (jnp.asarray(a, jnp.float32) for a in (x, y, var, sure))
    return closed_form_alpha_unchecked(x, y, var, sure, float(sigma), bool(per_channel),
                                       None if stops is None else float(stops))
