"""What ``model = "njs"`` trains: the neural James-Stein combiner's network over a frozen base,
on the inputs its cache holds (:mod:`jaxden.train.njs_cache`).

The loader (``data.dataset``, half A of every item) gives each batch's crops of half A's
colour and variance (to find the window and symmetry it cut) and of the reference; the cache
gives the same windows of the combined colour, its variance, olsA and olsB
(:meth:`jaxden.train.njs_cache.NJSCache.crops_for`). The step trains
``njs_apply(..., clamp=False)`` (:func:`jaxden.denoise.njs.njs_apply`; the authors train
unclamped) against the reference with ``optim.loss`` (``relmse_njs`` in the shipped config);
the logged baseline is the combined noisy colour. The checkpoints record
:func:`jaxden.denoise.njs_model.njs_meta` (kind ``buffer-denoiser``, the config with the
base's spec and digest), so a run folder is a whole model for
:func:`jaxden.denoise.njs_model.load_njs`.

The cache is the run's shared data (:func:`njs_shared_data`): keyed by both datasets, the
base and the cross-regression settings, built once before runs that share it start.
:mod:`jaxden.train.tasks` registers the entry; this module does not import it.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxden.denoise.njs_model import (
    NJSModelConfig,
    njs_meta,
    njs_model_apply,
    njs_model_init,
)
from jaxden.errors import ConfigError, FrameError
from jaxden.train.task import Task

#: The NJSModelConfig fields that decide its cache (with the two datasets).
CACHE_FIELDS = ("base", "base_sha256", "cache", "build_cache", "train_bandwidth",
                "ols_window", "ols_ridge")


def njs_config(train_config) -> NJSModelConfig:
    """``train_config.model_config`` as an :class:`NJSModelConfig` (a ConfigError names the
    model and the key)."""
    from jaxden.config import load_config

    try:
        return load_config(dict(train_config.model_config), NJSModelConfig)
    except ConfigError as error:
        raise ConfigError(f"[model_config] of model 'njs': {error}") from None


def _dataset(train_config) -> str:
    if not train_config.data.dataset:
        raise ConfigError("data.dataset must name a dataset folder (built by `jaxden dataset "
                          "build`): the A halves; model_config.replica the B halves")
    return train_config.data.dataset


def njs_task(train_config) -> Task:
    """The :class:`~jaxden.train.task.Task` that trains ``model = "njs"`` (module docstring);
    opens (building or finishing, with ``build_cache``) its cache first."""
    from jaxden.train.njs_cache import open_njs_cache

    config = njs_config(train_config)
    cache = open_njs_cache(_dataset(train_config), config)

    def prepare(batch):
        if batch.input.variance is None:
            raise FrameError("NJS training needs the input variance (loader feature "
                             "'variance') to find each crop in its cache")
        inputs = cache.crops_for(batch)
        return {**inputs, "reference": np.asarray(batch.reference.color, np.float32)}

    def predict(params, batch):
        return njs_model_apply(params, config, batch["noisy"], batch["variance"],
                               batch["ols_a"], batch["ols_b"], clamp=False)

    return Task(
        init=lambda key, batch: njs_model_init(key, config),
        predict=predict,
        features=("color", "variance"),
        meta=njs_meta(config),
        prepare=prepare,
        target=lambda batch: batch["reference"],
        baseline=lambda batch: batch["noisy"],
    )


def njs_shared_data(train_config, config: NJSModelConfig):
    """``(key, prepare)`` of the run's cache (None without a dataset): keyed by both
    datasets, the base and the cross-regression settings; ``prepare()`` builds, finishes or
    confirms it (:func:`jaxden.train.njs_cache.open_njs_cache`)."""
    dataset = train_config.data.dataset
    if not dataset:
        return None
    key = json.dumps(["njs", str(Path(dataset).absolute()),
                      str(Path(config.replica).absolute()) if config.replica else "",
                      *(getattr(config, name) for name in CACHE_FIELDS)], default=str)

    def prepare() -> None:
        from jaxden.train.njs_cache import open_njs_cache

        open_njs_cache(dataset, config)

    return key, prepare


__all__ = ["CACHE_FIELDS", "njs_config", "njs_model_apply", "njs_model_init",
           "njs_shared_data", "njs_task"]
