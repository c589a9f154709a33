"""The neural James-Stein combiner as a trained model (``njs``): its config over a frozen base
denoiser, its checkpoints, and inference from two half buffers.

The combiner itself (cross regressions, network, James-Stein combination) is
:mod:`jaxden.denoise.njs`; this module puts a base denoiser under it. From two independent
half buffers A and B of one image (Frames with colour, variance, albedo, normal, depth and
``spp``):

1. the combined frame ``combine_buffers([A, B])`` (:mod:`jaxden.data.merge`: the mean colour,
   the exactly pooled variance of the mean; one render of twice the samples);
2. the base on each half, ``z_A = base(A)``, ``z_B = base(B)``;
3. the cross regressions ``olsA``, ``olsB`` (:func:`jaxden.denoise.njs.cross_regressions`):
   at test time with the image-wide bandwidth, in training with the per-pixel one (the
   authors');
4. the network and the combination on (combined colour, its variance, olsA, olsB), clamped at
   0 at test time (:func:`jaxden.denoise.njs.njs_apply`).

:func:`njs_inputs_from_halves` is steps 1-3 (the training cache,
:mod:`jaxden.train.njs_cache`, stores its output per dataset item); :func:`njs_denoise` is
all four.

**The base.** ``NJSModelConfig.base`` is a denoiser spec for
:func:`jaxden.denoise.load_denoiser` (default ``oidn-jax``, Intel's OIDN weights in JAX; a
black box such as ``oidn`` works too: NJS never differentiates through its base).
``base_sha256`` (:func:`jaxden.denoise.frozen_base.base_sha256`: the base's name, config
and weights) is filled in when the config is validated and checked whenever it loads again,
as the Deep Combiner does: a run folder of ``njs`` is a whole model, and a run over other base
weights than the base now named is refused (:class:`BaseMismatchError`).

**Checkpoints.** A training run of ``model = "njs"`` writes checkpoints whose meta record says
``kind = "buffer-denoiser"``, ``model = "njs"`` and the ``model_config`` (this config); their
parameters are the network's alone (:func:`jaxden.denoise.njs.njs_init`). :func:`load_njs`
reads one (a run folder, a checkpoint folder, a released ``.msgpack``); ``jaxden denoise IN
--model RUN --buffers A.exr B.exr`` runs it (:data:`NJS_BUFFER_DENOISER`, the entry of
:data:`jaxden.denoise.nfor.BUFFER_DENOISERS`). No tiling: the cross regression's window is 51
pixels and the depth is normalised per image, so NJS runs on whole frames (the base may tile).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.config import bounded, check_fields
from jaxden.denoise.frozen_base import BaseMismatchError, check_base, load_base
from jaxden.denoise.njs import (
    OLS_RIDGE,
    OLS_WINDOW,
    NJSConfig,
    block_side,
    cross_regressions,
    half_buffers,
    njs_apply,
    njs_init,
)
from jaxden.denoise.nn.njs import KERNEL_SIZE, WIDTHS
from jaxden.errors import CheckpointError, ConfigError, FrameError
from jaxden.frame import Frame

#: The trainable model's name (``model = "njs"``) and its checkpoints' ``model``.
NJS_MODEL = "njs"
#: The ``kind`` of its checkpoints' meta record: a denoiser of sub-buffers, not of one frame.
NJS_KIND = "buffer-denoiser"
#: The default base: OIDN in JAX (Intel's weights).
DEFAULT_BASE = "oidn-jax"
#: The fields every half buffer needs (besides those its base reads).
HALF_FIELDS = ("color", "variance", "albedo", "normal", "depth")


def resolve_base(spec: str):
    """``(base Denoiser, its digest)`` for a base spec, read once per process and per version
    of the file it names (:func:`jaxden.denoise.frozen_base.load_base`). ConfigError when it
    does not load."""
    return load_base(spec, NJS_MODEL)


# -------------------------------------------------------------------------------- config
@dataclasses.dataclass(frozen=True)
class NJSModelConfig:
    """``[model_config]`` of ``model = "njs"``: the neural James-Stein combiner over a frozen
    base.

    ``base``: the base denoiser's spec; ``base_sha256``: its digest when the run was trained
    (``""``: filled in from the base as it loads now; another is refused). Training data:
    ``replica``, the replica dataset (``jaxden dataset build ... replica=1``) whose items are
    the B halves of the training dataset's (``data.dataset``) A halves; ``cache``, the folder
    of the cross-regression cache (``""``: ``DATASET/derived/njs-<base>-<key>``,
    :mod:`jaxden.train.njs_cache`); ``build_cache``: build or finish it when training starts
    (else a missing cache is an error); ``train_bandwidth``: the bandwidth of the training
    inputs' cross regressions (``pixel``, the authors'; test time always uses ``image``).
    The combiner: ``widths`` of the network (32, 64, 128), ``kernel_size`` of the combination
    window (15), ``ols_window`` (51) and ``ols_ridge`` (0.1) of the cross regressions."""

    base: str = DEFAULT_BASE
    base_sha256: str = ""
    replica: str = ""
    cache: str = ""
    build_cache: bool = True
    train_bandwidth: Literal["pixel", "image"] = "pixel"
    widths: tuple[int, ...] = WIDTHS
    kernel_size: int = bounded(KERNEL_SIZE, low=3, high=63, unit="pixels")
    ols_window: int = bounded(OLS_WINDOW, low=1, high=255, unit="pixels")
    ols_ridge: float = bounded(OLS_RIDGE, low=0, low_open=True)

    def __post_init__(self):
        from jaxden.paths import expand_path

        check_fields(self)
        if not isinstance(self.base, str) or not self.base:
            raise ConfigError(f"{NJS_MODEL}: base must name a denoiser, got {self.base!r}")
        for name in ("base", "replica", "cache"):
            object.__setattr__(self, name, expand_path(getattr(self, name)))
        object.__setattr__(self, "widths", tuple(self.widths))
        self.njs()  # the combiner's own checks (three widths, odd windows)
        _, current = resolve_base(self.base)
        if not self.base_sha256:
            object.__setattr__(self, "base_sha256", current)
        else:
            check_base(self.base, self.base_sha256, NJS_MODEL, "NJS")

    def njs(self, bandwidth: str = "image") -> NJSConfig:
        """The combiner's :class:`~jaxden.denoise.njs.NJSConfig` (``bandwidth``: of the cross
        regressions it computes; ``image`` at test time)."""
        return NJSConfig(widths=self.widths, kernel_size=self.kernel_size,
                         ols_window=self.ols_window, ols_ridge=self.ols_ridge,
                         bandwidth=bandwidth)


def checked_base(config: NJSModelConfig):
    """The base ``config`` names, refused (:class:`BaseMismatchError`) unless its digest is
    the recorded one."""
    base = check_base(config.base, config.base_sha256, NJS_MODEL, "NJS")
    return base


def njs_model_init(key: jax.Array, config: NJSModelConfig):
    """The network's parameters (the base's are its own file's)."""
    return njs_init(key, config.njs())


def njs_model_apply(params, config: NJSModelConfig, noisy, variance, ols_a, ols_b, *,
                    clamp: bool = True) -> jax.Array:
    """:func:`jaxden.denoise.njs.njs_apply` with ``config``'s combiner (clamped at 0 unless
    ``clamp`` is False, as in training)."""
    return njs_apply(params, noisy, variance, ols_a, ols_b, config.njs(), clamp=clamp)


def njs_meta(config: NJSModelConfig) -> dict[str, Any]:
    """The meta record of an NJS checkpoint: kind, model and config."""
    from jaxden.config import config_to_dict

    return {"kind": NJS_KIND, "model": NJS_MODEL, "model_config": config_to_dict(config)}


# ---------------------------------------------------------------------------- checkpoints
class NJSModel(NamedTuple):
    """A loaded combiner: the network's ``params``, its ``config`` and its ``base``
    (a :class:`jaxden.denoise.Denoiser`, checked against the recorded digest)."""

    params: Any
    config: NJSModelConfig
    base: Any


def load_njs(spec: str | os.PathLike) -> NJSModel:
    """A trained NJS from a training run folder, a checkpoint folder or a released
    ``.msgpack`` (with its ``.json``). CheckpointError when it is not there, holds another
    kind of model, its config does not validate, or its base now loads other weights."""
    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import load_config
    from jaxden.paths import resolve_weights

    path = resolve_weights(spec) or Path(spec)
    if not path.exists():
        raise CheckpointError(f"{spec}: no such run folder or weights file (train NJS with "
                              f"`jaxden train experiments/configs/train-njs.toml`)")
    meta = read_checkpoint_meta(path)
    if (meta.get("kind"), meta.get("model")) != (NJS_KIND, NJS_MODEL):
        raise CheckpointError(f"{path}: holds a {meta.get('kind', 'unknown')!r} checkpoint "
                              f"(model {meta.get('model')!r}), not the neural James-Stein "
                              f"combiner (kind {NJS_KIND!r}, model {NJS_MODEL!r})")
    try:
        config = load_config(meta.get("model_config", {}), NJSModelConfig)
    except ConfigError as error:
        raise CheckpointError(f"{path}: its model_config does not fit {NJS_MODEL!r}: "
                              f"{error}") from None
    target = jax.eval_shape(lambda: njs_model_init(jax.random.PRNGKey(0), config))
    params, _ = load_trained_params(path, target,
                                    expect={"kind": NJS_KIND, "model": NJS_MODEL})
    return NJSModel(params, config, checked_base(config))


def as_njs_model(model) -> NJSModel:
    """An :class:`NJSModel`, or one loaded from a spec (:func:`load_njs`)."""
    if isinstance(model, NJSModel):
        return model
    if isinstance(model, (str, os.PathLike)):
        return load_njs(model)
    raise ConfigError(f"NJS: expected a run folder, a weights file or an NJSModel, got "
                      f"{type(model).__name__}")


# ------------------------------------------------------------------------------ inference
class NJSInputs(NamedTuple):
    """What the network reads, from two half buffers (:func:`njs_inputs_from_halves`), each
    (H, W, 3) float32: ``noisy`` (the combined colour), ``variance`` (its variance of the
    mean), ``ols_a``, ``ols_b``; and ``denoised_a``, ``denoised_b`` (the base on each half);
    ``combined``: the combined Frame."""

    noisy: np.ndarray
    variance: np.ndarray
    ols_a: np.ndarray
    ols_b: np.ndarray
    denoised_a: np.ndarray
    denoised_b: np.ndarray
    combined: Frame


def combined_frame(frame_a: Frame, frame_b: Frame) -> Frame:
    """The two halves as one frame of their samples: :func:`jaxden.data.merge.combine_buffers`
    (exact pooled variance) when both record ``spp``; else the mean colour with the variance
    of the mean ``(var_A + var_B) / 4`` (the spread of the two means unused). Its image
    fields float32."""
    from jaxden.data.merge import combine_buffers

    if frame_a.spp is not None and frame_b.spp is not None:
        combined = combine_buffers([frame_a, frame_b])
    else:
        mean = {name: (np.asarray(getattr(frame_a, name), np.float64)
                       + np.asarray(getattr(frame_b, name), np.float64)) / 2
                for name in frame_a.features()
                if name not in ("variance", "covariance", "boxcox")
                and getattr(frame_b, name) is not None}
        variance = (np.asarray(frame_a.variance, np.float64)
                    + np.asarray(frame_b.variance, np.float64)) / 4
        combined = frame_a.replace(**mean, variance=variance, covariance=None, boxcox=None)
    return combined.replace(**{name: np.asarray(getattr(combined, name), np.float32)
                               for name in combined.features()})


def check_halves(frame_a: Frame, frame_b: Frame, base=None) -> None:
    """FrameError unless both halves have :data:`HALF_FIELDS` (and the base's), one (H, W)."""
    needed = (*HALF_FIELDS, *(() if base is None else base.definition.required(base.config)))
    for name, frame in (("A", frame_a), ("B", frame_b)):
        frame.require(*dict.fromkeys(needed), who=f"NJS (half buffer {name})")
        if np.ndim(frame.color) != 3:
            raise FrameError(f"NJS: half buffer {name} must be one (H, W, 3) image, got colour "
                             f"of shape {np.shape(frame.color)}")
    if np.shape(frame_a.color) != np.shape(frame_b.color):
        raise FrameError(f"NJS: the half buffers differ in size: {np.shape(frame_a.color)} "
                         f"and {np.shape(frame_b.color)}")


def regression_block(height: int, width: int) -> int:
    """The block side of the cross regressions (:func:`jaxden.denoise.njs.block_side`): on
    the CPU the side of at most 64 pixels that cuts the image into the fewest blocks with the
    least overshoot (96 x 96: 48, not 64 with a 128-pixel grid; measured 1.6x faster), 0
    (the whole image) elsewhere. The result does not depend on the block."""
    if jax.default_backend() != "cpu":
        return 0
    side = block_side(0)
    return max(-(-size // -(-size // side)) for size in (height, width))


def njs_inputs_from_halves(base, frame_a: Frame, frame_b: Frame, *, bandwidth="image",
                           window: int = OLS_WINDOW, ridge: float = OLS_RIDGE,
                           tile: int | None = None, limit: int | None = None) -> NJSInputs:
    """Steps 1-3 of the module docstring: the combined frame, the base on each half (over
    tiles where the base tiles: :func:`jaxden.denoise.tiled.denoise_frame`) and the cross
    regressions with ``bandwidth`` (``image`` at test time, ``pixel`` in training)."""
    from jaxden.denoise.tiled import denoise_frame

    check_halves(frame_a, frame_b, base)
    combined = combined_frame(frame_a, frame_b)
    denoised_a, _ = denoise_frame(base, frame_a, tile=tile, limit=limit)
    denoised_b, _ = denoise_frame(base, frame_b, tile=tile, limit=limit)
    half_a, half_b = half_buffers(frame_a, frame_b, denoised_a, denoised_b)
    ols_a, ols_b = cross_regressions(half_a, half_b, bandwidth, window=window, ridge=ridge,
                                     block=regression_block(*np.shape(frame_a.color)[:2]))
    f32 = lambda a: np.asarray(a, np.float32)
    return NJSInputs(f32(combined.color), f32(combined.variance), f32(ols_a), f32(ols_b),
                     f32(denoised_a), f32(denoised_b), combined)


_apply = jax.jit(njs_apply, static_argnames=("config", "clamp"))


def njs_denoise(model, frame_a: Frame, frame_b: Frame, *, tile: int | None = None,
                limit: int | None = None) -> tuple[np.ndarray, Frame]:
    """The trained combiner on two independent half buffers of one image.

    ``model``: a run folder, a checkpoint, a ``.msgpack`` or an :class:`NJSModel`;
    ``frame_a``, ``frame_b``: (H, W, C) Frames with :data:`HALF_FIELDS` (and ``spp`` for the
    exact pooled variance) and whatever the base reads. ``tile``, ``limit``: the base's
    tiling (:func:`jaxden.denoise.tiled.denoise_frame`). The image-wide bandwidth and the
    clamp at 0, as the authors' test step.

    Returns ``(image (H, W, 3) float32, the combined Frame)`` (the frame the image denoises:
    its colour is the halves' mean, its ``spp`` their sum)."""
    model = as_njs_model(model)
    config = model.config
    inputs = njs_inputs_from_halves(model.base, frame_a, frame_b, bandwidth="image",
                                    window=config.ols_window, ridge=config.ols_ridge,
                                    tile=tile, limit=limit)
    image = _apply(model.params, jnp.asarray(inputs.noisy), jnp.asarray(inputs.variance),
                   jnp.asarray(inputs.ols_a), jnp.asarray(inputs.ols_b), config.njs(),
                   clamp=True)
    return np.asarray(image, np.float32), inputs.combined


# ------------------------------------------------------------ the sub-buffer denoiser entry
def njs_required(model: NJSModel) -> tuple[str, ...]:
    """The fields each half buffer needs: :data:`HALF_FIELDS` and the base's."""
    base = model.base
    return tuple(dict.fromkeys((*HALF_FIELDS, *base.definition.required(base.config))))


def njs_denoise_buffers(buffers, model: NJSModel, *, tile: int | None = None,
                        limit: int | None = None, progress: bool = False) -> np.ndarray:
    """``denoise`` of :data:`jaxden.denoise.nfor.BUFFER_DENOISERS`: exactly two half
    buffers; ``tile`` and ``limit`` go to the base."""
    if len(buffers) != 2:
        raise FrameError(f"NJS combines exactly two independent half buffers A and B, got "
                         f"{len(buffers)} (merge renders into two halves first)")
    image, _ = njs_denoise(model, buffers[0], buffers[1], tile=tile, limit=limit)
    return image


def njs_radius(model: NJSModel) -> int:
    """The local receptive field: the cross regression's collaborative window (two radii: a
    pixel reads its window's fits, each fitted over its own window) and the combination's
    (the network's U-Net adds more). The image-wide bandwidth and depth scale make every
    pixel depend on the whole frame a little too, so NJS runs on whole frames."""
    config = model.config
    return 2 * (config.ols_window // 2) + 2 * (config.kernel_size // 2)


__all__ = [
    "DEFAULT_BASE",
    "HALF_FIELDS",
    "NJS_KIND",
    "NJS_MODEL",
    "BaseMismatchError",
    "NJSInputs",
    "NJSModel",
    "NJSModelConfig",
    "as_njs_model",
    "check_halves",
    "checked_base",
    "combined_frame",
    "load_njs",
    "njs_denoise",
    "njs_denoise_buffers",
    "njs_inputs_from_halves",
    "njs_meta",
    "njs_model_apply",
    "njs_model_init",
    "njs_radius",
    "njs_required",
    "regression_block",
    "resolve_base",
]
