"""Training: one entry point, ``train_and_evaluate(config, workdir)``, for every trainable model.

The loop is the flax-examples shape: a pure jitted ``train_step(state, batch) -> (state,
metrics)`` with the state's buffers donated, data-parallel over all local devices with
``jax.sharding`` (the batch is split along its first axis, parameters are replicated), an optax
Adam optimiser with a one-cycle cosine schedule, orbax checkpoints every ``checkpoint_every``
steps, a JSONL metrics log and a progress bar.

Resuming: batches are a pure function of (seed, step) (the loader's epoch plan), and the state
is restored from the newest checkpoint, so a killed run restarted with the same command
continues from the last checkpoint and reaches the same parameters as an uninterrupted run.

What is trained is a :class:`Task`: how to initialise parameters from a sample batch, how to
predict an image from (params, batch), and which image is the target. Denoisers from the
registry are one task; the progressive-denoising mixer is another (``jaxden.progressive``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxden.errors import ConfigError, JaxdenError


# ------------------------------------------------------------------------------------ config
@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Which dataset and how batches are drawn from it."""

    dataset: str = ""  # a dataset folder built by `jaxden dataset build`
    split: str = "train"
    val_split: str = "val"
    crop_size: int = 64
    batch_size: int = 8
    spp: tuple[int, ...] | None = None  # None: every input spp level of the dataset
    augment: bool = True


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    steps: int = 1000
    learning_rate: float = 1e-3  # the peak of the one-cycle schedule
    schedule: Literal["onecycle", "constant"] = "onecycle"
    warmup_fraction: float = 0.05
    loss: Literal["smape", "relmse", "relmse_sg", "l1", "l2"] = "smape"
    # How the per-image losses of a batch become one number: "mean" (the plain mean over
    # every pixel) or "log_ratio" (the mean of log(loss_i / loss_i(baseline)), the baseline
    # being the task's image to beat: every image weighs the same, whatever its noise level;
    # jaxden.losses.log_ratio_loss).
    loss_reduction: Literal["mean", "log_ratio"] = "mean"
    grad_clip_norm: float | None = None

    def __post_init__(self):
        if self.steps < 1:
            raise ConfigError(f"optim.steps must be >= 1, got {self.steps}")
        if not self.learning_rate > 0:
            raise ConfigError(f"optim.learning_rate must be > 0, got {self.learning_rate}")
        if not 0 <= self.warmup_fraction < 1:
            raise ConfigError(f"optim.warmup_fraction must be in [0, 1), got {self.warmup_fraction}")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """A training run. ``model`` names a registered denoiser (or 'mixer'); ``model_config``
    holds that model's own options (validated against its config class)."""

    model: str = "wskp"
    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    seed: int = 0
    log_every: int = 10
    eval_every: int = 200
    eval_batches: int = 8
    checkpoint_every: int = 200
    keep_checkpoints: int = 2

    def __post_init__(self):
        for name in ("log_every", "eval_every", "eval_batches", "checkpoint_every", "keep_checkpoints"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1, got {getattr(self, name)}")


def load_train_config(source, overrides=()) -> TrainConfig:
    """Load a training config and check its ``model`` and ``[model_config]`` now, so that a
    typo there is reported with the file's name before any work starts."""
    from jaxden.config import load_config

    config = load_config(source, TrainConfig, overrides)
    where = f"{source}: " if isinstance(source, (str, os.PathLike)) else ""
    if config.model == "mixer":
        from jaxden.progressive import MixerConfig

        config_cls = MixerConfig
    else:
        from jaxden.denoisers import get_definition

        try:
            config_cls = get_definition(config.model).config_cls
        except ConfigError as error:
            raise ConfigError(f"{where}model = {config.model!r}: {error} (or 'mixer')") from None
    if config_cls is not None:
        try:
            load_config(dict(config.model_config), config_cls)
        except ConfigError as error:
            raise ConfigError(f"{where}[model_config] of model '{config.model}': {error}") from None
    return config


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


def denoiser_task(config: TrainConfig) -> Task:
    """A registered (JAX) denoiser trained on (noisy frame -> reference colour)."""
    from jaxden.config import config_to_dict, load_config
    from jaxden.denoisers import get_definition

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
        from jaxden.progressive import mixer_task

        return mixer_task(config)
    return denoiser_task(config)


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
    from jaxden import losses

    table = losses.LOSSES
    if name not in table:
        raise ConfigError(f"unknown loss {name!r}; choose from {', '.join(table)}")
    if reduction == "mean":
        return lambda prediction, target, baseline=None: table[name](prediction, target)
    if reduction == "log_ratio":
        def log_ratio(prediction, target, baseline=None):
            if baseline is None:
                raise ValueError("the log_ratio loss needs the baseline image")
            return losses.log_ratio_loss(name, prediction, target, baseline)

        return log_ratio
    raise ConfigError(f"unknown loss reduction {reduction!r}; choose from mean, log_ratio")


@jax.tree_util.register_dataclass
@dataclasses.dataclass
class TrainState:
    params: Any
    opt_state: Any
    step: jax.Array


def make_train_step(task: Task, optimizer: optax.GradientTransformation, loss_fn):
    """The pure step: (state, batch) -> (state, {'loss', 'baseline_loss'})."""

    def objective(params, batch):
        prediction = task.predict(params, batch)
        return loss_fn(prediction, task.target(batch), task.baseline(batch))

    def train_step(state: TrainState, batch) -> tuple[TrainState, dict[str, jax.Array]]:
        loss, grads = jax.value_and_grad(objective)(state.params, batch)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics = {"loss": loss, "grad_norm": optax.global_norm(grads)}
        return TrainState(params, opt_state, state.step + 1), metrics

    return train_step


def make_eval_step(task: Task, loss_fn):
    def eval_step(params, batch) -> dict[str, jax.Array]:
        prediction = task.predict(params, batch)
        target = task.target(batch)
        baseline = task.baseline(batch)
        return {"loss": loss_fn(prediction, target, baseline),
                "baseline_loss": loss_fn(baseline, target, baseline)}

    return eval_step


# --------------------------------------------------------------------------------- sharding
def data_mesh(devices=None) -> jax.sharding.Mesh:
    devices = np.asarray(devices if devices is not None else jax.devices())
    return jax.sharding.Mesh(devices, ("data",))


def shard_batch(batch: Any, mesh: jax.sharding.Mesh) -> Any:
    """Place a host batch on the mesh, split along the first axis of every array."""
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    count = mesh.devices.size

    def put(array):
        array = np.asarray(array)
        if array.ndim == 0:
            return jax.device_put(array, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
        if array.shape[0] % count:
            raise ConfigError(
                f"batch size {array.shape[0]} must be a multiple of the number of devices ({count})"
            )
        return jax.device_put(array, spec)

    return jax.tree_util.tree_map(put, batch)


def replicate(tree: Any, mesh: jax.sharding.Mesh) -> Any:
    return jax.device_put(tree, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))


# ------------------------------------------------------------------------------------ loop
def _loaders(config: TrainConfig, task: Task):
    from jaxden.data.loader import DatasetLoader

    data = config.data
    if not data.dataset:
        raise ConfigError("data.dataset must name a dataset folder (built by `jaxden dataset build`)")
    common = dict(
        crop_size=data.crop_size,
        spp=data.spp,
        features=tuple(dict.fromkeys(("color",) + task.features)),
        reference_features=("color",),
    )
    train = DatasetLoader(
        data.dataset, data.split, data.batch_size, seed=config.seed, augment=data.augment, **common
    )
    val = DatasetLoader(
        data.dataset, data.val_split, data.batch_size, seed=config.seed + 1, augment=False,
        shuffle=False, drop_last=False, **common,
    )
    return train, val


def batches_from(loader, start_step: int) -> Iterator[Any]:
    """Batches for steps start_step, start_step + 1, ... (epochs are pure functions of the seed)."""
    per_epoch = len(loader)
    epoch, skip = divmod(start_step, per_epoch)
    while True:
        for index, batch in enumerate(loader.epoch(epoch)):
            if index >= skip:
                yield batch
        epoch, skip = epoch + 1, 0


class MetricsLog:
    """Append-only JSONL log; entries of steps beyond a resumed checkpoint are dropped first."""

    def __init__(self, path: Path, resume_step: int):
        self.path = path
        if path.exists():
            kept = [
                line for line in path.read_text().splitlines()
                if line.strip() and json.loads(line).get("step", 0) <= resume_step
            ]
            path.write_text("".join(line + "\n" for line in kept))

    def write(self, record: dict[str, Any]) -> None:
        with open(self.path, "a") as handle:
            handle.write(json.dumps(record) + "\n")


def evaluate(eval_step, params, loader, mesh, max_batches: int, prepare) -> dict[str, float]:
    totals: dict[str, float] = {}
    count = 0
    for index, batch in enumerate(loader.epoch(0)):
        if index >= max_batches:
            break
        prepared = prepare(batch)
        if np.shape(jax.tree_util.tree_leaves(prepared)[0])[0] % mesh.devices.size:
            continue  # a last partial batch that does not split over the devices
        metrics = eval_step(params, shard_batch(prepared, mesh))
        for key, value in metrics.items():
            totals[key] = totals.get(key, 0.0) + float(value)
        count += 1
    if not count:
        raise JaxdenError("the validation split produced no batch that fits the device count")
    return {f"val_{key}": value / count for key, value in totals.items()}


def _resolved_model_config(config: TrainConfig, saved: Any) -> Any:
    """A checkpoint's recorded model_config with today's defaults filled in (None if it no
    longer loads), so that adding a config field with a default keeps old runs resumable."""
    from jaxden.config import config_to_dict, load_config

    if not isinstance(saved, dict):
        return None
    try:
        if config.model == "mixer":
            from jaxden.progressive import MixerConfig

            cls = MixerConfig
        else:
            from jaxden.denoisers import get_definition

            cls = get_definition(config.model).config_cls
        return config_to_dict(load_config(dict(saved), cls))
    except (ConfigError, TypeError, ValueError):
        return None


def train_and_evaluate(
    config: TrainConfig, workdir: str | os.PathLike, *, progress: bool = True, stop_after: int | None = None
) -> dict[str, Any]:
    """Train (or resume) in ``workdir``; returns the final evaluation metrics.

    ``stop_after``: stop after this many steps of this call (for tests of resumption).
    """
    from jaxden.checkpoint import Checkpointer
    from jaxden.config import config_diff, config_to_dict, dump_config, load_config

    workdir = Path(workdir)
    if workdir.exists() and not workdir.is_dir():
        raise ConfigError(f"--workdir {workdir} is a file, not a folder")
    resolved = config_to_dict(config)
    config_file = workdir / "config.toml"
    saved_json = workdir / "config.json"
    if saved_json.exists():
        previous = json.loads(saved_json.read_text())
        with contextlib.suppress(ConfigError, TypeError, ValueError):
            # Today's defaults for fields added since the run started (same run).
            previous = config_to_dict(load_config(previous, TrainConfig))
        differences = config_diff(previous, resolved)
        if differences:
            raise ConfigError(
                f"{workdir} holds a run with another config ({'; '.join(differences[:5])}); "
                f"use a new --workdir"
            )

    # Everything the config can get wrong fails here, before the workdir records the config
    # (a failed start must not leave a workdir that refuses the corrected config).
    task = make_task(config)
    loss_fn = loss_function(config.optim.loss, config.optim.loss_reduction)
    optimizer = make_optimizer(config.optim)
    train_loader, val_loader = _loaders(config, task)
    mesh = data_mesh()
    if config.data.batch_size % mesh.devices.size:
        raise ConfigError(
            f"data.batch_size {config.data.batch_size} must be a multiple of the {mesh.devices.size} devices"
        )

    key = jax.random.PRNGKey(config.seed)
    first = task.prepare(next(iter(train_loader.epoch(0))))
    params = task.init(key, first)
    state = TrainState(params, optimizer.init(params), jnp.asarray(0, jnp.int32))

    workdir.mkdir(parents=True, exist_ok=True)
    if not saved_json.exists():
        from jaxden.fileio import atomic_write_text

        atomic_write_text(config_file, dump_config(config, header="resolved training config"))
        atomic_write_text(saved_json, json.dumps(resolved, indent=2))
    meta = {**task.meta, "train_config": resolved}
    checkpointer = Checkpointer(workdir, max_to_keep=config.keep_checkpoints)
    start = 0
    if checkpointer.latest_step() is not None:
        expect = {k: task.meta[k] for k in ("kind", "model", "model_config")}
        saved = checkpointer.read_meta().get("model_config")
        if saved != expect["model_config"] and _resolved_model_config(config, saved) == \
                expect["model_config"]:
            # Saved before a config field with a default was added: the same model.
            expect["model_config"] = saved
        state, _ = checkpointer.restore(state, expect=expect)
        start = int(state.step)
    state = replicate(state, mesh)

    train_step = jax.jit(make_train_step(task, optimizer, loss_fn), donate_argnums=0)
    eval_step = jax.jit(make_eval_step(task, loss_fn))
    log = MetricsLog(workdir / "metrics.jsonl", start)
    schedule = make_schedule(config.optim)
    end = config.optim.steps if stop_after is None else min(config.optim.steps, start + stop_after)

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=config.optim.steps, initial=start, desc=f"train {config.model}", unit="step")
    last_eval: dict[str, float] = {}
    if start == 0:  # where the curve starts: the untrained model on the validation split
        initial = evaluate(eval_step, state.params, val_loader, mesh, config.eval_batches, task.prepare)
        log.write({"step": 0, **initial})
    tick = time.perf_counter()
    batches = batches_from(train_loader, start)
    for step in range(start, end):
        batch = shard_batch(task.prepare(next(batches)), mesh)
        state, metrics = train_step(state, batch)
        done = step + 1
        if done % config.log_every == 0 or done == end:
            loss = float(metrics["loss"])
            if not math.isfinite(loss):
                raise JaxdenError(f"training diverged at step {done}: loss {loss}; lower optim.learning_rate")
            now = time.perf_counter()
            log.write({"step": done, "loss": loss, "grad_norm": float(metrics["grad_norm"]),
                       "lr": float(schedule(step)), "seconds": now - tick})
            tick = now
            if bar is not None:
                bar.set_postfix(loss=f"{loss:.4g}")
        if done % config.eval_every == 0 or done == config.optim.steps:
            last_eval = evaluate(eval_step, state.params, val_loader, mesh, config.eval_batches, task.prepare)
            log.write({"step": done, **last_eval})
        if done % config.checkpoint_every == 0 or done == end:
            checkpointer.save(done, state, meta)
        if bar is not None:
            bar.update(1)
    checkpointer.wait()
    checkpointer.close()
    if bar is not None:
        bar.close()
    if not last_eval:
        last_eval = evaluate(eval_step, state.params, val_loader, mesh, config.eval_batches, task.prepare)
    return {"step": end, **last_eval}
