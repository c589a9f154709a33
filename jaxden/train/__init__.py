"""Training: ``train_and_evaluate(config, workdir)`` for every trainable model.

- :mod:`~jaxden.train.config`: TrainConfig (data, optimiser, model) from TOML;
- :mod:`~jaxden.train.task`: the Task protocol between the loop and what it trains;
- :mod:`~jaxden.train.tasks`: the denoiser task and the mixer task;
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
    denoiser_task,
    make_task,
)

__all__ = [
    "DataConfig",
    "OptimConfig",
    "Task",
    "TrainConfig",
    "denoiser_task",
    "load_train_config",
    "make_optimizer",
    "make_schedule",
    "make_task",
    "train_and_evaluate",
]
