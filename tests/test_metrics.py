"""Tests for jaxden.metrics against hand-computed values and independent references."""

import jax
import numpy as np
import pytest
from scipy import ndimage

from jaxden import metrics
from jaxden.errors import FrameError


@pytest.fixture
def rng():
    return np.random.default_rng(99)


# Two 1 x 2 x 1 "images": estimate x = (1, 3), reference y = (2, 1); errors (-1, 2).
X = np.array([[[1.0], [3.0]]], np.float32)
Y = np.array([[[2.0], [1.0]]], np.float32)


def test_pixel_metrics_by_hand():
    np.testing.assert_allclose(metrics.mse(X, Y), (1 + 4) / 2, rtol=1e-6)
    np.testing.assert_allclose(metrics.rmse(X, Y), np.sqrt(2.5), rtol=1e-6)
    np.testing.assert_allclose(metrics.mae(X, Y), (1 + 2) / 2, rtol=1e-6)
    np.testing.assert_allclose(metrics.relmse(X, Y), (1 / 4.01 + 4 / 1.01) / 2, rtol=1e-6)
    np.testing.assert_allclose(metrics.smape(X, Y), (1 / 3.01 + 2 / 4.01) / 2, rtol=1e-6)
    np.testing.assert_allclose(metrics.relmse(X, Y, eps=1.0), (1 / 5 + 4 / 2) / 2, rtol=1e-6)
    np.testing.assert_allclose(metrics.smape(X, Y, eps=0.0), (1 / 3 + 2 / 4) / 2, rtol=1e-6)
    # relMSE normalises by the *reference*: swapping the arguments changes it.
    np.testing.assert_allclose(metrics.relmse(Y, X), (1 / 1.01 + 4 / 9.01) / 2, rtol=1e-6)


def test_per_image_reduction_over_batch(rng):
    x = rng.random((2, 3, 4, 5, 3)).astype(np.float32)
    y = rng.random((2, 3, 4, 5, 3)).astype(np.float32)
    for name in ("mse", "rmse", "mae", "relmse", "smape", "psnr"):
        fn = getattr(metrics, name)
        batched = np.asarray(fn(x, y))
        assert batched.shape == (2, 3), name
        np.testing.assert_allclose(batched[1, 2], fn(x[1, 2], y[1, 2]), rtol=1e-6, err_msg=name)
    # A metric is a plain function of arrays: it jits and accepts NumPy input.
    np.testing.assert_allclose(jax.jit(metrics.smape)(x, y), metrics.smape(x, y), rtol=1e-6)


def test_tonemap_and_psnr_by_hand():
    np.testing.assert_allclose(
        metrics.tonemap(np.array([-1.0, 0.0, 0.25, 1.0, 7.0])),
        [0.0, 0.0, 0.25 ** (1 / 2.2), 1.0, 1.0],
        rtol=1e-6,
    )
    # Display-space inputs with MSE 0.01 -> 20 dB.
    x = np.full((4, 4, 3), 0.5, np.float32)
    y = x + np.float32(0.1)
    np.testing.assert_allclose(metrics.psnr(x, y, tonemap_inputs=False), 20.0, rtol=1e-5)
    # Linear inputs 1.0 and 0.25: tone-mapped 1 and 0.25^(1/2.2) everywhere.
    expected = -10 * np.log10((1 - 0.25 ** (1 / 2.2)) ** 2)
    np.testing.assert_allclose(
        metrics.psnr(np.ones((4, 4, 3)), np.full((4, 4, 3), 0.25)), expected, rtol=1e-5
    )
    assert np.isinf(metrics.psnr(x, x))


def _scipy_ssim(x, y):
    """SSIM from SciPy's Gaussian filter (radius 5 -> 11 x 11, sigma 1.5), cropped to 'valid'."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)

    def blur(a):
        full = ndimage.gaussian_filter(a, sigma=(1.5, 1.5, 0), radius=(5, 5, 0), mode="constant")
        return full[5:-5, 5:-5]

    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    )
    return ssim_map.mean()


def test_ssim_matches_scipy_reference(rng):
    # Structured image (smooth gradient + squares) plus noise, in linear HDR-ish range.
    yy, xx = np.mgrid[0:40, 0:33] / 40.0
    clean = np.stack([xx, yy, 0.5 * (xx + yy)], axis=-1)
    clean[10:20, 5:15] = 1.5
    noisy = clean + 0.15 * rng.standard_normal(clean.shape)
    expected = _scipy_ssim(metrics.tonemap(noisy), metrics.tonemap(clean))
    assert 0.1 < expected < 0.95  # a non-trivial value
    np.testing.assert_allclose(metrics.ssim(noisy, clean), expected, rtol=1e-5)
    np.testing.assert_allclose(
        metrics.ssim(noisy, clean), metrics.ssim(clean, noisy), rtol=1e-6
    )  # symmetric
    np.testing.assert_allclose(metrics.ssim(clean, clean), 1.0, rtol=1e-6)
    batch = np.stack([noisy, clean])
    np.testing.assert_allclose(
        metrics.ssim(batch, np.stack([clean, clean])), [expected, 1.0], rtol=1e-5
    )


def test_ssim_decreases_with_noise(rng):
    clean = rng.random((32, 32, 3)) * 0.8
    values = [
        float(metrics.ssim(clean + s * rng.standard_normal(clean.shape), clean))
        for s in (0.01, 0.05, 0.2)
    ]
    assert values[0] > values[1] > values[2]


def test_noise_corrected_mse_is_unbiased(rng):
    # Truth t, a fixed estimate z, and references r = t + noise with known variance of the
    # mean var_r (varying per pixel). Over N independent references the mean of the
    # corrected MSE must match mse(z, t) within 4 standard errors, while the plain MSE is
    # off by mean(var_r) = many standard errors (so the test can fail).
    shape = (8, 8, 3)
    truth = rng.random(shape)
    estimate = truth + 0.1 * rng.standard_normal(shape)
    variance = rng.uniform(0.001, 0.05, shape)
    draws = 4000
    references = truth + np.sqrt(variance) * rng.standard_normal((draws,) + shape)
    corrected = np.asarray(
        metrics.noise_corrected_mse(
            np.broadcast_to(estimate, references.shape), references,
            np.broadcast_to(variance, references.shape),
        ),
        np.float64,
    )
    target = np.mean((estimate - truth) ** 2)
    standard_error = corrected.std(ddof=1) / np.sqrt(draws)
    assert abs(corrected.mean() - target) < 4 * standard_error
    plain = np.asarray(metrics.mse(np.broadcast_to(estimate, references.shape), references))
    assert abs(plain.mean() - target) > 20 * standard_error
    np.testing.assert_allclose(plain.mean() - corrected.mean(), variance.mean(), rtol=1e-5)


def test_flip_identity_and_monotone(rng):
    clean = rng.random((48, 48, 3)).astype(np.float32) * 2.0  # HDR: values above 1
    clean[10:20, 10:20] = 8.0
    assert float(metrics.flip(clean, clean)) == 0.0
    errors = [
        float(metrics.flip(np.abs(clean + s * rng.standard_normal(clean.shape)), clean))
        for s in (0.02, 0.2, 1.0)
    ]
    assert 0.0 < errors[0] < errors[1] < errors[2]
    ldr = np.clip(clean / 8.0, 0, 1)
    noisy = np.clip(ldr + 0.1 * rng.standard_normal(ldr.shape), 0, 1)
    assert float(metrics.flip(ldr, ldr, "LDR")) == 0.0
    assert float(metrics.flip(noisy, ldr, "LDR")) > 0.01


def test_flip_batches_and_maps(rng):
    reference = rng.random((2, 24, 24, 3)).astype(np.float32)
    estimate = np.abs(reference + 0.1 * rng.standard_normal(reference.shape)).astype(np.float32)
    means, maps = metrics.flip(estimate, reference, return_map=True)
    assert means.shape == (2,) and maps.shape == (2, 24, 24)
    np.testing.assert_allclose(means, maps.mean(axis=(1, 2)), rtol=1e-4)
    np.testing.assert_allclose(means[1], metrics.flip(estimate[1], reference[1]), rtol=1e-6)


def test_errors():
    with pytest.raises(FrameError, match=r"rmse: estimate and reference must have the same"):
        metrics.rmse(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(FrameError, match=r"\(\.\.\., H, W, C\)"):
        metrics.mse(np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(FrameError, match="at least 11 x 11"):
        metrics.ssim(np.zeros((10, 30, 3)), np.zeros((10, 30, 3)))
    with pytest.raises(FrameError, match="reference_variance must have"):
        metrics.noise_corrected_mse(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.zeros((4, 4, 1)))
    with pytest.raises(FrameError, match="dynamic_range must be"):
        metrics.flip(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), "hdr")
    bad = np.zeros((16, 16, 3), np.float32)
    bad[3, 4, 1] = np.nan
    with pytest.raises(FrameError, match="estimate has 1 non-finite"):
        metrics.flip(bad, np.zeros_like(bad))
