"""The optimiser: Adam with a one-cycle cosine (or constant) schedule, optional gradient clipping,
and the loss chosen by name.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import optax

from jaxden.errors import ConfigError
from jaxden.train.config import OptimConfig


# ------------------------------------------------------------------------------ optimisation
def make_schedule(optim: OptimConfig) -> optax.Schedule:
    if optim.schedule == "constant":
        return optax.constant_schedule(optim.learning_rate)
    return optax.cosine_onecycle_schedule(
        transition_steps=optim.steps,
        peak_value=optim.learning_rate,
        pct_start=max(optim.warmup_fraction, 1e-6),
        div_factor=25.0,
        final_div_factor=1e4,
    )


def make_optimizer(optim: OptimConfig) -> optax.GradientTransformation:
    parts = []
    if optim.grad_clip_norm is not None:
        parts.append(optax.clip_by_global_norm(optim.grad_clip_norm))
    parts.append(optax.adam(make_schedule(optim)))
    return optax.chain(*parts)


def loss_function(name: str, reduction: str = "mean") -> Callable[..., jax.Array]:
    """``loss(prediction, target, baseline=None) -> scalar``: loss ``name`` reduced over the
    batch by ``reduction`` ('mean', or 'log_ratio' against ``baseline``)."""
    from jaxden.train import losses

    loss = losses.get_loss(name)
    if reduction == "mean":
        return lambda prediction, target, baseline=None: loss(prediction, target)
    if reduction == "log_ratio":
        def log_ratio(prediction, target, baseline=None):
            if baseline is None:
                raise ValueError("the log_ratio loss needs the baseline image")
            return losses.log_ratio_loss(name, prediction, target, baseline)

        return log_ratio
    raise ConfigError(f"unknown loss reduction {reduction!r}; choose from mean, log_ratio")
