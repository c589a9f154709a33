"""Training: one entry point, ``train_and_evaluate(config, workdir)``, for every trainable model.

The loop is the flax-examples shape: a pure jitted ``train_step(state, batch) -> (state,
metrics)`` with the state's buffers donated, data-parallel over all local devices with
``jax.sharding`` (the batch is split along its first axis, parameters are replicated), an optax
Adam optimiser with a one-cycle cosine schedule, orbax checkpoints every ``checkpoint_every``
steps, a JSONL metrics log and a progress bar. A checkpoint's meta record holds the task's
record, the training config and the features of the training data (``trained_features``:
:mod:`jaxden.data.features`).

Validation (:func:`evaluate`) is the mean over every example of the validation split (its
first ``eval_batches`` batches), the same numbers on any device count: a batch that does not
split over the devices is padded and the padding weighs nothing. Training batches are not
padded: the loop uses the most devices that split ``data.batch_size`` evenly.

Resuming: batches are a pure function of (seed, step) (the loader's epoch plan), and the state
is restored from the newest checkpoint, so a killed run restarted with the same command
continues from the last checkpoint and reaches the same parameters as an uninterrupted run.
A workdir is locked while a run trains in it; a diverged state (NaN / inf) is never saved;
Ctrl-C lets a checkpoint being written finish.

Several processes (hosts): after :func:`jaxden.distributed.initialize` the same call in every
process trains one model over the devices of all of them. The global batch (``data.batch_size``)
is split over every device; each process reads only its rows of each batch; process 0 alone
writes the workdir (which every process must see: a shared filesystem). The result equals one
process with the same devices and global batch (tests/test_distributed.py). Data that runs
share is prepared first (:func:`prepare_shared_data`; sweeps call it before dispatching runs).

What is trained is a :class:`Task`: how to initialise parameters from a sample batch, how to
predict an image from (params, batch), and which image is the target. The model's entry in
:mod:`jaxden.train.tasks` makes it (every registered denoiser, and the progressive-denoising
mixer); the loop never branches on the model. The workdir's bookkeeping (lock, recorded
config, metrics log) is :mod:`jaxden.train.workdir`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
import os
import signal
import sys
import threading
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
from jaxden.train.sharding import (
    data_mesh,
    host_value,
    pad_to_devices,
    process_rows,
    replicate,
    shard_batch,
)
from jaxden.train.task import Task
from jaxden.train.tasks import get_trainable, make_task, model_config
from jaxden.train.workdir import (
    MetricsLog,
    check_workdir,
    claim_workdir,
    has_checkpoint,
    recorded_init,
    remove_partial_checkpoints,
    resume_expectation,
)


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
    """The pure evaluation step: (params, batch, weights) -> {'loss', 'baseline_loss'}, each
    the sum over the batch of the per-example loss times the example's weight (0 for the
    padding rows of :func:`evaluate`).

    An example's loss is ``loss_fn`` on a batch of that one example. Every loss (and the
    log-ratio reduction) is the mean over a batch of one value per image, and the crops of a
    loader have one size, so the mean of these values over any set of examples is that set's
    loss as one batch: per image equals per pixel here."""

    def one(prediction, target, baseline):
        return loss_fn(prediction[None], target[None], baseline[None])

    each = jax.vmap(one)

    def eval_step(params, batch, weights) -> dict[str, jax.Array]:
        prediction = task.predict(params, batch)
        target = task.target(batch)
        baseline = task.baseline(batch)
        per_example = {"loss": each(prediction, target, baseline),
                       "baseline_loss": each(baseline, target, baseline)}
        # where, not a product alone: a padding row never brings a NaN into the sum
        return {key: jnp.sum(jnp.where(weights > 0, values * weights, 0.0))
                for key, values in per_example.items()}

    return eval_step


# ------------------------------------------------------------------------------------ loop
def _loaders(config: TrainConfig, task: Task):
    from jaxden.data.loader import DatasetLoader

    data = config.data
    if not data.dataset:
        raise ConfigError("data.dataset must name a dataset folder (built by `jaxden dataset build`)")
    if data.target_spp is not None and (config.optim.loss not in ("l2", "relmse_sg")
                                        or config.optim.loss_reduction != "mean"):
        import warnings

        warnings.warn(
            f"data.target_spp trains against noisy targets, but optim.loss = "
            f"{config.optim.loss!r} with reduction {config.optim.loss_reduction!r} is biased by "
            f"their noise (only 'l2' and 'relmse_sg' with 'mean' are not)", stacklevel=2)
    common = {
        "crop_size": data.crop_size,
        "spp": data.spp,
        "features": tuple(dict.fromkeys(("color",) + task.features)),
        "reference_features": ("color",),
    }
    train = DatasetLoader(
        data.dataset, data.split, data.batch_size, seed=config.seed, augment=data.augment,
        target_spp=data.target_spp, **common
    )
    val = DatasetLoader(
        data.dataset, data.val_split, data.batch_size, seed=config.seed + 1, augment=False,
        shuffle=False, drop_last=False, **common,
    )
    return train, val


def batches_from(loader, start_step: int, mesh=None) -> Iterator[Any]:
    """Batches for steps start_step, start_step + 1, ... (epochs are pure functions of the seed).

    With ``mesh`` in a multi-process job: this process's rows of each batch only."""
    per_epoch = len(loader)
    epoch, skip = divmod(start_step, per_epoch)
    while True:
        for index, (batch, _) in enumerate(epoch_batches(loader, epoch, mesh)):
            if index >= skip:
                yield batch
        epoch, skip = epoch + 1, 0


def epoch_batches(loader, epoch: int, mesh=None) -> Iterator[tuple[Any, int]]:
    """``(batch, global size)`` for every batch of ``loader.epoch(epoch)``.

    One process: the loader's batches. Several (``mesh`` spans them): only the rows this
    process's devices take (:func:`jaxden.train.sharding.process_rows`), read alone, so each
    process loads its share; ``None`` for a batch that does not split over the mesh (every
    process skips it)."""
    if mesh is None or jax.process_count() == 1:
        for batch in loader.epoch(epoch):
            yield batch, len(batch.items)
        return
    for draws in loader.batch_draws(epoch):
        rows = process_rows(len(draws), mesh)
        yield (None if rows is None else loader.read(draws[rows])), len(draws)


def evaluate(eval_step, params, loader, mesh, max_batches: int, prepare) -> dict[str, float]:
    """``val_NAME``: the mean of each metric of ``eval_step`` over every example of the first
    ``max_batches`` batches of ``loader``'s epoch 0 (the whole split when it has no more).

    The numbers do not depend on the device count (to float rounding): a batch that does not
    split over the mesh, a short last one or a split smaller than one batch, is padded with
    copies of its last example that weigh 0 (:func:`jaxden.train.sharding.pad_to_devices`), and
    the weighted sums are divided by the number of real examples, so a short batch weighs by
    its examples. Nor on the batch size when the split fits in ``max_batches`` batches: the
    validation loader's draws (order, windows) are per example, whatever the batch size.
    Several processes: each reads and prepares only its rows of every padded batch."""
    several = jax.process_count() > 1
    totals: dict[str, float] = {}
    count = 0
    for draws in itertools.islice(loader.batch_draws(0), max_batches):
        draws, weights = pad_to_devices(draws, mesh.devices.size)
        size = len(draws)
        rows = process_rows(size, mesh) if several else slice(None)
        batch = shard_batch(prepare(loader.read(draws[rows])), mesh, size)
        sums = eval_step(params, batch, shard_batch(weights[rows], mesh, size))
        for key, value in sums.items():
            totals[key] = totals.get(key, 0.0) + float(host_value(value))
        count += int(weights.sum())
    if not count:  # the loader refuses an empty split; a guard against dividing by zero
        raise JaxdenError("the validation split produced no example")
    return {f"val_{key}": value / count for key, value in totals.items()}


# ------------------------------------------------------------------------- shared data
def _shared_data(config: TrainConfig):
    """The :class:`jaxden.train.tasks.SharedData` of the run (None when it reads none)."""
    trainable = get_trainable(config.model)
    if trainable.shared_data is None:
        return None
    return trainable.shared_data(config, model_config(config))


def shared_data_key(config: TrainConfig) -> str | None:
    """What identifies the data a run reads that other runs may share (a mixer's SURE cache:
    dataset, denoiser and SURE settings); None when the run needs none."""
    shared = _shared_data(config)
    return None if shared is None else shared.key


def prepare_shared_data(config: TrainConfig, *, progress: bool = True) -> None:
    """Build (or finish, or just confirm) the data that several runs share, before they start
    (its model's hook in :mod:`jaxden.train.tasks`; a mixer's SURE cache:
    :func:`jaxden.progressive.cache_build.open_training_cache`). Runs started afterwards find
    it complete and only read it. Raises what preparing it raises (an incomplete cache with
    ``build_cache = false``, another dataset's cache, ...)."""
    shared = _shared_data(config)
    if shared is not None:
        shared.prepare()


# ------------------------------------------------------------------------- reliability
@jax.jit
def _all_finite(tree) -> jax.Array:
    leaves = [jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


def check_finite_state(state: TrainState, step: int, last_saved: int | None) -> None:
    """Raise (one line, naming the step and the first bad array) unless every value of the
    parameters and of the optimiser state is finite: a checkpoint is never written from a
    diverged state."""
    tree = {"params": state.params, "opt_state": state.opt_state}
    if bool(host_value(_all_finite(tree))):
        return
    where = "the state"
    for name in ("params", "opt_state"):  # the parameters first: they go bad first
        bad = [jax.tree_util.keystr(path)
               for path, leaf in jax.tree_util.tree_leaves_with_path(tree[name])
               if np.issubdtype(host_value(leaf).dtype, np.inexact)
               and not np.isfinite(host_value(leaf)).all()]
        if bad:
            where = name + bad[0]
            break
    kept = f"the last checkpoint (step {last_saved}) is kept" if last_saved else \
        "no checkpoint was saved"
    raise JaxdenError(
        f"training diverged by step {step}: {where} holds NaN or inf, so checkpoint {step} was "
        f"not written ({kept}); lower optim.learning_rate or set optim.grad_clip_norm"
    )


class HoldInterrupts:
    """Ctrl-C inside the block is held until the block ends, then raised: orbax never sees a
    KeyboardInterrupt half-way through writing or finishing a checkpoint."""

    def __enter__(self):
        self.pending = False
        self.previous = None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._hold)
        return self

    def _hold(self, signum, frame) -> None:
        self.pending = True

    def __exit__(self, kind, value, traceback) -> None:
        if self.previous is None:
            return
        signal.signal(signal.SIGINT, self.previous)
        if self.pending and kind is None:
            if callable(self.previous):
                self.previous(signal.SIGINT, None)  # the default handler raises KeyboardInterrupt
            elif self.previous == signal.SIG_DFL:
                raise KeyboardInterrupt


def _training_mesh(batch_size: int, progress: bool):
    """The mesh the batch is split over: every device of every process in a multi-process job
    (the batch must split over them); in one process the most local devices that split the
    batch evenly (a note says when some stay idle)."""
    devices = jax.devices()
    if jax.process_count() > 1:
        if batch_size % len(devices):
            raise ConfigError(
                f"data.batch_size {batch_size} must be a multiple of the {len(devices)} devices "
                f"of the {jax.process_count()} processes (the global batch is split over all)")
        return data_mesh(devices)
    count = max(k for k in range(1, len(devices) + 1) if batch_size % k == 0)
    if count < len(devices) and progress:
        print(f"jaxden: note: data.batch_size {batch_size} splits evenly over {count} of the "
              f"{len(devices)} JAX devices; training uses {count} (a batch size that is a "
              f"multiple of {len(devices)} uses all)", file=sys.stderr)
    return data_mesh(devices[:count])


def _peer_failure(error: BaseException) -> bool:
    """Whether an exception of a multi-process step means another process is gone."""
    if isinstance(error, JaxdenError):
        return False
    text = str(error)
    runtime = getattr(jax.errors, "JaxRuntimeError", ())
    return isinstance(error, runtime) or any(
        word in text for word in ("Gloo", "gloo", "coordination", "heartbeat", "UNAVAILABLE"))


def train_and_evaluate(
    config: TrainConfig, workdir: str | os.PathLike, *, progress: bool = True,
    stop_after: int | None = None, tensorboard: bool = True,
) -> dict[str, Any]:
    """Train (or resume) in ``workdir``; returns the final evaluation metrics.

    ``stop_after``: stop after this many steps of this call (for tests of resumption).
    ``tensorboard``: also write the logged scalars as TensorBoard event files in ``workdir``
    (:mod:`jaxden.train.tensorboard`).

    ``config.init`` (fine-tuning, :mod:`jaxden.train.finetune`): a run that starts at step 0
    takes its parameters from that source (checked against the model first; the optimiser
    state starts fresh); a resume continues from the run's own checkpoints and refuses a source
    that has changed since the run started.

    The workdir is locked (a second run on it is an error). Before every checkpoint the
    parameters and optimiser state are checked for NaN / inf (a diverged state is never
    saved: a one-line error names the step). Ctrl-C waits for a checkpoint being written and
    then raises KeyboardInterrupt (nothing half-written is left). In a multi-process job
    (:func:`jaxden.distributed.initialize`) every process runs this with the same config and
    workdir (on a shared filesystem): each loads its rows of every batch, process 0 alone
    writes the workdir, and a job restarted after losing a process resumes from the last
    checkpoint.
    """
    workdir = Path(workdir)
    resuming, init_source = False, None
    if config.init:
        from jaxden.train.finetune import resolve_init

        resuming = has_checkpoint(workdir)
        init_source = resolve_init(config, recorded=recorded_init(workdir) if resuming else None)
    resolved = check_workdir(config, workdir,
                             None if init_source is None else init_source.record())
    several = jax.process_count() > 1
    primary = jax.process_index() == 0
    if several:  # shared data (a SURE cache) is built by process 0 alone, then only read
        from jax.experimental import multihost_utils

        if primary:
            prepare_shared_data(config, progress=progress)
        multihost_utils.sync_global_devices("jaxden: shared data ready")

    # Everything the config can get wrong fails here, before the workdir records the config
    # (a failed start must not leave a workdir that refuses the corrected config).
    task = make_task(config)
    loss_fn = loss_function(config.optim.loss, config.optim.loss_reduction)
    optimizer = make_optimizer(config.optim)
    train_loader, val_loader = _loaders(config, task)
    mesh = _training_mesh(config.data.batch_size, progress and primary)

    key = jax.random.PRNGKey(config.seed)
    first = task.prepare(next(iter(batches_from(train_loader, 0, mesh))))
    if init_source is not None and not resuming:  # fine-tuning: only a run at step 0 reads it
        from jaxden.train.finetune import load_init_params

        target = jax.eval_shape(task.init, key, first)
        params = jax.tree_util.tree_map(jnp.asarray, load_init_params(init_source, target))
    else:
        params = _initial_params(task, key, first)
    state = TrainState(params, optimizer.init(params), jnp.asarray(0, jnp.int32))

    with contextlib.ExitStack() as stack:
        if primary:
            stack.enter_context(claim_workdir(workdir, config, resolved))
        return _train(config, workdir, task, loss_fn, optimizer, train_loader, val_loader, mesh,
                      state, progress=progress and primary, stop_after=stop_after,
                      tensorboard=tensorboard)


def _initial_params(task: Task, key, first) -> Any:
    """``task.init`` as one jitted program (cached on disk like the steps, the same values as
    op by op). In a multi-process job process 0 alone computes it and sends it to the others:
    JAX caches compilations from process 0 only, and a program for another process's device
    would be compiled afresh there at every start."""
    init = jax.jit(task.init)
    if jax.process_count() == 1:
        return init(key, first)
    from jax.experimental import multihost_utils

    if jax.process_index() == 0:
        params = jax.device_get(init(key, first))
    else:
        params = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype),
                                        jax.eval_shape(init, key, first))
    return multihost_utils.broadcast_one_to_all(params)


def _latest_step(checkpointer) -> int | None:
    """The newest checkpoint's step, the same in every process (process 0's)."""
    latest = checkpointer.latest_step() if checkpointer is not None else None
    if jax.process_count() == 1:
        return latest
    from jax.experimental import multihost_utils

    shared = int(multihost_utils.broadcast_one_to_all(np.int32(-1 if latest is None else latest)))
    return None if shared < 0 else shared


def _train(config, workdir, task, loss_fn, optimizer, train_loader, val_loader, mesh, state, *,
           progress: bool, stop_after: int | None, tensorboard: bool = True) -> dict[str, Any]:
    """The loop of :func:`train_and_evaluate` once the workdir is locked."""
    from jaxden.checkpoint import Checkpointer
    from jaxden.config import config_to_dict
    from jaxden.data.features import META_KEY, dataset_features
    from jaxden.errors import CheckpointError

    primary = jax.process_index() == 0
    several = jax.process_count() > 1
    meta = {**task.meta, "train_config": config_to_dict(config)}
    # The features the model learns from: a frame of others is named when the model meets it.
    features = dataset_features(config.data.dataset)
    if features is not None:
        meta[META_KEY] = features.to_json()
    checkpointer = None
    if primary:
        checkpointer = Checkpointer(workdir, max_to_keep=config.keep_checkpoints)
        remove_partial_checkpoints(checkpointer.directory)
    elif workdir.is_dir():  # other processes only read, and only what process 0 saved
        with contextlib.suppress(CheckpointError):
            checkpointer = Checkpointer(workdir, create=False)
    # Everything from here runs under the try below, whose finally stops orbax's background
    # threads on every way out (an unreadable checkpoint included).
    start, latest, last_saved, done, end = 0, None, None, 0, config.optim.steps
    bar = log = None
    last_eval: dict[str, float] = {}
    try:
        latest = _latest_step(checkpointer)
        if latest is not None:
            if checkpointer is None:
                raise CheckpointError(
                    f"process {jax.process_index()} cannot see the checkpoints of {workdir} "
                    f"that process 0 found: every process needs the workdir on one shared "
                    f"filesystem")
            saved = checkpointer.read_meta(latest).get("model_config")
            expect = resume_expectation(task.meta, config, saved)
            state, _ = checkpointer.restore(state, step=latest, expect=expect)
            start = int(state.step)
        state = replicate(state, mesh)

        train_step = jax.jit(make_train_step(task, optimizer, loss_fn), donate_argnums=0)
        eval_step = jax.jit(make_eval_step(task, loss_fn))
        if primary:
            log = MetricsLog(workdir / "metrics.jsonl", start, tensorboard=tensorboard)
        schedule = make_schedule(config.optim)
        if stop_after is not None:
            end = min(config.optim.steps, start + stop_after)
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=config.optim.steps, initial=start, desc=f"train {config.model}",
                       unit="step")
        last_saved = latest
        done = start
        if start == 0:  # where the curve starts: the untrained model on the validation split
            initial = evaluate(eval_step, state.params, val_loader, mesh, config.eval_batches,
                               task.prepare)
            if log is not None:
                log.write({"step": 0, **initial})
        tick = time.perf_counter()
        batches = batches_from(train_loader, start, mesh)
        global_batch = config.data.batch_size
        for step in range(start, end):
            batch = shard_batch(task.prepare(next(batches)), mesh, global_batch)
            state, metrics = train_step(state, batch)
            done = step + 1
            if done % config.log_every == 0 or done == end:
                loss = float(host_value(metrics["loss"]))
                if not math.isfinite(loss):
                    raise JaxdenError(f"training diverged at step {done}: loss {loss}; lower "
                                      f"optim.learning_rate")
                now = time.perf_counter()
                if log is not None:
                    log.write({"step": done, "loss": loss,
                               "grad_norm": float(host_value(metrics["grad_norm"])),
                               "lr": float(schedule(step)), "seconds": now - tick})
                tick = now
                if bar is not None:
                    bar.set_postfix(loss=f"{loss:.4g}")
            if done % config.eval_every == 0 or done == config.optim.steps:
                last_eval = evaluate(eval_step, state.params, val_loader, mesh,
                                     config.eval_batches, task.prepare)
                if log is not None:
                    log.write({"step": done, **last_eval})
            if done % config.checkpoint_every == 0 or done == end:
                check_finite_state(state, done, last_saved)
                if primary:
                    host_state = jax.tree_util.tree_map(host_value, state) if several else state
                    with HoldInterrupts():
                        checkpointer.save(done, host_state, meta)
                last_saved = done
            if bar is not None:
                bar.update(1)
    except Exception as error:
        if several and _peer_failure(error):
            from jaxden.distributed import DistributedError

            first = (str(error).strip().splitlines() or [type(error).__name__])[0][:200]
            raise DistributedError(
                f"the distributed job stopped near step {done + 1}: another process failed or "
                f"was stopped ({first}); start every process again with the same command to "
                f"resume from the last checkpoint (step {last_saved or 0})") from None
        raise
    finally:
        if bar is not None:
            bar.close()
        if checkpointer is not None:
            with HoldInterrupts():  # a checkpoint being written is finished, never cut
                checkpointer.wait()
                checkpointer.close()
    if not last_eval:
        last_eval = evaluate(eval_step, state.params, val_loader, mesh, config.eval_batches,
                             task.prepare)
    return {"step": end, **last_eval}
