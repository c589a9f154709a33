"""The trainable tasks: a registered JAX denoiser, and the progressive-denoising mixer over a SURE
cache.
"""

from __future__ import annotations

import functools

import jax
import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.heads import _mix
from jaxden.progressive.inputs import swap_inputs
from jaxden.progressive.mixer import (
    CLOSED_FORM_SPEC,
    MixerConfig,
    _mixer_alpha,
    _mixer_meta,
    mixer_init,
)
from jaxden.train.config import TrainConfig
from jaxden.train.task import Task


def denoiser_task(config: TrainConfig) -> Task:
    """A registered (JAX) denoiser trained on (noisy frame -> reference colour)."""
    from jaxden.config import config_to_dict, load_config
    from jaxden.denoise.registry import get_definition

    definition = get_definition(config.model)
    if definition.init is None or not definition.differentiable:
        raise ConfigError(f"model '{config.model}' is not trainable (a black-box denoiser)")
    try:
        model_config = load_config(dict(config.model_config), definition.config_cls)
    except ConfigError as error:
        raise ConfigError(f"[model_config] of model '{config.model}': {error}") from None

    def predict(params, batch):
        return definition.apply(params, model_config, batch["input"])

    return Task(
        init=lambda key, batch: definition.init(key, model_config),
        predict=predict,
        features=tuple(definition.required(model_config)),
        meta={
            "kind": "denoiser",
            "model": config.model,
            "model_config": config_to_dict(model_config),
        },
        prepare=lambda batch: {"input": batch.input, "reference": batch.reference.color},
    )


def make_task(config: TrainConfig) -> Task:
    if config.model == "mixer":
        return mixer_task(config)
    return denoiser_task(config)


@functools.partial(jax.jit, static_argnames=("probability", "with_sure"))
def _swap_batch(key, x, y, var, sure, probability: float, with_sure: bool):
    """:func:`swap_inputs` with one key per sample (split from ``key``), (B, h, w, 3) each.

    Without SURE features (the "w/o SURE" ablation) only x and y are exchanged: the call
    passes var in both error slots, so var stays, and ``sure`` is returned unchanged.
    """
    keys = jax.random.split(key, x.shape[0])
    swap = jax.vmap(lambda k, a, b, c, d: swap_inputs(k, a, b, c, d, probability))
    x2, y2, var2, sure2, _ = swap(keys, x, y, var, sure if with_sure else var)
    return x2, y2, var2, sure2 if with_sure else sure


def mixer_task(train_config):
    """The :class:`jaxden.train.task.Task` that trains the mixer (``model = "mixer"``).

    ``train_config.model_config`` is a :class:`MixerConfig` table. Before training, the SURE
    cache of ``model_config.denoiser`` over the dataset is opened, and built (or finished)
    when missing and ``build_cache`` is true (:func:`jaxden.progressive.cache_build.build_sure_cache`; for
    OIDN on the default dataset a few minutes).

    Each batch: the loader's crops of the noisy frame (colour, variance) and the reference;
    :meth:`jaxden.progressive.cache.SureCache.crops_for` cuts the same windows (and symmetries) out of
    the cached denoised image and SURE map. Samples of the training split are swapped with
    :func:`swap_inputs` (probability ``swap_probability``) using a key derived from the seed
    and the batch (item ids and windows); batches are a pure function of (seed, step), so
    the swaps are too and a resumed run sees the same swaps. Validation batches are not
    swapped. Loss (``optim.loss``, SMAPE in the shipped configs) on z = x + alpha (y - x)
    against the reference; no t-statistic in training (paper).
    The logged ``val_baseline_loss`` is the denoiser output's loss (what the mixer must beat).
    """
    from jaxden.config import load_config
    from jaxden.data.layout import derive_seed
    from jaxden.progressive.cache_build import open_training_cache

    try:
        config = load_config(dict(train_config.model_config), MixerConfig)
    except ConfigError as error:
        raise ConfigError(f"[model_config] of model 'mixer': {error}") from None
    if config.kind != "network":
        raise ConfigError(
            f"[model_config] of model 'mixer': kind = {config.kind!r} has no parameters to "
            f"train; use it directly with --mixer {CLOSED_FORM_SPEC}"
        )
    if not train_config.data.dataset:
        raise ConfigError(
            "data.dataset must name a dataset folder (built by `jaxden dataset build`)"
        )
    cache = open_training_cache(train_config.data.dataset, config)
    swap_split = train_config.data.split
    seed = int(train_config.seed)

    def prepare(batch):
        if batch.input.variance is None:
            raise FrameError("mixer training needs the input variance (loader feature 'variance')")
        y, sure_map, windows = cache.crops_for(batch)
        x = np.asarray(batch.input.color, np.float32)
        var = np.asarray(batch.input.variance, np.float32)
        if config.swap_probability > 0 and all(cache.in_split(i, swap_split) for i in batch.items):
            swap_key = jax.random.PRNGKey(
                derive_seed(seed, "mixer-swap", list(batch.items), [list(w) for w in windows])
            )
            x, y, var, sure_map = _swap_batch(
                swap_key, x, y, var, sure_map, config.swap_probability, config.uses_sure
            )
        return {
            "x": np.asarray(x, np.float32),
            "y": np.asarray(y, np.float32),
            "var": np.asarray(var, np.float32),
            "sure": np.asarray(sure_map, np.float32),
            "reference": np.asarray(batch.reference.color, np.float32),
        }

    def predict(params, batch):
        alpha = _mixer_alpha(params, batch["x"], batch["y"], batch["var"], batch["sure"], config)
        return _mix(batch["x"], batch["y"], alpha)

    return Task(
        init=lambda key, batch: mixer_init(key, config),
        predict=predict,
        features=("color", "variance"),
        meta=_mixer_meta(config),
        prepare=prepare,
        target=lambda batch: batch["reference"],
        baseline=lambda batch: batch["y"],
    )
