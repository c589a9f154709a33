"""Tests for jaxden.train.losses: values by hand, analytic gradients, and consistency with metrics."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden import metrics
from jaxden.errors import FrameError
from jaxden.train import losses


def built_in_losses() -> dict:
    """jaxden's own losses (a plugin's, registered by another test file in this process, are
    not what these tests know the gradients of)."""
    from jaxden.registry import is_built_in

    return {name: loss for name, loss in losses.LOSSES.items()
            if is_built_in(losses.LOSSES.owner(name))}


@pytest.fixture
def rng():
    return np.random.default_rng(5)


X = np.array([[[1.0], [3.0]]], np.float32)  # (1, 2, 1): prediction
Y = np.array([[[2.0], [1.0]]], np.float32)  # target


def test_values_by_hand():
    np.testing.assert_allclose(losses.l1_loss(X, Y), 1.5, rtol=1e-6)
    np.testing.assert_allclose(losses.l2_loss(X, Y), 2.5, rtol=1e-6)
    np.testing.assert_allclose(losses.relmse_loss(X, Y), (1 / 4.01 + 4 / 1.01) / 2, rtol=1e-6)
    np.testing.assert_allclose(losses.relmse_sg_loss(X, Y), (1 / 1.01 + 4 / 9.01) / 2, rtol=1e-6)
    np.testing.assert_allclose(losses.smape_loss(X, Y), (1 / 3.01 + 2 / 4.01) / 2, rtol=1e-6)
    np.testing.assert_allclose(losses.smape_loss(X, Y, eps=0.5), (1 / 3.5 + 2 / 4.5) / 2, rtol=1e-6)


def test_gradients_analytic():
    x, y = X[0, :, 0], Y[0, :, 0]  # the two pixels, n = 2
    n = 2
    expected = {
        "l1": np.sign(x - y) / n,
        "l2": 2 * (x - y) / n,
        "relmse": 2 * (x - y) / (y**2 + 0.01) / n,
        "relmse_sg": 2 * (x - y) / (x**2 + 0.01) / n,  # no gradient through the denominator
        # the Deep Combiner's (jaxden.denoise.deep_combiner): the target's channel mean squared
        # in the denominator, here one channel
        "relmse_dc": 2 * (x - y) / (y**2 + 0.01) / n,
        # the neural James-Stein combiner's: relMSE of sign(v) log1p(|v|) of both images
        # (x, y > 0 here), the target's transformed channel mean squared in the denominator
        "relmse_njs": 2 * (np.log1p(x) - np.log1p(y)) / (1 + x) / (np.log1p(y) ** 2 + 0.01) / n,
        # d/dx |x-y| / (|x|+|y|+eps) = sign(x-y)/D - |x-y| sign(x) / D^2
        "smape": (
            np.sign(x - y) / (np.abs(x) + np.abs(y) + 0.01)
            - np.abs(x - y) * np.sign(x) / (np.abs(x) + np.abs(y) + 0.01) ** 2
        ) / n,
    }
    for name, loss in built_in_losses().items():
        grad = jax.jit(jax.grad(loss))(X, Y)
        np.testing.assert_allclose(grad[0, :, 0], expected[name], rtol=1e-5, err_msg=name)


def test_losses_are_batch_means_of_metrics(rng):
    x = rng.normal(0.5, 1.0, (3, 6, 7, 3)).astype(np.float32)
    y = rng.random((3, 6, 7, 3)).astype(np.float32)
    pairs = {"l1": metrics.mae, "l2": metrics.mse, "relmse": metrics.relmse, "smape": metrics.smape}
    for name, metric in pairs.items():
        np.testing.assert_allclose(
            losses.LOSSES[name](x, y), jnp.mean(metric(x, y)), rtol=1e-6, err_msg=name
        )
        # Over equal-size images the batch mean of per-image means is the plain mean.
        assert np.ndim(losses.LOSSES[name](x, y)) == 0


def test_zero_at_target_and_finite_gradient(rng):
    y = rng.random((4, 4, 3)).astype(np.float32)
    y[0, 0] = 0.0  # |x| and |x - y| at 0: the gradient must still be finite
    for name, loss in built_in_losses().items():
        assert float(loss(y, y)) == 0.0, name
        grad = jax.grad(loss)(y, y)
        assert np.all(np.isfinite(grad)), name


def test_relmse_sg_optimum_is_the_mean_of_a_skewed_noisy_target():
    """Fit one constant c to many draws of a firefly-like target r = mu * lognormal (mean mu).

    relmse_sg's gradient has zero mean at c = E[r], so 300 plain gradient steps from the
    median reach the sample mean (measured: to 2e-7); SMAPE stays at the median (0.61 x the
    mean) and target-normalised relMSE falls to 0.29 x the mean, which is why noisy Monte Carlo references bias them. Seed 11,
    20000 draws, sigma_log = 1 (mean / median = e^0.5 = 1.65).
    """
    rng = np.random.default_rng(11)
    sigma = 1.0
    r = (0.5 * np.exp(rng.normal(-sigma**2 / 2, sigma, 20000))).astype(np.float32)
    r = r.reshape(1, 200, 100, 1)
    mean = float(r.mean())

    def fit(loss, lr):
        def objective(c):
            return loss(jnp.full(r.shape, c), r)

        step = jax.jit(lambda c: c - lr * jax.grad(objective)(c))
        c = jnp.float32(np.median(r))  # start at the median, 0.6 x the mean
        for _ in range(300):
            c = step(c)
        return float(c)

    assert fit(losses.relmse_sg_loss, 0.02) == pytest.approx(mean, rel=1e-3)
    assert fit(losses.smape_loss, 0.2) < 0.8 * mean
    assert fit(losses.relmse_loss, 0.002) < 0.5 * mean


def test_short_aliases():
    assert losses.smape is losses.smape_loss and losses.relmse is losses.relmse_loss
    assert losses.relmse_sg is losses.relmse_sg_loss
    assert losses.l1 is losses.l1_loss and losses.l2 is losses.l2_loss


def test_shape_mismatch_raises():
    with pytest.raises(FrameError, match="same shape"):
        losses.smape_loss(np.zeros((4, 4, 3)), np.zeros((4, 4, 1)))


def test_log_ratio_loss_matches_numpy_and_is_scale_free_per_image(rng):
    target = rng.random((3, 6, 7, 3)).astype(np.float32) + 0.1
    # One error pattern for every image, at per-image scales (below).
    error = np.broadcast_to(rng.normal(0.0, 1.0, (1,) + target.shape[1:]), target.shape)
    base_error = np.broadcast_to(rng.normal(0.0, 1.0, (1,) + target.shape[1:]), target.shape)
    error, base_error = error.astype(np.float32), base_error.astype(np.float32)
    # Per-image error scales 100x apart: a 2-spp input beside a 4096-spp one.
    scales = np.array([1.0, 0.1, 0.01], np.float32).reshape(3, 1, 1, 1)
    prediction, baseline = target + 0.5 * scales * error, target + scales * base_error
    for name in ("l1", "l2"):
        per = {"l1": lambda a: np.mean(np.abs(a), axis=(1, 2, 3)),
               "l2": lambda a: np.mean(np.square(a), axis=(1, 2, 3))}[name]
        expected = np.mean(np.log(per(prediction.astype(np.float64) - target)
                                  / per(baseline.astype(np.float64) - target)))
        value = losses.log_ratio_loss(name, prediction, target, baseline)
        np.testing.assert_allclose(value, expected, rtol=1e-5, err_msg=name)
        # l1 and l2 are homogeneous in the error, so the per-image ratio, and with it the
        # loss, do not see the per-image scale: every image weighs the same.
        same = losses.log_ratio_loss(name, target + 0.5 * error, target, target + base_error)
        np.testing.assert_allclose(value, same, rtol=1e-5, err_msg=name)
        # ... whereas the plain mean is decided by the noisiest image.
        plain_grad = jax.grad(losses.LOSSES[name])(prediction, target)
        ratio_grad = jax.grad(losses.log_ratio_loss, argnums=1)(name, prediction, target,
                                                                 baseline)
        plain_norm = np.linalg.norm(np.asarray(plain_grad).reshape(3, -1) * scales.reshape(3, 1),
                                    axis=1)
        ratio_norm = np.linalg.norm(np.asarray(ratio_grad).reshape(3, -1) * scales.reshape(3, 1),
                                    axis=1)
        # Directional derivative along each image's own error scale: equal under log_ratio.
        np.testing.assert_allclose(ratio_norm / ratio_norm[0], 1.0, rtol=1e-4, err_msg=name)
        assert plain_norm[2] < 0.05 * plain_norm[0], name


def test_log_ratio_loss_has_no_gradient_through_the_baseline(rng):
    target = rng.random((2, 4, 4, 3)).astype(np.float32)
    baseline = target + 0.1
    grad = jax.grad(lambda b: losses.log_ratio_loss("smape", target + 0.2, target, b))(baseline)
    assert not np.any(np.asarray(grad))
    assert set(losses.PER_IMAGE) == set(losses.LOSSES)
