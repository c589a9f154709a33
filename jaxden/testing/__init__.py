"""Property-test helpers that users and jaxden's own tests share: is SURE unbiased for my
denoiser, is a mixer consistent, and the statistics to say so with a stated significance and
power.

Test SURE on your own denoiser (a JAX function of a :class:`jaxden.frame.Frame`)::

    import jax.numpy as jnp
    from jaxden.testing import check_sure_unbiased

    def my_denoiser(frame):                      # frame -> (H, W, 3), differentiable
        return 0.5 * frame.color + 0.5 * jnp.mean(frame.color, axis=(0, 1))

    print(check_sure_unbiased(my_denoiser))      # AssertionError if SURE is biased

On a built-in 16 x 16 frame (or pass your own clean ``frame``), seed 0, significance 1e-4, and
as many noisy draws as give power 0.99 against a divergence wrong by 10 %; the result states
the seed, the draws and the power reached. The same check rejects that denoiser with its
derivative made 10 % wrong (``scaled_colour_derivative(my_denoiser, 0.9)``).

- :mod:`~jaxden.testing.stats`: the z-test of a mean, its power, the draws a power needs;
- :mod:`~jaxden.testing.draws`: SURE and the true error over many noisy frames
  (:func:`sure_draws`, :class:`SureSampler`), compiled once;
- :mod:`~jaxden.testing.sure_check`: :func:`check_sure_unbiased`, the z-test of those draws;
- :mod:`~jaxden.testing.mixer_check`: :func:`check_mixer_consistent` (PD's error relative to
  MC's as the variance goes to 0);
- :mod:`~jaxden.testing.denoisers`: cheap JAX denoisers with a known flaw and the wrong-
  derivative wrapper;
- :mod:`~jaxden.testing.synthetic`: clean frames with every feature, and Monte Carlo noise;
- :mod:`~jaxden.testing.strategies`: Hypothesis strategies of frames and noise (imported on
  its own, ``from jaxden.testing import strategies``: Hypothesis is a test dependency, needed
  only when a strategy is built).
"""

from jaxden.testing.denoisers import (
    BiasedBlurConfig,
    biased_blur,
    box_blur,
    scaled_colour_derivative,
    shrink,
)
from jaxden.testing.draws import SureDraws, SureSampler, region_weights, sure_draws
from jaxden.testing.mixer_check import MixerCheck, check_mixer_consistent
from jaxden.testing.stats import (
    ZTest,
    p_value,
    power,
    relative_mean,
    required_draws,
    z_critical,
    z_score,
    z_test,
)
from jaxden.testing.sure_check import RegionCheck, SureCheck, check_sure_unbiased
from jaxden.testing.synthetic import NOISE_KINDS, monte_carlo_noise, synthetic_frame

__all__ = [
    "NOISE_KINDS",
    "BiasedBlurConfig",
    "MixerCheck",
    "RegionCheck",
    "SureCheck",
    "SureDraws",
    "SureSampler",
    "ZTest",
    "biased_blur",
    "box_blur",
    "check_mixer_consistent",
    "check_sure_unbiased",
    "monte_carlo_noise",
    "p_value",
    "power",
    "region_weights",
    "relative_mean",
    "required_draws",
    "scaled_colour_derivative",
    "shrink",
    "sure_draws",
    "synthetic_frame",
    "z_critical",
    "z_score",
    "z_test",
]
