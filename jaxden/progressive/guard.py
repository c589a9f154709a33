"""The error guard: a second consistency stage after the t-statistic scaling (our addition), which
keeps the mix from ending above the noisy render where the denoised image is far off, such as
on small bright lights and their glints.

Why the t-statistic scaling alone does not. It tests the *mixed* image z = x + alpha (y - x)
against x, pooled over an 11 x 11 window that also holds the window's noisiest pixel (M_p):
1. t_z = alpha t_y, so a small alpha over a far-off y passes the test (|t_z| < c - 3/a) while
   its error (alpha (y - x))^2 is t_z^2 times the variance of x;
2. next to a lamp the window's variance is ruled by the lamp's rim (pixels that some samples
   hit, with orders of magnitude more variance than the pixels around), so on the lamp's
   core, whose variance is 0 at low spp, t stays small whatever y does.
Both measured on the built-in small-lights scene (docs/departures.md; docs/history.md,
"Defaults of the code").

What the guard does. For z, the mix is better than x in expectation exactly when
``alpha <= 2 (var - Cov[x, y]) / E[(y - x)^2]`` (the expected squared error of z is a quadratic
in alpha, equal to var at 0 and at twice Eq. 9's optimum). The guard estimates
``chi^2 = E[(y - x)^2] / var`` by Gaussian local means of (y - x)^2 and var over a small window
(``guard_sigma`` pixels; summed over R, G, B unless ``per_channel``), drops Cov[x, y] (>= 0
for denoisers that average x's own pixel in; it makes the cap looser), and sets::

    alpha'' = min(alpha', gamma / chi^2) * (1 - S(a (chi - c)))

``gamma`` (2) is the break-even factor; the second factor is the t-statistic's own
significance scaling applied to y's deviation rather than z's: where y is c standard errors
off x, y is no estimate of this pixel and the mix weight vanishes rather than shrinking to
break-even. Where y is unbiased chi is about 1 (less when y keeps some of x's noise) and
neither factor acts (gamma / chi^2 >= 2). As var -> 0 with y's bias b fixed, chi^2 ~ b^2 /
var -> inf, so the guard is consistent on its own (it never raises alpha). A pixel whose
window has var 0 and y != x (a lamp's core all of whose samples hit the lamp) gets alpha 0,
which is exact there; the window (about 7 x 7 at sigma 1) lends a pixel with a spurious zero
variance (a dark pixel none of whose few samples found light) its neighbours' variance.


Noise strata. A Gaussian local mean of var is ruled by the window's noisiest pixels: beside a
lamp, its rim (orders of magnitude noisier) vouches for the dark pixel next to it onto which
the denoiser smeared the lamp, and for the lamp's core. The guard
therefore also pools within noise strata (a bilateral grid along log2 of each pixel's standard
deviation, tent bins as in the closed form's brightness strata), and its significance factor
uses the larger chi of the two poolings (the cap keeps the spatial chi: the strata select
pixels by their own noisy variance, which biases their chi^2 up, so they only decide where y
is many standard errors off). Three safeguards against that selection (each measured on
test-chain at 2..4 spp, where a variance of few samples can fall stops below its
neighbours': docs/history.md, "Defaults of the code"): the bins are at least
GUARD_STRATA_SPREAD times the image's measured scatter of the level around its local mean
wide; a pixel whose stratum holds less than GUARD_STRATA_SUPPORT of the window's weight keeps
the spatial chi; pixels of zero variance belong to no stratum (at low spp that is a pixel none
of whose samples found light, not one that is known exactly).

The variance is itself an estimate, with d degrees of freedom per pixel: d = n - 1 for the
sample variance of a pixel's own n samples, d = K - 1 for the variance of a mean of K
independent renders taken from their spread (``Frame.variance_dof``, :mod:`jaxden.data.merge`;
pooled from the renders' own variances it is K m - 1 = n - 1 again). Pooled over the window's
N_eff = (sum w)^2 / sum w^2 pixels (about 4 pi sigma^2, 12.6 at sigma 1), the local mean of
var has a relative standard deviation of about sqrt(2 / k), k = d N_eff (the chi-square law of
a sample variance; neighbouring pixels taken as independent). At 2..4 spp that is 0.4 to 0.23,
so chi^2 = E[(y - x)^2] / var is often overstated (1 / var is convex) and the guard cut alpha
where y was fine. The guard therefore divides by an upper confidence bound of the variance::

    var (1 + guard_confidence sqrt(2 / k)),   k = max(d, 1) N_eff,
    d = variance_dof where the frame records it, else spp - 1

when either is known (neither: no bound, the variance is taken as exact): a factor of 1.8 at
2 spp, 1.025 at 1024 spp, 1 in the limit; 1.46 for a frame merged from K = 4 renders by their
spread, whatever their sample count. A bounded factor leaves the guard consistent (chi^2 still
grows without bound as var -> 0 with y's bias fixed). The bound is approximate: at
guard_confidence 2 it covers the true variance with probability P(chi^2_k >= k / (1 + 2
sqrt(2 / k))), 0.93 at k = 3 N_eff (tests/test_merge_buffers.py), not the 0.977 of two normal
standard deviations.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtr

from jaxden.progressive.closed_form import blur_2d, gaussian_taps, strata_local_sums

#: The noise level (log2 of a pixel's standard deviation over the image's mean of it) is
#: clipped to +-16 stops.
GUARD_STRATA_RANGE = 16.0
#: Noise strata are at least this many times the image's scatter of the level around its
#: Gaussian local mean wide (so that neighbours are not sorted by the noise of their own
#: variance estimates; measured: docs/history.md, "Defaults of the code").
GUARD_STRATA_SPREAD = 3.0
#: A pixel whose noise stratum holds less than this fraction of the window's weight keeps
#: the spatial chi (a lone low variance among its neighbours is more likely luck than signal).
GUARD_STRATA_SUPPORT = 0.3


def _effective_pixels(taps) -> float:
    """N_eff = (sum w)^2 / sum w^2 of the separable 2-D window with 1-D ``taps``."""
    taps = np.asarray(taps, np.float64)
    return float((taps.sum() ** 2 / np.square(taps).sum()) ** 2)


def variance_inflation(spp, config, variance_dof=None):
    """1 + guard_confidence sqrt(2 / (d N_eff)), d the variance's degrees of freedom per pixel:
    ``variance_dof`` where given, else n - 1 for n = ``spp`` samples per pixel (d taken as at
    least 1): the factor by which the guard raises the local variance to an upper confidence
    bound. Broadcasts over ``spp`` (or ``variance_dof``)."""
    n_eff = _effective_pixels(gaussian_taps(config.guard_sigma))
    per_pixel = (jnp.asarray(spp, jnp.float32) - 1.0 if variance_dof is None
                 else jnp.asarray(variance_dof, jnp.float32))
    dof = jnp.maximum(per_pixel, 1.0) * n_eff
    return 1.0 + config.guard_confidence * jnp.sqrt(2.0 / dof)


def guard_sample_count(spp, variance_dof):
    """The sample count to pass the guard (``guard_alpha``'s ``spp``) for a variance with
    ``variance_dof`` degrees of freedom per pixel: ``spp`` itself where that is None, else
    ``variance_dof + 1``, whose n - 1 is those degrees of freedom (the guard reads the count
    only through n - 1, :func:`variance_inflation`). None where both are None."""
    if variance_dof is None:
        return spp
    return np.asarray(variance_dof, np.float64) + 1.0


def _ratio(local_residual, local_var):
    """chi^2 = E[(y - x)^2] / var from local sums; 0 where y == x on the whole window (no
    constraint), inf where the window has no variance but y differs."""
    positive = local_var > 0
    return jnp.where(positive, local_residual / jnp.where(positive, local_var, 1.0),
                     jnp.where(local_residual > 0, jnp.inf, 0.0))


def _noise_level(var, taps):
    """(level, member, width): per pixel log2 of the standard deviation (channel mean of var)
    minus the image's mean of it, clipped to +-GUARD_STRATA_RANGE, (H, W, 1); which pixels
    take part (variance > 0); and the strata width in stops, max(1, GUARD_STRATA_SPREAD x the
    root-mean-square deviation of the level from its Gaussian local mean over members, large
    deviations (>= 8 stops: edges of emitters) left out)."""
    std = jnp.sqrt(jnp.mean(var, axis=-1, keepdims=True))
    member = std > 0
    log_std = jnp.log2(jnp.where(member, std, 1.0))
    scale = jnp.sum(jnp.where(member, log_std, 0.0)) / jnp.maximum(jnp.sum(member), 1)
    level = jnp.where(member, jnp.clip(log_std - scale, -GUARD_STRATA_RANGE,
                                       GUARD_STRATA_RANGE), 0.0)
    weight = member.astype(level.dtype)
    local = blur_2d(level, taps) / jnp.maximum(blur_2d(weight, taps), 1e-12)
    deviation = jnp.abs(level - local)
    counted = member & (deviation < 8.0)
    spread = jnp.sqrt(jnp.sum(jnp.where(counted, jnp.square(deviation), 0.0))
                      / jnp.maximum(jnp.sum(counted), 1))
    return level, member, spread


def _guard_chi2(x, y, var, inflation, config):
    """(chi^2 of the cap, chi^2 of the significance factor) for one image (H, W, 3), each
    (H, W, 1) (or (H, W, 3) per channel): the spatial pooling, and the larger of it and the
    noise-strata pooling. The local variance is multiplied by ``inflation`` (a scalar)."""
    residual = jnp.square(y - x)
    pooled_var = var
    if not config.per_channel:
        residual = jnp.sum(residual, axis=-1, keepdims=True)
        pooled_var = jnp.sum(var, axis=-1, keepdims=True)
    taps = jnp.asarray(gaussian_taps(config.guard_sigma), x.dtype)
    terms = jnp.concatenate([pooled_var * inflation, residual], axis=-1)
    local_var, local_residual = jnp.split(blur_2d(terms, taps), 2, axis=-1)
    chi2 = _ratio(local_residual, local_var)
    if config.guard_strata is None:
        return chi2, chi2
    level, member, spread = _noise_level(var, taps)
    width = jnp.maximum(config.guard_strata, GUARD_STRATA_SPREAD * spread)
    bound = math.ceil(GUARD_STRATA_RANGE / config.guard_strata)
    # Non-members sit outside every bin (level far below the lowest), so they neither pool
    # nor are pooled.
    position = jnp.where(member, level / width, -2.0 * bound - 4.0)
    ones = member.astype(x.dtype)
    sums = strata_local_sums(jnp.concatenate([terms, ones], axis=-1), position, -bound, bound,
                             taps)
    channels = terms.shape[-1] // 2
    strata_var, strata_residual, support = jnp.split(sums, [channels, 2 * channels], axis=-1)
    support = support / blur_2d(jnp.ones_like(ones), taps)
    strata_chi2 = jnp.where(support >= GUARD_STRATA_SUPPORT,
                            _ratio(strata_residual, strata_var), 0.0)
    return chi2, jnp.maximum(chi2, strata_chi2)


@functools.partial(jax.jit, static_argnames=("config",))
def guard_alpha(alpha, x, y, var, config, spp=None):
    """alpha'' = min(alpha, gamma / chi_cap^2) (1 - S(a (chi_test - c))), batched over leading
    dims; ``spp`` (None: unknown, no inflation; else a scalar or one per leading index; for a
    variance of known degrees of freedom, :func:`guard_sample_count`)."""
    lead = x.shape[:-3]
    flat = [a.reshape((-1,) + a.shape[-3:]) for a in (x, y, var)]
    count = int(np.prod(lead, dtype=np.int64))
    if spp is None:
        inflation = jnp.ones((count,), x.dtype)
    else:
        inflation = jnp.broadcast_to(variance_inflation(spp, config), lead).reshape(count)
    single = lambda args: _guard_chi2(*args, config)
    # With strata, lax.map (not vmap) keeps the skipping of empty bins a real branch.
    run = jax.vmap(single) if config.guard_strata is None else functools.partial(
        jax.lax.map, single)
    chi2_cap, chi2_test = (c.reshape(lead + c.shape[1:]) for c in run((*flat, inflation)))
    u = config.a * (jnp.sqrt(chi2_test) - config.c)
    keep = ndtr(-u) if config.squash == "normal_cdf" else jax.nn.sigmoid(-u)
    return jnp.minimum(alpha, config.guard_gamma / chi2_cap) * keep
