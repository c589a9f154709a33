"""Task: the protocol between the training loop and what it trains (init, predict, target, baseline)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax


# ------------------------------------------------------------------------------------- tasks
@dataclasses.dataclass
class Task:
    """What a training run optimises.

    ``init(key, batch) -> params``; ``predict(params, batch) -> (B, h, w, 3)`` (pure JAX);
    ``features``: frame fields the loader must provide; ``meta``: the checkpoint record that
    identifies the model (kind, model, model_config); ``baseline(batch)``: the image the
    model should beat (the noisy input), for the log.
    """

    init: Callable[[jax.Array, Any], Any]
    predict: Callable[[Any, Any], jax.Array]
    features: tuple[str, ...]
    meta: dict[str, Any]
    prepare: Callable[[Any], Any] = lambda batch: batch  # host-side batch -> device pytree
    target: Callable[[Any], jax.Array] = lambda batch: batch["reference"]
    baseline: Callable[[Any], jax.Array] = lambda batch: batch["input"].color
