"""Denoisers for property checks: cheap JAX denoisers with a known flaw, and a wrapper that gets a
denoiser's derivative wrong on purpose (to show that a check has power against that flaw).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from jaxden.denoise.registry import Denoiser, DenoiserDef
from jaxden.errors import ConfigError


def box_blur(color, radius: int = 1):
    """The (2 radius + 1)^2 box mean of (..., H, W, C), per channel, edges replicated: linear,
    spatially mixing, d y_i / d x_i = 1 / (2 radius + 1)^2 away from the edges."""
    size = 2 * radius + 1
    pad = [(0, 0)] * (color.ndim - 3) + [(radius, radius), (radius, radius), (0, 0)]
    padded = jnp.pad(color, pad, mode="edge")
    height, width = color.shape[-3], color.shape[-2]
    total = sum(padded[..., i:i + height, j:j + width, :]
                for i in range(size) for j in range(size))
    return total / float(size * size)


def shrink(frame, tau: float = 0.1):
    """A smooth, nonlinear, spatially mixing JAX denoiser ``frame -> (..., H, W, 3)``: deviations
    d of x from its 3 x 3 mean m are shrunk, ``y = m + d - tau tanh(d / tau)`` (small d, noise,
    goes to m; large d, edges, passes less ``tau``). ``d y_i / d x_i = 1/9 + (8/9) tanh^2(d_i /
    tau)`` lies between 1/9 and 1, so the divergence depends on x and SURE's jvp matters."""
    mean = box_blur(frame.color, 1)
    deviation = frame.color - mean
    return mean + deviation - tau * jnp.tanh(deviation / tau)


def scaled_colour_derivative(denoise_fn, factor):
    """``denoise_fn`` (``frame -> image``) with the same values and its derivative with respect
    to the colour multiplied by ``factor`` (a number or an array broadcasting to the colour),
    through ``jax.custom_jvp``: a denoiser whose jvp, hence the divergence SURE computes by
    ``method="jvp"``, is wrong by ``factor - 1`` while its output is right. (SURE by finite
    differences sees the true derivative: the values are unchanged.) Derivatives with respect
    to the other frame fields are kept.

    ``scaled_colour_derivative(f, 0.9)`` is the mutant that :func:`check_sure_unbiased` must
    reject: its SURE is ``0.2 var J_ii`` too low per pixel, a 10 % error of the divergence
    term.
    """

    @jax.custom_jvp
    def of_colour(color, rest):
        return denoise_fn(rest.replace(color=color))

    @of_colour.defjvp
    def _scaled_jvp(primals, tangents):
        color, rest = primals
        color_tangent, rest_tangent = tangents
        return jax.jvp(lambda c, r: denoise_fn(r.replace(color=c)), (color, rest),
                       (jnp.asarray(factor, color.dtype) * color_tangent, rest_tangent))

    @functools.wraps(denoise_fn)
    def scaled(frame):
        return of_colour(frame.color, frame)

    return scaled


# ---------------------------------------------------------------- a denoiser with a fixed bias


@dataclasses.dataclass(frozen=True)
class BiasedBlurConfig:
    """``y = (1 + gain_bias) * box_blur(x, radius)``: a box blur (a bias where the image is not
    flat) whose output is also off by a constant factor ``1 + gain_bias`` (a bias everywhere:
    it does not vanish as the variance does, which is what a consistency check needs)."""

    radius: int = 1
    gain_bias: float = 0.1

    def __post_init__(self):
        if not isinstance(self.radius, int) or self.radius < 0:
            raise ConfigError(f"BiasedBlurConfig.radius must be an integer >= 0, got "
                              f"{self.radius!r}")


def _biased_blur_apply(params, config: BiasedBlurConfig, frame):
    return (1.0 + config.gain_bias) * box_blur(frame.color, config.radius)


#: The definition of :func:`biased_blur` (not registered: a test fixture, not a method).
BIASED_BLUR = DenoiserDef(
    name="testing-biased-blur",
    description="box blur times (1 + gain_bias): a cheap JAX denoiser with a fixed bias",
    config_cls=BiasedBlurConfig,
    required=lambda config: (),
    apply=_biased_blur_apply,
)


def biased_blur(radius: int = 1, gain_bias: float = 0.1) -> Denoiser:
    """A :class:`jaxden.denoise.Denoiser` (differentiable, no parameters, colour only) whose
    output is ``(1 + gain_bias)`` times the ``(2 radius + 1)^2`` box mean of the colour: a
    bias that stays as the variance goes to 0 (see :class:`BiasedBlurConfig`)."""
    return Denoiser(BIASED_BLUR, BiasedBlurConfig(radius=radius, gain_bias=gain_bias), None)
