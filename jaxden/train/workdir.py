"""A training run's folder (its workdir): the lock, the recorded config, the metrics log, and
what resuming from its checkpoints checks.

A workdir holds ``config.toml`` and ``config.json`` (the resolved config, written once when
the run starts), ``metrics.jsonl`` (:class:`MetricsLog`), TensorBoard event files
(``events.out.tfevents.*``, the same scalars) and the orbax checkpoints
(:class:`jaxden.checkpoint.Checkpointer`). A run on a workdir that holds checkpoints of a run
with another config is refused (one that stopped before its first checkpoint holds no work:
the new config replaces its record); one run at a time trains in it (:data:`TRAIN_LOCK`).
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from jaxden.errors import ConfigError, JaxdenError

#: The lock file of a training workdir (two runs writing one workdir would mix checkpoints).
TRAIN_LOCK = ".train.lock"
CONFIG_TOML = "config.toml"
CONFIG_JSON = "config.json"


def check_workdir(config, workdir: Path, init_record: dict[str, Any] | None = None
                  ) -> dict[str, Any]:
    """The resolved config (a dict) of a run of ``config`` in ``workdir``; ConfigError when
    ``workdir`` is a file or holds checkpoints of a run with another config (today's defaults
    filled in for fields added since that run started: the same run).

    A workdir whose run recorded another config but stopped before its first checkpoint (a
    config that failed at its first step, a kill during compilation) holds no work: the new
    config is accepted there, with one line on stderr, and :func:`claim_workdir` records it.

    ``init_record``: a fine-tuning run's resolved source
    (:meth:`jaxden.train.finetune.InitSource.record`), kept in the resolved config under
    :data:`~jaxden.train.finetune.INIT_RECORD`; a run whose recorded source has another digest
    (the weights changed since it started) is refused too, unless it saved no checkpoint."""
    from jaxden.config import config_to_dict
    from jaxden.train.finetune import INIT_RECORD

    if workdir.exists() and not workdir.is_dir():
        raise ConfigError(f"--workdir {workdir} is a file, not a folder")
    resolved = config_to_dict(config)
    if init_record is not None:
        resolved[INIT_RECORD] = init_record
    problem = _recorded_difference(workdir, config, resolved)
    if problem is not None:
        if has_checkpoint(workdir):
            raise ConfigError(problem)
        from jaxden.distributed import is_primary

        if is_primary():
            print(f"jaxden: note: {workdir} recorded a run with another config that saved no "
                  f"checkpoint: training there with this config", file=sys.stderr, flush=True)
    return resolved


def _recorded_difference(workdir: Path, config, resolved: dict[str, Any]) -> str | None:
    """Why the run recorded in ``workdir`` is not a run of ``resolved`` (another config, or a
    fine-tuning source that has changed since it started), in words; None when it is, or when
    ``workdir`` records no run."""
    from jaxden.config import config_diff, config_to_dict, load_config
    from jaxden.fileio import read_json
    from jaxden.train.config import TrainConfig
    from jaxden.train.finetune import INIT_RECORD

    saved_json = workdir / CONFIG_JSON
    if not saved_json.exists():
        return None
    previous = read_json(saved_json, "the run's recorded config", error=ConfigError)
    previous_init = previous.pop(INIT_RECORD, None)
    with contextlib.suppress(ConfigError, TypeError, ValueError):
        # Today's defaults for fields added since the run started (same run).
        previous = config_to_dict(load_config(previous, TrainConfig))
    now = {key: value for key, value in resolved.items() if key != INIT_RECORD}
    differences = config_diff(previous, now)
    if differences:
        return (f"{workdir} holds a run with another config ({'; '.join(differences[:5])}); "
                f"use a new --workdir")
    init_record = resolved.get(INIT_RECORD)
    if isinstance(init_record, dict) and isinstance(previous_init, dict):
        before, after = previous_init.get("sha256"), init_record.get("sha256")
        if before != after:
            return (f"{workdir} holds a run fine-tuned from init = {config.init!r} as it was "
                    f"when the run started (sha256 {str(before)[:12]}..., step "
                    f"{previous_init.get('step')}); it has changed since (sha256 "
                    f"{str(after)[:12]}..., step {init_record.get('step')}, "
                    f"{init_record.get('path')}); use a new --workdir")
    return None


def recorded_init(workdir: Path) -> dict[str, Any] | None:
    """The resolved ``init`` source recorded by the run in ``workdir`` (None: none)."""
    from jaxden.fileio import read_json
    from jaxden.train.finetune import INIT_RECORD

    saved_json = workdir / CONFIG_JSON
    if not saved_json.is_file():
        return None
    record = read_json(saved_json, "the run's recorded config", error=ConfigError).get(INIT_RECORD)
    return record if isinstance(record, dict) else None


def has_checkpoint(workdir: Path) -> bool:
    """Whether ``workdir`` holds a finished checkpoint that a run resumes from (as orbax sees
    its checkpoint folder)."""
    from jaxden.checkpoint import Checkpointer

    if not workdir.is_dir():
        return False
    with Checkpointer(workdir, create=False) as checkpointer:
        return checkpointer.latest_step() is not None


@contextlib.contextmanager
def claim_workdir(workdir: Path, config, resolved: dict[str, Any]):
    """Create and lock ``workdir`` for the block, recording the run's config the first time,
    and again over a recorded config of another run that saved no checkpoint
    (:func:`check_workdir`; checked again under the lock: a run that has saved checkpoints
    since is refused)."""
    from jaxden.config import dump_config
    from jaxden.fileio import atomic_write_text, folder_lock

    workdir.mkdir(parents=True, exist_ok=True)
    with folder_lock(workdir, TRAIN_LOCK, "training run"):
        recorded = (workdir / CONFIG_JSON).exists()
        problem = _recorded_difference(workdir, config, resolved) if recorded else None
        if problem is not None and has_checkpoint(workdir):
            raise ConfigError(problem)
        if not recorded or problem is not None:
            atomic_write_text(workdir / CONFIG_TOML,
                              dump_config(config, header="resolved training config"))
            atomic_write_text(workdir / CONFIG_JSON, json.dumps(resolved, indent=2))
        yield


class MetricsLog:
    """Append-only JSONL log. On resume from the checkpoint of ``resume_step`` the entries of
    later steps (and of step 0 when no checkpoint is kept: the run starts over) are dropped,
    and so is a last line cut short by a kill; any other broken line is a one-line error
    naming the file and the line. Each entry is appended whole or not at all.

    ``tensorboard``: every numeric field of every entry also goes, as a scalar of that name at
    the entry's step, into a TensorBoard event file beside the log
    (:class:`jaxden.train.tensorboard.EventWriter`; a new file per start of the run)."""

    def __init__(self, path: Path, resume_step: int, *, tensorboard: bool = False):
        from jaxden.fileio import atomic_write_text, read_jsonl

        self.path = path
        self.events = None
        if path.exists():
            records, cut = read_jsonl(path, "the metrics log", error=JaxdenError,
                                      fields={"step?": int})
            kept = [r for r in records if resume_step > 0 and r.get("step", 0) <= resume_step]
            if cut or len(kept) < len(records):
                atomic_write_text(path, "".join(json.dumps(r) + "\n" for r in kept))
        if tensorboard:
            from jaxden.train.tensorboard import EventWriter

            self.events = EventWriter(path.parent, resume_step=resume_step)

    def write(self, record: dict[str, Any]) -> None:
        from jaxden.fileio import append_line

        append_line(self.path, json.dumps(record))
        if self.events is not None:
            self.events.scalars(int(record.get("step", 0)), {
                key: value for key, value in record.items()
                if key != "step" and isinstance(value, (int, float))
                and not isinstance(value, bool)})


def remove_partial_checkpoints(directory: Path) -> None:
    """Orbax's temporary step folders (a save cut short by a crash): never a resumable state."""
    if not directory.is_dir():
        return
    for path in directory.iterdir():
        if path.is_dir() and ".orbax-checkpoint-tmp" in path.name:
            shutil.rmtree(path, ignore_errors=True)


def resolved_model_config(config, saved: Any) -> Any:
    """A checkpoint's recorded model_config with today's defaults filled in (None if it no
    longer loads), so that adding a config field with a default keeps old runs resumable."""
    from jaxden.config import config_to_dict, load_config
    from jaxden.train.tasks import get_trainable

    if not isinstance(saved, dict):
        return None
    try:
        return config_to_dict(load_config(dict(saved), get_trainable(config.model).config_cls))
    except (ConfigError, TypeError, ValueError):
        return None


def resume_expectation(task_meta: dict[str, Any], config, saved_model_config: Any) -> dict:
    """What the checkpoint to resume from must record (kind, model, model_config): the task's,
    with the checkpoint's own model_config where it is the same model saved before a config
    field with a default was added."""
    expect = {k: task_meta[k] for k in ("kind", "model", "model_config")}
    if saved_model_config != expect["model_config"] and resolved_model_config(
            config, saved_model_config) == expect["model_config"]:
        expect["model_config"] = saved_model_config
    return expect
