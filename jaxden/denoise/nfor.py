"""NFOR: nonlinearly weighted first-order regression (Bitterli et al., EGSR 2016), in pure JAX.

The pipeline follows the first author's public re-implementation in Tungsten
(``src/denoiser``; BASELINES.md section 6); docs/departures.md, "NFOR", lists where jaxden
departs from it. NFOR needs two independent half buffers A and B of the same image:

1. **Feature prefiltering** (cross): every feature channel of half A is NL-means filtered with
   half B's as the guide, and B with A's (patch 7 x 7, window 11 x 11, ``k = 0.5``, variance
   scale 2).
2. **First-order regressions** at each bandwidth ``k`` of ``bandwidths`` (0.5 and 1): colour
   half A is regressed on the prefiltered features of B with NL-means weights from colour
   half B, and B the other way round (cross-filtering). Per pixel ``p``, weighted least
   squares over the 19 x 19 window with the design row ``[1, dx, dy, f(q) - f(p)]``; the fit
   is evaluated at every pixel of the window and the fits are averaged with the same weights
   (*collaborative* regression).
3. **Error estimate** per bandwidth from the halves' cross error,
   ``((B - f_A)^2 - 2 var + (A - f_B)^2 - 2 var) / 2 - (f_B - f_A)^2 / 4`` (the MSE of the
   halves' mean), NL-means filtered (patch 3 x 3, window 19 x 19, ``k = 1``) with the mean
   colour as the guide.
4. **Selection**: per pixel and channel, the bandwidth with the least filtered error (a
   one-hot map, ties to the later bandwidth), the maps NL-means filtered as the error, and
   each half becomes the map-weighted mix of its regressions.
5. **Second pass**: the mean of the prefiltered features (variance from their difference),
   NL-means filtered on itself (patch 7 x 7, window 5 x 5, ``k = 0.5``), and one more
   collaborative regression (``k = 1``) of the mean of the two selected halves on itself,
   with the variance from their difference.

**Variances.** ``variance`` below is always the variance of the mean of the two halves, the
convention of Tungsten's variance buffers (sample variance over all samples / spp), so the
variance scale 2 makes it the variance of one half. Colour: from the buffers' own ``variance``
(``Frame.variance``, the variance of each buffer's mean) when every buffer carries one,
``(var_A + var_B) / 4``; else from the spread of the K buffers, ``sum_k (c_k - mean)^2 /
(K (K - 1))`` (``(A - B)^2 / 4`` for two). Features: jaxden frames carry no feature variance,
so it is always the spread of the buffers' features, as the colour's without own variances.

**Regression** (:mod:`jaxden.denoise.nl_means`). All pixels' small systems are solved at
once: ``lax.scan`` over the window's offsets accumulates ``X^T W X`` (upper triangle) and
``X^T W Y`` per pixel, so memory is ``O(pixels x d^2)`` (d = 3 + feature channels = 10), never
``O(pixels x window)``; the normal equations are scaled to a unit diagonal (Jacobi), a ridge
``ridge`` is added to every coefficient but the intercept, and a batched Cholesky solves them.
Tungsten solves each system by column-pivoted Householder QR instead, without a ridge.

API: :func:`nfor` (two half-buffer Frames), :func:`nfor_frames` (K >= 2 sub-buffers),
:func:`nfor_core` on :class:`NFORInputs`, :func:`denoise_buffers` (tiled, NumPy out; what a
CLI calls), :func:`nfor_radius` (the receptive field), :data:`BUFFER_DENOISERS` (NFOR and
the trained neural James-Stein combiner) and :func:`buffer_denoiser`. Shapes:
``(H, W, C)`` single images (no batch dimensions); linear radiance; pixels.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.config import bounded, check_fields
from jaxden.denoise.njs_model import (
    NJS_KIND,
    NJS_MODEL,
    NJSModel,
    load_njs,
    njs_denoise_buffers,
    njs_radius,
    njs_required,
)
from jaxden.denoise.nl_means import (
    collaborative_regression,
    nl_means,
    nl_means_radius,
    regression_radius,
)
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

#: Features NFOR can regress on, with their channel counts (Tungsten: depth, albedo, normal).
FEATURE_CHANNELS = {"depth": 1, "albedo": 3, "normal": 3, "position": 3}


@dataclasses.dataclass(frozen=True)
class NFORConfig:
    """NFOR's parameters; the defaults are Tungsten's ``nforDenoiser`` (:data:`NFOR_TUNGSTEN`).

    Each NL-means stage has a ``*_patch`` F (patch ``(2F+1)^2``), a ``*_window`` R (search
    window ``(2R+1)^2``) and a bandwidth ``k``. ``features``: the frame fields regressed on (one
    column per channel); ``prefilter_*``: step 1 (``prefilter_variance_scale`` multiplies the
    feature variance); ``regression_patch`` / ``regression_window``: the regressions' NL-means
    patch and window; ``bandwidths``: step 2's ``k`` values; ``regression_variance_scale``:
    multiplies the colour variance in the regressions' weights; ``selection_*``: the filter of
    the error estimates and of the selection maps; ``second_pass``: run step 5 (False: the mean
    of the selected halves is the output); ``final_feature_*``: its feature filter;
    ``final_bandwidth``: its regression's ``k``; ``ridge``: added to the unit-diagonal normal
    equations of every coefficient but the intercept (a jaxden addition; Tungsten has none);
    ``block``: the side of the square blocks the filters sweep their windows over (0: 64 on the
    CPU, the whole image on accelerators; :func:`jaxden.denoise.nl_means.block_side`): speed and memory only, not the
    result.
    """

    features: tuple[str, ...] = ("depth", "albedo", "normal")
    prefilter_patch: int = bounded(3, low=0, high=16)
    prefilter_window: int = bounded(5, low=0, high=32)
    prefilter_bandwidth: float = bounded(0.5, low=0, low_open=True)
    prefilter_variance_scale: float = bounded(2.0, low=0)
    regression_patch: int = bounded(3, low=0, high=16)
    regression_window: int = bounded(9, low=1, high=32)
    bandwidths: tuple[float, ...] = (0.5, 1.0)
    regression_variance_scale: float = bounded(2.0, low=0)
    selection_patch: int = bounded(1, low=0, high=16)
    selection_window: int = bounded(9, low=0, high=32)
    selection_bandwidth: float = bounded(1.0, low=0, low_open=True)
    second_pass: bool = True
    final_feature_patch: int = bounded(3, low=0, high=16)
    final_feature_window: int = bounded(2, low=0, high=32)
    final_feature_bandwidth: float = bounded(0.5, low=0, low_open=True)
    final_bandwidth: float = bounded(1.0, low=0, low_open=True)
    ridge: float = bounded(1e-5, low=1e-6, high=1)
    block: int = bounded(0, low=0)

    def __post_init__(self) -> None:
        check_fields(self)
        unknown = [name for name in self.features if name not in FEATURE_CHANNELS]
        if unknown or len(set(self.features)) != len(self.features):
            raise ConfigError(f"NFORConfig.features: expected distinct names out of "
                              f"{sorted(FEATURE_CHANNELS)}, got {list(self.features)}")
        if not self.bandwidths or any(not k > 0 for k in self.bandwidths):
            raise ConfigError(f"NFORConfig.bandwidths: expected one or more bandwidths > 0, "
                              f"got {list(self.bandwidths)}")


#: Tungsten's parameters (``src/denoiser/denoiser.cpp``).
NFOR_TUNGSTEN = NFORConfig()


class NFORInputs(NamedTuple):
    """What NFOR reads, ``(H, W, C)`` each: the two halves' colours (3) and features (the
    ``features`` channels stacked), and the variances of the halves' *mean* (see the module
    docstring)."""

    color_a: jax.Array
    color_b: jax.Array
    color_variance: jax.Array
    features_a: jax.Array
    features_b: jax.Array
    feature_variance: jax.Array


# ------------------------------------------------------------------------------ the pipeline
def prefilter_features(inputs: NFORInputs, config: NFORConfig = NFOR_TUNGSTEN):
    """Step 1: ``(features_a, features_b)``, each half's features NL-means filtered with the
    other half's as the guide (per channel; one compiled filter, ``lax.map`` over the two)."""
    def one(args):
        image, guide = args
        return nl_means(image, guide, inputs.feature_variance, config.prefilter_patch,
                        config.prefilter_window, config.prefilter_bandwidth,
                        config.prefilter_variance_scale, config.block)

    filtered = jax.lax.map(one, (jnp.stack([inputs.features_a, inputs.features_b]),
                                 jnp.stack([inputs.features_b, inputs.features_a])))
    return filtered[0], filtered[1]


def cross_regressions(inputs: NFORInputs, features_a, features_b,
                      config: NFORConfig = NFOR_TUNGSTEN):
    """Step 2: ``(filtered_a, filtered_b)``, each ``(len(bandwidths), H, W, 3)``: half A
    regressed on B's prefiltered features with weights from B's colour, B the other way round,
    at each bandwidth (one compiled regression, ``lax.map`` over the 2 x bandwidths runs)."""
    runs = len(config.bandwidths)
    stack = lambda a, b: jnp.stack([a] * runs + [b] * runs)
    images = stack(inputs.color_a, inputs.color_b)
    guides = stack(inputs.color_b, inputs.color_a)
    features = stack(features_b, features_a)
    ks = jnp.asarray(list(config.bandwidths) * 2, inputs.color_a.dtype)

    def one(args):
        image, guide, feature, k = args
        return collaborative_regression(
            image, guide, feature, inputs.color_variance, config.regression_patch,
            config.regression_window, k, config.regression_variance_scale, config.ridge,
            config.block)

    filtered = jax.lax.map(one, (images, guides, features, ks))
    return filtered[:runs], filtered[runs:]


def error_estimate(color_a, color_b, color_variance, filtered_a, filtered_b) -> jax.Array:
    """Step 3 before filtering: the MSE of ``(f_A + f_B) / 2`` from the halves' cross errors,
    ``((B - f_A)^2 - 2 var + (A - f_B)^2 - 2 var) / 2 - (f_B - f_A)^2 / 4`` (``var``: of the
    halves' mean; ``f`` may carry a leading bandwidth axis)."""
    error_a = (color_b - filtered_a) ** 2 - 2.0 * color_variance
    error_b = (color_a - filtered_b) ** 2 - 2.0 * color_variance
    return 0.5 * (error_a + error_b) - 0.25 * (filtered_b - filtered_a) ** 2


def select_bandwidths(inputs: NFORInputs, filtered_a, filtered_b,
                      config: NFORConfig = NFOR_TUNGSTEN):
    """Steps 3 and 4: ``(result_a, result_b, selection)``: the error estimates and then the
    one-hot maps of the least error (per pixel and channel; ties to the later bandwidth, as
    Tungsten's ``mse0 < mse1 ? 0 : 1``) NL-means filtered with the halves' mean as the guide;
    ``selection (len(bandwidths), H, W, 3)`` (sums to 1 per pixel and channel) mixes each half's
    regressions. With two bandwidths this is Tungsten's lerp by the filtered map."""
    mean = 0.5 * (inputs.color_a + inputs.color_b)
    filt = functools.partial(nl_means, guide=mean, variance=inputs.color_variance,
                             patch=config.selection_patch, window=config.selection_window,
                             k=config.selection_bandwidth, block=config.block)
    errors = filt(error_estimate(inputs.color_a, inputs.color_b, inputs.color_variance,
                                 filtered_a, filtered_b))
    runs = errors.shape[0]
    best = runs - 1 - jnp.argmin(errors[::-1], axis=0)
    onehot = (jnp.arange(runs)[:, None, None, None] == best[None]).astype(errors.dtype)
    selection = filt(onehot)
    return (jnp.sum(selection * filtered_a, axis=0), jnp.sum(selection * filtered_b, axis=0),
            selection)


def final_pass(features_a, features_b, result_a, result_b,
               config: NFORConfig = NFOR_TUNGSTEN) -> jax.Array:
    """Step 5: the mean features, NL-means filtered on themselves with the variance
    ``(f_B - f_A)^2 / 4``; one collaborative regression of ``(r_A + r_B) / 2`` on itself with the
    variance ``(r_B - r_A)^2 / 4``."""
    features = 0.5 * (features_a + features_b)
    features = nl_means(features, features, 0.25 * (features_b - features_a) ** 2,
                        config.final_feature_patch, config.final_feature_window,
                        config.final_feature_bandwidth, block=config.block)
    color = 0.5 * (result_a + result_b)
    variance = 0.25 * (result_b - result_a) ** 2
    return collaborative_regression(color, color, features, variance, config.regression_patch,
                                    config.regression_window, config.final_bandwidth,
                                    config.regression_variance_scale, config.ridge,
                                    config.block)


def nfor_core(inputs: NFORInputs, config: NFORConfig = NFOR_TUNGSTEN) -> jax.Array:
    """The whole pipeline on :class:`NFORInputs` -> ``(H, W, 3)``. Pure; jit it with ``config``
    static (:func:`nfor` does)."""
    features_a, features_b = prefilter_features(inputs, config)
    filtered_a, filtered_b = cross_regressions(inputs, features_a, features_b, config)
    result_a, result_b, _ = select_bandwidths(inputs, filtered_a, filtered_b, config)
    if not config.second_pass:
        return 0.5 * (result_a + result_b)
    return final_pass(features_a, features_b, result_a, result_b, config)


# ------------------------------------------------------------------------------ inputs
def _spread(values: list) -> jax.Array:
    """The variance of the mean of K >= 2 independent estimates: ``sum (v_k - mean)^2 / (K (K -
    1))``."""
    stack = jnp.stack(values)
    count = stack.shape[0]
    return jnp.sum((stack - jnp.mean(stack, axis=0)) ** 2, axis=0) / (count * (count - 1))


def check_buffers(buffers: Sequence[Frame], config: NFORConfig = NFOR_TUNGSTEN) -> None:
    """Raise FrameError unless ``buffers`` are K >= 2 single ``(H, W, C)`` frames of one size,
    each with colour and ``config.features`` of their channel counts (shapes only: works on
    tracers)."""
    if len(buffers) < 2:
        raise FrameError(f"NFOR needs at least 2 independent buffers of the image, got "
                         f"{len(buffers)}")
    size = np.shape(buffers[0].color)[:-1]
    for i, buffer in enumerate(buffers):
        buffer.require("color", *config.features, who=f"NFOR (buffer {i})")
        if np.ndim(buffer.color) != 3:
            raise FrameError(f"NFOR takes single (H, W, C) images; buffer {i} has colour of "
                             f"shape {np.shape(buffer.color)}")
        for name, channels in (("color", 3), ("variance", 3),
                               *((n, FEATURE_CHANNELS[n]) for n in config.features)):
            value = getattr(buffer, name)
            if value is not None and np.shape(value) != (*size, channels):
                raise FrameError(f"NFOR: buffer {i}'s {name} has shape {np.shape(value)}, "
                                 f"expected {(*size, channels)} (the size of buffer 0)")


def nfor_inputs(buffers: Sequence[Frame], config: NFORConfig = NFOR_TUNGSTEN) -> NFORInputs:
    """:class:`NFORInputs` from K >= 2 independent sub-buffers of one image (``(H, W, C)``
    Frames with ``config.features``): half A the mean of buffers 0, 2, 4, ..., half B of 1, 3,
    ... (Tungsten alternates samples so). Colour variance of the halves' mean: from the
    buffers' own ``variance`` when all carry one (``(var_A + var_B) / 4``, ``var_A = sum_A var_k
    / |A|^2``), else the spread of the K colours; feature variance: the spread of the K
    buffers' features (see the module docstring). Pure."""
    check_buffers(buffers, config)
    halves = (buffers[0::2], buffers[1::2])
    colors = [[jnp.asarray(b.color, jnp.float32) for b in half] for half in halves]
    features = [[jnp.concatenate([jnp.asarray(getattr(b, name), jnp.float32)
                                  for name in config.features], -1) for b in half]
                for half in halves]
    mean = lambda values: sum(values[1:], values[0]) / len(values)
    if all(b.variance is not None for b in buffers):
        half_variance = [sum(jnp.asarray(b.variance, jnp.float32) for b in half) / len(half) ** 2
                         for half in halves]
        color_variance = 0.25 * (half_variance[0] + half_variance[1])
    else:
        color_variance = _spread(colors[0] + colors[1])
    return NFORInputs(color_a=mean(colors[0]), color_b=mean(colors[1]),
                      color_variance=color_variance, features_a=mean(features[0]),
                      features_b=mean(features[1]),
                      feature_variance=_spread(features[0] + features[1]))


@functools.partial(jax.jit, static_argnames="config")
def _nfor_jitted(buffers, config):
    return nfor_core(nfor_inputs(buffers, config), config)


def _used(frame: Frame, config: NFORConfig) -> Frame:
    """``frame`` with only what NFOR reads (one compile whatever else frames carry)."""
    return Frame(color=frame.color, variance=frame.variance,
                 **{name: getattr(frame, name) for name in config.features})


def nfor(buffer_a: Frame, buffer_b: Frame, config: NFORConfig = NFOR_TUNGSTEN) -> jax.Array:
    """NFOR of two independent half buffers (``(H, W, C)`` Frames with colour and
    ``config.features``; their ``variance`` is used when both have one) -> the denoised
    ``(H, W, 3)`` linear radiance (an estimate of the halves' mean). Jitted, pure."""
    return nfor_frames([buffer_a, buffer_b], config)


def nfor_frames(buffers: Sequence[Frame], config: NFORConfig = NFOR_TUNGSTEN) -> jax.Array:
    """NFOR of K >= 2 independent sub-buffers, split into the halves of :func:`nfor_inputs`
    (alternating; for odd K, A has one buffer more) -> ``(H, W, 3)``. Jitted, pure."""
    buffers = list(buffers)
    check_buffers(buffers, config)
    return _nfor_jitted([_used(b, config) for b in buffers], config)


# ------------------------------------------------------------------------------ tiling
def nfor_radius(config: NFORConfig = NFOR_TUNGSTEN) -> int:
    """NFOR's receptive field (pixels, each side): the output at ``p`` depends on the inputs
    within this distance only (65 for :data:`NFOR_TUNGSTEN`)."""
    prefiltered = nl_means_radius(config.prefilter_patch, config.prefilter_window, 0, 0)
    filtered = regression_radius(config.regression_patch, config.regression_window, 0, 0,
                                 prefiltered)
    errors = nl_means_radius(config.selection_patch, config.selection_window, 0, filtered)
    selection = nl_means_radius(config.selection_patch, config.selection_window, 0, errors)
    results = max(selection, filtered)
    if not config.second_pass:
        return results
    features = nl_means_radius(config.final_feature_patch, config.final_feature_window,
                               prefiltered, prefiltered)
    return regression_radius(config.regression_patch, config.regression_window, results,
                             results, features)


@functools.lru_cache(maxsize=16)
def _tile_function(config: NFORConfig):
    """``buffers -> {"image": (h, w, 3)}`` for one config, one function object per config
    (JAX keeps traces and compiled programs per function object: the tiles and frames of one
    size compile once)."""
    return lambda buffers: {"image": _nfor_jitted(buffers, config)}


def denoise_buffers(buffers: Sequence[Frame], config: NFORConfig = NFOR_TUNGSTEN, *,
                    tile: int | None = None, limit: int | None = None,
                    progress: bool = False) -> np.ndarray:
    """NFOR of K >= 2 sub-buffer Frames as NumPy float32 ``(H, W, 3)``, over tiles overlapping
    by :func:`nfor_radius` (the result equals the whole frame's to float round-off). ``tile``:
    the tile side (None: the largest whose compiled working set fits ``limit``, by default
    :func:`jaxden.limits.memory_limit`; 0: the whole frame at once). Validates the frames
    (:meth:`Frame.validated`)."""
    from jaxden.denoise.tiled import window
    from jaxden.limits import memory_limit
    from jaxden.tiling import TileProgram, largest_tile, run_tiles, tile_budget, tile_grid

    buffers = [b.validated(where=f"NFOR buffer {i}") for i, b in enumerate(buffers)]
    check_buffers(buffers, config)
    buffers = [_used(b, config).numpy() for b in buffers]
    if tile == 0:
        return np.asarray(_nfor_jitted(buffers, config), np.float32)
    height, width = np.shape(buffers[0].color)[:2]
    radius = nfor_radius(config)
    program = TileProgram(_tile_function(config), lambda t: ([window(b, t) for b in buffers],))
    limit = memory_limit() if limit is None else int(limit)
    frame_bytes = sum(np.asarray(a).nbytes for b in buffers
                      for a in jax.tree_util.tree_leaves(b)) + height * width * 12
    what = f"NFOR of a {width}x{height} frame"
    if tile is None:
        tile, _ = largest_tile(program, height, width, radius, 1,
                               tile_budget(limit, frame_bytes, what), what)
    outputs = {"image": np.empty((height, width, 3), np.float32)}
    run_tiles(program, tile_grid(height, width, tile, radius), outputs, progress)
    return outputs["image"]


# ------------------------------------------------------------------------------ the hook
@dataclasses.dataclass(frozen=True)
class BufferDenoiserDef:
    """A denoiser of K >= ``min_buffers`` independent sub-buffers of one image (not a
    single-frame :class:`jaxden.denoise.registry.DenoiserDef`): ``denoise(buffers, config,
    tile=, limit=, progress=) -> (H, W, 3)`` NumPy float32; ``required(config)``: the fields
    every buffer needs; ``radius(config)``: its receptive field. ``load``: for a trained
    one, ``load(spec) -> config`` (its weights inside) from a run folder or weights file
    whose checkpoints record ``kind = "buffer-denoiser"`` and this ``name`` as their model
    (:func:`buffer_denoiser`); None: the config is ``config_cls()``."""

    name: str
    description: str
    config_cls: type
    required: Callable[[Any], tuple[str, ...]]
    denoise: Callable[..., np.ndarray]
    radius: Callable[[Any], int]
    min_buffers: int = 2
    load: Callable[[Any], Any] | None = None


#: Sub-buffer denoisers by name (``jaxden denoise --model nfor --buffers A.exr B.exr``).
BUFFER_DENOISERS: dict[str, BufferDenoiserDef] = {
    "nfor": BufferDenoiserDef(
        name="nfor",
        description="NFOR (Bitterli et al. 2016) after Tungsten's re-implementation: two half "
                    "buffers, cross-filtered first-order regressions, no training (JAX)",
        config_cls=NFORConfig,
        required=lambda config: ("color", *config.features),
        denoise=denoise_buffers,
        radius=nfor_radius,
    ),
    NJS_MODEL: BufferDenoiserDef(
        name=NJS_MODEL,
        description="the neural James-Stein combiner (Gu et al. 2022) over a frozen base: "
                    "two half buffers, cross-regressed base outputs, trained (`jaxden train "
                    "experiments/configs/train-njs.toml`; --model names the run folder)",
        config_cls=NJSModel,
        required=njs_required,
        denoise=njs_denoise_buffers,
        radius=njs_radius,
        load=load_njs,
    ),
}


def buffer_denoiser(spec) -> tuple[BufferDenoiserDef, Any] | None:
    """The sub-buffer denoiser ``spec`` (``--model``) names and its config: a name of
    :data:`BUFFER_DENOISERS` (its default config; ConfigError for a trained one, which
    needs its run), or a run folder / weights file whose meta record says ``kind =
    "buffer-denoiser"`` (the entry of its ``model``, the config its ``load`` reads); None
    for anything else (a single-frame denoiser's spec, or a path that holds none)."""
    from pathlib import Path

    from jaxden.errors import CheckpointError

    definition = BUFFER_DENOISERS.get(str(spec))
    if definition is not None:
        if definition.load is not None:
            raise ConfigError(f"{spec} is trained: --model names its run folder (or weights "
                              f"file), not {spec!r}")
        return definition, definition.config_cls()
    if not Path(spec).exists():
        return None
    from jaxden.checkpoint import read_checkpoint_meta

    try:
        meta = read_checkpoint_meta(spec)
    except CheckpointError:
        return None
    definition = BUFFER_DENOISERS.get(str(meta.get("model")))
    if meta.get("kind") != NJS_KIND or definition is None or definition.load is None:
        return None
    return definition, definition.load(spec)
