"""Checkpoints: orbax for training state, and a single-file format for released weights.

A training checkpoint folder (``WORKDIR/checkpoints/<step>/``) holds the train state pytree
(params, optimiser state, step) and a JSON ``meta`` record::

    {"kind": "denoiser" | "mixer", "model": "wskp", "model_config": {...},
     "jaxden_version": "...", "step": 1200, "train_config": {...},
     "trained_features": {"aux": "first-hit", "feature_spp": 16}}

``trained_features``: how the training dataset's features were rendered (its manifest's
``aux`` and ``feature_spp``; absent for an imported dataset and in checkpoints written before
the record), compared with a frame's by :mod:`jaxden.data.features`.

Orbax writes each step to a temporary folder and renames it when complete, so an interrupted
save never leaves a half-written checkpoint that looks finished.

Loading checks the record before the arrays: a checkpoint of another model, another config or
another kind is a :class:`~jaxden.errors.CheckpointError` that names both sides, never a shape
error from inside orbax.

Released weights (shipped inside the package) are one ``.msgpack`` file of parameters plus a
``.json`` record of the same form, written atomically.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
from pathlib import Path
from typing import Any, Self

import jax
import numpy as np

from jaxden.errors import CheckpointError, OutputError
from jaxden.fileio import check_json_fields, read_json


class _QuietOrbaxMetadata(logging.Filter):
    """Orbax warns on every restore of a checkpoint saved without its optional metadata file
    (all of ours): noise for users, so that one message is dropped. So are the tracebacks its
    background threads log when the disk refuses a write: that error reaches ``save`` /
    ``wait``, which report it in one line (:meth:`Checkpointer._save_failed`)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "Metadata file does not exist" in message or "Failed to get item metadata" in message:
            return False  # the second: a damaged checkpoint, which restore reports in one line
        failed = record.exc_info[1] if record.exc_info else None
        return record.levelno < logging.ERROR or (
            _write_failure(message) is None and (failed is None or _write_failure(failed) is None))


logging.getLogger("absl").addFilter(_QuietOrbaxMetadata())
logging.getLogger("asyncio").addFilter(_QuietOrbaxMetadata())

CHECKPOINT_SUBDIR = "checkpoints"


class _LateCallbackTolerantLoop(asyncio.SelectorEventLoop):
    """An event loop that drops callbacks scheduled from other threads once it is closed.

    Orbax restores in a fresh event loop that awaits every array read of TensorStore at once.
    When one read fails (a damaged file), the loop stops and is closed while the other reads
    are still running in TensorStore's threads; as each finishes, its completion callback
    calls ``loop.call_soon_threadsafe`` on the closed loop, and TensorStore prints that
    RuntimeError ("Event loop is closed") with its traceback, after jaxden's one error line.
    The results have no one left to receive them, so dropping them is what should happen."""

    def call_soon_threadsafe(self, callback, *args, context=None):
        if self.is_closed():
            return None
        return super().call_soon_threadsafe(callback, *args, context=context)


class _TolerantLoopPolicy(asyncio.DefaultEventLoopPolicy):
    def new_event_loop(self):
        return _LateCallbackTolerantLoop()


@contextlib.contextmanager
def late_callbacks_dropped():
    """The event loops created inside the block (orbax's, for a restore) drop callbacks that
    arrive after they are closed (:class:`_LateCallbackTolerantLoop`)."""
    previous = asyncio.get_event_loop_policy()
    asyncio.set_event_loop_policy(_TolerantLoopPolicy())
    try:
        yield
    finally:
        asyncio.set_event_loop_policy(previous)
#: The fields every meta record (checkpoint or released weights) must have, with their types.
META_FIELDS = {"kind": str, "model?": str, "model_config?": dict, "step?": int,
               "trained_features?": dict}


def _ocp():
    import orbax.checkpoint as ocp

    return ocp


def _checkpoint_root(directory: str | os.PathLike) -> Path:
    directory = Path(directory)
    if directory.name != CHECKPOINT_SUBDIR and (directory / CHECKPOINT_SUBDIR).is_dir():
        directory = directory / CHECKPOINT_SUBDIR
    return directory


class Checkpointer:
    """Save/restore a training state with its meta record; keeps the newest ``max_to_keep``.

    Orbax works in background threads: :meth:`close` (or a ``with`` block) stops them, and must
    run on every way out, errors included. A restore that fails on a damaged file gives one
    CheckpointError and nothing else on stderr (:func:`late_callbacks_dropped`)."""

    def __init__(self, directory: str | os.PathLike, max_to_keep: int = 3, create: bool = True):
        ocp = _ocp()
        self.directory = _checkpoint_root(directory).absolute()
        if not create and not self.directory.is_dir():
            raise CheckpointError(f"{directory}: no checkpoint folder found")
        options = {"max_to_keep": max_to_keep, "create": create}
        if jax.process_count() > 1:
            # In a multi-process job (jaxden.train.loop) process 0 alone saves and every
            # process restores by itself: no checkpointer waits for the others.
            me = jax.process_index()
            options["multiprocessing_options"] = ocp.options.MultiprocessingOptions(
                primary_host=me, active_processes={me})
            if create:  # orbax cannot create the folder for a subset of processes
                self.directory.mkdir(parents=True, exist_ok=True)
                options["create"] = False
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(**options))

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def save(self, step: int, state: Any, meta: dict[str, Any]) -> None:
        """Start saving ``step`` (orbax writes in the background; :meth:`wait` for it).

        A disk without room for it is an OutputError before anything is written; a write the
        disk refuses later is one too (see :meth:`_save_failed`)."""
        ocp = _ocp()
        meta = {**meta, "step": int(step)}
        _check_room(self.directory, state, step)
        try:
            self._manager.save(
                int(step),
                args=ocp.args.Composite(
                    state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)
                ),
            )
        except Exception as error:  # noqa: BLE001 - orbax raises ValueError for ENOSPC
            raise self._save_failed(error) from None

    def wait(self) -> None:
        try:
            self._manager.wait_until_finished()
        except Exception as error:  # noqa: BLE001
            raise self._save_failed(error) from None

    def _save_failed(self, error: Exception) -> Exception:
        """What to raise for a failed save: an OutputError naming the folder and the reason
        when the file system refused a write, else ``error`` itself (a bug keeps its
        traceback). The unfinished step folder is removed once orbax stops writing (whatever
        is left is removed when the run starts again); finished checkpoints are kept."""
        reason = _write_failure(error)
        if reason is None:
            return error
        with contextlib.suppress(Exception):
            self._manager.close()
        for path in self.directory.glob("*.orbax-checkpoint-tmp*"):
            shutil.rmtree(path, ignore_errors=True)
        return OutputError(f"cannot write a checkpoint into {self.directory}: {reason} (the "
                           f"checkpoints saved before are kept; make room and run the same "
                           f"command to resume)")

    def read_meta(self, step: int | None = None) -> dict[str, Any]:
        ocp = _ocp()
        step = self._resolve_step(step)
        where = f"{self.directory / str(step)}: the checkpoint's meta record"
        try:
            with late_callbacks_dropped():
                restored = self._manager.restore(
                    step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
            meta = restored.meta
        except Exception as error:  # noqa: BLE001 - orbax raises many kinds on bad files
            first = str(error).strip().splitlines()[0] if str(error).strip() else ""
            raise CheckpointError(f"{where} cannot be read ({type(error).__name__}: "
                                  f"{first[:200]})") from None
        return dict(check_json_fields(meta, META_FIELDS, where, CheckpointError))

    def restore(
        self, target: Any = None, step: int | None = None, expect: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Restore (state, meta). ``target``: a pytree of the expected structure (shapes are
        checked against it); ``expect``: meta fields that must match (e.g. model, model_config)."""
        ocp = _ocp()
        step = self._resolve_step(step)
        meta = self.read_meta(step)
        if expect:
            check_meta(meta, expect, where=str(self.directory / str(step)))
        # Restore onto this process's first device whatever device layout the run was saved
        # with (orbax refuses another topology unless it is given target shardings); callers
        # replicate or shard the result as they need.
        device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        try:
            if target is None:
                with ocp.StandardCheckpointer() as reader, late_callbacks_dropped():
                    tree = reader.metadata(self.directory / str(step) / "state").item_metadata
                abstract = jax.tree_util.tree_map(
                    lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device), tree
                )
            else:
                abstract = jax.tree_util.tree_map(
                    lambda x: jax.ShapeDtypeStruct(np.shape(x), jax.numpy.asarray(x).dtype,
                                                   sharding=device), target
                )
            with late_callbacks_dropped():  # a damaged file: no tracebacks after the error
                restored = self._manager.restore(
                    step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract))
                )
        except Exception as error:  # orbax raises many types for structure mismatches
            text = str(error).splitlines()[0] if str(error) else type(error).__name__
            if isinstance(error, json.JSONDecodeError) or any(
                    word in text for word in _DAMAGED_FILE_WORDS):  # the files themselves
                raise CheckpointError(
                    f"{self.directory / str(step)}: the saved arrays cannot be read (a corrupt "
                    f"or incomplete checkpoint; delete that step folder to resume from an "
                    f"earlier one): {text.split('See full TensorStore details')[0][:200]}"
                ) from None
            raise CheckpointError(
                f"{self.directory / str(step)}: the saved state does not match the model: "
                f"{text[:300]}"
            ) from None
        state = restored.state
        if target is not None:
            check_same_structure(state, target, where=str(self.directory / str(step)))
        return state, meta

    def _resolve_step(self, step: int | None) -> int:
        steps = self._manager.all_steps()
        if not steps:
            raise CheckpointError(f"{self.directory}: holds no finished checkpoint")
        if step is None:
            return max(steps)
        if step not in steps:
            raise CheckpointError(f"{self.directory}: no checkpoint at step {step}; have {sorted(steps)}")
        return step

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


#: Words of orbax's and TensorStore's errors that mean a checkpoint's files are damaged or cut
#: short (not a state of another structure).
_DAMAGED_FILE_WORDS = ("TensorStore", "reading array", "Error reading", "OCDBT", "DATA_LOSS",
                       "OUT_OF_RANGE")
_WRITE_FAILURES = ("No space left on device", "Disk quota exceeded", "Read-only file system",
                   "Permission denied")
#: Room a checkpoint needs beyond its arrays' bytes (orbax's metadata, the meta record).
CHECKPOINT_MARGIN_BYTES = 1 << 20


def _write_failure(error: BaseException | str) -> str | None:
    """The reason when ``error`` (an OSError, or orbax's / TensorStore's errors or log
    messages that carry the OS message in their text) is the file system refusing a write;
    None otherwise."""
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    text = str(error)
    return next((reason for reason in _WRITE_FAILURES if reason in text), None)


def _check_room(directory: Path, state: Any, step: int) -> None:
    """OutputError when ``directory``'s disk has less free space than the state's bytes plus
    :data:`CHECKPOINT_MARGIN_BYTES` (a save that would run out of space half way)."""
    need = sum(int(getattr(leaf, "nbytes", 0)) for leaf in jax.tree_util.tree_leaves(state))
    need += CHECKPOINT_MARGIN_BYTES
    try:
        free = shutil.disk_usage(directory if directory.exists() else directory.parent).free
    except OSError:
        return
    if free < need:
        raise OutputError(
            f"cannot write checkpoint {step} into {directory}: No space left on device (it "
            f"needs about {need / 1e6:.1f} MB, {free / 1e6:.1f} MB are free; the checkpoints "
            f"saved before are kept; make room and run the same command to resume)")


def check_meta(meta: dict[str, Any], expect: dict[str, Any], where: str) -> None:
    """Raise CheckpointError naming every field of ``expect`` that differs in ``meta``."""
    problems = []
    for key, value in expect.items():
        found = meta.get(key)
        if _jsonable(found) != _jsonable(value):
            problems.append(f"{key}: checkpoint has {found!r}, expected {value!r}")
    if problems:
        raise CheckpointError(f"{where}: checkpoint of another model or config ({'; '.join(problems)})")


def check_finite_params(params: Any, where: str) -> None:
    """Raise CheckpointError unless every parameter is a floating-point array of finite
    values: weights with NaN, inf or an integer dtype would denoise to a NaN, inf or zero
    image without complaint."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        array = np.asarray(leaf)
        name = jax.tree_util.keystr(path)
        if not np.issubdtype(array.dtype, np.floating):
            raise CheckpointError(f"{where}: parameter {name} has dtype {array.dtype}; weights "
                                  f"must be floating point")
        if not np.isfinite(array).all():
            bad = int(array.size - np.count_nonzero(np.isfinite(array)))
            raise CheckpointError(f"{where}: parameter {name} holds {bad} non-finite value(s) "
                                  f"(NaN or inf): the weights are broken (a diverged run?)")


def check_same_structure(params: Any, target: Any, where: str) -> None:
    """Raise CheckpointError naming the first leaf whose path or shape differs."""
    got = {jax.tree_util.keystr(p): np.shape(v) for p, v in jax.tree_util.tree_leaves_with_path(params)}
    want = {jax.tree_util.keystr(p): np.shape(v) for p, v in jax.tree_util.tree_leaves_with_path(target)}
    if got.keys() != want.keys():
        extra = sorted(got.keys() - want.keys())[:3]
        lacking = sorted(want.keys() - got.keys())[:3]
        raise CheckpointError(
            f"{where}: parameter names differ from the model's (unexpected {extra}, missing {lacking})"
        )
    for path, shape in want.items():
        if got[path] != shape:
            raise CheckpointError(f"{where}: parameter {path} has shape {got[path]}, the model needs {shape}")


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=list))


# ------------------------------------------------------------------------- released weights
def save_weights(path: str | os.PathLike, params: Any, meta: dict[str, Any]) -> None:
    """Write ``path`` (.msgpack, parameters) and ``path`` with .json (meta), atomically."""
    from flax import serialization

    path = Path(path)
    blob = serialization.to_bytes(jax.tree_util.tree_map(np.asarray, params))
    from jaxden.fileio import atomic_write_bytes

    for target, data in ((path, blob), (path.with_suffix(".json"), json.dumps(meta, indent=2).encode())):
        atomic_write_bytes(target, data)


def load_weights(
    path: str | os.PathLike, target: Any, expect: dict[str, Any] | None = None
) -> tuple[Any, dict[str, Any]]:
    """Read released weights into the structure of ``target``; check the meta record first."""
    from flax import serialization

    path = Path(path)
    meta_path = path.with_suffix(".json")
    if not path.is_file() or not meta_path.is_file():
        raise CheckpointError(f"{path}: released weights need both {path.name} and {meta_path.name}")
    meta = read_json(meta_path, "the weights' meta record", error=CheckpointError,
                     fields=META_FIELDS)
    if expect:
        check_meta(meta, expect, where=str(path))
    try:
        state = serialization.msgpack_restore(path.read_bytes())
    except Exception as error:
        raise CheckpointError(f"{path}: corrupt weights file ({error})") from None
    check_same_structure(state, target, where=str(path))
    params = serialization.from_state_dict(target, state)
    check_finite_params(params, str(path))
    return params, meta


def load_trained_params(
    source: str | os.PathLike, target: Any, expect: dict[str, Any] | None = None
) -> tuple[Any, dict[str, Any]]:
    """Parameters from a training workdir / checkpoint folder, or a released ``.msgpack`` file.

    ``target``: freshly initialised parameters of the expected model (structure and shapes are
    checked against it); ``expect``: meta fields that must match.
    """
    source = Path(source)
    if source.is_file():
        return load_weights(source, target, expect)
    checkpointer = Checkpointer(source, create=False)
    try:
        meta = checkpointer.read_meta()
        where = str(checkpointer.directory / str(meta.get("step", "?")))
        if expect:
            check_meta(meta, expect, where=where)
        state, _ = checkpointer.restore()
    finally:
        checkpointer.close()
    params = state["params"] if isinstance(state, dict) and "params" in state else state
    check_same_structure(params, target, where=where)
    check_finite_params(params, where)
    return params, meta


def read_checkpoint_meta(source: str | os.PathLike) -> dict[str, Any]:
    """The meta record of a released weights file or of a checkpoint folder's newest step."""
    source = Path(source)
    if source.is_file():
        meta_path = source.with_suffix(".json")
        if not meta_path.is_file():
            raise CheckpointError(f"{source}: no {meta_path.name} beside it")
        return read_json(meta_path, "the weights' meta record", error=CheckpointError,
                         fields=META_FIELDS)
    checkpointer = Checkpointer(source, create=False)
    try:
        return checkpointer.read_meta()
    finally:
        checkpointer.close()
