"""What ``model = NAME`` trains: one name -> :class:`Trainable` table over every registered
denoiser (:mod:`jaxden.denoise.registry`), the progressive-denoising mixer over a SURE cache and
the neural James-Stein combiner over its cache (``njs``: :mod:`jaxden.train.njs_task`).

A :class:`Trainable` is a config class for ``[model_config]``, a training task (init and
predict through :class:`~jaxden.train.task.Task`), the kind of checkpoint it writes, and
optionally a hook for data that several runs share (the mixer's SURE cache). The training
loop, ``load_train_config`` and sweeps look a model up here and never branch on its name.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxden.denoise.njs_model import NJS_KIND, NJS_MODEL, NJSModelConfig
from jaxden.errors import ConfigError, FrameError
from jaxden.progressive.inputs import swap_inputs
from jaxden.progressive.mixer_checkpoints import MIXER_KIND, MIXER_MODEL, mixer_meta
from jaxden.progressive.mixer_config import CLOSED_FORM_SPEC, MixerConfig
from jaxden.progressive.network import mixer_apply, mixer_init
from jaxden.registry import Registry
from jaxden.train.njs_task import njs_model_apply, njs_model_init, njs_shared_data, njs_task
from jaxden.train.task import Task


# -------------------------------------------------------------------------------- the table
@dataclasses.dataclass(frozen=True)
class SharedData:
    """Data that several runs read (a SURE cache): ``key`` identifies it (runs with equal keys
    share it), ``prepare()`` builds, finishes or confirms it."""

    key: str
    prepare: Callable[[], None]


@dataclasses.dataclass(frozen=True)
class Trainable:
    """An entry of the table: ``config_cls`` validates ``[model_config]``;
    ``init(key, model_config) -> params`` and ``apply(params, model_config, ...)`` are the
    model's pure functions (a denoiser's ``apply(params, config, frame) -> image``, the
    mixer's :func:`~jaxden.progressive.mixer.mixer_apply`); ``task(train_config) -> Task``
    trains it; ``kind``: what its checkpoints hold (their meta record's ``kind``:
    ``"denoiser"``, ``"mixer"`` or ``"buffer-denoiser"``); ``shared_data(train_config,
    model_config)``: the :class:`SharedData` the run reads, or None (None: the model never
    has any)."""

    name: str
    kind: str
    config_cls: type
    init: Callable[..., Any] | None
    apply: Callable[..., Any]
    task: Callable[[Any], Task]
    shared_data: Callable[[Any, Any], SharedData | None] | None = None


#: Trainable models that are not denoisers: the mixer, and those plugins register
#: (:func:`register_trainable`). Every registered JAX denoiser is trainable too.
TRAINABLES: Registry = Registry("trainable model")
_REGISTER_PLUMBING = True  # registrations through this module belong to their caller


def register_trainable(trainable: Trainable, *, owner: str | None = None) -> Trainable:
    """Add a trainable model that is not a registered denoiser (a denoiser is trainable as
    soon as it is registered with an ``init``); a name that a built-in or another module
    holds, as a trainable model or a denoiser, is refused in one line."""
    from jaxden.denoise.registry import REGISTRY
    from jaxden.registry import caller_module, check_free

    if not isinstance(trainable, Trainable):
        raise ConfigError(f"register_trainable() takes a Trainable, got "
                          f"{type(trainable).__name__}")
    owner = owner or caller_module()
    check_free(trainable.name, "trainable model", owner, REGISTRY)
    return TRAINABLES.add(trainable.name, trainable, owner)


def trainables() -> dict[str, Trainable]:
    """The name -> :class:`Trainable` table: every registered denoiser (black boxes too: their
    task refuses to train them, naming why), the mixer and the plugins' trainable models."""
    from jaxden.denoise.registry import REGISTRY
    from jaxden.registry import PluginClashError

    table = {name: Trainable(name, "denoiser", definition.config_cls, definition.init,
                             definition.apply, denoiser_task)
             for name, definition in REGISTRY.items()}
    for name, trainable in TRAINABLES.items():
        if name in table and REGISTRY.owner(name) != TRAINABLES.owner(name):
            raise PluginClashError(REGISTRY.clash_message(name, REGISTRY.owner(name),
                                                          TRAINABLES.owner(name)))
        table[name] = trainable
    return table


def get_trainable(name: str) -> Trainable:
    """The table's entry for ``name`` (plugins named by ``JAXDEN_PLUGINS`` or entry points
    are imported first); ConfigError listing the names if there is none."""
    table = trainables()
    if name not in table:
        from jaxden.plugins import load_ambient

        load_ambient()
        table = trainables()
    if name not in table:
        raise ConfigError(f"unknown model {name!r}; the trainable models: "
                          f"{', '.join(sorted(table))} (a model of your own: name its module "
                          f"with --plugin, JAXDEN_PLUGINS or plugins = [...], "
                          f"docs/your-denoiser.md)")
    return table[name]


def model_config(train_config) -> Any:
    """``train_config.model_config`` validated into its model's config class (a ConfigError
    names the model and the key)."""
    from jaxden.config import load_config

    trainable = get_trainable(train_config.model)
    try:
        return load_config(dict(train_config.model_config), trainable.config_cls)
    except ConfigError as error:
        raise ConfigError(f"[model_config] of model '{train_config.model}': {error}") from None


def make_task(config) -> Task:
    """The :class:`Task` that trains ``config.model``."""
    return get_trainable(config.model).task(config)


# ------------------------------------------------------------------------------- denoisers
def denoiser_task(config) -> Task:
    """A registered (JAX) denoiser trained on (noisy frame -> reference colour)."""
    from jaxden.config import config_to_dict
    from jaxden.denoise.registry import get_definition

    definition = get_definition(config.model)
    if definition.init is None or not definition.differentiable:
        raise ConfigError(f"model '{config.model}' is not trainable (a black-box denoiser)")
    options = model_config(config)

    def predict(params, batch):
        return definition.apply(params, options, batch["input"])

    return Task(
        init=lambda key, batch: definition.init(key, options),
        predict=predict,
        features=tuple(definition.required(options)),
        meta={
            "kind": "denoiser",
            "model": config.model,
            "model_config": config_to_dict(options),
        },
        prepare=lambda batch: {"input": batch.input, "reference": batch.reference.color},
    )


# ----------------------------------------------------------------------------------- mixer
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
    from jaxden.data.layout import derive_seed
    from jaxden.progressive.cache_build import open_training_cache

    config = model_config(train_config)
    if config.kind == "network":
        from jaxden.progressive.network import get_mixer_network

        get_mixer_network(config.network)  # before any data is read: a ConfigError
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
        z, _ = mixer_apply(params, config, batch["x"], batch["y"], batch["var"], batch["sure"])
        return z

    return Task(
        init=lambda key, batch: mixer_init(key, config),
        predict=predict,
        features=("color", "variance"),
        meta=mixer_meta(config),
        prepare=prepare,
        target=lambda batch: batch["reference"],
        baseline=lambda batch: batch["y"],
    )


#: The MixerConfig fields that decide its SURE cache (with the dataset): the SURE
#: settings as one value.
_CACHE_FIELDS = ("denoiser", "cache", "sure", "build_cache")


def mixer_shared_data(train_config, config: MixerConfig) -> SharedData | None:
    """A mixer network's SURE cache over its dataset (None for a closed-form mixer or no
    dataset): keyed by the dataset, the denoiser and the SURE settings; prepared by
    :func:`jaxden.progressive.cache_build.open_training_cache`."""
    dataset = train_config.data.dataset
    if not dataset or config.kind != "network":
        return None
    key = json.dumps([str(Path(dataset).absolute()),
                      *(getattr(config, name) for name in _CACHE_FIELDS)],
                     default=lambda value: (dataclasses.asdict(value)  # the SURE settings
                                            if dataclasses.is_dataclass(value) else str(value)))

    def prepare() -> None:
        from jaxden.progressive.cache_build import open_training_cache

        open_training_cache(dataset, config)

    return SharedData(key, prepare)


MIXER = register_trainable(
    Trainable(MIXER_MODEL, MIXER_KIND, MixerConfig, mixer_init, mixer_apply, mixer_task,
              mixer_shared_data), owner=__name__)


def _njs_shared_data(train_config, config: NJSModelConfig) -> SharedData | None:
    """The neural James-Stein combiner's cache (:func:`jaxden.train.njs_task.njs_shared_data`)."""
    shared = njs_shared_data(train_config, config)
    return None if shared is None else SharedData(*shared)


NJS = register_trainable(
    Trainable(NJS_MODEL, NJS_KIND, NJSModelConfig, njs_model_init, njs_model_apply, njs_task,
              _njs_shared_data), owner="jaxden.train.njs_task")
