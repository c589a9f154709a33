"""Progressive denoising (Firmino, Frisvad, Jensen 2022): the pure parts of the mixer.

Pipeline: ``x`` (Monte Carlo colour, "hdr"), ``var`` (variance of the pixel mean), ``y = F(x)``
(denoised, "den") and its per-pixel ``sure`` (:mod:`jaxden.sure`) go into the mixer network
``h``; its 9 raw outputs become a per-channel mixing weight ``alpha = f_act(raw)``; the
t-statistic scaling turns it into ``alpha'`` and the output is ``z' = x + alpha' (y - x)``.
The scaling makes ``z'`` consistent: where the denoiser is biased, ``alpha' -> 0`` as the
variance goes to 0 (see :func:`t_statistic_scaling` for exactly what is guaranteed).

This module holds the pure, jitted functions: :func:`mixer_inputs`, :func:`f_act`,
:func:`alpha_direct` (the "w/o f_act" ablation), :func:`mix`, :func:`t_statistic`,
:func:`t_statistic_scaling`, :func:`consistent_mix` and :func:`swap_inputs` (the training
augmentation). The network module and training live elsewhere.

All images are NHWC linear radiance, (..., H, W, 3), leading batch dimensions allowed.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtr

from jaxden.errors import ConfigError, FrameError

__all__ = [
    "ALPHA_HEADS",
    "EXTRA_MIXER_FEATURES",
    "MIXER_FEATURES",
    "MIXER_FEATURES_NO_SURE",
    "MIXER_LAYOUT",
    "SURE_BASED_FEATURES",
    "TStatConfig",
    "alpha_direct",
    "alpha_from_head",
    "consistent_mix",
    "f_act",
    "mix",
    "mixer_channel_slices",
    "mixer_inputs",
    "swap_inputs",
    "t_statistic",
    "t_statistic_scaling",
]

# ---------------------------------------------------------------------------------- inputs

#: Mixer input features, in the authors' order; 3 channels (R, G, B) each:
#:   hdr        x, linear radiance
#:   den        y, linear radiance
#:   var        atan(var)
#:   sure       atan(SURE)
#:   residual   atan((x - y)^2)
#:   divergence atan(SURE + var - (x - y)^2) = atan(2 var dy/dx), the paper's sigma^2 f'(x)
#:              term up to the factor 2 (the authors feed it with the factor)
MIXER_FEATURES: tuple[str, ...] = ("hdr", "den", "var", "sure", "residual", "divergence")
#: Optional features beyond the authors' (our addition; not in the default set):
#:   closed_form  the closed-form mixer's alpha (:func:`closed_form_alpha`, width
#:                ``MixerConfig.closed_form_sigma``), in [0, 1], untransformed: the network
#:                starts from Eq. 9's answer and learns where to depart from it.
EXTRA_MIXER_FEATURES: tuple[str, ...] = ("closed_form",)
#: Features computed from SURE; dropped together for the paper's "w/o SURE" ablation.
SURE_BASED_FEATURES: frozenset[str] = frozenset({"sure", "divergence", "closed_form"})
#: The "w/o SURE" ablation input set (12 channels).
MIXER_FEATURES_NO_SURE: tuple[str, ...] = tuple(
    f for f in MIXER_FEATURES if f not in SURE_BASED_FEATURES
)
CHANNELS_PER_FEATURE = 3
#: The "log" input transform: LOG_SCALE * sign(v) * log(1 + |v| / LOG_FLOOR), v in radiance^2.
LOG_FLOOR = 1e-8
LOG_SCALE = 0.1


def _signed_log(v):
    return LOG_SCALE * jnp.sign(v) * jnp.log1p(jnp.abs(v) / LOG_FLOOR)


#: Transforms of the non-radiance features (var, sure, residual, divergence), by name:
#:   atan  the authors' arctan. Linear below ~1, so at the variances of renders of 64 spp
#:         and more (about 1e-3 down to 1e-7 radiance^2 on our test crops) these inputs are ~0
#:         next to the radiance inputs and the biases (the trained first-layer weights on them
#:         are ~0.1), and the mixer cannot compare SURE with var there (measured: the
#:         shipped atan mixer's alpha is ~0.45 at both 1024 and 4096 spp on a crop where
#:         OIDN's SURE is 2.5x and 9x the render's variance).
#:   log   a signed log (LOG_FLOOR, LOG_SCALE): O(1) at every scale from 1e-7 to 1e4, and
#:         differences of features are log-ratios (log SURE - log var). Our addition.
INPUT_TRANSFORMS: dict[str, Callable] = {"atan": jnp.arctan, "log": _signed_log}


def mixer_channel_slices(features: tuple[str, ...] = MIXER_FEATURES) -> dict[str, slice]:
    """Channel slice of each feature in ``mixer_inputs(..., features=features)``."""
    _check_features(features)
    return {
        name: slice(CHANNELS_PER_FEATURE * i, CHANNELS_PER_FEATURE * (i + 1))
        for i, name in enumerate(features)
    }


#: Layout of the full 18-channel input: hdr 0:3, den 3:6, var 6:9, sure 9:12,
#: residual 12:15, divergence 15:18.
MIXER_LAYOUT: dict[str, slice] = {
    name: slice(3 * i, 3 * (i + 1)) for i, name in enumerate(MIXER_FEATURES)
}


def _check_features(features) -> None:
    if not isinstance(features, tuple) or not features:
        raise ConfigError(f"mixer features must be a non-empty tuple of names, got {features!r}")
    allowed = MIXER_FEATURES + EXTRA_MIXER_FEATURES
    unknown = [f for f in features if f not in allowed]
    if unknown:
        raise ConfigError(
            f"unknown mixer feature(s) {unknown}; allowed: {', '.join(allowed)}"
        )
    if len(set(features)) != len(features):
        raise ConfigError(f"mixer features contain duplicates: {features}")


def _check_image(name: str, array, where: str, channels: tuple[int, ...] = (3,)) -> tuple:
    shape = np.shape(array)
    if len(shape) < 3 or shape[-1] not in channels:
        raise FrameError(
            f"{where}: '{name}' must have shape (..., H, W, {' or '.join(map(str, channels))}), "
            f"got {shape}"
        )
    return shape


def _check_same(where: str, **arrays) -> tuple:
    """All arrays (..., H, W, 3) with the same shape; returns it."""
    shapes = {name: _check_image(name, a, where) for name, a in arrays.items()}
    first_name, first = next(iter(shapes.items()))
    for name, shape in shapes.items():
        if shape != first:
            raise FrameError(f"{where}: '{name}' has shape {shape} but '{first_name}' has {first}")
    return first


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _check_variance_values(var, where: str) -> None:
    """Variance must be finite and >= 0 (only checked on concrete arrays)."""
    if not _is_concrete(var):
        return
    values = np.asarray(var)
    bad = ~np.isfinite(values) | (values < 0)
    if bad.any():
        index = tuple(int(i) for i in np.argwhere(bad)[0])
        raise FrameError(
            f"{where}: variance must be finite and >= 0 but {int(bad.sum())} value(s) are not "
            f"(first at index {index}: {values[index]})"
        )


@functools.partial(jax.jit, static_argnames=("features", "transform", "closed_form_sigma",
                                             "closed_form_stops"))
def _mixer_inputs(x, y, var, sure, features, transform: str = "atan",
                  closed_form_sigma: float = 12.0, closed_form_stops: float | None = None):
    residual_sq = jnp.square(x - y)
    f = INPUT_TRANSFORMS[transform]
    parts = {
        "hdr": lambda: x,
        "den": lambda: y,
        "var": lambda: f(var),
        "sure": lambda: f(sure),
        "residual": lambda: f(residual_sq),
        "divergence": lambda: f(sure + var - residual_sq),
        "closed_form": lambda: _closed_form_alpha(x, y, var, sure, closed_form_sigma, False,
                                                  closed_form_stops),
    }
    return jnp.concatenate([parts[name]() for name in features], axis=-1)


def mixer_inputs(x, y, var, sure=None, *, features: tuple[str, ...] = MIXER_FEATURES,
                 transform: str = "atan", closed_form_sigma: float = 12.0,
                 closed_form_stops: float | None = None):
    """Mixer ("PDNet") input features, (..., H, W, 3 * len(features)); 18 channels by default.

    Args:
      x: noisy colour (hdr), (..., H, W, 3). y: denoised colour (den), same shape.
      var: variance of the pixel mean of x, same shape. sure: per-pixel SURE of y (from
        :func:`jaxden.sure.sure`), same shape; may be None when ``features`` has no
        SURE-based feature.
      features: which features, in which order (see :data:`MIXER_FEATURES`;
        :data:`MIXER_FEATURES_NO_SURE` for the "w/o SURE" ablation;
        :data:`EXTRA_MIXER_FEATURES`). Channel slices: :func:`mixer_channel_slices`.
      closed_form_sigma, closed_form_stops: width and brightness strata of the
        ``closed_form`` feature's local means (see :func:`closed_form_alpha`).

    Non-radiance features go through ``transform`` (:data:`INPUT_TRANSFORMS`): arctan by
    default (bounded, and defined for the negative values SURE takes), as in the paper's Sec.
    4.3; radiance stays linear as in the authors' code.
    """
    _check_features(features)
    if transform not in INPUT_TRANSFORMS:
        raise ConfigError(f"mixer_inputs: unknown transform {transform!r}; allowed: "
                          f"{', '.join(INPUT_TRANSFORMS)}")
    needs_sure = any(f in SURE_BASED_FEATURES for f in features)
    if needs_sure and sure is None:
        raise FrameError(
            f"mixer_inputs: features {sorted(SURE_BASED_FEATURES & set(features))} need 'sure', "
            f"got None"
        )
    arrays = {"x": x, "y": y, "var": var}
    if needs_sure:
        arrays["sure"] = sure
    _check_same("mixer_inputs", **arrays)
    x, y, var = jnp.asarray(x), jnp.asarray(y), jnp.asarray(var)
    sure = jnp.asarray(sure) if needs_sure else jnp.zeros_like(x)
    return _mixer_inputs(x, y, var, sure, features, transform, float(closed_form_sigma),
                         None if closed_form_stops is None else float(closed_form_stops))


def swap_inputs(key, x, y, var, sure, probability: float = 0.5):
    """Training augmentation: swap (x, var) with (y, sure) per image with ``probability``.

    Shapes (B, H, W, 3) (or (H, W, 3), one draw). Returns ``(x', y', var', sure', swapped)``
    with ``swapped`` a bool array of shape (B,) (or ()). The target is unchanged: after a swap
    the mixer learns ``beta = 1 - alpha`` (paper Sec. 4.3).
    """
    _check_same("swap_inputs", x=x, y=y, var=var, sure=sure)
    if not 0.0 <= probability <= 1.0:
        raise ConfigError(f"swap_inputs: probability must be in [0, 1], got {probability}")
    lead = np.shape(x)[:-3]
    swapped = jax.random.bernoulli(key, probability, lead)
    s = swapped[..., None, None, None]
    return (
        jnp.where(s, y, x),
        jnp.where(s, x, y),
        jnp.where(s, sure, var),
        jnp.where(s, var, sure),
        swapped,
    )


# ---------------------------------------------------------------------------------- alpha

#: Raw output channels per alpha head: the paper's f_act (3 values per colour channel), the
#: "w/o f_act" ablation where the network predicts alpha directly, and ``closed_form_logit``
#: (our addition): a correction to the closed-form alpha in logit space,
#: alpha = sigmoid(logit(alpha_cf) + raw), so an output of 0 is Eq. 9 with local means.
ALPHA_HEADS: dict[str, int] = {"f_act": 9, "sigmoid": 3, "clip": 3, "closed_form_logit": 3}

#: alpha_cf is clipped to [eps, 1 - eps] before its logit in the ``closed_form_logit`` head.
CLOSED_FORM_LOGIT_EPS = 1e-3


@functools.partial(jax.jit, static_argnames=("grouping",))
def _f_act(raw, eps, grouping):
    if grouping == "by_role":
        x1, x2, x3 = raw[..., 0:3], raw[..., 3:6], raw[..., 6:9]
    else:
        x1, x2, x3 = raw[..., 0::3], raw[..., 1::3], raw[..., 2::3]
    return jnp.clip((x1 - x2) / jnp.maximum(x3, eps), 0.0, 1.0)


def f_act(raw, eps: float = 1e-6, *, grouping: Literal["by_role", "by_channel"] = "by_role"):
    """Paper Eq. 19 with the authors' clip: alpha = clip((x1 - x2) / max(x3, eps), 0, 1).

    ``raw``: (..., H, W, 9) network outputs; returns alpha (..., H, W, 3), one per colour
    channel. Grouping of the 9 channels (our choice; for a trained network it only permutes
    the last layer's filters, it matters when importing foreign weights):

    - ``"by_role"`` (default): [x1_R, x1_G, x1_B, x2_R, x2_G, x2_B, x3_R, x3_G, x3_B];
    - ``"by_channel"``: [x1_R, x2_R, x3_R, x1_G, x2_G, x3_G, x1_B, x2_B, x3_B].

    Mirrors Eqs. 9-10: alpha is a difference of two quantities over a third. Note
    ``max(x3, eps)`` has zero gradient w.r.t. x3 below eps and the clip zero gradient outside
    [0, 1] (as in the authors' code).
    """
    _check_image("raw", raw, "f_act", channels=(9,))
    if grouping not in ("by_role", "by_channel"):
        raise ConfigError(f"f_act: grouping must be 'by_role' or 'by_channel', got {grouping!r}")
    if not (isinstance(eps, (int, float, np.floating)) and math.isfinite(eps) and eps > 0):
        raise ConfigError(f"f_act: eps must be > 0, got {eps!r}")
    return _f_act(jnp.asarray(raw), eps, grouping)


def alpha_direct(raw, kind: Literal["sigmoid", "clip"] = "sigmoid"):
    """"w/o f_act" ablation (paper Table 4): alpha from 3 raw outputs, (..., H, W, 3).

    ``"sigmoid"``: alpha = sigmoid(raw); ``"clip"``: alpha = clip(raw, 0, 1). The paper does
    not say which squashing its ablation used; sigmoid is the default (nonzero gradient).
    """
    _check_image("raw", raw, "alpha_direct")
    raw = jnp.asarray(raw)
    if kind == "sigmoid":
        return jax.nn.sigmoid(raw)
    if kind == "clip":
        return jnp.clip(raw, 0.0, 1.0)
    raise ConfigError(f"alpha_direct: kind must be 'sigmoid' or 'clip', got {kind!r}")


def alpha_from_head(raw, head: str = "f_act", eps: float = 1e-6):
    """alpha from the network's raw output for a head of :data:`ALPHA_HEADS`."""
    if head == "f_act":
        return f_act(raw, eps)
    if head in ("sigmoid", "clip"):
        return alpha_direct(raw, head)
    if head == "closed_form_logit":
        raise ConfigError("the closed_form_logit head needs the closed-form alpha of the "
                          "inputs: use mixer_alpha (or closed_form_logit_alpha)")
    raise ConfigError(f"unknown alpha head {head!r}; allowed: {', '.join(ALPHA_HEADS)}")


def closed_form_logit_alpha(raw, alpha_cf, bound: float | None = None,
                            eps: float = CLOSED_FORM_LOGIT_EPS):
    """The ``closed_form_logit`` head: sigmoid(logit(clip(alpha_cf, eps, 1 - eps)) + c).

    ``raw`` (..., H, W, 3) network outputs, ``alpha_cf`` (..., H, W, 1 or 3) from
    :func:`closed_form_alpha`; returns (..., H, W, 3) in (0, 1). The correction is c = raw,
    or with a ``bound`` B, c = B tanh(raw / B): the logit then never moves more than B from
    Eq. 9's (a trust region around the closed form; slope 1 at raw = 0). Swap-consistent:
    logit(1 - a) = -logit(a) and the bound is odd, so the swapped inputs (whose closed form is
    exactly 1 - alpha_cf) see the same correction problem with the sign flipped.
    """
    a = jnp.clip(jnp.asarray(alpha_cf), eps, 1.0 - eps)
    correction = jnp.asarray(raw)
    if bound is not None:
        correction = bound * jnp.tanh(correction / bound)
    return jax.nn.sigmoid(jnp.log(a) - jnp.log1p(-a) + correction)


@jax.jit
def _mix(x, y, alpha):
    return x + alpha * (y - x)


def mix(x, y, alpha):
    """z = x + alpha * (y - x); x, y (..., H, W, 3), alpha broadcastable (..., H, W, 1 or 3)."""
    shape = _check_same("mix", x=x, y=y)
    alpha_shape = _check_image("alpha", alpha, "mix", channels=(1, 3))
    if alpha_shape[:-1] != shape[:-1]:
        raise FrameError(f"mix: 'alpha' has shape {alpha_shape} but x has {shape}")
    return _mix(jnp.asarray(x), jnp.asarray(y), jnp.asarray(alpha))


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
    """

    window: int = 11
    a: float = 2.0
    c: float = 4.2
    squash: Literal["normal_cdf", "logistic"] = "normal_cdf"
    sigma_rule: Literal["mean_variance", "image_mean_variance", "fixed"] = "mean_variance"
    sigma_scale: float = 100.0
    sigma_variance_cap: float = 1.0
    sigma_min: float = 1e-3
    sigma_fixed: float = 1.0
    use_max_variance_neighbour: bool = True
    neighbour_weight: float = 1.0 / 3.0
    per_channel: bool = False
    eps: float = 1e-6

    def __post_init__(self):
        def fail(field, expected):
            raise ConfigError(
                f"TStatConfig.{field}: expected {expected}, got {getattr(self, field)!r}"
            )

        if not isinstance(self.window, int) or self.window < 1 or self.window % 2 == 0:
            fail("window", "an odd integer >= 1")
        for field in ("a", "sigma_scale", "sigma_variance_cap", "sigma_min", "sigma_fixed", "eps"):
            value = getattr(self, field)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                fail(field, "a finite number > 0")
        for field in ("c", "neighbour_weight"):
            value = getattr(self, field)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                fail(field, "a finite number")
        if self.squash not in ("normal_cdf", "logistic"):
            fail("squash", "'normal_cdf' or 'logistic'")
        if self.sigma_rule not in ("mean_variance", "image_mean_variance", "fixed"):
            fail("sigma_rule", "'mean_variance', 'image_mean_variance' or 'fixed'")
        for field in ("use_max_variance_neighbour", "per_channel"):
            if not isinstance(getattr(self, field), bool):
                fail(field, "a bool")


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
    """Zero-padded correlation of (H, W, C) along ``axis`` (0: H, 1: W), odd-length ``taps``.

    A depthwise convolution (the taps are traced values: s depends on the data); 'SAME'
    padding with zeros = neighbours outside the image are absent from the sum.
    """
    channels, size = image.shape[-1], taps.shape[0]
    kernel_hw = (size, 1) if axis == 0 else (1, size)
    kernel = jnp.broadcast_to(taps.reshape(kernel_hw + (1, 1)), kernel_hw + (1, channels))
    out = jax.lax.conv_general_dilated(
        image[None], kernel.astype(image.dtype), window_strides=(1, 1), padding="SAME",
        dimension_numbers=("NHWC", "HWIO", "NHWC"), feature_group_count=channels,
        precision=jax.lax.Precision.HIGHEST,
    )
    return out[0]


def _max_variance_neighbour(var, diff, window: int):
    """Per channel, var and diff at M_p = argmax of var over the in-image window of p.

    Ties go to the first maximum in row-major window order (top-left first), which for a
    fixed p is the smallest row-major image index; out-of-image positions never win (the
    window is padded with var = -inf). The reduction "larger var, then smaller index" is a
    total order, so ``reduce_window``'s unspecified reduction order cannot change the result.
    Returns (var_M, diff_M), each (H, W, C).
    """
    radius = window // 2
    height, width, channels = var.shape
    var = jax.lax.stop_gradient(var)  # M_p is a selection; no derivative through it
    index = jnp.broadcast_to(
        jnp.arange(height * width, dtype=jnp.int32).reshape(height, width, 1), var.shape
    )

    def pick(a, b):
        (var_a, index_a), (var_b, index_b) = a, b
        take_b = (var_b > var_a) | ((var_b == var_a) & (index_b < index_a))
        return jnp.where(take_b, var_b, var_a), jnp.where(take_b, index_b, index_a)

    init = (jnp.array(-jnp.inf, var.dtype), jnp.array(np.iinfo(np.int32).max, jnp.int32))
    var_m, index_m = jax.lax.reduce_window(
        (var, index), init, pick, (window, window, 1), (1, 1, 1),
        ((radius, radius), (radius, radius), (0, 0)),
    )
    flat_diff = diff.reshape(height * width, channels)
    diff_m = jnp.take_along_axis(flat_diff, index_m.reshape(height * width, channels), axis=0)
    return var_m, diff_m.reshape(height, width, channels)


def _t_single(x, z, var, config: TStatConfig):
    """t for one image (H, W, 3) -> (H, W, 1), or (H, W, 3) if per_channel."""
    s = _gaussian_sigma(var, config)
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
def _t_statistic(x, z, var, config: TStatConfig):
    lead = x.shape[:-3]
    flat = [a.reshape((-1,) + a.shape[-3:]) for a in (x, z, var)]
    t = jax.vmap(lambda a, b, c: _t_single(a, b, c, config))(*flat)
    return t.reshape(lead + t.shape[1:])


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
    _check_same("t_statistic", x=x, z=z, var=var)
    _check_variance_values(var, "t_statistic")
    return _t_statistic(jnp.asarray(x), jnp.asarray(z), jnp.asarray(var), config)


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
    shape = _check_same("t_statistic_scaling", x=x, z=z, var=var)
    alpha_shape = _check_image("alpha", alpha, "t_statistic_scaling", channels=(1, 3))
    if alpha_shape[:-1] != shape[:-1]:
        raise FrameError(
            f"t_statistic_scaling: 'alpha' has shape {alpha_shape} but x has {shape}"
        )
    _check_variance_values(var, "t_statistic_scaling")
    t = _t_statistic(jnp.asarray(x), jnp.asarray(z), jnp.asarray(var), config)
    return _scale_alpha(jnp.asarray(alpha), t, config)


def consistent_mix(x, y, alpha, var, config: TStatConfig | None = None, **overrides):
    """The inference output: (z', alpha') with z = mix(x, y, alpha), alpha' the scaled alpha
    and z' = x + alpha' (y - x). Shapes as in :func:`t_statistic_scaling`."""
    z = mix(x, y, alpha)
    alpha_prime = t_statistic_scaling(alpha, x, z, var, config, **overrides)
    return mix(x, y, alpha_prime), alpha_prime


# ------------------------------------------------------------------------ closed-form mixer

#: Mixer spec (``--mixer``, :func:`load_mixer`) of the closed-form mixer; options as
#: ``closed-form:sigma=4,per_channel=true``.
CLOSED_FORM_SPEC = "closed-form"
#: Option names of the closed-form spec -> :class:`MixerConfig` fields.
CLOSED_FORM_OPTIONS = {"sigma": "closed_form_sigma", "per_channel": "closed_form_per_channel",
                       "stops": "closed_form_stops"}


def _gaussian_taps(sigma: float) -> np.ndarray:
    radius = max(1, math.ceil(3.0 * sigma))
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-np.square(offsets) / (2.0 * sigma * sigma)).astype(np.float32)


def _blur_shifted(image, taps, axis: int):
    """Zero-padded correlation of (H, W, C) along ``axis`` with odd-length ``taps`` as a loop of
    shifted, weighted adds: for the closed form's 73 taps (sigma 12) on 1280 x 720, 85x faster
    than the depthwise convolution of :func:`_blur_1d` on XLA:CPU (22 ms against 1.9 s for
    both axes, measured on the project machine), same result to float32 rounding."""
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


def _blur_2d(image, taps):
    return _blur_shifted(_blur_shifted(image, taps, 0), taps, 1)


def _range_strata(level, lo: int, hi: int):
    """Tent memberships of ``level`` (in bin units) in the integer bins lo..hi: they sum to 1
    wherever lo <= level <= hi, and each is nonzero only within one bin of its centre."""
    for b in range(lo, hi + 1):
        yield jnp.clip(1.0 - jnp.abs(level - b), 0.0, 1.0)


def _range_local_means(terms, x, y, taps, stops: float):
    """Gaussian local sums of ``terms`` (H, W, C) restricted to pixels of similar brightness.

    A bilateral grid along log2 brightness with tent bins ``stops`` wide: for each bin b the
    terms of its member pixels (weight s_b) are blurred, and a pixel collects sum_b s_b(p)
    blur(s_b terms)(p). Neighbours more than two bins apart in brightness do not contribute,
    so a bright emitter does not set the alpha of the dim wall beside it. Empty bins are
    skipped at run time.
    """
    proxy = jnp.mean((x + y) * 0.5, axis=-1, keepdims=True)
    proxy = _blur_2d(proxy, jnp.asarray(_gaussian_taps(CLOSED_FORM_PROXY_SIGMA), x.dtype))
    proxy = jnp.clip(proxy, CLOSED_FORM_RANGE_FLOOR, CLOSED_FORM_RANGE_CEIL)
    level = jnp.log2(proxy) / stops
    lo = math.floor(math.log2(CLOSED_FORM_RANGE_FLOOR) / stops)
    hi = math.ceil(math.log2(CLOSED_FORM_RANGE_CEIL) / stops)
    total = jnp.zeros_like(terms)
    for weight in _range_strata(level, lo, hi):
        total = jax.lax.cond(
            jnp.any(weight > 0),
            lambda t, w=weight: t + w * _blur_2d(terms * w, taps),
            lambda t: t,
            total,
        )
    return total


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
        sums = _blur_2d(both, taps)
    else:
        sums = _range_local_means(both, x, y, taps, stops)
    numerator, denominator = jnp.split(sums, 2, axis=-1)
    positive = denominator > 0
    # y == x on the whole window: every alpha gives the same z; take y.
    alpha = jnp.where(positive, numerator / jnp.where(positive, denominator, 1.0), 1.0)
    return jnp.broadcast_to(jnp.clip(alpha, 0.0, 1.0), x.shape)


@functools.partial(jax.jit, static_argnames=("sigma", "per_channel", "stops"))
def _closed_form_alpha(x, y, var, sure, sigma: float, per_channel: bool,
                       stops: float | None = None):
    taps = jnp.asarray(_gaussian_taps(sigma), x.dtype)
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
    noisy to use (paper Sec. 4.1; measured: at sigma 2 the mix is already worse than OIDN
    alone, experiments/results/closed-form-sigma.md), so both
    numerator and denominator are replaced by local means, Gaussian weights of standard
    deviation ``sigma`` pixels (truncated at 3 sigma, only in-image pixels), summed over the
    colour channels unless ``per_channel``, and the ratio is clipped to [0, 1].

    Properties: swap-symmetric by construction (exchanging (x, var) with (y, SURE) gives
    1 - alpha before clipping); consistent on its own (as var -> 0 with y's bias fixed, the
    numerator -> 0 and the denominator -> 2 bias^2, so alpha -> 0), and the t-statistic
    scaling still applies on top in :func:`progressive_denoise`. Where y == x on a whole
    window alpha is 1 (any value gives the same z).

    ``stops`` (None: off) makes the local means range-aware (our addition): only neighbours of
    similar brightness count, through tent bins ``stops`` wide in log2 of the channel mean of
    (x + y) / 2 (blurred by :data:`CLOSED_FORM_PROXY_SIGMA` px; see
    :func:`_range_local_means`). Without it, a window holding an emitter or a bright
    highlight is ruled by that spot's errors, which are orders of magnitude larger than those
    of the dim surfaces around it, and its alpha is forced on them (measured on the demo's
    Cornell box: relMSE 2.4x OIDN's at 64 spp; with stops = 1, 0.6x). The proxy is symmetric
    in x and y, so swap symmetry and consistency hold as above.

    Inputs (..., H, W, 3) as in :func:`mixer_alpha`; returns alpha (..., H, W, 3) in [0, 1].
    Pure and jitted (``sigma``, ``per_channel`` and ``stops`` static).
    """
    config = MixerConfig(kind="closed_form", closed_form_sigma=sigma,
                         closed_form_per_channel=per_channel, closed_form_stops=stops)
    x, y, var, sure = _mixer_arrays("closed_form_alpha", config, x, y, var, sure)
    return _closed_form_alpha(x, y, var, sure, float(sigma), per_channel,
                              None if stops is None else float(stops))


def closed_form_mixer(spec: str = CLOSED_FORM_SPEC):
    """``({}, MixerConfig)`` of the closed-form mixer for a spec ``closed-form`` or
    ``closed-form:KEY=VALUE,...`` (keys: :data:`CLOSED_FORM_OPTIONS`)."""
    from jaxden.config import load_config

    name, _, options = spec.partition(":")
    if name != CLOSED_FORM_SPEC:
        raise ConfigError(f"mixer {spec!r}: not a closed-form mixer spec ({CLOSED_FORM_SPEC})")
    overrides = []
    for option in filter(None, (o.strip() for o in options.split(","))):
        key, equals, value = option.partition("=")
        if not equals or key.strip() not in CLOSED_FORM_OPTIONS:
            raise ConfigError(
                f"mixer {spec!r}: expected options KEY=VALUE with KEY one of "
                f"{', '.join(CLOSED_FORM_OPTIONS)}, got {option!r}"
            )
        overrides.append(f"{CLOSED_FORM_OPTIONS[key.strip()]}={value.strip()}")
    try:
        config = load_config(MixerConfig(kind="closed_form"), MixerConfig, overrides=overrides)
    except ConfigError as error:
        raise ConfigError(f"mixer {spec!r}: {error}") from None
    return {}, config


# ==================================================================================== mixer
# The mixer network, its config, training task, checkpoints and the inference pipeline.
# (Appended to the pure functions above; the network module is jaxden.nn.mixer.PDNet.)

MIXER_KIND = "mixer"
MIXER_MODEL = "mixer"
#: MixerConfig.kind: the paper's network, or Eq. 9 with local means (:func:`closed_form_alpha`).
MIXER_KINDS = ("network", "closed_form")


@dataclasses.dataclass(frozen=True)
class MixerConfig:
    """The progressive-denoising mixer ("PDNet") and the data it is trained on.

    Network:
      features: mixer inputs (:data:`MIXER_FEATURES`, 18 channels; :data:`MIXER_FEATURES_NO_SURE`
        for the "w/o SURE" ablation, 12 channels).
      head: ``"f_act"`` (paper Eq. 19, 9 outputs) or ``"sigmoid"`` / ``"clip"`` (the "w/o f_act"
        ablation: alpha predicted directly, 3 outputs), or ``"closed_form_logit"`` (our
        addition, 3 outputs: a logit-space correction of the closed-form alpha with this
        config's ``closed_form_sigma`` / ``closed_form_per_channel``; an untrained network
        starts at the closed form). See :data:`ALPHA_HEADS`.
      width: hidden channels (48). centred_head: start alpha near 0.5 (see
        :func:`jaxden.nn.mixer.head_bias`; our choice, the paper does not say).
      init_output_scale: factor on the initial output-layer kernel (0.1): with the full
        LeCun scale the untrained f_act mixer has a third of its alphas saturated at 0 or 1
        (zero gradient) on the tiny dataset, mean 0.15; at 0.1 none, 0.46 +- 0.03.
      f_act_eps: the eps of f_act (1e-6).
      input_transform: ``"atan"`` (the authors') or ``"log"`` (a signed log; our addition) for
        the var, SURE, residual and divergence inputs; see :data:`INPUT_TRANSFORMS`.
      logit_bound: with the ``closed_form_logit`` head, None (the correction is the raw
        output) or B > 0: the correction is B tanh(raw / B), so alpha's logit stays within B
        of Eq. 9's whatever the inputs (see :func:`closed_form_logit_alpha`).
      logit_eps: with the ``closed_form_logit`` head, alpha_cf is clipped to [eps, 1 - eps]
        before its logit (default :data:`CLOSED_FORM_LOGIT_EPS`).

    Closed-form mixer (no network; our addition, see :func:`closed_form_alpha`):
      kind: ``"network"`` (the paper's PDNet) or ``"closed_form"`` (the paper's Eq. 9 with
        Gaussian local means of the per-pixel estimates; no parameters, works for any
        denoiser without training; load it with the spec :data:`CLOSED_FORM_SPEC`).
      closed_form_sigma: standard deviation in pixels of the Gaussian local means (also of
        the network's optional ``closed_form`` input feature; 12: the
        best geometric-mean RMSE ratio over OIDN on the 480 inputs of data/default-chain, flat
        within 0.3 % from 8 to 16; experiments/results/closed-form-sigma.md).
      closed_form_per_channel: one alpha per colour channel instead of one for all three.
      closed_form_stops: None (plain Gaussian local means) or the width in stops (log2) of
        the brightness strata of range-aware local means (see :func:`closed_form_alpha`);
        also used by the ``closed_form_logit`` head and the ``closed_form`` feature.
      With ``kind = "closed_form"`` the network fields (features, head, width, ...) are unused.

    Training:
      swap_probability: probability of swapping (x, var) with (y, SURE) per training sample
        (0.5, paper Sec. 4.3). With the "w/o SURE" features the swap exchanges x and y only
        (there is no error estimate of y to exchange var with; our choice).

    Inference:
      tstat: the t-statistic scaling (:class:`TStatConfig`), applied only at inference.
      swap_average: use (alpha(x, y, var, SURE) + 1 - alpha(y, x, SURE, var)) / 2, the mean
        of the mixer and its swapped call (test-time symmetrisation of the swap invariance the
        training encourages; our addition, not in the paper; costs a second mixer call).
        Measured with the shipped OIDN mixer (with the t-statistic scaling), PD(OIDN) / OIDN
        mean over spp went from 0.928 / 0.893 to 0.923 / 0.887 (RMSE / relMSE, test set,
        2..1024 spp) and from 0.807 / 0.788 to 0.806 / 0.780 (test-high, 32..4096 spp;
        experiments/results/pd-oidn*.md). Default off, so a mixer trained and evaluated
        before this option behaves as it did; the shipped ``oidn-pd`` turns it on.

    SURE cache (the denoised images and SURE maps the mixer is trained on, computed once per
    dataset item by :func:`jaxden.pdcache.build_sure_cache`):
      denoiser: denoiser spec (``oidn``, a checkpoint folder or a .msgpack file).
      cache: cache folder; empty = ``DATASET/derived/<denoiser>`` (see
        :func:`jaxden.pdcache.default_cache_dir`).
      sure_probes, sure_method (``auto``: jvp for JAX denoisers, fd for black boxes),
      sure_eps (None: the measured default of :func:`jaxden.pdcache.default_eps`), sure_seed.
      build_cache: build (or finish) the cache when training starts if it is missing or
        incomplete; else a missing cache is an error.
    """

    features: tuple[str, ...] = MIXER_FEATURES
    kind: Literal["network", "closed_form"] = "network"
    closed_form_sigma: float = 12.0
    closed_form_per_channel: bool = False
    closed_form_stops: float | None = None
    head: Literal["f_act", "sigmoid", "clip", "closed_form_logit"] = "f_act"
    width: int = 48
    centred_head: bool = True
    init_output_scale: float = 0.1
    f_act_eps: float = 1e-6
    input_transform: Literal["atan", "log"] = "atan"
    logit_bound: float | None = None
    logit_eps: float = CLOSED_FORM_LOGIT_EPS
    swap_probability: float = 0.5
    tstat: TStatConfig = TStatConfig()
    swap_average: bool = False
    denoiser: str = "oidn"
    cache: str = ""
    sure_probes: int = 4
    sure_method: Literal["auto", "jvp", "fd"] = "auto"
    sure_eps: float | None = None
    sure_seed: int = 0
    build_cache: bool = True

    def __post_init__(self):
        if isinstance(self.features, list):  # a list from Python code; jit needs it hashable
            object.__setattr__(self, "features", tuple(self.features))
        _check_features(self.features)
        if self.kind not in MIXER_KINDS:
            raise ConfigError(
                f"MixerConfig.kind: unknown mixer kind {self.kind!r}; allowed: "
                f"{', '.join(MIXER_KINDS)}"
            )
        if not (isinstance(self.closed_form_sigma, (int, float))
                and not isinstance(self.closed_form_sigma, bool)
                and math.isfinite(self.closed_form_sigma) and self.closed_form_sigma > 0):
            raise ConfigError(
                f"MixerConfig.closed_form_sigma: expected a number > 0 (pixels), got "
                f"{self.closed_form_sigma!r}"
            )
        if self.closed_form_stops is not None and not (
                isinstance(self.closed_form_stops, (int, float))
                and not isinstance(self.closed_form_stops, bool)
                and math.isfinite(self.closed_form_stops) and self.closed_form_stops > 0):
            raise ConfigError(
                f"MixerConfig.closed_form_stops: expected a number > 0 (stops) or none, got "
                f"{self.closed_form_stops!r}"
            )
        if not isinstance(self.closed_form_per_channel, bool):
            raise ConfigError(
                f"MixerConfig.closed_form_per_channel: expected true or false, got "
                f"{self.closed_form_per_channel!r}"
            )
        if self.head not in ALPHA_HEADS:
            raise ConfigError(
                f"MixerConfig.head: unknown alpha head {self.head!r}; allowed: "
                f"{', '.join(ALPHA_HEADS)}"
            )
        if not isinstance(self.width, int) or self.width < 1:
            raise ConfigError(f"MixerConfig.width: expected an integer >= 1, got {self.width!r}")
        if not (math.isfinite(self.init_output_scale) and self.init_output_scale >= 0):
            raise ConfigError(
                f"MixerConfig.init_output_scale: expected >= 0, got {self.init_output_scale!r}"
            )
        if not (math.isfinite(self.f_act_eps) and self.f_act_eps > 0):
            raise ConfigError(f"MixerConfig.f_act_eps: expected > 0, got {self.f_act_eps!r}")
        if self.input_transform not in INPUT_TRANSFORMS:
            raise ConfigError(
                f"MixerConfig.input_transform: unknown transform {self.input_transform!r}; "
                f"allowed: {', '.join(INPUT_TRANSFORMS)}"
            )
        if self.logit_bound is not None and not (
                isinstance(self.logit_bound, (int, float)) and not isinstance(self.logit_bound, bool)
                and math.isfinite(self.logit_bound) and self.logit_bound > 0):
            raise ConfigError(
                f"MixerConfig.logit_bound: expected a number > 0 or none, got {self.logit_bound!r}"
            )
        if not (isinstance(self.logit_eps, (int, float)) and not isinstance(self.logit_eps, bool)
                and 0.0 < self.logit_eps < 0.5):
            raise ConfigError(
                f"MixerConfig.logit_eps: expected a number in (0, 0.5), got {self.logit_eps!r}"
            )
        if self.head != "closed_form_logit" and (
                self.logit_bound is not None or self.logit_eps != CLOSED_FORM_LOGIT_EPS):
            raise ConfigError(
                f"MixerConfig.logit_bound / logit_eps apply only to head = 'closed_form_logit' "
                f"(head is {self.head!r})"
            )
        if not 0.0 <= self.swap_probability <= 1.0:
            raise ConfigError(
                f"MixerConfig.swap_probability: expected a value in [0, 1], got "
                f"{self.swap_probability!r}"
            )
        if not isinstance(self.tstat, TStatConfig):
            raise ConfigError(f"MixerConfig.tstat: expected a TStatConfig, got {self.tstat!r}")
        if not isinstance(self.swap_average, bool):
            raise ConfigError(
                f"MixerConfig.swap_average: expected true or false, got {self.swap_average!r}"
            )
        if not isinstance(self.sure_probes, int) or self.sure_probes < 1:
            raise ConfigError(
                f"MixerConfig.sure_probes: expected an integer >= 1, got {self.sure_probes!r}"
            )
        if self.sure_eps is not None and not (math.isfinite(self.sure_eps) and self.sure_eps > 0):
            raise ConfigError(f"MixerConfig.sure_eps: expected > 0 or none, got {self.sure_eps!r}")
        if not self.denoiser:
            raise ConfigError("MixerConfig.denoiser: name the denoiser whose output is mixed")

    @property
    def in_channels(self) -> int:
        return CHANNELS_PER_FEATURE * len(self.features)

    @property
    def out_channels(self) -> int:
        return ALPHA_HEADS[self.head]

    @property
    def uses_sure(self) -> bool:
        return (self.kind == "closed_form" or self.head == "closed_form_logit"
                or any(f in SURE_BASED_FEATURES for f in self.features))


def mixer_layout(config: MixerConfig) -> dict:
    """The input/output layout a mixer's parameters belong to (stored in checkpoints).

    ``{"features": [...], "in_channels": 18, "out_channels": 9, "head": "f_act",
    "channels": {"hdr": [0, 3], ...}}`` (JSON-able).
    """
    slices = mixer_channel_slices(tuple(config.features))
    return {
        "features": list(config.features),
        "in_channels": config.in_channels,
        "out_channels": config.out_channels,
        "head": config.head,
        "channels": {name: [s.start, s.stop] for name, s in slices.items()},
    }


def mixer_module(config: MixerConfig):
    """The flax module (:class:`jaxden.nn.mixer.PDNet`) for ``config``."""
    from jaxden.nn.mixer import PDNet

    return PDNet(
        width=config.width,
        out_channels=config.out_channels,
        head=config.head,
        centred_head=config.centred_head,
    )


_INIT_CHUNK = 1 << 16


@jax.jit
def _normal_chunk(key, index):
    # One fixed shape: XLA:CPU compiles a threefry draw in ~1.5 s, once per shape; a flax
    # init compiles one per parameter shape (~9 s for PDNet on the project machine).
    return jax.random.normal(jax.random.fold_in(key, index), (_INIT_CHUNK,), jnp.float32)


def mixer_init(key, config: MixerConfig = MixerConfig()):
    """Fresh mixer parameters (a pytree) for ``config``.

    Kernels are LeCun-normal, ``N(0, 1 / fan_in)`` (fan_in = k * k * C_in; flax's default is a
    truncated variant), the output kernel times ``config.init_output_scale``; biases zero
    except the output bias (:func:`jaxden.nn.mixer.head_bias` when ``centred_head``). The
    values come from one flat standard-normal sequence drawn in fixed-size chunks of ``key``
    (so initialising any config reuses one compiled draw) and are assigned to the kernels in
    parameter-path order. Same structure as ``PDNet.init``.
    """
    from jaxden.nn.mixer import head_bias

    if config.kind == "closed_form":
        return {}
    sample = jax.ShapeDtypeStruct((1, 8, 8, config.in_channels), jnp.float32)
    shapes = jax.eval_shape(mixer_module(config).init, jax.random.PRNGKey(0), sample)
    leaves, tree = jax.tree_util.tree_flatten_with_path(shapes)
    kernels = [(i, leaf.shape) for i, (path, leaf) in enumerate(leaves)
               if jax.tree_util.keystr(path).endswith("['kernel']")]
    total = sum(math.prod(shape) for _, shape in kernels)
    chunks = [_normal_chunk(key, i) for i in range(-(-total // _INIT_CHUNK))]
    flat = jnp.concatenate(chunks) if len(chunks) > 1 else chunks[0]
    values = [jnp.zeros(leaf.shape, leaf.dtype) for _, leaf in leaves]
    offset = 0
    for index, shape in kernels:
        size = math.prod(shape)
        fan_in = math.prod(shape[:-1])
        values[index] = flat[offset : offset + size].reshape(shape) / math.sqrt(fan_in)
        offset += size
    for index, (path, leaf) in enumerate(leaves):
        name = jax.tree_util.keystr(path)
        if "conv_out" not in name:
            continue
        if name.endswith("['kernel']"):
            values[index] = values[index] * config.init_output_scale
        elif config.centred_head:
            values[index] = jnp.asarray(head_bias(config.out_channels, config.head))
    return jax.tree_util.tree_unflatten(tree, values)


def _mixer_swap_args(config: MixerConfig, x, y, var, sure):
    """Arguments of the mixer with the roles of x and y exchanged (see MixerConfig)."""
    if config.uses_sure:
        return y, x, sure, var
    return y, x, var, sure


@functools.partial(jax.jit, static_argnames=("config",))
def _mixer_alpha(params, x, y, var, sure, config: MixerConfig):
    stops = None if config.closed_form_stops is None else float(config.closed_form_stops)
    if config.kind == "closed_form":
        return _closed_form_alpha(x, y, var, sure, float(config.closed_form_sigma),
                                  config.closed_form_per_channel, stops)
    inputs = _mixer_inputs(x, y, var, sure, tuple(config.features), config.input_transform,
                           float(config.closed_form_sigma), stops)
    raw = mixer_module(config).apply(params, inputs)
    if config.head == "f_act":
        return _f_act(raw, config.f_act_eps, "by_role")
    if config.head == "closed_form_logit":
        alpha_cf = _closed_form_alpha(x, y, var, sure, float(config.closed_form_sigma),
                                      config.closed_form_per_channel, stops)
        return closed_form_logit_alpha(raw, alpha_cf, config.logit_bound, config.logit_eps)
    if config.head == "sigmoid":
        return jax.nn.sigmoid(raw)
    return jnp.clip(raw, 0.0, 1.0)


def _mixer_arrays(where: str, config: MixerConfig, x, y, var, sure):
    if config.uses_sure and sure is None:
        raise FrameError(f"{where}: the mixer's features {list(config.features)} need 'sure'")
    arrays = {"x": x, "y": y, "var": var}
    if sure is not None:
        arrays["sure"] = sure
    _check_same(where, **arrays)
    x, y, var = (jnp.asarray(a, jnp.float32) for a in (x, y, var))
    sure = jnp.zeros_like(x) if sure is None else jnp.asarray(sure, jnp.float32)
    return x, y, var, sure


def mixer_alpha(params, config: MixerConfig, x, y, var, sure=None):
    """alpha = head(PDNet(mixer_inputs(x, y, var, sure))), (..., H, W, 3) in [0, 1].

    x: noisy colour, y: denoised colour, var: variance of the pixel mean of x, sure: SURE of
    y; all (..., H, W, 3) linear radiance (radiance^2 for var and sure). Pure and jitted
    (``config`` is static), differentiable in ``params``. No t-statistic scaling.
    """
    x, y, var, sure = _mixer_arrays("mixer_alpha", config, x, y, var, sure)
    return _mixer_alpha(params, x, y, var, sure, config)


def mixer_apply(params, config: MixerConfig, x, y, var, sure=None):
    """The training-time mixer: ``(z, alpha)`` with ``z = x + alpha (y - x)``; shapes as in
    :func:`mixer_alpha`. No t-statistic scaling (the paper applies it only at inference)."""
    x, y, var, sure = _mixer_arrays("mixer_apply", config, x, y, var, sure)
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    return _mix(x, y, alpha), alpha


def _inference_alpha(params, x, y, var, sure, config: MixerConfig, swap_average: bool):
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    if not swap_average:
        return alpha
    swapped = _mixer_alpha(params, *_mixer_swap_args(config, x, y, var, sure), config)
    return 0.5 * (alpha + (1.0 - swapped))


def swap_symmetry(params, config: MixerConfig, x, y, var, sure=None, *, per_pixel: bool = False):
    """How far a mixer is from swap symmetry: mean |alpha(x, y, var, sure) - (1 - alpha(y, x,
    sure, var))|.

    A mixer that learned the paper's swap invariance (Sec. 4.3, 7: swapping the inputs turns
    alpha into beta = 1 - alpha) gives 0; the training swap only encourages it, so expect a
    small positive number for a trained mixer. Inputs (..., H, W, 3). Returns a float (mean over
    everything), or the per-pixel map (..., H, W, 3) with ``per_pixel=True``. With the
    "w/o SURE" features the swapped call is alpha(y, x, var) (see :class:`MixerConfig`).
    """
    x, y, var, sure = _mixer_arrays("swap_symmetry", config, x, y, var, sure)
    alpha = _mixer_alpha(params, x, y, var, sure, config)
    swapped = _mixer_alpha(params, *_mixer_swap_args(config, x, y, var, sure), config)
    gap = jnp.abs(alpha - (1.0 - swapped))
    return gap if per_pixel else float(jnp.mean(gap))


# ------------------------------------------------------------------------------ checkpoints

def _mixer_meta(config: MixerConfig) -> dict:
    from jaxden.config import config_to_dict

    return {
        "kind": MIXER_KIND,
        "model": MIXER_MODEL,
        "model_config": config_to_dict(config),
        "layout": mixer_layout(config),
    }


def save_mixer(path, params, config: MixerConfig, **extra_meta) -> None:
    """Write released mixer weights: ``path`` (.msgpack) and its .json meta record (atomic).

    ``extra_meta``: anything worth recording (training steps, dataset, measured metrics).
    """
    from jaxden.checkpoint import save_weights

    save_weights(path, params, {**extra_meta, **_mixer_meta(config)})


def load_mixer(spec, *, expect_features: tuple[str, ...] | None = None):
    """``(params, config)`` of a trained mixer.

    ``spec``: a training workdir or checkpoint folder of ``jaxden train`` with ``model =
    "mixer"``, a released ``.msgpack`` file (with its .json), the name of weights shipped in
    ``jaxden/weights/<name>.msgpack``, or ``closed-form[:KEY=VALUE,...]`` for the mixer
    without weights (:func:`closed_form_mixer`; params ``{}``). ``expect_features``: the input layout the caller needs.

    Raises CheckpointError naming the difference when the checkpoint is not a mixer (e.g. a
    denoiser checkpoint), its config is not a valid :class:`MixerConfig`, its recorded input
    layout differs from what this jaxden builds for that config, its features differ from
    ``expect_features``, or a parameter's shape does not fit the config.
    """
    from pathlib import Path

    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import config_diff, load_config
    from jaxden.errors import CheckpointError

    if isinstance(spec, str) and spec.partition(":")[0] == CLOSED_FORM_SPEC:
        return closed_form_mixer(spec)
    path = Path(spec)
    if not path.exists() and isinstance(spec, str):
        from jaxden.denoisers import WEIGHTS_DIR

        shipped = WEIGHTS_DIR / f"{spec}.msgpack"
        if shipped.is_file():
            path = shipped
    if not path.exists():
        raise CheckpointError(
            f"mixer {spec}: no such checkpoint folder or weights file (train one with "
            f"`jaxden train` and a config with model = \"mixer\")"
        )
    meta = read_checkpoint_meta(path)
    if meta.get("kind") != MIXER_KIND:
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind', 'unknown')!r} checkpoint (model "
            f"{meta.get('model')!r}), not a mixer; a denoiser goes to --denoiser"
        )
    try:
        config = load_config(dict(meta.get("model_config", {})), MixerConfig)
    except ConfigError as error:
        raise CheckpointError(
            f"{path}: its model_config is not a valid mixer config: {error}"
        ) from None
    layout = mixer_layout(config)
    stored = meta.get("layout")
    if stored is not None:
        differences = config_diff(stored, layout)
        if differences:
            raise CheckpointError(
                f"{path}: the recorded mixer input layout differs from the one this jaxden "
                f"builds for its config (stored -> built): {'; '.join(differences)}"
            )
    if expect_features is not None and tuple(expect_features) != tuple(config.features):
        raise CheckpointError(
            f"{path}: the mixer was trained on features {list(config.features)}, expected "
            f"{list(expect_features)}"
        )
    # Shapes only: the loader checks names and shapes against it and fills in the values.
    target = jax.eval_shape(lambda: mixer_init(jax.random.PRNGKey(0), config))
    expect = {"kind": MIXER_KIND, "model": MIXER_MODEL}
    params, _ = load_trained_params(path, target, expect=expect)
    return params, config


# ------------------------------------------------------------------------------ inference

_FROM_CONFIG = object()


def progressive_denoise(
    frame,
    denoiser,
    mixer_params,
    mixer_config: MixerConfig,
    key,
    *,
    num_probes: int = 4,
    tstat=_FROM_CONFIG,
    method: str = "auto",
    eps: float | None = None,
    probe_batch: int | None = None,
    nonfinite: str = "error",
    swap_average: bool | None = None,
):
    """The whole progressive-denoising pipeline on one frame (paper Fig. 6).

    y = D(x); SURE of y (jvp for JAX denoisers, finite differences for black boxes such as
    OIDN; :func:`jaxden.pdcache.denoise_with_sure`); alpha = mixer; alpha' = t-statistic
    scaling; z' = x + alpha' (y - x).

    Args:
      frame: :class:`jaxden.frame.Frame` (H, W, 3) (leading batch dims if the denoiser takes
        them) with colour and ``variance`` (the variance of the pixel mean; required) plus
        the features the denoiser uses.
      denoiser: a :class:`jaxden.denoisers.Denoiser` or a spec for
        :func:`jaxden.denoisers.load_denoiser` (``"oidn"``, a checkpoint folder, ...).
      mixer_params, mixer_config: from :func:`load_mixer` (or :func:`mixer_init`).
      key: PRNG key of the SURE probes.
      num_probes, method (``auto``/``jvp``/``fd``), eps (None: measured default),
        probe_batch: SURE options (:func:`jaxden.sure.sure`).
      tstat: :class:`TStatConfig`; default the mixer config's; None skips the scaling
        (the paper's "w/o t-test" ablation).
      nonfinite: ``"error"`` or ``"zero"`` (the authors' repair of NaN / negative variance).
      swap_average: average alpha with 1 - alpha of the swapped inputs (see
        :class:`MixerConfig`); None: the mixer config's ``swap_average``.

    Returns:
      ``(z_prime, alpha_prime, extras)``: output colour and the scaled alpha, (..., H, W, 3)
      float32 JAX arrays, and a dict with ``denoised``, ``sure``, ``divergence`` (var dy/dx),
      ``alpha`` (before scaling) and ``mixed`` (x + alpha (y - x), before scaling).

    Raises:
      FrameError: no variance (SURE needs it), negative or non-finite values, missing
        denoiser features. ConfigError: bad options.
    """
    from jaxden.pdcache import denoise_with_sure

    if tstat is _FROM_CONFIG:
        tstat = mixer_config.tstat
    if tstat is not None and not isinstance(tstat, TStatConfig):
        raise ConfigError(
            f"progressive_denoise: tstat must be a TStatConfig or None, got {tstat!r}"
        )
    result, frame = denoise_with_sure(
        denoiser, frame, key, num_probes=num_probes, method=method, eps=eps,
        probe_batch=probe_batch, nonfinite=nonfinite, where="progressive_denoise",
    )
    x = jnp.asarray(frame.color, jnp.float32)
    var = jnp.asarray(frame.variance, jnp.float32)
    y = jnp.asarray(result.denoised, jnp.float32)
    sure_map = jnp.asarray(result.sure, jnp.float32)
    if swap_average is None:
        swap_average = mixer_config.swap_average
    alpha = _inference_alpha(mixer_params, x, y, var, sure_map, mixer_config, bool(swap_average))
    mixed = _mix(x, y, alpha)
    if tstat is None:
        z_prime, alpha_prime = mixed, alpha
    else:
        t = _t_statistic(x, mixed, var, tstat)
        alpha_prime = _scale_alpha(alpha, t, tstat)
        z_prime = _mix(x, y, alpha_prime)
    extras = {
        "denoised": y,
        "sure": sure_map,
        "divergence": jnp.asarray(result.divergence_term, jnp.float32),
        "alpha": alpha,
        "mixed": mixed,
    }
    return z_prime, alpha_prime, extras


#: Mixers shipped in ``jaxden/weights/`` per denoiser name: ``{denoiser: weights name}``.
SHIPPED_MIXERS: dict[str, str] = {"oidn": "oidn-pd"}


def shipped_mixer_path(denoiser: str = "oidn"):
    """Path of the shipped mixer's .msgpack for ``denoiser``, or None if none ships."""
    from jaxden.denoisers import WEIGHTS_DIR

    name = SHIPPED_MIXERS.get(denoiser)
    if name is None:
        return None
    path = WEIGHTS_DIR / f"{name}.msgpack"
    return path if path.is_file() and path.with_suffix(".json").is_file() else None


def shipped_progressive_denoiser(denoiser: str = "oidn", *, seed: int = 0, num_probes: int = 4):
    """PD(denoiser) with the mixer shipped in the package, or None when none ships.

    Returns a function ``frame -> (z_prime, alpha_prime)`` (NumPy float32, (H, W, 3) each):
    :func:`progressive_denoise` with the shipped mixer (``jaxden/weights/oidn-pd.msgpack`` for
    OIDN; see its model card ``oidn-pd.md``), its t-statistic config, ``num_probes`` SURE
    probes drawn from ``PRNGKey(seed)``.
    """
    path = shipped_mixer_path(denoiser)
    if path is None:
        return None
    from jaxden.denoisers import load_denoiser

    params, config = load_mixer(str(path))
    model = load_denoiser(denoiser)
    key = jax.random.PRNGKey(seed)

    def run(frame):
        z, alpha, _ = progressive_denoise(frame, model, params, config, key,
                                          num_probes=num_probes)
        return np.asarray(z), np.asarray(alpha)

    return run


# ------------------------------------------------------------------------------ training

@functools.partial(jax.jit, static_argnames=("probability", "with_sure"))
def _swap_batch(key, x, y, var, sure, probability: float, with_sure: bool):
    """:func:`swap_inputs` with one key per sample (split from ``key``), (B, h, w, 3) each.

    Without SURE features (the "w/o SURE" ablation) only x and y are exchanged: the call
    passes var in both error slots, so var stays, and ``sure`` is returned unchanged.
    """
    keys = jax.random.split(key, x.shape[0])
    swap = jax.vmap(lambda k, a, b, c, d: swap_inputs(k, a, b, c, d, probability))
    x2, y2, var2, sure2, _ = swap(keys, x, y, var, sure if with_sure else var)
    return x2, y2, var2, sure2 if with_sure else sure


def mixer_task(train_config):
    """The :class:`jaxden.train.Task` that trains the mixer (``model = "mixer"``).

    ``train_config.model_config`` is a :class:`MixerConfig` table. Before training, the SURE
    cache of ``model_config.denoiser`` over the dataset is opened, and built (or finished)
    when missing and ``build_cache`` is true (:func:`jaxden.pdcache.build_sure_cache`; for
    OIDN on the default dataset a few minutes).

    Each batch: the loader's crops of the noisy frame (colour, variance) and the reference;
    :meth:`jaxden.pdcache.SureCache.crops_for` cuts the same windows (and symmetries) out of
    the cached denoised image and SURE map. Samples of the training split are swapped with
    :func:`swap_inputs` (probability ``swap_probability``) using a key derived from the seed
    and the batch (item ids and windows); batches are a pure function of (seed, step), so
    the swaps are too and a resumed run sees the same swaps. Validation batches are not
    swapped. Loss (``optim.loss``, SMAPE in the shipped configs) on z = x + alpha (y - x)
    against the reference; no t-statistic in training (paper).
    The logged ``val_baseline_loss`` is the denoiser output's loss (what the mixer must beat).
    """
    from jaxden.config import load_config
    from jaxden.data.layout import derive_seed
    from jaxden.pdcache import open_training_cache
    from jaxden.train import Task

    try:
        config = load_config(dict(train_config.model_config), MixerConfig)
    except ConfigError as error:
        raise ConfigError(f"[model_config] of model 'mixer': {error}") from None
    if config.kind != "network":
        raise ConfigError(
            f"[model_config] of model 'mixer': kind = {config.kind!r} has no parameters to "
            f"train; use it directly with --mixer {CLOSED_FORM_SPEC}"
        )
    if not train_config.data.dataset:
        raise ConfigError(
            "data.dataset must name a dataset folder (built by `jaxden dataset build`)"
        )
    cache = open_training_cache(train_config.data.dataset, config)
    swap_split = train_config.data.split
    seed = int(train_config.seed)

    def prepare(batch):
        if batch.input.variance is None:
            raise FrameError("mixer training needs the input variance (loader feature 'variance')")
        y, sure_map, windows = cache.crops_for(batch)
        x = np.asarray(batch.input.color, np.float32)
        var = np.asarray(batch.input.variance, np.float32)
        if config.swap_probability > 0 and all(cache.in_split(i, swap_split) for i in batch.items):
            swap_key = jax.random.PRNGKey(
                derive_seed(seed, "mixer-swap", list(batch.items), [list(w) for w in windows])
            )
            x, y, var, sure_map = _swap_batch(
                swap_key, x, y, var, sure_map, config.swap_probability, config.uses_sure
            )
        return {
            "x": np.asarray(x, np.float32),
            "y": np.asarray(y, np.float32),
            "var": np.asarray(var, np.float32),
            "sure": np.asarray(sure_map, np.float32),
            "reference": np.asarray(batch.reference.color, np.float32),
        }

    def predict(params, batch):
        alpha = _mixer_alpha(params, batch["x"], batch["y"], batch["var"], batch["sure"], config)
        return _mix(batch["x"], batch["y"], alpha)

    return Task(
        init=lambda key, batch: mixer_init(key, config),
        predict=predict,
        features=("color", "variance"),
        meta=_mixer_meta(config),
        prepare=prepare,
        target=lambda batch: batch["reference"],
        baseline=lambda batch: batch["y"],
    )


__all__ += [
    "CLOSED_FORM_SPEC",
    "MixerConfig",
    "closed_form_alpha",
    "closed_form_mixer",
    "load_mixer",
    "mixer_alpha",
    "mixer_apply",
    "mixer_init",
    "mixer_layout",
    "mixer_module",
    "mixer_task",
    "progressive_denoise",
    "save_mixer",
    "swap_symmetry",
]
