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
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxden.errors import ConfigError, JaxdenError
from jaxden.train.config import TrainConfig
from jaxden.train.optim import loss_function, make_optimizer, make_schedule
from jaxden.train.sharding import data_mesh, replicate, shard_batch
from jaxden.train.task import Task
from jaxden.train.tasks import make_task


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
            from jaxden.progressive.mixer import MixerConfig

            cls = MixerConfig
        else:
            from jaxden.denoise.registry import get_definition

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
