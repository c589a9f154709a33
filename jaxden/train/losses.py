"""Training losses: scalar, differentiable, jit-able; definitions shared with metrics.py.

Each loss takes ``(prediction, target)`` of shape (..., H, W, C) (any leading batch
dimensions) and returns a scalar: the per-image metric from :mod:`jaxden.metrics` averaged over
the batch (equal image sizes, so this is the plain mean over every element). ``eps`` defaults
to 0.01, as in OIDN, progressive denoising and WSKP. :func:`log_ratio_loss` reduces the
per-image losses (:data:`PER_IMAGE`) differently: the mean of their log ratios to a baseline
image (training option ``optim.loss_reduction = "log_ratio"``).

Gradients are taken through the whole expression, denominator included (for SMAPE the
``|prediction|`` term), as in the authors' PyTorch losses; the target gets gradients too if
it is traced, so pass it as a constant (or ``jax.lax.stop_gradient`` it) when training.
At ``prediction == target`` |x - y| has a subgradient; JAX returns sign(0) = 0 there.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp

from jaxden import metrics
from jaxden.errors import ConfigError
from jaxden.registry import Registry


def l1_loss(prediction, target):
    """Mean absolute error over all elements: scalar."""
    return jnp.mean(metrics.mae(prediction, target))


def l2_loss(prediction, target):
    """Mean squared error over all elements: scalar."""
    return jnp.mean(metrics.mse(prediction, target))


def relmse_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of (x - y)^2 / (y^2 + eps) with y the target: scalar."""
    return jnp.mean(metrics.relmse(prediction, target, eps))


def _relmse_sg_per_image(prediction, target, eps: float = metrics.EPS):
    pred, target = metrics._pair(prediction, target, "relmse_sg")
    scale = jnp.square(jax.lax.stop_gradient(pred)) + eps
    return jnp.mean(jnp.square(pred - target) / scale, axis=(-3, -2, -1))


def relmse_sg_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of (x - y)^2 / (sg(x)^2 + eps), sg = stop_gradient: scalar.

    relMSE normalised by the prediction instead of the target, with no gradient through the
    denominator (Lehtinen et al. 2018, Noise2Noise, Sec. 3.3, for Monte Carlo targets). With a
    noisy reference y = mu + n, E[n] = 0, the gradient 2 (x - y) / (sg(x)^2 + eps) has zero
    mean exactly at x = mu, so reference noise does not move the optimum; ``relmse`` (target
    in the denominator) and ``smape`` both pull x below mu where the reference noise is skewed
    (fireflies).
    """
    return jnp.mean(_relmse_sg_per_image(prediction, target, eps))


def smape_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of |x - y| / (|x| + |y| + eps): scalar (WSKP's and PDNet's training loss)."""
    return jnp.mean(metrics.smape(prediction, target, eps))


def signed_log(x):
    """``sign(x) log(1 + |x|)``: a logarithmic range compression that keeps the sign (the
    Neural James-Stein combiner's training transform). Its JAX derivative at 0 is 0 (that of
    ``sign`` times ``log1p |x|``, as TensorFlow's, which the authors trained with)."""
    return jnp.sign(x) * jnp.log1p(jnp.abs(x))


def _relmse_njs_per_image(prediction, target, eps: float = metrics.EPS):
    pred, target = metrics._pair(prediction, target, "relmse_njs")
    pred, target = signed_log(pred), signed_log(target)
    scale = jnp.square(jnp.mean(target, axis=-1, keepdims=True)) + eps
    return jnp.mean(jnp.square(pred - target) / scale, axis=(-3, -2, -1))


def relmse_njs_loss(prediction, target, eps: float = metrics.EPS):
    """Mean of (x' - y')^2 / (mean_c(y')^2 + eps) with x' = :func:`signed_log` of the prediction,
    y' of the target, and mean_c the mean over the channels (one value per pixel): scalar.

    The training loss of the Neural James-Stein combiner (Gu et al. 2022, ``main.py``
    ``train_step``): relMSE with the target's channel mean in the denominator, as the Deep
    Combiner's ``relmse_dc``, on log-compressed images (a firefly costs about its log).
    """
    return jnp.mean(_relmse_njs_per_image(prediction, target, eps))


# Short aliases (jaxden.train looks losses up as losses.smape, losses.relmse, ...).
l1 = l1_loss
l2 = l2_loss
relmse = relmse_loss
relmse_njs = relmse_njs_loss
relmse_sg = relmse_sg_loss
smape = smape_loss

#: Every loss by name: ``loss(prediction, target) -> scalar``, the mean over the batch of
#: its per-image form (:data:`PER_IMAGE`); jaxden's own and those of plugins
#: (:func:`register_loss`).
LOSSES: Registry = Registry("loss")
#: The same losses per image, (..., H, W, C) -> (...): for reductions other than the plain
#: mean (``log_ratio_loss``).
PER_IMAGE: dict[str, Callable] = {}
_REGISTER_PLUMBING = True  # registrations through this module belong to their caller


def register_loss(name: str, per_image: Callable, loss: Callable | None = None, *,
                  owner: str | None = None) -> Callable:
    """Add a training loss: ``per_image(prediction, target) -> (...,)`` over (..., H, W, C)
    images (what the ``log_ratio`` reduction and masked validation means use), and
    ``loss(prediction, target) -> scalar`` (default: the mean of ``per_image``, which is the
    mean over every pixel for images of one size). A name that jaxden or another module holds
    is refused in one line. Then ``optim.loss = NAME`` in a train config."""
    from jaxden.registry import caller_module

    owner = owner or caller_module()
    if loss is None:
        def loss(prediction, target):
            return jnp.mean(per_image(prediction, target))
    LOSSES.add(name, loss, owner)
    PER_IMAGE[name] = per_image
    return loss


def get_loss(name: str, where: str = "loss") -> Callable:
    """The loss called ``name`` (plugins named by ``JAXDEN_PLUGINS`` or entry points are
    imported first); ConfigError naming the registered losses otherwise."""
    if LOSSES.find(name) is None:
        raise ConfigError(f"{where}: unknown loss {name!r}; the losses: {', '.join(LOSSES)} "
                          f"(a loss of your own: jaxden.train.losses.register_loss in a plugin "
                          f"module)")
    return LOSSES[name]


for _name, _loss, _per_image in (("l1", l1_loss, metrics.mae), ("l2", l2_loss, metrics.mse),
                                 ("relmse", relmse_loss, metrics.relmse),
                                 ("relmse_sg", relmse_sg_loss, _relmse_sg_per_image),
                                 ("relmse_njs", relmse_njs_loss, _relmse_njs_per_image),
                                 ("smape", smape_loss, metrics.smape)):
    register_loss(_name, _per_image, _loss, owner=__name__)
del _name, _loss, _per_image

#: Floor inside the logarithms of :func:`log_ratio_loss` (a perfect image has loss 0).
LOG_RATIO_FLOOR = 1e-12


def log_ratio_loss(name: str, prediction, target, baseline):
    """Mean over images of log(loss_i(prediction) / loss_i(baseline)): scalar.

    ``loss_i`` is the per-image form of loss ``name`` (:data:`PER_IMAGE`); exp of the result is
    the geometric mean over the batch of the per-image ratio to a baseline (for the mixer:
    the denoised image y it must beat). Its gradient is that of each image's loss divided by
    the image's own loss, so an input at 4096 spp, whose SMAPE is tens of times smaller than
    at 2 spp, pulls as hard as one at 2 spp; with the plain mean the low-spp inputs decide.
    The baseline carries no gradient (it is a constant of the batch).
    """
    per_image = PER_IMAGE[name]
    floor = LOG_RATIO_FLOOR
    base = jax.lax.stop_gradient(per_image(baseline, target))
    return jnp.mean(jnp.log(per_image(prediction, target) + floor) - jnp.log(base + floor))


__all__ = [
    "LOSSES",
    "PER_IMAGE",
    "get_loss",
    "l1",
    "l1_loss",
    "l2",
    "l2_loss",
    "log_ratio_loss",
    "register_loss",
    "relmse",
    "relmse_loss",
    "relmse_njs",
    "relmse_njs_loss",
    "relmse_sg",
    "relmse_sg_loss",
    "signed_log",
    "smape",
    "smape_loss",
]
