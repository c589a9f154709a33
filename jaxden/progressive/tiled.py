"""Progressive denoising of frames of any size in bounded memory: the pipeline over tiles.

Every stage after the denoiser is local (:mod:`jaxden.tiling`), with these receptive fields
(pixels each side, from the architecture; ``tests/test_tiled.py`` checks each against the
measured support and shows a smaller overlap at the seams):

- the mixer network (PDNet): a 5 x 5 convolution, two residual blocks of two 3 x 3 and a 3 x 3
  output: 2 + 4 + 1 = 7; with the closed form as an input feature, plus the closed form's;
- the closed form (Eq. 9 with Gaussian local means): its taps, ceil(3 sigma) (36 at sigma 12),
  plus the brightness proxy's blur (6) with range strata;
- the t-statistic: half its window (5 for 11 x 11; the noisiest neighbour M_p lies in it too);
  the error guard after it: its Gaussian's taps (3 at sigma 1); the two read alpha, x, y and
  var around p, so the stage after the mixer adds max(5, 3);
- a JAX denoiser: its :class:`jaxden.tiling.TileSpec` (WSKP-6: 6 RepVGG blocks of 5 x 5 and
  kernels up to 13 x 13: 18; the U-Net: 109, on its 16-pixel pooling grid). SURE by jvp
  (or finite differences) on a tile is exact within the denoiser's field: (J b)_p depends on
  b within it, and the tile's probes are the whole frame's (:func:`jaxden.sure.window_normal`).

Whole-frame statistics are taken once on the frame: the t-statistic's Gaussian width (from the
mean variance), WSKP's depth normalisation. The guard's noise strata (``guard_strata``) pool a
whole-frame noise level: frames with it run whole.

A JAX denoiser with a TileSpec runs the whole pipeline per tile (halo = the sum of the three
fields). Black boxes (OIDN) and JAX denoisers without one run whole-frame for y and SURE
(OIDN tiles large frames itself; the finite differences go one probe at a time,
:func:`jaxden.sure.stein.sure_blackbox_streamed`), then the mixer and the t-statistic go
over tiles. With K sub-buffers of the frame (``buffers``), SURE is the sub-buffer SURE of
:func:`jaxden.sure.sure_buffers` (K + 1 whole-frame denoiser calls, no probes) for every
denoiser, and the mixer and the t-statistic go over tiles as for a black box.

Memory is planned before any work (:class:`Plan`): the frame's own arrays, plus the working
set of one tile as XLA's compiled memory analysis reports it; the largest tile that fits the
budget is taken, and a frame for which even the smallest tile does not fit is refused in one
line naming the stage.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import ConfigError
from jaxden.frame import IMAGE_FIELDS, Frame
from jaxden.limits import format_bytes, memory_limit
from jaxden.progressive.closed_form import CLOSED_FORM_PROXY_SIGMA, gaussian_taps
from jaxden.progressive.mixer_config import MixerConfig
from jaxden.progressive.tstat import TStatConfig, tstat_sigma
from jaxden.sure.settings import SureSettings, resolve_settings
from jaxden.tiling import (
    MemoryPlanError,  # noqa: F401  (re-exported)
    Tile,
    TileProgram,
    largest_tile,
    run_tiles,
    tile_budget,
    tile_grid,
)

#: Bytes a pixel that the process holds besides the frame's arrays while a black box runs
#: whole-frame (:func:`jaxden.sure.stein.sure_blackbox_streamed`): y, the float32 probe,
#: perturbed colour and output (48), the float64 sum (24) and OIDN's clipped copies of its
#: colour, albedo and normal (36).
BLACKBOX_BYTES_PER_PIXEL = 108
#: Bytes a pixel that sub-buffer SURE (:func:`jaxden.sure.sure_buffers`, in float64) holds
#: besides the frame's arrays, the K float32 buffers and the denoiser's own: about ten
#: three-channel float64 images (x, y, the buffers' mean, a leave-one-out mean and its denoised
#: image, the running sum, the variance, the squared residual, the results and their float32
#: copies), and SUB_BUFFER_BYTES_PER_PIXEL more a buffer (its float64 copy).
SUB_BUFFER_SURE_BYTES_PER_PIXEL = 240
SUB_BUFFER_BYTES_PER_PIXEL = 24

# --------------------------------------------------------------------------- receptive fields
def taps_radius(sigma: float) -> int:
    return len(gaussian_taps(sigma)) // 2


def closed_form_radius(config: MixerConfig) -> int:
    radius = taps_radius(config.closed_form_sigma)
    if config.closed_form_stops is not None:
        radius += taps_radius(CLOSED_FORM_PROXY_SIGMA)
    return radius


def mixer_radius(config: MixerConfig) -> int:
    """Pixels each side that the mixer's alpha at p reads of x, y, var and SURE."""
    closed_form = closed_form_radius(config)
    if config.kind == "closed_form":
        return closed_form
    from jaxden.progressive.network import get_mixer_network

    network = get_mixer_network(config.network).radius
    if "closed_form" in config.features:
        network += closed_form
    if config.head == "closed_form_logit":
        return max(network, closed_form)
    return network


def tstat_radius(tstat: TStatConfig | None) -> int:
    """Pixels each side that the t-statistic scaling and the error guard read of alpha, x, y
    and var (0 without the scaling)."""
    if tstat is None:
        return 0
    radius = tstat.window // 2
    if tstat.guard:
        from jaxden.progressive.guard import cap_window_radius

        radius = max(radius, cap_window_radius(tstat))
    return radius


def whole_frame_reason(denoiser, tstat: TStatConfig | None) -> str | None:
    """Why nothing of the pipeline may be tiled (None: the mixer stage can be)."""
    if tstat is not None and tstat.guard and tstat.guard_strata is not None:
        return "the error guard's noise strata (tstat.guard_strata) pool a whole-frame level"
    return None


# ------------------------------------------------------------------------------------- plan
@dataclasses.dataclass(frozen=True)
class Plan:
    """How a frame will run: ``tile`` 0 = whole; ``stage`` what runs per tile (``all``: the
    denoiser, SURE, mixer and t-statistic; ``mixer``: the mixer and t-statistic after a
    whole-frame denoiser); the estimated peak and its parts (bytes)."""

    tile: int
    halo: int
    multiple: int
    stage: str
    frame_bytes: int
    tile_bytes: int
    limit: int

    @property
    def peak(self) -> int:
        return self.frame_bytes + self.tile_bytes

    def describe(self, height: int, width: int) -> str:
        if not self.tile:
            return f"whole frame, about {format_bytes(self.peak)}"
        count = len(tile_grid(height, width, self.tile, self.halo, self.multiple))
        return (f"{count} tiles of {self.tile} px + {self.halo} px overlap ({self.stage}), "
                f"about {format_bytes(self.peak)} of {format_bytes(self.limit)}")


# ------------------------------------------------------------------------------------ stages
def _tile_all(denoiser_params, mixer_params, frame, key, origin, eps, sigma, *, apply,
              mixer_config, tstat, swap_average, spp, variance_dof, settings, frame_shape,
              keep):
    """Denoiser, SURE (the tile's window of the frame's probes), mixer, t-statistic: one tile."""
    from jaxden.progressive.pipeline import mix_given_sure
    from jaxden.sure.stein import sure

    result = sure(apply, frame, key, eps=eps, settings=settings, params=denoiser_params,
                  probe_window=(frame_shape, origin))
    z, alpha_prime, alpha, _ = mix_given_sure(
        frame.color, result.denoised, frame.variance, result.sure, mixer_params, mixer_config,
        tstat=tstat, swap_average=swap_average, spp=spp, sigma=sigma, variance_dof=variance_dof)
    parts = {"z": z, "alpha_prime": alpha_prime, "alpha": alpha, "denoised": result.denoised,
             "sure": result.sure, "divergence": result.divergence_term}
    return {name: parts[name] for name in keep}


def _tile_mixer(mixer_params, x, y, var, sure_map, sigma, *, mixer_config, tstat, swap_average,
                spp, variance_dof, keep):
    """Mixer and t-statistic on one tile of a whole-frame denoiser's y and SURE."""
    from jaxden.progressive.pipeline import mix_given_sure

    z, alpha_prime, alpha, _ = mix_given_sure(x, y, var, sure_map, mixer_params, mixer_config,
                                              tstat=tstat, swap_average=swap_average, spp=spp,
                                              sigma=sigma, variance_dof=variance_dof)
    parts = {"z": z, "alpha_prime": alpha_prime, "alpha": alpha}
    return {name: parts[name] for name in keep if name in parts}


@functools.lru_cache(maxsize=64)
def _cached_stage(stage, **options):
    return functools.partial(stage, **options)


def _stage_function(stage, **options):
    """``functools.partial(stage, **options)``, one object per (stage, options): JAX keeps
    traces and compiled programs per function object, so the frames of a batch that share a
    size and settings compile once (not once a frame). Options that cannot be hashed (a
    mixer config holding arrays) get a new object, compiled anew."""
    try:
        return _cached_stage(stage, **options)
    except TypeError:
        return functools.partial(stage, **options)


#: What :func:`progressive_denoise_tiled` can return (``keep``): z', alpha', alpha, y, SURE,
#: var dy/dx.
OUTPUTS = ("z", "alpha_prime", "alpha", "denoised", "sure", "divergence")


def tile_halo(denoiser, mixer_config: MixerConfig, tstat: TStatConfig | None,
              whole_frame_denoiser: bool = False) -> int:
    """The overlap the pipeline needs (module docstring): the denoiser's field when it runs
    per tile (not with ``whole_frame_denoiser``: sub-buffer SURE), the mixer's and the
    t-statistic's."""
    spec = (denoiser.tile_spec() if denoiser.differentiable and not whole_frame_denoiser
            else None)
    return (mixer_radius(mixer_config) + tstat_radius(tstat)
            + (spec.radius if spec is not None else 0))


def progressive_denoise_tiled(frame: Frame, denoiser, mixer_params, mixer_config: MixerConfig,
                              key, *, tstat: TStatConfig | None,
                              sure: SureSettings | None = None,
                              swap_average: bool | None = None,
                              keep: tuple[str, ...] = ("z", "alpha_prime", "alpha"),
                              tile: int | None = None, halo: int | None = None,
                              limit: int | None = None, progress: bool = False,
                              plan_only: bool = False, on_plan=None, buffers=None, **options):
    """:func:`jaxden.progressive.progressive_denoise` over tiles: the same outputs (to float
    rounding) in memory set by the tile (module docstring).

    ``frame``: one validated image (H, W, 3), NumPy (the caller validates it once, as
    :func:`jaxden.sure.denoise_with_sure` does). ``sure``: the
    :class:`~jaxden.sure.settings.SureSettings` (unset fields: the mixer's; the older keywords
    ``options``, ``num_probes=`` and the rest, override it where given). ``keep``: which of
    :data:`OUTPUTS` to return. ``tile``: the tile side (None: the largest that fits
    ``limit``, default :func:`jaxden.limits.memory_limit`; 0: the whole frame as one tile).
    ``halo``: the overlap (None: :func:`tile_halo`; smaller only to show the seams).
    ``progress``: a bar over tiles. ``plan_only``: return ``(None, plan)`` without running;
    ``on_plan(plan)`` is called before the work starts (the command line tells the plan).
    ``buffers``: (K, H, W, 3) colours of K >= 2 independent sub-buffers whose mean is the
    frame's colour: SURE is then their sub-buffer SURE (:func:`jaxden.sure.sure_buffers`;
    ``divergence`` its covariance term) instead of probe SURE, with the denoiser on the whole
    frame and the mixer stage over tiles; ``sure`` and ``key`` then go unused.

    Returns ``(outputs, plan)``: float32 NumPy arrays (H, W, 3) by name, and the :class:`Plan`.
    Raises MemoryPlanError when the frame's arrays, or its smallest tile, do not fit.
    """
    from jaxden.denoise.tiled import blackbox_memory, bound_apply, tile_inputs, window
    from jaxden.sure.buffers import sure_buffers
    from jaxden.sure.denoiser import for_denoiser, resolve_denoiser
    from jaxden.sure.stein import sure_blackbox_streamed, sure_input

    settings = resolve_settings(sure, mixer_config.sure, **options)
    denoiser = resolve_denoiser(denoiser)
    unknown = sorted(set(keep) - set(OUTPUTS))
    if unknown:
        raise ConfigError(f"progressive_denoise_tiled: unknown outputs {unknown}; "
                          f"choose from {', '.join(OUTPUTS)}")
    color = np.asarray(frame.color, np.float32)
    if color.ndim != 3:
        raise ConfigError(f"progressive_denoise_tiled: one image (H, W, 3), got {color.shape}")
    reason = whole_frame_reason(denoiser, tstat)
    if reason is not None and tile != 0:
        raise ConfigError(f"progressive_denoise_tiled: {reason}: run the frame whole")
    if buffers is not None:
        buffers = np.asarray(buffers, np.float32)
        if buffers.ndim != 4 or buffers.shape[1:] != color.shape:
            raise ConfigError(f"progressive_denoise_tiled: buffers must be (K, *{color.shape}), "
                              f"got {buffers.shape}")
    spec = (denoiser.tile_spec() if denoiser.differentiable and buffers is None else None)
    if denoiser.differentiable and spec is None and buffers is None:
        raise ConfigError(
            f"progressive_denoise_tiled: denoiser '{denoiser.name}' declares no receptive "
            f"field (TileSpec): it runs on whole frames only")
    frame = sure_input(frame, settings)  # without the covariance the mixer did not learn
    if swap_average is None:
        swap_average = mixer_config.swap_average
    settings = for_denoiser(settings, denoiser)
    eps = 1e-4 if settings.eps is None else settings.eps  # traced; jvp ignores it
    height, width = color.shape[:2]
    spp = None if frame.spp is None else float(np.asarray(frame.spp))
    variance_dof = (None if frame.variance_dof is None
                    else float(np.asarray(frame.variance_dof)))
    sigma = None if tstat is None else tstat_sigma(jnp.asarray(frame.variance), tstat)
    stage = "all" if spec is not None else "mixer"
    multiple = spec.multiple if spec is not None else 1
    halo = (tile_halo(denoiser, mixer_config, tstat, whole_frame_denoiser=buffers is not None)
            if halo is None else int(halo))
    limit = memory_limit() if limit is None else int(limit)
    frame_bytes = sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(frame))
    frame_bytes += len(keep) * color.nbytes
    blackbox_context, blackbox_bytes = blackbox_memory(denoiser, frame, limit)
    if buffers is not None:
        frame_bytes += buffers.nbytes + blackbox_bytes + height * width * (
            SUB_BUFFER_SURE_BYTES_PER_PIXEL + SUB_BUFFER_BYTES_PER_PIXEL * len(buffers))
    elif stage == "mixer":
        frame_bytes += BLACKBOX_BYTES_PER_PIXEL * height * width + blackbox_bytes

    if stage == "all":
        params, apply = tile_inputs(denoiser, frame)
        apply = bound_apply(apply, denoiser.config)
        run_tile = _stage_function(
            _tile_all, apply=apply, mixer_config=mixer_config, tstat=tstat,
            swap_average=bool(swap_average), spp=spp, variance_dof=variance_dof,
            settings=settings, frame_shape=(height, width, 3), keep=tuple(keep))

        def tile_args(tile_: Tile, arrays):
            sub = window(frame, tile_)
            origin = np.asarray([tile_.src[0][0], tile_.src[1][0]], np.int32)
            return (params, mixer_params, sub, key, origin, np.float32(eps), sigma)
    else:
        run_tile = _stage_function(
            _tile_mixer, mixer_config=mixer_config, tstat=tstat,
            swap_average=bool(swap_average), spp=spp, variance_dof=variance_dof,
            keep=tuple(keep))

        def tile_args(tile_: Tile, arrays):
            rows, cols = tile_.src_slices
            return (mixer_params, *(arrays[n][rows, cols] for n in ("x", "y", "var", "sure")),
                    sigma)

    # ``arrays`` is read when a tile runs: stand-ins of the right shape while planning, the
    # frame's x, var, y and SURE after the whole-frame stage.
    program = TileProgram(run_tile, lambda tile_: tile_args(tile_, arrays))
    what = (f"progressive denoising of a {width}x{height} frame"
            + (": the denoiser, SURE, mixer and t-statistic" if stage == "all"
               else ": the mixer and t-statistic")
            + ("" if buffers is None else f" (SURE from {len(buffers)} sub-buffers)"))
    arrays = {"x": color, "y": color, "var": color, "sure": color}  # for planning: shapes
    budget = tile_budget(limit, frame_bytes, what)
    estimate = 0
    if tile is None:
        tile, estimate = largest_tile(program, height, width, halo, multiple, budget, what)
    tile = tile or max(height, width)
    tiles = tile_grid(height, width, tile, halo, multiple)
    plan = Plan(tile=0 if len(tiles) == 1 else tile, halo=halo, multiple=multiple, stage=stage,
                frame_bytes=frame_bytes, tile_bytes=estimate, limit=limit)
    if plan_only:
        return None, plan
    if on_plan is not None:
        on_plan(plan)

    outputs = {name: np.empty_like(color) for name in keep}
    arrays = {"x": color, "var": np.asarray(frame.variance, np.float32)}
    if stage == "mixer":
        with blackbox_context:
            if buffers is None:
                result = sure_blackbox_streamed(denoiser.function(), frame, key, settings)
            else:
                result = sure_buffers(denoiser, frame, buffers)
        arrays |= {"y": result.denoised, "sure": result.sure}
        for name, value in (("denoised", result.denoised), ("sure", result.sure),
                            ("divergence", result.divergence_term)):
            if name in outputs:
                outputs[name][...] = value
        del result
    run_tiles(program, tiles, outputs, progress)
    return outputs, plan


def progressive_frame(frame: Frame, denoiser, mixer_params, mixer_config: MixerConfig, key, *,
                      sure: SureSettings | None = None, tstat="config",
                      swap_average: bool | None = None, nonfinite: str = "error",
                      keep: tuple[str, ...] = ("z", "alpha_prime", "alpha"),
                      tile: int | None = None, limit: int | None = None,
                      progress: bool = False, on_plan=None, buffers=None, **options):
    """Progressive denoising of one frame as the command line runs it: validated once, then
    over tiles when every stage allows (:func:`progressive_denoise_tiled`, planned from the
    memory limit), else whole (:func:`jaxden.progressive.progressive_denoise`: batched frames,
    the guard's noise strata, JAX denoisers without a receptive field, ``tile=0``).

    ``sure``: the :class:`~jaxden.sure.settings.SureSettings`, unset fields the mixer's (the
    older keywords ``options``, ``num_probes=`` and the rest, override it where given).
    ``tstat``: ``"config"`` (the mixer's), a :class:`TStatConfig` or None (no scaling).
    ``buffers``: (K, H, W, 3) sub-buffer colours of the (one) frame: SURE from them
    (:func:`progressive_denoise_tiled`; whole-frame denoiser, the mixer stage over tiles, or
    as one tile where something must run whole). A denoiser other than the mixer's is mixed
    with a warning (:func:`jaxden.progressive.pipeline.warn_if_other_denoiser`).
    Returns ``(outputs, plan)``: float32 NumPy arrays by name (``keep``, from :data:`OUTPUTS`)
    and the :class:`Plan` (None when the frame ran whole through the untiled pipeline).
    """
    from jaxden.progressive.pipeline import progressive_denoise, warn_if_other_denoiser
    from jaxden.sure.denoiser import resolve_denoiser
    from jaxden.sure.stein import require_variance, sure_input

    settings = resolve_settings(sure, mixer_config.sure, **options)
    spec, denoiser = denoiser, resolve_denoiser(denoiser)
    warn_if_other_denoiser(mixer_config, denoiser, spec)
    if isinstance(tstat, str):
        tstat = mixer_config.tstat
    require_variance(frame, "progressive_denoise", held_in="EXR channels variance.R/G/B")
    # Fields no stage reads (depth for OIDN, motion, position, ...) are dropped first: at
    # 7680 x 4320 each three-channel field is 400 MB.
    used = {"color", "variance", "covariance", *denoiser.fields_read()}
    frame = frame.replace(**{name: None for name in IMAGE_FIELDS if name not in used})
    frame = sure_input(frame, settings).numpy().validated(where="progressive_denoise",
                                                          nonfinite=nonfinite)
    denoiser.check_frame(frame)
    common = {"sure": settings, "swap_average": swap_average, "keep": keep, "limit": limit,
              "progress": progress, "on_plan": on_plan}
    if buffers is not None:
        if np.ndim(frame.color) != 3:
            raise ConfigError(f"progressive_denoise: sub-buffer SURE takes one image (H, W, 3), "
                              f"got {np.shape(frame.color)}")
        whole = tile == 0 or whole_frame_reason(denoiser, tstat) is not None
        return progressive_denoise_tiled(frame, denoiser, mixer_params, mixer_config, key,
                                         tstat=tstat, tile=0 if whole else tile,
                                         buffers=buffers, **common)
    tileable = (np.ndim(frame.color) == 3 and whole_frame_reason(denoiser, tstat) is None
                and (not denoiser.differentiable or denoiser.tile_spec() is not None))
    if tile != 0 and tileable:
        return progressive_denoise_tiled(frame, denoiser, mixer_params, mixer_config, key,
                                         tstat=tstat, tile=tile, **common)
    z, alpha_prime, extras = progressive_denoise(
        frame, denoiser, mixer_params, mixer_config, key, sure=settings, tstat=tstat,
        nonfinite=nonfinite, swap_average=swap_average)
    everything = {"z": z, "alpha_prime": alpha_prime, "alpha": extras["alpha"],
                  "denoised": extras["denoised"], "sure": extras["sure"],
                  "divergence": extras["divergence"]}
    return {name: np.asarray(everything[name], np.float32) for name in keep}, None
