"""The error guard: a second consistency stage after the t-statistic scaling (our addition), which
keeps the mix from ending above the noisy render where the denoised image is far off, such as
on small bright lights and their glints.

Why the t-statistic scaling alone does not. It tests the *mixed* image z = x + alpha (y - x)
against x, pooled over an 11 x 11 window that also holds the window's noisiest pixel (M_p):
1. t_z = alpha t_y, so a small alpha over a far-off y passes the test (|t_z| < c - 3/a) while
   its error (alpha (y - x))^2 is t_z^2 times the variance of x: a lamp pixel at 1024 spp with
   y 41 standard errors below x and alpha 0.067 has t_z 2.3 and 7x MC's error there;
2. next to a lamp the window's variance is ruled by the lamp's rim (pixels that some samples
   hit, with 10^3..10^4 times the variance of the pixels around), so on the lamp's core,
   whose variance is 0 at 8 spp, t is about 1.5 whatever y does.
Both measured on the built-in small-lights scene (docs/departures.md).

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
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.scipy.special import ndtr

from jaxden.progressive.closed_form import _blur_2d, _gaussian_taps


def _guard_cap(x, y, var, config):
    """(gamma / chi^2, chi) for one image (H, W, 3) -> two (H, W, 1) (or (H, W, 3))."""
    residual = jnp.square(y - x)
    if not config.per_channel:
        residual = jnp.sum(residual, axis=-1, keepdims=True)
        var = jnp.sum(var, axis=-1, keepdims=True)
    taps = jnp.asarray(_gaussian_taps(config.guard_sigma), x.dtype)
    sums = _blur_2d(jnp.concatenate([var, residual], axis=-1), taps)
    local_var, local_residual = jnp.split(sums, 2, axis=-1)
    # chi^2 = E[(y - x)^2] / var; 0 where y == x on the whole window (no constraint), inf
    # where the window has no variance but y differs.
    positive = local_var > 0
    chi2 = jnp.where(positive, local_residual / jnp.where(positive, local_var, 1.0),
                     jnp.where(local_residual > 0, jnp.inf, 0.0))
    cap = config.guard_gamma / chi2  # inf where chi2 == 0
    return cap, jnp.sqrt(chi2)


@functools.partial(jax.jit, static_argnames=("config",))
def _guard_alpha(alpha, x, y, var, config):
    """alpha'' = min(alpha, gamma / chi^2) (1 - S(a (chi - c))), batched over leading dims."""
    lead = x.shape[:-3]
    flat = [a.reshape((-1,) + a.shape[-3:]) for a in (x, y, var)]
    cap, chi = jax.vmap(lambda a, b, c: _guard_cap(a, b, c, config))(*flat)
    cap = cap.reshape(lead + cap.shape[1:])
    chi = chi.reshape(lead + chi.shape[1:])
    u = config.a * (chi - config.c)
    keep = ndtr(-u) if config.squash == "normal_cdf" else jax.nn.sigmoid(-u)
    return jnp.minimum(alpha, cap) * keep
