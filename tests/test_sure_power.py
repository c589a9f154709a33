"""SURE's unbiasedness tests with real power: heterogeneous images and per-pixel variances, and
mutation tests that the same z-test must reject.

Draws. Images and variances come from seeds (hypothesis draws the seed and the shape of the
distribution): a smooth random field plus per-pixel texture, and a per-pixel variance that is
log-uniform over two decades and partly follows the image (as Monte Carlo variance does), so
no two neighbouring pixels share a value. A test on arrays that repeat one value cannot see
a mistake in where the variance goes; these can.

The statistic is that of tests/test_sure_properties.py, drawn by jaxden.testing (``sure_draws``,
``z_score``): per noise draw, D = mean SURE - mean (F(x) - mu)^2, E[D] = 0 for a correct
estimator; |mean D| / stderr <= 4.5 over 512 draws (a correct estimator fails with probability
~7e-6).

Power. The broken estimators below shift E[D] by a known amount B (stated per test, as a sum
over the pixels: D's shift is B over their count); the z-test rejects when B / stderr > 4.5.
Each must-fail test asserts z > 8 on its fixed seed over 4096 draws (measured z is printed in
the assertion message), so the margin is not luck:
- a 10 % divergence bias: B = 0.2 sum var_i J_ii;
- the variance map shifted by one pixel: B = 2 sum (var_{i-1} - var_i) J_ii, nonzero because
  J_ii follows the (heterogeneous) variance;
- probes drawn with the image-mean variance: B = 2 sum (mean(var) - var_i) J_ii, likewise.
The denoiser for them is a per-pixel gain y_i = g_i x_i, g_i = (1 + var_i / max var) / 2
(J = diag g): the gain follows the variance, as a denoiser smooths more where the noise is
larger.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxden.frame import Frame
from jaxden.testing import sure_draws, z_score

SHAPE = (8, 8, 3)
DRAWS = 512
Z_LIMIT = 4.5
POWER_DRAWS = 4096  # the must-fail tests: z grows as sqrt(draws)
SETTINGS = settings(max_examples=6, deadline=None, derandomize=True)


def heterogeneous(seed: int, decades: float = 2.0, follow: float = 0.5):
    """(clean image, per-pixel variance of the mean), float32 (8, 8, 3): smooth field +
    texture; variance log-uniform over ``decades`` decades, a fraction ``follow`` of its log
    taken from the image."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0.1, 1.5, (3, 3, 3))
    smooth = np.kron(coarse, np.ones((3, 3, 1)))[:8, :8]
    clean = np.clip(smooth + 0.3 * rng.standard_normal(SHAPE), 0.01, None)
    own = rng.uniform(0.0, 1.0, SHAPE)
    brightness = (clean - clean.min()) / (np.ptp(clean) + 1e-9)
    level = (1 - follow) * own + follow * brightness
    var = 0.1 * 10.0 ** (-decades * (1.0 - level))
    return clean.astype(np.float32), var.astype(np.float32)


def gain(g, frame):
    """y_i = g_i x_i: linear, pixelwise, J = diag(g)."""
    return g * frame.color


def statistics(denoise_fn, params, clean, var, seed: int, mode: str = "correct",
               draws: int = DRAWS):
    """Per draw: (mean SURE, mean true squared error) for the correct estimator or a broken one
    (``mode``: "bias10", "shifted", "mean_probes"). The noise has the variance ``var``; SURE is
    told ``var`` or, broken, a shifted or flattened map (its probes and divergence follow what
    it is told) and its -var term always uses the true map."""
    told = {"correct": var, "bias10": var, "shifted": np.roll(var, 1, axis=1),
            "mean_probes": np.full_like(var, np.mean(var))}[mode]
    d = sure_draws(denoise_fn, Frame(color=np.asarray(clean), variance=np.asarray(told)),
                   draws=draws, batch=DRAWS, probes=4, method="jvp", seed=key(seed),
                   params=params, noise_variance=np.asarray(var))
    value = d.residual - float(np.mean(var, dtype=np.float64)) + 2.0 * d.divergence
    if mode == "bias10":
        value = value + 0.2 * d.divergence
    return value, d.truth


def key(seed):
    return jax.random.key(seed, impl="rbg")


@SETTINGS
@given(seed=st.integers(0, 2**31 - 1), decades=st.floats(0.5, 3.0), follow=st.floats(0.0, 1.0))
def test_correct_sure_is_unbiased_on_heterogeneous_draws(seed, decades, follow):
    clean, var = heterogeneous(seed, decades, follow)
    g = jnp.asarray(var / var.max())
    z = z_score(*statistics(gain, g, clean, var, seed))
    assert abs(z) <= Z_LIMIT, z


@functools.lru_cache(maxsize=1)
def _z_correct_at_power_draws() -> float:
    """The correct estimator's z on the must-fail tests' draws (the same key: computed once)."""
    clean, var = heterogeneous(11, decades=2.0, follow=0.5)
    g = 0.5 + 0.5 * var / var.max()
    return z_score(*statistics(gain, jnp.asarray(g), clean, var, 5, draws=POWER_DRAWS))


@pytest.mark.parametrize("mode, shift", [
    ("bias10", "0.2 sum var J"),
    ("shifted", "2 sum (var_{i-1} - var_i) J_ii"),
    ("mean_probes", "2 sum (mean var - var_i) J_ii"),
])
def test_broken_estimators_are_rejected(mode, shift):
    """Fixed seed; the expected shift of E[D] (``shift``) is computed and the measured z must
    exceed 8 in its direction."""
    clean, var = heterogeneous(11, decades=2.0, follow=0.5)
    g = 0.5 + 0.5 * var / var.max()
    expected = {"bias10": 0.2 * np.sum(var * g),
                "shifted": 2 * np.sum((np.roll(var, 1, axis=1) - var) * g),
                "mean_probes": 2 * np.sum((var.mean() - var) * g)}[mode]
    z_ok = _z_correct_at_power_draws()
    z_bad = z_score(*statistics(gain, jnp.asarray(g), clean, var, 5, mode=mode,
                                draws=POWER_DRAWS))
    assert abs(z_ok) <= Z_LIMIT, z_ok
    assert np.sign(z_bad) == np.sign(expected) and abs(z_bad) > 8.0, (z_bad, expected, shift)


def test_homogeneous_variance_cannot_see_a_shifted_variance_map():
    """Why the draws must be heterogeneous: with one variance everywhere, the shifted map is
    the same map and the broken estimator passes (the old tests' blind spot)."""
    clean, _ = heterogeneous(11)
    var = np.full(SHAPE, 0.05, np.float32)
    g = jnp.asarray(np.random.default_rng(0).uniform(0.2, 1.0, SHAPE).astype(np.float32))
    z = z_score(*statistics(gain, g, clean, var, 5, mode="shifted"))
    assert abs(z) <= Z_LIMIT, z


# ---------------------------------------------------------------- real JAX denoisers


def _frame_features(seed, size=16):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.2, 0.9, (size, size, 3)).astype(np.float32)
    normal = np.zeros((size, size, 3), np.float32)
    normal[..., 2] = 1.0
    depth = rng.uniform(1.0, 2.0, (size, size, 1)).astype(np.float32)
    clean = (albedo * rng.uniform(0.3, 1.2, (size, size, 1))).astype(np.float32)
    var = (0.02 * clean * rng.uniform(0.2, 2.0, (size, size, 3))).astype(np.float32)
    return clean, var, albedo, normal, depth


@pytest.mark.parametrize("name", ["wskp", "unet"])
def test_sure_is_unbiased_through_a_random_jax_denoiser(name):
    """A random (untrained) WSKP and U-Net: spatially mixing, nonlinear, with features; 256
    draws on 16 x 16. Correct SURE passes the z-test. For WSKP the same draws with the
    divergence term dropped are rejected (the test's power on it); the untrained small U-Net
    barely responds to its colour input (divergence near 0), so there that mutation is below
    detection and only unbiasedness is asserted."""
    from jaxden.denoise.registry import Denoiser, get_definition

    definition = get_definition(name)
    config = (definition.config_cls(num_layers=2, width=6, kernel_sizes=(3, 5))
              if name == "wskp" else definition.config_cls(
                  features=("hdr", "alb", "nrm"), encoder_widths=(4,) * 5, decoder_widths=(4,) * 5))
    model = Denoiser(definition, config, definition.init(jax.random.PRNGKey(3), config))
    clean, var, albedo, normal, depth = _frame_features(4)
    frame = Frame(color=clean, variance=var, albedo=albedo, normal=normal, depth=depth)
    draws = sure_draws(model, frame, draws=256, probes=2, method="jvp", seed=key(21))
    broken = draws.residual - float(np.mean(var, dtype=np.float64))
    assert abs(z_score(draws.sure, draws.truth)) <= Z_LIMIT
    if name == "wskp":
        assert abs(z_score(broken, draws.truth)) > 6.0
