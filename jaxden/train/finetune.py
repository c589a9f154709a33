"""Fine-tuning: a run's parameters start from trained weights instead of a random draw.

``init`` in the training config names the source:

- a shipped model (``jaxden/weights/NAME.msgpack``: ``"wskp-6"``, ``"wskp-6-pd"``, ...);
- a released ``.msgpack`` weights file (its ``.json`` meta record beside it);
- a training workdir or its ``checkpoints`` folder (the newest checkpoint).

A path that exists wins over a shipped name. The source must hold the run's model: the same
kind (denoiser or mixer), the same registered name (``model``) and the same ``[model_config]``
(today's defaults filled in on both sides), with parameters of the shapes that model has, all
finite. Anything else, and a missing or corrupt source, is a one-line error that names the
source and the difference, raised before the workdir is written. Only the parameters are
taken: the optimiser state starts fresh, at step 0.

The run records the resolved source in its ``config.json`` (key ``init_source``: the spec, the
path, a checkpoint's step and the SHA-256 of the source's bytes, :func:`source_digest`), so a
resume whose source has changed since the run started is refused. A resume continues from the
run's own checkpoints and never reads the weights again; a source deleted since is accepted
then (the recorded digest stands for it).
"""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxden.errors import CheckpointError, ConfigError

#: The key of ``config.json`` that records the resolved source of a fine-tuning run.
INIT_RECORD = "init_source"


@dataclasses.dataclass(frozen=True)
class InitSource:
    """A resolved ``init``: ``path`` (a weights file or a checkpoint folder), ``step`` (the
    checkpoint's step; None for a weights file), ``sha256`` (:func:`source_digest`) and the
    source's ``meta`` record; ``available`` is False for a source gone since the run started
    (only a resume accepts one, taken from the run's record)."""

    spec: str
    path: Path
    step: int | None
    sha256: str
    meta: dict[str, Any]
    available: bool = True

    @property
    def where(self) -> str:
        """How errors name the source: the spec, and the path it resolved to."""
        shown = str(self.path)
        return f"init = {self.spec!r}" + ("" if shown == self.spec else f" ({shown})")

    def record(self) -> dict[str, Any]:
        """The entry of the run's recorded config."""
        return {"spec": self.spec, "path": str(self.path), "step": self.step,
                "sha256": self.sha256}


def shipped_weights() -> list[str]:
    """The names of every model shipped in ``jaxden/weights`` (denoisers and mixers)."""
    from jaxden.paths import shipped_weights_names

    return shipped_weights_names()


def locate(spec: str) -> Path:
    """The file or folder ``spec`` names (module docstring); ConfigError when there is none."""
    from jaxden.paths import shipped_weights_file

    path = Path(spec)
    if path.exists():
        if path.is_file() and path.suffix != ".msgpack":
            raise ConfigError(f"init = {spec!r}: expected a .msgpack weights file (its .json "
                              f"beside it), a training workdir or a shipped model's name")
        return path
    shipped = shipped_weights_file(spec)
    if shipped is not None:
        return shipped
    raise ConfigError(f"init = {spec!r}: no such file or folder, and no shipped model of that "
                      f"name (shipped: {', '.join(shipped_weights())}); give a shipped model, a "
                      f".msgpack weights file or a training workdir")


def source_digest(path: Path, step: int | None) -> str:
    """SHA-256 of a weights file's bytes, or of a checkpoint step folder (every file's
    relative path and bytes, in sorted order)."""
    digest = hashlib.sha256()
    if step is None:
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        return digest.hexdigest()
    folder = Path(path) / str(step)
    for file in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(str(file.relative_to(folder)).encode() + b"\0")
        with open(file, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


def expected_meta(config) -> dict[str, Any]:
    """What the source's meta record must say for the run of ``config``: the kind, the model
    and its ``model_config`` (defaults filled in)."""
    from jaxden.config import config_to_dict
    from jaxden.train.tasks import get_trainable, model_config

    trainable = get_trainable(config.model)
    return {"kind": trainable.kind, "model": trainable.name,
            "model_config": config_to_dict(model_config(config))}


def check_source_meta(meta: dict[str, Any], config, where: str) -> None:
    """CheckpointError naming ``where`` and the first difference unless ``meta`` describes the
    model that ``config`` trains."""
    from jaxden.config import config_diff, config_to_dict, load_config
    from jaxden.train.tasks import get_trainable

    expect = expected_meta(config)
    kind, model = meta.get("kind"), meta.get("model")
    if kind != expect["kind"]:
        raise CheckpointError(
            f"{where}: holds a {kind} (model {model!r}), but this run trains a {expect['kind']} "
            f"(model {config.model!r}); fine-tuning starts from weights of the same model")
    if model != expect["model"]:
        raise CheckpointError(
            f"{where}: holds the {kind} {model!r}, but this run trains {config.model!r}; set "
            f"model = {model!r} (and its [model_config]) to fine-tune it")
    try:
        saved = config_to_dict(load_config(dict(meta.get("model_config") or {}),
                                           get_trainable(config.model).config_cls))
    except ConfigError as error:
        raise CheckpointError(f"{where}: its model_config does not fit {model!r}: "
                              f"{error}") from None
    differences = config_diff(saved, expect["model_config"])
    if differences:
        more = f" and {len(differences) - 5} more" if len(differences) > 5 else ""
        raise CheckpointError(
            f"{where}: holds {model!r} with another [model_config] (source -> this run: "
            f"{'; '.join(differences[:5])}{more}); fine-tuning needs the source's architecture "
            f"and config: set [model_config] to the source's")


def resolve_init(config, *, digest: bool = True, recorded: dict[str, Any] | None = None
                 ) -> InitSource:
    """The source ``config.init`` names, its meta record checked against the run's model
    (:func:`check_source_meta`). ``digest``: also hash its bytes (False: sha256 is "").
    ``recorded``: the run's own record of its source (a resume): used, unavailable, when the
    source is gone. Raises ConfigError / CheckpointError naming the source."""
    from jaxden.checkpoint import Checkpointer, read_checkpoint_meta

    spec = config.init
    try:
        path = locate(spec)
    except ConfigError:
        if recorded is None or recorded.get("spec") != spec:
            raise
        return InitSource(spec, Path(recorded.get("path", spec)), recorded.get("step"),
                          str(recorded.get("sha256", "")), {}, available=False)
    shown = f"init = {spec!r}" + ("" if str(path) == spec else f" ({path})")
    try:
        if path.is_file():
            step, meta = None, read_checkpoint_meta(path)
        else:
            with Checkpointer(path, create=False) as checkpointer:
                step = checkpointer.latest_step()
                if step is None:
                    raise CheckpointError(f"{checkpointer.directory}: holds no finished "
                                          f"checkpoint")
                meta = checkpointer.read_meta(step)
                path = checkpointer.directory
    except CheckpointError as error:
        raise CheckpointError(f"{shown}: {error}") from None
    check_source_meta(meta, config, shown)
    sha256 = source_digest(path, step) if digest else ""
    return InitSource(spec, path, step, sha256, meta)


def load_init_params(source: InitSource, target: Any) -> Any:
    """The source's parameters in the structure of ``target`` (a pytree of arrays or
    ``jax.ShapeDtypeStruct``: the model's freshly initialised parameters), each cast to its
    target's dtype. Raises CheckpointError naming the source for another structure or shape, a
    corrupt file or non-finite values."""
    from jaxden.checkpoint import (
        Checkpointer,
        check_finite_params,
        check_same_structure,
        load_weights,
    )

    if not source.available:
        raise CheckpointError(f"{source.where}: no such file or folder any more")
    try:
        if source.step is None:
            params, _ = load_weights(source.path, target)
        else:
            with Checkpointer(source.path, create=False) as checkpointer:
                state, _ = checkpointer.restore(step=source.step)
            params = state["params"] if isinstance(state, dict) and "params" in state else state
            where = str(source.path / str(source.step))
            check_same_structure(params, target, where=where)
            check_finite_params(params, where)
    except CheckpointError as error:
        raise CheckpointError(f"{source.where}: {error}") from None
    values = {jax.tree_util.keystr(path): value
              for path, value in jax.tree_util.tree_leaves_with_path(params)}
    return jax.tree_util.tree_map_with_path(
        lambda path, want: np.asarray(values[jax.tree_util.keystr(path)], want.dtype), target)
