"""TrainConfig: what a training run trains, on which data, with which optimiser (validated from TOML)."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Literal

from jaxden.config import bounded, check_fields
from jaxden.errors import ConfigError


# ------------------------------------------------------------------------------------ config
@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Which dataset and how batches are drawn from it."""

    dataset: str = ""  # a dataset folder built by `jaxden dataset build`
    split: str = "train"
    val_split: str = "val"
    crop_size: int = bounded(64, low=1, high=4096, unit='pixels')
    batch_size: int = bounded(8, low=1, high=65536)
    spp: tuple[int, ...] | None = bounded(None, low=1, high=2**24)  # None: every input spp level of the dataset
    augment: bool = True
    # Noise2Noise: train against the crop's own input at this spp level (an independent noisy
    # render) instead of its reference; validation keeps the references. Only a loss whose
    # expectation over the target's noise is the clean loss plus a term without gradient keeps
    # the clean optimum: "l2" and "relmse_sg" qualify (their gradient is linear in the target);
    # "l1", "smape", "relmse" and the "log_ratio" reduction do not (the training loop warns).
    target_spp: int | None = bounded(None, low=1, high=2**24)

    def __post_init__(self):
        from jaxden.paths import expand_path

        # "$JAXDEN_HOME/data/rt" and "~/..." work in configs and overrides
        object.__setattr__(self, "dataset", expand_path(self.dataset))


@dataclasses.dataclass(frozen=True)
class OptimConfig:
    steps: int = bounded(1000, low=1, high=10**9)
    learning_rate: float = bounded(1e-3, low=0, low_open=True, high=10)  # the peak of the one-cycle schedule
    schedule: Literal["onecycle", "constant"] = "onecycle"
    warmup_fraction: float = bounded(0.05, low=0, high=0.99)
    # A registered loss (jaxden.train.losses: smape, relmse, relmse_sg, relmse_dc, relmse_njs,
    # l1, l2, and those of plugins, register_loss).
    loss: str = "smape"
    # How the per-image losses of a batch become one number: "mean" (the plain mean over
    # every pixel) or "log_ratio" (the mean of log(loss_i / loss_i(baseline)), the baseline
    # being the task's image to beat: every image weighs the same, whatever its noise level;
    # jaxden.train.losses.log_ratio_loss).
    loss_reduction: Literal["mean", "log_ratio"] = "mean"
    grad_clip_norm: float | None = bounded(None, low=0, low_open=True, high=1e9)

    def __post_init__(self):
        check_fields(self)  # the bounded ranges above, for a config built in Python too
        from jaxden.train.losses import get_loss

        get_loss(self.loss, where="optim.loss")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """A training run. ``model`` names a trainable model (a registered denoiser or 'mixer':
    :func:`jaxden.train.tasks.trainables`); ``model_config`` holds that model's own options
    (validated against its config class)."""

    model: str = "wskp"
    model_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    # Fine-tuning: the parameters start from trained weights instead of a random draw: a
    # shipped model's name ("wskp-6"), a .msgpack weights file or a training workdir (its
    # newest checkpoint), of this model and [model_config] (jaxden.train.finetune). "": none.
    init: str = ""
    data: DataConfig = DataConfig()
    optim: OptimConfig = OptimConfig()
    seed: int = bounded(0, low=0, high=4294967295)
    log_every: int = bounded(10, low=1, high=10**9)
    eval_every: int = bounded(200, low=1, high=10**9)
    eval_batches: int = bounded(8, low=1, high=10**6)
    checkpoint_every: int = bounded(200, low=1, high=10**9)
    keep_checkpoints: int = bounded(2, low=1, high=1000)
    # Modules to import before any name resolves (jaxden.plugins): the model, loss or
    # evaluator of a user's own module; recorded in the run's provenance.
    plugins: tuple[str, ...] = ()

    def __post_init__(self):
        from jaxden.paths import expand_path

        check_fields(self)  # the bounded ranges above, for a config built in Python too
        object.__setattr__(self, "init", expand_path(self.init))


def load_train_config(source, overrides=()) -> TrainConfig:
    """Load a training config and check its ``model``, ``[model_config]`` and ``init`` now, so
    that a typo there is reported with the file's name before any work starts."""
    from jaxden.config import load_config
    from jaxden.train.tasks import get_trainable, model_config

    _load_plugins_of(source)
    config = load_config(source, TrainConfig, overrides)
    where = f"{source}: " if isinstance(source, (str, os.PathLike)) else ""
    try:
        get_trainable(config.model)
    except ConfigError as error:
        raise ConfigError(f"{where}model = {config.model!r}: {error}") from None
    try:
        model_config(config)
    except ConfigError as error:
        raise ConfigError(f"{where}{error}") from None
    if config.init:  # the source exists and holds this model (its bytes are hashed at the start)
        from jaxden.train.finetune import resolve_init

        resolve_init(config, digest=False)
    return config


def _load_plugins_of(source) -> None:
    """Import the plugins a train config names (``plugins = [...]``) before it is validated:
    its model, loss or evaluator names may be theirs."""
    import tomllib

    from jaxden.plugins import load_config_plugins

    if isinstance(source, (str, os.PathLike)):
        try:
            data = tomllib.loads(Path(source).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
            return  # load_config reports the file's problem
        load_config_plugins(data, str(source))
    elif isinstance(source, dict):
        load_config_plugins(source, "")
    elif dataclasses.is_dataclass(source):
        load_config_plugins({"plugins": list(getattr(source, "plugins", ()) or ())}, "")
