"""Training losses: scalar, differentiable, jit-able; definitions shared with metrics.py.

Each loss takes ``(prediction, target)`` of shape (..., H, W, C) (any leading batch
dimensions) and returns a scalar: the per-image metric from :mod:`jaxden.metrics` averaged over
the batch (equal image sizes, so this is the plain mean over every element). ``eps`` defaults
to 0.01, as in OIDN, progressive denoising and WSKP.

Gradients are taken through the whole expression, denominator included (for SMAPE the
``|prediction|`` term), as in the authors' PyTorch losses; the target gets gradients too if
it is traced, so pass it as a constant (or ``jax.lax.stop_gradient`` it) when training.
At ``prediction == target`` |x - y| has a subgradient; JAX returns sign(0) = 0 there.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxden import metrics


def l1_loss(prediction, target):
    """Mean absolute error over all elements: scalar."""
    return jnp.mean(metrics.mae(prediction, target))


def l2_loss(prediction, target):
    """Mean squared error over all elements: scalar."""
    return jnp.mean(metrics.mse(prediction, target))


def relmse_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of (x - y)^2 / (y^2 + eps) with y the target: scalar."""
    return jnp.mean(metrics.relmse(prediction, target, eps))


def relmse_sg_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of (x - y)^2 / (sg(x)^2 + eps), sg = stop_gradient: scalar.

    relMSE normalised by the prediction instead of the target, with no gradient through the
    denominator (Lehtinen et al. 2018, Noise2Noise, Sec. 3.3, for Monte Carlo targets). With a
    noisy reference y = mu + n, E[n] = 0, the gradient 2 (x - y) / (sg(x)^2 + eps) has zero
    mean exactly at x = mu, so reference noise does not move the optimum; ``relmse`` (target
    in the denominator) and ``smape`` both pull x below mu where the reference noise is skewed
    (fireflies).
    """
    pred, target = metrics._pair(prediction, target, "relmse_sg")
    scale = jnp.square(jax.lax.stop_gradient(pred)) + eps
    return jnp.mean(jnp.square(pred - target) / scale)


def smape_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of |x - y| / (|x| + |y| + eps): scalar (WSKP's and PDNet's training loss)."""
    return jnp.mean(metrics.smape(prediction, target, eps))


# Short aliases (jaxden.train looks losses up as losses.smape, losses.relmse, ...).
l1 = l1_loss
l2 = l2_loss
relmse = relmse_loss
relmse_sg = relmse_sg_loss
smape = smape_loss

LOSSES = {
    "l1": l1_loss,
    "l2": l2_loss,
    "relmse": relmse_loss,
    "relmse_sg": relmse_sg_loss,
    "smape": smape_loss,
}

__all__ = [
    "LOSSES", "l1", "l1_loss", "l2", "l2_loss", "relmse", "relmse_loss", "relmse_sg",
    "relmse_sg_loss", "smape", "smape_loss",
]
