"""SURE of frames of any size in bounded memory: a JAX denoiser with a receptive field runs
with its jvp (or finite differences) over tiles overlapping by that field; each tile's probes
are its window of the whole frame's (:func:`jaxden.sure.stein.window_normal`), so the result
equals the whole frame's to float rounding. Black boxes run whole-frame, one probe at a time
(:func:`jaxden.sure.stein.sure_blackbox_streamed`)."""

from __future__ import annotations

import functools

import jax
import numpy as np

from jaxden.frame import IMAGE_FIELDS, Frame
from jaxden.limits import memory_limit
from jaxden.sure.settings import SureSettings, resolve_settings
from jaxden.tiling import TileProgram, largest_tile, run_tiles, tile_budget, tile_grid

FIELDS = ("sure", "residual_sq", "divergence_term", "denoised")


def _tile_sure(params, frame, key, origin, eps, *, apply, settings, frame_shape):
    from jaxden.sure.stein import sure

    result = sure(apply, frame, key, eps=eps, settings=settings, params=params,
                  probe_window=(frame_shape, origin))
    return result._asdict()


def sure_frame(denoiser, frame: Frame, key, *, sure: SureSettings | None = None,
               nonfinite: str = "error", where: str = "sure", tile: int | None = None,
               limit: int | None = None, progress: bool = False, on_plan=None, **options):
    """:func:`jaxden.sure.denoise_with_sure` of one frame (``sure`` and the older keywords
    ``options`` as there), over tiles when the denoiser is a JAX denoiser with a receptive
    field (``tile``: the side, None: the largest that fits ``limit``, 0: whole). Returns
    ``(SureResult of NumPy float32, tile)`` (tile 0: whole)."""
    from jaxden.denoise.tiled import blackbox_memory, bound_apply, tile_inputs, window
    from jaxden.sure.denoiser import denoise_with_sure, for_denoiser, resolve_denoiser
    from jaxden.sure.stein import SureResult, require_variance, sure_input

    settings = resolve_settings(sure, **options)
    denoiser = resolve_denoiser(denoiser)
    spec = denoiser.tile_spec() if denoiser.differentiable else None
    if tile == 0 or spec is None or np.ndim(frame.color) != 3:
        with blackbox_memory(denoiser, frame, limit)[0]:
            result, _ = denoise_with_sure(denoiser, frame, key, sure=settings,
                                          nonfinite=nonfinite, where=where)
        return SureResult(*(np.asarray(a, np.float32) for a in result)), 0
    require_variance(frame, where, held_in="EXR channels variance.R/G/B")
    used = {"color", "variance", "covariance", *denoiser.fields_read()}
    frame = frame.replace(**{name: None for name in IMAGE_FIELDS if name not in used})
    frame = sure_input(frame, settings).numpy().validated(where=where, nonfinite=nonfinite)
    denoiser.check_frame(frame)
    settings = for_denoiser(settings, denoiser)
    eps = 1e-4 if settings.eps is None else settings.eps  # traced; jvp ignores it
    height, width = np.shape(frame.color)[:2]
    params, apply = tile_inputs(denoiser, frame)
    run = functools.partial(_tile_sure, apply=bound_apply(apply, denoiser.config),
                            settings=settings, frame_shape=(height, width, 3))

    def args_for(t):
        origin = np.asarray([t.src[0][0], t.src[1][0]], np.int32)
        return (params, window(frame, t), key, origin, np.float32(eps))

    program = TileProgram(run, args_for)
    limit = memory_limit() if limit is None else int(limit)
    frame_bytes = sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(frame))
    frame_bytes += len(FIELDS) * height * width * 12
    what = f"SURE of {denoiser.name} on a {width}x{height} frame"
    budget = tile_budget(limit, frame_bytes, what)
    if tile is None:
        tile, _ = largest_tile(program, height, width, spec.radius, spec.multiple, budget, what)
    tiles = tile_grid(height, width, tile or max(height, width), spec.radius, spec.multiple)
    tile = 0 if len(tiles) == 1 else tile
    if on_plan is not None:
        on_plan(tile, spec.radius)
    outputs = {name: np.empty((height, width, 3), np.float32) for name in FIELDS}
    run_tiles(program, tiles, outputs, progress)
    return SureResult(**outputs), tile
