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

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.checks import check_same
from jaxden.progressive.closed_form import closed_form_alpha_unchecked

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
#:         are ~0.1), and the mixer cannot compare SURE with var there (measured:
#:         docs/history.md, "Defaults of the code").
#:   log   a signed log (LOG_FLOOR, LOG_SCALE): O(1) at every scale from 1e-7 to 1e4, and
#:         differences of features are log-ratios (log SURE - log var). Our addition.
INPUT_TRANSFORMS: dict[str, Callable] = {"atan": jnp.arctan, "log": _signed_log}


def mixer_channel_slices(features: tuple[str, ...] = MIXER_FEATURES) -> dict[str, slice]:
    """Channel slice of each feature in ``mixer_inputs(..., features=features)``."""
    check_mixer_features(features)
    return {
        name: slice(CHANNELS_PER_FEATURE * i, CHANNELS_PER_FEATURE * (i + 1))
        for i, name in enumerate(features)
    }


#: Layout of the full 18-channel input: hdr 0:3, den 3:6, var 6:9, sure 9:12,
#: residual 12:15, divergence 15:18.
MIXER_LAYOUT: dict[str, slice] = {
    name: slice(3 * i, 3 * (i + 1)) for i, name in enumerate(MIXER_FEATURES)
}


def check_mixer_features(features) -> None:
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


@functools.partial(jax.jit, static_argnames=("features", "transform", "closed_form_sigma",
                                             "closed_form_stops"))
def mixer_inputs_unchecked(x, y, var, sure, features, transform: str = "atan",
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
        "closed_form": lambda: closed_form_alpha_unchecked(x, y, var, sure, closed_form_sigma,
                                                           False, closed_form_stops),
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
    check_mixer_features(features)
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
    check_same("mixer_inputs", **arrays)
    x, y, var = jnp.asarray(x), jnp.asarray(y), jnp.asarray(var)
    sure = jnp.asarray(sure) if needs_sure else jnp.zeros_like(x)
    return mixer_inputs_unchecked(x, y, var, sure, features, transform, float(closed_form_sigma),
                                  None if closed_form_stops is None else float(closed_form_stops))


def swap_inputs(key, x, y, var, sure, probability: float = 0.5):
    """Training augmentation: swap (x, var) with (y, sure) per image with ``probability``.

    Shapes (B, H, W, 3) (or (H, W, 3), one draw). Returns ``(x', y', var', sure', swapped)``
    with ``swapped`` a bool array of shape (B,) (or ()). The target is unchanged: after a swap
    the mixer learns ``beta = 1 - alpha`` (paper Sec. 4.3).
    """
    check_same("swap_inputs", x=x, y=y, var=var, sure=sure)
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
