"""Denoising frames of any size in bounded memory: a JAX denoiser with a receptive field
(:class:`jaxden.tiling.TileSpec`) runs over tiles overlapping by that field, on its pooling
grid, with its whole-frame statistics taken once; black boxes (OIDN, which tiles large frames
itself) and denoisers without a field run on the whole frame."""

from __future__ import annotations

import contextlib
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.frame import IMAGE_FIELDS, Frame
from jaxden.limits import memory_limit
from jaxden.tiling import TileProgram, largest_tile, run_tiles, tile_budget, tile_grid


@dataclasses.dataclass(frozen=True)
class DenoisePlan:
    """``tile`` (0: one tile, the whole frame), ``halo`` (the denoiser's field), the tile's
    compiled working set and the frame's arrays (bytes)."""

    tile: int
    halo: int
    tile_bytes: int
    frame_bytes: int


#: OIDN's scratch when its default would take more. Measured at 3840 x 2160 on the 2 cores
#: (pyoidn 2.5.1, 'high', idle machine, one call): default (~3.2 GB of scratch) 43 s; 2 GiB
#: 47.5 s; 1 GiB 56 s; its own tiles cost time as they shrink.
OIDN_SCRATCH_CAP = 2 << 30


def blackbox_memory(denoiser, frame: Frame, limit: int | None = None):
    """``(context, bytes)`` for a black box on the whole of ``frame``: OIDN's scratch is held
    to OIDN_SCRATCH_CAP and to a quarter of ``limit`` (None:
    :func:`jaxden.limits.memory_limit`) when its default would take more
    (:func:`jaxden.denoise.oidn.max_memory`), and ``bytes`` is what it will use."""
    from jaxden.denoise.oidn import default_memory, max_memory
    from jaxden.tiling import TILE_BUDGET_SHARE

    if denoiser.differentiable or denoiser.name.partition("+")[0] != "oidn":
        return contextlib.nullcontext(), 0
    limit = memory_limit() if limit is None else int(limit)
    needed = default_memory(int(np.prod(np.shape(frame.color)[:-1])))
    cap = min(OIDN_SCRATCH_CAP, int(limit * TILE_BUDGET_SHARE))
    if needed <= cap:
        return contextlib.nullcontext(), needed
    return max_memory(cap >> 20), cap


@functools.lru_cache(maxsize=64)
def bound_apply(apply, config):
    """A stable ``(params, frame) -> image`` per (apply, config): SURE compiles per function
    object, so the same object must come back for every tile and frame."""
    return lambda params, frame: apply(params, config, frame)


@functools.lru_cache(maxsize=64)
def tile_function(apply, config):
    """``(params, tile_frame) -> {"image": (h, w, 3) float32}`` of a denoiser's tile, one
    function object per (apply, config): JAX keeps traces and compiled programs per function
    object, so the frames of a batch that share a size compile once (not once a frame)."""

    def run(params, sub):
        return {"image": jnp.asarray(apply(params, config, sub), jnp.float32)}

    return run


def tile_inputs(denoiser, frame: Frame):
    """``(params, apply)`` for running ``denoiser`` on tiles of ``frame``: the whole-frame
    statistics of its TileSpec packed beside its parameters (see
    :class:`jaxden.tiling.TileSpec`), and ``apply(params, config, tile_frame)``."""
    spec = denoiser.tile_spec()
    if spec.constants is None:
        return denoiser.params, denoiser.definition.apply
    device_frame = jax.tree_util.tree_map(jnp.asarray, frame)
    return ({"params": denoiser.params,
             "constants": spec.constants(denoiser.config, device_frame)}, spec.apply)


def window(frame: Frame, tile) -> Frame:
    """The part of ``frame`` a tile reads (image fields sliced, scalars such as spp kept)."""
    rows, cols = tile.src_slices
    return jax.tree_util.tree_map(lambda a: np.asarray(a)[rows, cols] if np.ndim(a) >= 3 else a,
                                  frame)


def denoise_frame(denoiser, frame: Frame, *, tile: int | None = None, limit: int | None = None,
                  progress: bool = False, on_plan=None):
    """``denoiser(frame)`` as NumPy float32 (H, W, 3), over tiles when the denoiser declares
    its receptive field and the frame is one image (``tile``: the side, None: the largest that
    fits ``limit``, 0: whole). Returns ``(image, plan)`` (plan None when it ran whole)."""
    denoiser.check_frame(frame)
    spec = denoiser.tile_spec() if denoiser.differentiable else None
    if tile == 0 or spec is None or np.ndim(frame.color) != 3:
        with blackbox_memory(denoiser, frame, limit)[0]:
            return np.asarray(denoiser(frame), np.float32), None
    used = {"color", *denoiser.fields_read()}
    frame = frame.replace(**{name: None for name in IMAGE_FIELDS if name not in used}).numpy()
    height, width = np.shape(frame.color)[:2]
    params, apply = tile_inputs(denoiser, frame)
    program = TileProgram(tile_function(apply, denoiser.config),
                          lambda t: (params, window(frame, t)))
    limit = memory_limit() if limit is None else int(limit)
    frame_bytes = sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(frame))
    frame_bytes += height * width * 12
    what = f"denoising a {width}x{height} frame with {denoiser.name}"
    budget = tile_budget(limit, frame_bytes, what)
    estimate = 0
    if tile is None:
        tile, estimate = largest_tile(program, height, width, spec.radius, spec.multiple,
                                      budget, what)
    tiles = tile_grid(height, width, tile or max(height, width), spec.radius, spec.multiple)
    plan = DenoisePlan(tile=0 if len(tiles) == 1 else tile, halo=spec.radius,
                       tile_bytes=estimate, frame_bytes=frame_bytes)
    if on_plan is not None:
        on_plan(plan)
    outputs = {"image": np.empty((height, width, 3), np.float32)}
    run_tiles(program, tiles, outputs, progress)
    return outputs["image"], plan
