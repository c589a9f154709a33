"""The t-statistic scaling (paper Sec. 4.3): alpha' = alpha (1 - Phi(a (|t| - c))), which makes
the mix consistent (z' -> the true image as the variance goes to 0).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtr

from jaxden.config import bounded
from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_image, check_same, check_spp, check_variance_values
from jaxden.progressive.closed_form import blur_shifted
from jaxden.progressive.guard import guard_alpha
from jaxden.progressive.heads import mix_unchecked

# ---------------------------------------------------------------------------------- t-test


@dataclasses.dataclass(frozen=True)
class TStatConfig:
    """Constants of the t-statistic scaling (paper Sec. 4.2, Eqs. 12-18; authors' code).

    Attributes:
      window: side of the square neighbourhood N_p (11).
      a: strength (2). c: shift (4.2). alpha' = alpha * (1 - S(a (|t| - c))).
      squash: S, ``"normal_cdf"`` (paper and code) or ``"logistic"`` (the paper's alternative).
      sigma_rule: Gaussian width s of the weights kappa:
        ``"mean_variance"`` (authors' code): s = sigma_scale * sqrt(clip(mean(var), 0,
        sigma_variance_cap)), mean over the whole image (H, W and channels), per image;
        ``"image_mean_variance"`` (a literal reading of the paper: Var of the image mean
        x_bar = mean of H*W*3 values, i.e. mean(var) / (3 H W)), same scale and cap;
        ``"fixed"``: s = sigma_fixed.
        The result is clipped to >= sigma_min in every rule.
      use_max_variance_neighbour: add the M_p terms (Eqs. 12-14, 16).
      neighbour_weight: weight of the M_p value in the colour and mixed sums (1/3 in the
        authors' code, which sums the three channels' M_p values; the variance gets its
        square, 1/9). The paper's Eqs. 12-14 have weight 1 and no channel sum.
      per_channel: False (authors): one t per pixel from channel-summed sums, shared by R, G,
        B. True: one t per pixel and channel (same sums without the channel sum).
      eps: added to the standard deviation in t's denominator (1e-6).
      guard: apply the error guard after the scaling (:mod:`jaxden.progressive.guard`, our
        addition; on by default, off reproduces the paper): alpha'' = min(alpha',
        guard_gamma / chi^2) (1 - S(a (chi - c))), chi^2 the local mean of (y - x)^2 over the
        local mean of var, so that the mix never ends far above x where y is far off x.
      guard_gamma: the cap's factor on var / E[(y - x)^2]: 2 is where the mix breaks even
        with x in expectation.
      guard_sigma: standard deviation in pixels of the guard's Gaussian local means
        (truncated at 3 sigma).
      guard_confidence: where the sample count n is known, the guard divides by the local
        variance raised by this many of its relative standard deviations, sqrt(2 / ((n - 1)
        N_eff)) (an upper confidence bound; 0 turns it off): few-sample variances would
        otherwise overstate chi^2 at 2..8 spp.
      guard_strata: None (the default: chi^2 from spatial local means only) or the least
        width in stops (log2 of the standard deviation) of the noise strata of a second
        pooling, which the significance factor then also uses: its local means take only
        neighbours of similar noise level, so that a lamp's rim does not vouch for the dark
        pixel beside it onto which the denoiser smeared the lamp. A trade, off by default: it
        cuts relMSE on emitters in view at 4..64 spp and costs RMSE where a lamp is seen
        through a diffuser at 4 spp (:mod:`jaxden.progressive.guard`).
      guard_cap_spp: None (the default: the cap reads the ``guard_sigma`` window alone) or a
        sample count m: below m samples per pixel (d < m - 1 degrees of freedom of the
        variance, where the sample count or ``variance_dof`` is known) the cap also pools over
        a window widened by sqrt((m - 1) / d), which holds about the degrees of freedom the
        ``guard_sigma`` window holds at m samples, and takes the looser of the two caps (the
        smaller chi^2), so that the cap pulls towards x only where a window of enough samples
        also finds y off. At m samples and above the guard is unchanged. An option, off by
        default: at m = 16 it keeps PD(OIDN) within 1 % of OIDN at 4 and 16 spp on the
        textured out-of-distribution scenes, where today's cap costs up to 3 % at 4 spp
        (experiments/results/pd/pd-guard-textured.md; :mod:`jaxden.progressive.guard`).
    """

    window: int = bounded(11, low=1, high=255, unit='pixels')
    a: float = bounded(2.0, low=0, low_open=True, high=1e3)
    c: float = bounded(4.2, low=0, high=1e3)
    squash: Literal["normal_cdf", "logistic"] = "normal_cdf"
    sigma_rule: Literal["mean_variance", "image_mean_variance", "fixed"] = "mean_variance"
    sigma_scale: float = bounded(100.0, low=0, low_open=True, high=1e4)
    sigma_variance_cap: float = bounded(1.0, low=0, low_open=True, high=1e6)
    sigma_min: float = bounded(1e-3, low=0, low_open=True, high=256, unit='pixels')
    sigma_fixed: float = bounded(1.0, low=0, low_open=True, high=256, unit='pixels')
    use_max_variance_neighbour: bool = True
    neighbour_weight: float = bounded(1.0 / 3.0, low=0, high=1)
    per_channel: bool = False
    eps: float = bounded(1e-6, low=0, low_open=True, high=1)
    guard: bool = True
    guard_gamma: float = bounded(2.0, low=0, low_open=True, high=1e3)
    guard_sigma: float = bounded(1.0, low=0, low_open=True, high=64, unit='pixels')
    guard_confidence: float = bounded(2.0, low=0, high=100)
    guard_strata: float | None = bounded(None, low=0.0625, high=16, unit='stops')  # >= 1/16 stop
    guard_cap_spp: float | None = bounded(None, low=2, high=1e6, unit='samples')

    def __post_init__(self):
        from jaxden.config import check_fields

        check_fields(self)  # types, choices and the bounded ranges, as declared above
        if self.window % 2 == 0:
            raise ConfigError(f"TStatConfig.window: expected an odd integer >= 1, got "
                              f"{self.window!r}")


def _gaussian_sigma(var, config: TStatConfig):
    """s for one image (H, W, 3)."""
    if config.sigma_rule == "fixed":
        s = jnp.asarray(config.sigma_fixed, var.dtype)
    else:
        mean_var = jnp.mean(var)
        if config.sigma_rule == "image_mean_variance":
            mean_var = mean_var / var.size
        s = config.sigma_scale * jnp.sqrt(jnp.clip(mean_var, 0.0, config.sigma_variance_cap))
    return jnp.maximum(s, config.sigma_min)


def _blur_1d(image, taps, axis: int):
    """Zero-padded correlation of (H, W, C) along ``axis`` (0: H, 1: W), odd-length ``taps``
    (traced values: s depends on the data); neighbours outside the image are absent from the
    sum. Shifted, weighted adds (:func:`jaxden.progressive.closed_form.blur_shifted`): on
    XLA:CPU far faster than the depthwise convolution this was (measured: docs/history.md,
    "Defaults of the code")."""
    return blur_shifted(image, taps, axis)


def _pick_along(var, index, diff, window: int, axis: int):
    """One separable pass of the max-variance selection: per pixel, the (var, index, diff) of
    the ``window`` neighbours along ``axis`` that is largest in var, then smallest in index;
    out-of-image neighbours (var -inf, index int32 max) never win. Unrolled over the offsets
    (static slices) on channel-first planes, carrying diff along instead of gathering it
    afterwards: on XLA:CPU several times faster than a fori_loop of dynamic slices on
    (H, W, C) followed by a gather."""
    radius = window // 2
    size = var.shape[axis]
    pad = [(0, 0)] * var.ndim
    pad[axis] = (radius, radius)
    padded = (jnp.pad(var, pad, constant_values=-jnp.inf),
              jnp.pad(index, pad, constant_values=np.iinfo(np.int32).max),
              jnp.pad(diff, pad))
    best = [jax.lax.slice_in_dim(a, 0, size, axis=axis) for a in padded]
    for offset in range(1, window):
        var_b, index_b, diff_b = (jax.lax.slice_in_dim(a, offset, offset + size, axis=axis)
                                  for a in padded)
        take_b = (var_b > best[0]) | ((var_b == best[0]) & (index_b < best[1]))
        best = [jnp.where(take_b, b, a) for a, b in zip(best, (var_b, index_b, diff_b))]
    return best


def _max_variance_neighbour(var, diff, window: int):
    """Per channel, var and diff at M_p = argmax of var over the in-image window of p.

    Ties go to the first maximum in row-major window order (top-left first), which for a
    fixed p is the smallest row-major image index; out-of-image positions never win (the
    window is padded with var = -inf).
    Returns (var_M, diff_M), each (H, W, C).
    """
    height, width, _ = var.shape
    var = jax.lax.stop_gradient(var)  # M_p is a selection; no derivative through it
    index = jnp.broadcast_to(
        jnp.arange(height * width, dtype=jnp.int32).reshape(height, width, 1), var.shape
    )
    # "Larger var, then smaller index" is a total order, so the best of the window is the
    # best of the per-row bests: two separable passes of `window` comparisons each (on
    # XLA:CPU about 9x faster than the 2-D reduce_window over the pairs at 1280 x 720).
    planes = [jnp.moveaxis(a, -1, 0) for a in (var, index, diff)]  # (C, H, W)
    var_m, _, diff_m = _pick_along(*_pick_along(*planes, window, axis=2), window, axis=1)
    return jnp.moveaxis(var_m, 0, -1), jnp.moveaxis(diff_m, 0, -1)


def _t_single(x, z, var, config: TStatConfig, sigma=None):
    """t for one image (H, W, 3) -> (H, W, 1), or (H, W, 3) if per_channel. ``sigma``: the
    Gaussian width s (None: from this image's variance; a tile gets its frame's)."""
    s = _gaussian_sigma(var, config) if sigma is None else sigma
    radius = config.window // 2
    offsets = jnp.arange(-radius, radius + 1, dtype=x.dtype)
    g = jnp.exp(-jnp.square(offsets) / (2.0 * s * s))
    norm = 1.0 / (s * math.sqrt(2.0 * math.pi))
    # kappa(dy, dx) = norm * g[dy] * g[dx] (separable); the variance uses kappa^2.
    # blur(z) - blur(x) is computed as blur(z - x): equal in exact arithmetic, and it avoids
    # cancelling two large sums when z - x is small (the regime the test is about).
    diff = z - x

    def reduce_channels(a):
        return a if config.per_channel else jnp.sum(a, axis=-1, keepdims=True)

    numerator = norm * _blur_1d(_blur_1d(reduce_channels(diff), g, 0), g, 1)
    g2 = g * g
    variance = norm * norm * _blur_1d(_blur_1d(reduce_channels(var), g2, 0), g2, 1)
    if config.use_max_variance_neighbour:
        var_m, diff_m = _max_variance_neighbour(var, diff, config.window)
        w = config.neighbour_weight
        numerator = numerator + w * reduce_channels(diff_m)
        variance = variance + (w * w) * reduce_channels(var_m)
    return jnp.abs(numerator) / (jnp.sqrt(jnp.maximum(variance, 0.0)) + config.eps)


@functools.partial(jax.jit, static_argnames=("config",))
def _t_statistic(x, z, var, config: TStatConfig, sigma=None):
    lead = x.shape[:-3]
    flat = [a.reshape((-1,) + a.shape[-3:]) for a in (x, z, var)]
    if sigma is None:
        t = jax.vmap(lambda a, b, c: _t_single(a, b, c, config))(*flat)
    else:
        sigma = jnp.broadcast_to(jnp.asarray(sigma, x.dtype), lead).reshape(-1)
        t = jax.vmap(lambda a, b, c, s: _t_single(a, b, c, config, s))(*flat, sigma)
    return t.reshape(lead + t.shape[1:])


@functools.partial(jax.jit, static_argnames=("config",))
def tstat_sigma(var, config: TStatConfig):
    """The t-statistic's Gaussian width s per image (the leading dims of ``var``, (..., H, W,
    3)): a whole-frame statistic (``sigma_rule``), computed once and handed to each tile."""
    lead = var.shape[:-3]
    flat = var.reshape((-1,) + var.shape[-3:])
    return jax.vmap(lambda v: _gaussian_sigma(v, config))(flat).reshape(lead)


def _resolve_config(config: TStatConfig | None, overrides: dict) -> TStatConfig:
    config = TStatConfig() if config is None else config
    if not isinstance(config, TStatConfig):
        raise ConfigError(f"expected a TStatConfig, got {type(config).__name__}")
    allowed = {f.name for f in dataclasses.fields(TStatConfig)}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise ConfigError(
            f"unknown t-statistic option(s) {unknown}; allowed: {', '.join(sorted(allowed))}"
        )
    return dataclasses.replace(config, **overrides) if overrides else config


def t_statistic(x, z, var, config: TStatConfig | None = None, **overrides):
    """The t-statistic of Eq. 17, (..., H, W, 1) (or (..., H, W, 3) if ``per_channel``).

    For each pixel p, with Gaussian weights kappa over the window N_p (zero outside the
    image) and M_p,c the in-window pixel of maximum variance in channel c::

        num_p = sum_c [ sum_q kappa_pq (z_qc - x_qc) + w (z_{M_pc,c} - x_{M_pc,c}) ]
        var_p = sum_c [ sum_q kappa_pq^2 var_qc     + w^2 var_{M_pc,c} ]
        t_p   = |num_p| / (sqrt(var_p) + eps)

    with ``w = neighbour_weight`` (1/3) and the sum over c dropped when ``per_channel``.
    ``num_p`` is blur(z) - blur(x) of the reference notes (computed as blur(z - x)).

    Args: x noisy colour, z mixed colour (x + alpha (y - x)), var variance of the pixel mean
    of x; all (..., H, W, 3). ``config``/``overrides``: :class:`TStatConfig` fields.
    """
    config = _resolve_config(config, overrides)
    check_same("t_statistic", x=x, z=z, var=var)
    check_variance_values(var, "t_statistic")
    return _t_statistic(jnp.asarray(x), jnp.asarray(z), jnp.asarray(var), config)


def _check_alpha(alpha, shape: tuple, where: str) -> None:
    """alpha (..., H, W, 1 or 3) over the (..., H, W) of the colour shape ``shape``."""
    alpha_shape = check_image("alpha", alpha, where, channels=(1, 3))
    if alpha_shape[:-1] != shape[:-1]:
        raise FrameError(f"{where}: 'alpha' has shape {alpha_shape} but x has {shape}")


@functools.partial(jax.jit, static_argnames=("config",))
def _scale_alpha(alpha, t, config: TStatConfig):
    # Separate from _t_statistic so both public functions share its compiled code.
    u = config.a * (t - config.c)
    keep = ndtr(-u) if config.squash == "normal_cdf" else jax.nn.sigmoid(-u)
    return alpha * keep


def t_statistic_scaling(alpha, x, z, var, config: TStatConfig | None = None, **overrides):
    """alpha' = alpha * (1 - S(a (|t| - c))) (paper Eq. 18), shape of ``alpha`` broadcast.

    Args:
      alpha: mixing weight (..., H, W, 3) or (..., H, W, 1), in [0, 1].
      x: noisy colour (..., H, W, 3); z: mixed colour x + alpha (y - x); var: variance of
        the pixel mean of x. ``config``/``overrides``: :class:`TStatConfig` fields (e.g.
        ``window=11, a=2.0, c=4.2``). ``1 - Phi(u)`` is computed as ``Phi(-u)`` (no
        cancellation in the tail).

    What it guarantees (and what not). Let the variance shrink, var = v * 4^-k, with
    x = mu + sqrt(var) n, and hold the denoised image at a fixed bias y = mu + b. Then
    z - x = alpha (b - sqrt(var) n) -> alpha b while sqrt(var_p) -> 0 like 2^-k, so t_p -> inf
    and alpha'_p -> 0 (Gaussian-tail fast) at every pixel where the limit numerator
    D_p = sum_c [sum_q kappa_pq alpha_qc b_qc + w alpha_{M,c} b_{M,c}] is non-zero. Then
    z'_p - x_p = alpha'_p (y_p - x_p) -> 0 and z'_p -> mu_p. Where D_p = 0 nothing is
    guaranteed: biases that cancel over the window or, with the authors' channel sum, over
    R, G, B (e.g. a hue shift b = (+beta, -beta, 0) with equal alpha per channel) are
    invisible to the test and alpha' stays ~ alpha. ``per_channel=True`` removes the channel
    cancellation (then D_pc = 0 needs a cancellation within one channel's window, impossible
    when the bias has one sign there). Also s (the Gaussian width) shrinks with the mean
    variance, down to sigma_min, so in the limit the window is essentially p itself (plus
    M_p).

    Departures, paper vs authors' code (we follow the code, via the reference notes):
    (1) the paper's Eqs. 12-14 add x_{M_p} with weight 1; the code sums the three channels'
    M_p values with weight 1/3 (variance 1/9) -- ``neighbour_weight``; (2) the paper's sums
    are per channel; the code sums over R, G, B for one t per pixel -- ``per_channel``;
    (3) the paper's s = min(sqrt(Var[x_bar]), 1) * 100 "with x_bar the image mean"; the code
    uses the mean per-pixel variance -- ``sigma_rule``; (4) kappa is the unnormalised 2-D
    Gaussian with the 1-D constant 1 / (s sqrt(2 pi)) in both; it cancels in t except against
    the M_p terms and eps. Our choices where neither says: pixels outside the image count as
    absent (zero padding of the sums; never chosen as M_p); ties for M_p go to the first
    maximum in row-major window order; the Var of the M_p term is added as if independent of
    the window sum (as in both).
    """
    config = _resolve_config(config, overrides)
    shape = check_same("t_statistic_scaling", x=x, z=z, var=var)
    _check_alpha(alpha, shape, "t_statistic_scaling")
    check_variance_values(var, "t_statistic_scaling")
    t = _t_statistic(jnp.asarray(x), jnp.asarray(z), jnp.asarray(var), config)
    return _scale_alpha(jnp.asarray(alpha), t, config)


def error_guard(alpha, x, y, var, config: TStatConfig | None = None, *, spp=None,
                **overrides):
    """The error guard alone (:mod:`jaxden.progressive.guard`): alpha'' = min(alpha,
    gamma / chi^2) (1 - S(a (chi - c))), shape of ``alpha`` broadcast. Applied whatever
    ``config.guard`` says (that flag is for :func:`consistent_mix` and the pipeline).

    Args: alpha (..., H, W, 3) or (..., H, W, 1); x noisy colour, y denoised colour, var the
    variance of the pixel mean of x, all (..., H, W, 3). ``config``/``overrides``:
    :class:`TStatConfig` fields (``guard_gamma``, ``guard_sigma``, ``guard_confidence``,
    ``guard_strata``, ``guard_cap_spp``, ``a``, ``c``, ``squash``, ``per_channel``). ``spp``:
    samples per pixel that ``var`` was estimated from (scalar or one per leading index); None:
    unknown, the variance is taken as exact (and ``guard_cap_spp`` does nothing).
    """
    config = _resolve_config(config, overrides)
    shape = check_same("error_guard", x=x, y=y, var=var)
    _check_alpha(alpha, shape, "error_guard")
    check_variance_values(var, "error_guard")
    spp = check_spp(spp, tuple(shape[:-3]), "error_guard")
    return guard_alpha(jnp.asarray(alpha), jnp.asarray(x), jnp.asarray(y), jnp.asarray(var),
                       config, spp)


def consistent_alpha(alpha, x, y, var, mixed, config: TStatConfig, spp=None, sigma=None):
    """The inference stage after the mixer, on validated arrays: the t-statistic scaling of
    alpha (``mixed`` = x + alpha (y - x)), then the error guard when ``config.guard``.
    ``sigma``: the t-statistic's Gaussian width per image (None: :func:`tstat_sigma` of
    ``var``; a tile passes its frame's)."""
    scaled = _scale_alpha(alpha, _t_statistic(x, mixed, var, config, sigma), config)
    return guard_alpha(scaled, x, y, var, config, spp) if config.guard else scaled


def consistent_mix(x, y, alpha, var, config: TStatConfig | None = None, *, spp=None,
                   **overrides):
    """The inference output: (z', alpha') with alpha' the t-statistic scaling of alpha (over
    z = mix(x, y, alpha)) followed by the error guard (when ``config.guard``, the default),
    and z' = x + alpha' (y - x). Shapes as in :func:`t_statistic_scaling`; ``spp`` as in
    :func:`error_guard`."""
    config = _resolve_config(config, overrides)
    shape = check_same("consistent_mix", x=x, y=y, var=var)
    _check_alpha(alpha, shape, "consistent_mix")
    check_variance_values(var, "consistent_mix")
    spp = check_spp(spp, tuple(shape[:-3]), "consistent_mix")
    x, y, var, alpha = (jnp.asarray(a) for a in (x, y, var, alpha))
    alpha_prime = consistent_alpha(alpha, x, y, var, mix_unchecked(x, y, alpha), config, spp)
    return mix_unchecked(x, y, alpha_prime), alpha_prime
