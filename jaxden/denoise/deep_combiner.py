"""Registers ``dc``: the Deep Combiner (Back et al. 2020), single buffer, over a frozen base.

``apply(params, config, frame) = combine(frame.color, base(frame), features)``: the base
denoiser named by ``config.base`` (a spec for :func:`jaxden.denoise.load_denoiser`: a shipped
name such as ``wskp-6``, ``oidn-jax``, a training workdir or ``.msgpack`` file, with options)
computes the correlated estimate inside ``apply``, and the combiner
(:mod:`jaxden.denoise.nn.combiner`) mixes it with the noisy colour through 15 x 15 kernels.
A ``dc`` checkpoint is therefore a whole JAX denoiser: ``jaxden denoise --model RUN``,
``jaxden progressive --denoiser RUN`` and SURE by ``jax.jvp`` go through base and combiner
(the divergence includes the base's d out / d colour, as it must).

How the base is held. The parameters of ``dc`` (what ``init`` returns, what the training loop
optimises and checkpoints) are the combiner's alone. The base's weights are read from the
base's own file (shipped weights, its checkpoint, or for ``oidn-jax`` Intel's library) when a
config names it, once per process and file version (:func:`resolve_base`), and enter ``apply``
as constants: no optimiser sees them, while ``jax.jvp`` / ``jax.grad`` with respect to the
*frame* go through them. The config records which base it was trained over:
``base_sha256`` is a digest of the base's definition, config and weights, filled in when the
config is validated (``""``: the base's current weights), and checked against the base as it
loads now. A checkpoint trained over other weights than the base now named (the base's file
retrained or replaced, a config edited to another base) is refused when it loads
(:class:`BaseMismatchError`, a ConfigError, which a checkpoint load reports as a
CheckpointError naming the file), when a run resumes or fine-tunes from it, and by ``apply``.

The base must be differentiable JAX (``oidn``, the pyoidn black box, is refused: use
``oidn-jax``). No tiling: ``dc`` runs on whole frames (its base's own tiling constants, e.g.
WSKP's frame depth maximum, and the combiner's per-image depth normalisation would have to be
carried across tiles).

The base runs inside every training step, on the loader's crops. It is a small part of a
step (batch 8 of 64 x 64 crops, 2-core CPU: 2.10 CPU-seconds per step with WSKP-6's output
precomputed, 2.10 with WSKP-6 inside, 2.20 with OIDN in JAX inside), so there is no path for
precomputed base outputs (the SURE cache's stored denoised images could feed one).

Training loss: ``relmse_dc`` (registered here), the authors' relMSE
``mean((x - y)^2 / (mean_c(y)^2 + 0.01))`` with the target's channel mean in the denominator
(jaxden's ``relmse`` uses each channel's own value).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp

from jaxden.config import bounded, check_fields
from jaxden.denoise.frozen_base import (
    BaseMismatchError,
    base_sha256,
    load_base,
    mismatch_error,
)
from jaxden.denoise.nn.combiner import (
    HIDDEN_WIDTHS,
    INPUT_CHANNELS,
    KERNEL_SIZE,
    CombinerNet,
    combiner_output,
)
from jaxden.denoise.registry import Denoiser, DenoiserDef, register
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

#: The registered name.
MODEL_NAME = "dc"
#: The features the combiner itself reads besides the colour.
COMBINER_FEATURES = ("albedo", "normal", "depth")
#: The default base: the shipped real-time denoiser.
DEFAULT_BASE = "wskp-6"
#: The loss of the authors' code (``loss.py``), registered under this name.
LOSS_NAME = "relmse_dc"
RELMSE_EPS = 0.01


def resolve_base(spec: str) -> tuple[Denoiser, str]:
    """``(base, base_sha256(base))`` for a base spec, read once per process and per version
    of the file it names (:func:`jaxden.denoise.frozen_base.load_base`). ConfigError when it
    does not load or is not differentiable JAX."""
    base, digest = load_base(spec, MODEL_NAME)
    if not base.differentiable:
        raise ConfigError(
            f"{MODEL_NAME}: base {spec!r} is a black box (NumPy in, NumPy out); the Deep "
            f"Combiner runs its base inside JAX (training, SURE by jvp): use a JAX denoiser, "
            f"e.g. 'oidn-jax' for OIDN")
    return base, digest


# ------------------------------------------------------------------------------ config
@dataclasses.dataclass(frozen=True)
class DeepCombinerConfig:
    """The Deep Combiner over a frozen base.

    ``base``: the base denoiser's spec (a JAX denoiser); ``base_sha256``: the digest of the
    base the combiner was trained over (:func:`base_sha256`; ``""``: filled in from the base
    as it loads now; a different one is refused); ``depth``: ``minmax`` (each image's depth
    min-max normalised, as the authors' loader does) or ``zero`` (their network as released,
    whose re-normalisation makes the depth input 0); ``hidden_widths``: the first five
    convolutions' widths (the authors: 100 each); ``kernel_size``: the combination window
    (15)."""

    base: str = DEFAULT_BASE
    base_sha256: str = ""
    depth: Literal["minmax", "zero"] = "minmax"
    hidden_widths: tuple[int, ...] = bounded(HIDDEN_WIDTHS, low=1, high=4096)
    kernel_size: int = bounded(KERNEL_SIZE, low=1, high=63, unit="pixels")

    def __post_init__(self):
        from jaxden.paths import expand_path

        check_fields(self)
        if self.kernel_size % 2 == 0:
            raise ConfigError(f"{MODEL_NAME}: kernel_size must be odd (a window centred on the "
                              f"pixel), got {self.kernel_size}")
        if not self.hidden_widths:
            raise ConfigError(f"{MODEL_NAME}: hidden_widths needs at least one width")
        if not isinstance(self.base, str) or not self.base:
            raise ConfigError(f"{MODEL_NAME}: base must name a denoiser, got {self.base!r}")
        object.__setattr__(self, "base", expand_path(self.base))
        object.__setattr__(self, "hidden_widths", tuple(self.hidden_widths))
        _, current = resolve_base(self.base)
        if not self.base_sha256:
            object.__setattr__(self, "base_sha256", current)
        elif self.base_sha256 != current:
            raise mismatch_error(self.base, self.base_sha256, current, MODEL_NAME,
                                 "a Deep Combiner")


# ---------------------------------------------------------------------- model functions
def combiner_net(config: DeepCombinerConfig) -> CombinerNet:
    return CombinerNet(tuple(config.hidden_widths), config.kernel_size)


def dc_init(key: jax.Array, config: DeepCombinerConfig):
    """The combiner's parameters (flax variables ``{"params": ...}``); the base has none
    here: they are its own file's (module docstring)."""
    sample = jnp.zeros((1, 16, 16, INPUT_CHANNELS), jnp.float32)
    return combiner_net(config).init(key, sample)


def checked_base(config: DeepCombinerConfig) -> Denoiser:
    """The base ``config`` names, refused (:class:`BaseMismatchError`) unless its digest is
    the recorded one."""
    base, current = resolve_base(config.base)
    if current != config.base_sha256:
        raise mismatch_error(config.base, config.base_sha256, current, MODEL_NAME,
                             "a Deep Combiner")
    return base


def dc_apply(params, config: DeepCombinerConfig, frame: Frame) -> jax.Array:
    """(..., H, W, 3): the base's output combined with ``frame.color`` (pure, differentiable
    in the frame and in ``params``; the base's weights are constants)."""
    base = checked_base(config)
    for name in ("color", *COMBINER_FEATURES):
        if getattr(frame, name) is None:
            raise FrameError(f"denoiser '{MODEL_NAME}' needs the frame field {name!r}")
    corr = base.definition.apply(base.params, base.config, frame)
    return combiner_output(combiner_net(config), params, corr, frame.color, frame.normal,
                           frame.albedo, frame.depth, config.depth)


def dc_required(config: DeepCombinerConfig) -> tuple[str, ...]:
    base = resolve_base(config.base)[0]
    return tuple(dict.fromkeys(("color", *base.definition.required(base.config),
                                *COMBINER_FEATURES)))


def dc_optional(config: DeepCombinerConfig) -> tuple[str, ...]:
    base = resolve_base(config.base)[0]
    optional = base.definition.optional
    return () if optional is None else tuple(optional(base.config))


register(DenoiserDef(
    name=MODEL_NAME,
    description="Deep Combiner (Back et al. 2020), single buffer: 15 x 15 kernels combine a "
                "frozen base denoiser's output with the noisy colour (trainable)",
    config_cls=DeepCombinerConfig,
    required=dc_required,
    apply=dc_apply,
    init=dc_init,
    optional=dc_optional,
))


# -------------------------------------------------------------------------------- loss
def relmse_channel_mean(prediction, target, eps: float = RELMSE_EPS):
    """Per image ``mean((x - y)^2 / (mean_c(y)^2 + eps))`` over (H, W, C): (..., H, W, C)
    -> (...). The authors' training loss: the denominator is the square of the target's
    mean over the colour channels, one value per pixel."""
    x = jnp.asarray(prediction, jnp.float32)
    y = jnp.asarray(target, jnp.float32)
    if x.ndim < 3 or x.shape != y.shape:
        raise FrameError(f"{LOSS_NAME}: prediction and target must have one shape "
                         f"(..., H, W, C), got {x.shape} and {y.shape}")
    scale = jnp.square(jnp.mean(y, axis=-1, keepdims=True)) + eps
    return jnp.mean(jnp.square(x - y) / scale, axis=(-3, -2, -1))


def _register_loss() -> None:
    from jaxden.train.losses import register_loss

    register_loss(LOSS_NAME, relmse_channel_mean, owner=__name__)


_register_loss()

__all__ = [
    "COMBINER_FEATURES",
    "DEFAULT_BASE",
    "LOSS_NAME",
    "MODEL_NAME",
    "BaseMismatchError",
    "DeepCombinerConfig",
    "base_sha256",
    "checked_base",
    "combiner_net",
    "dc_apply",
    "dc_init",
    "dc_optional",
    "dc_required",
    "relmse_channel_mean",
    "resolve_base",
]
