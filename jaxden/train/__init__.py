"""Training: ``train_and_evaluate(config, workdir)`` for every trainable model.

- :mod:`~jaxden.train.config`: TrainConfig (data, optimiser, model) from TOML;
- :mod:`~jaxden.train.task`: the Task protocol between the loop and what it trains;
- :mod:`~jaxden.train.tasks`: what ``model = NAME`` trains: the name -> Trainable table (every
  registered denoiser and the mixer), their tasks and the mixer's shared SURE cache;
- :mod:`~jaxden.train.workdir`: a run's folder (lock, recorded config, metrics log);
- :mod:`~jaxden.train.losses`, :mod:`~jaxden.train.optim`: losses, schedule and optimiser;
- :mod:`~jaxden.train.sharding`: data parallelism over local devices;
- :mod:`~jaxden.train.loop`: the jitted train / eval steps and the resumable loop.
"""

from jaxden.train.config import (
    DataConfig,
    OptimConfig,
    TrainConfig,
    load_train_config,
)
from jaxden.train.loop import (
    train_and_evaluate,
)
from jaxden.train.optim import (
    make_optimizer,
    make_schedule,
)
from jaxden.train.task import (
    Task,
)
from jaxden.train.tasks import (
    Trainable,
    denoiser_task,
    get_trainable,
    make_task,
    mixer_task,
    trainables,
)

__all__ = [
    "DataConfig",
    "OptimConfig",
    "Task",
    "TrainConfig",
    "Trainable",
    "denoiser_task",
    "get_trainable",
    "load_train_config",
    "make_optimizer",
    "make_schedule",
    "make_task",
    "mixer_task",
    "train_and_evaluate",
    "trainables",
]
