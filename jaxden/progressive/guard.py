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

A wider cap at few samples (``guard_cap_spp = m``, an option, off by default). At 2..8 spp the
cap's chi^2 is itself noisy: where y is good its numerator is mostly x's own noise, (y - x)^2 ~
(x - mu)^2, pooled over N_eff = 12.6 pixels, and its denominator a variance of 1..7 degrees of
freedom per pixel from samples far from normal (a rough conductor reflecting soft boxes: a
sample finds the bright reflection or not). Windows where x is off by more than its estimated
variance says reach chi^2 = 2..10, just past gamma / alpha' (on the textured conductor in the
studio of data/ood at 4 spp, at the pixels with chi^2 in [2, 3): the render's local variance
0.54 of the true one, x's local squared error 1.6 times the true variance), and the cap pulls z
towards an x whose error there is 14 times y's: PD(OIDN) ended 1.025x OIDN's RMSE there (1.031x
relMSE) against 0.996x (0.986x) with the t-test alone, 88 % of the excess on the 0.8 % of
pixels with chi^2 in [2, 3) (experiments/results/pd/pd-guard-textured.md). Twice the variance
bound (guard_confidence 4) removes it too, but loosens the cap at every spp: on the stress set
it costs 1 % in relMSE (3 % at 64 spp) and raises three images a little at the top spp. With
the option, where the variance has d < m - 1 degrees of freedom per pixel the cap also reads
chi^2 over a Gaussian window widened by sqrt((m - 1) / d), which pools about the d N_eff of the
``guard_sigma`` window at m samples (its variance bound from its own N_eff), and uses the
smaller of the two chi^2: the cap acts where a window of enough samples also finds y off.
Taking the looser of the two keeps the narrow window's separation of a lamp from its
neighbours: a wide window alone spreads a lamp's residual onto the dark pixels around it (a
2-pixel guard window throughout: PD's relMSE on small-lights at 8 spp 2.7x OIDN's against
0.72x). The significance factor keeps its own window. At m samples and more, and where the
sample count is unknown, nothing changes, so consistency is untouched. With m = 16: every
ood-low scene within 1 % of OIDN at 4 and 16 spp (two SURE seeds), test-chain better at 2..8
spp, pd-test-high (32 spp and up) and every top spp unchanged; on the stress set 4..8 spp
relMSE moves by -8 % (the dark room lit through a slit) to +0.4 % (the sun glitter) per image,
+0.008 % in the mean over spp. Tiles (:mod:`jaxden.progressive.tiled`) must overlap by
:func:`cap_window_radius` for it.
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


def cap_window_radius(config) -> int:
    """Pixels each side that the guard's cap reads with ``guard_cap_spp`` set: the truncation
    radius of its widest window (1 degree of freedom, sigma = guard_sigma sqrt(m - 1)); that of
    the ``guard_sigma`` window without it."""
    sigma = config.guard_sigma
    if config.guard_cap_spp is not None:
        sigma *= math.sqrt(max(config.guard_cap_spp - 1.0, 1.0))
    return max(1, math.ceil(3.0 * sigma))


def _cap_windows(spp, config, count: int, dtype):
    """Per image (``count`` of them), the cap's widened window for ``guard_cap_spp`` = m:
    (taps (count, 2 R + 1) of sigma = guard_sigma sqrt(max(1, (m - 1) / d)), truncated at
    3 sigma as :func:`gaussian_taps` on the static support R of :func:`cap_window_radius`;
    the variance bound 1 + guard_confidence sqrt(2 / (d N_eff)) of that window; whether it
    is used, d < m - 1), d = max(spp - 1, 1)."""
    radius = cap_window_radius(config)
    dof = jnp.maximum(jnp.broadcast_to(jnp.asarray(spp, jnp.float32), (count,)) - 1.0, 1.0)
    target = config.guard_cap_spp - 1.0
    sigma = config.guard_sigma * jnp.sqrt(jnp.maximum(target / dof, 1.0))
    offsets = jnp.arange(-radius, radius + 1, dtype=jnp.float32)[None, :]
    reach = jnp.minimum(jnp.maximum(jnp.ceil(3.0 * sigma), 1.0), float(radius))[:, None]
    taps = jnp.where(jnp.abs(offsets) <= reach,
                     jnp.exp(-jnp.square(offsets) / (2.0 * jnp.square(sigma[:, None]))), 0.0)
    n_eff = jnp.square(jnp.square(taps.sum(-1)) / jnp.square(taps).sum(-1))
    inflation = 1.0 + config.guard_confidence * jnp.sqrt(2.0 / (dof * n_eff))
    return taps.astype(dtype), inflation.astype(dtype), dof < target


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


def _guard_chi2(x, y, var, inflation, config, wide=None):
    """(chi^2 of the cap, chi^2 of the significance factor) for one image (H, W, 3), each
    (H, W, 1) (or (H, W, 3) per channel): the spatial pooling (for the cap the smaller of it
    and the widened window's where ``wide`` = (taps, inflation, used) of
    :func:`_cap_windows` says so), and the larger of it and the noise-strata pooling. The
    local variance is multiplied by ``inflation`` (a scalar)."""
    residual = jnp.square(y - x)
    pooled_var = var
    if not config.per_channel:
        residual = jnp.sum(residual, axis=-1, keepdims=True)
        pooled_var = jnp.sum(var, axis=-1, keepdims=True)
    taps = jnp.asarray(gaussian_taps(config.guard_sigma), x.dtype)
    terms = jnp.concatenate([pooled_var * inflation, residual], axis=-1)
    local_var, local_residual = jnp.split(blur_2d(terms, taps), 2, axis=-1)
    chi2 = _ratio(local_residual, local_var)
    chi2_cap = chi2
    if wide is not None:
        wide_taps, wide_inflation, used = wide
        wide_var, wide_residual = jnp.split(
            blur_2d(jnp.concatenate([pooled_var, residual], axis=-1), wide_taps), 2, axis=-1)
        chi2_cap = jnp.where(used, jnp.minimum(chi2, _ratio(wide_residual,
                                                             wide_var * wide_inflation)), chi2)
    if config.guard_strata is None:
        return chi2_cap, chi2
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
    return chi2_cap, jnp.maximum(chi2, strata_chi2)


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
    # The widened cap window needs the variance's degrees of freedom: none without spp.
    widen = config.guard_cap_spp is not None and spp is not None
    if widen:
        spp_each = jnp.broadcast_to(jnp.asarray(spp, jnp.float32), lead).reshape(count)
        extra = _cap_windows(spp_each, config, count, x.dtype)
        single = lambda args: _guard_chi2(*args[:4], config, wide=args[4:])
    else:
        extra = ()
        single = lambda args: _guard_chi2(*args, config)
    # With strata, lax.map (not vmap) keeps the skipping of empty bins a real branch.
    run = jax.vmap(single) if config.guard_strata is None else functools.partial(
        jax.lax.map, single)
    chi2_cap, chi2_test = (c.reshape(lead + c.shape[1:])
                           for c in run((*flat, inflation, *extra)))
    u = config.a * (jnp.sqrt(chi2_test) - config.c)
    keep = ndtr(-u) if config.squash == "normal_cdf" else jax.nn.sigmoid(-u)
    return jnp.minimum(alpha, config.guard_gamma / chi2_cap) * keep
