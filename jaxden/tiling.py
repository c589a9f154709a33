"""Tiles with overlap: run a local image computation over a frame piece by piece, so that its
working memory is set by the tile, not by the frame.

A computation is *local with radius r* when its output at pixel p depends only on inputs within
r pixels of p (a stack of 'SAME' convolutions, a Gaussian local mean of width 3 sigma, the
t-statistic's window). Run it on a tile grown by a halo of at least r on every side that is
inside the frame (edges of the frame are not grown: they are the frame's own edges, padded
there exactly as on the whole frame), keep the tile's centre, and the result equals the
whole-frame result to float rounding. Networks that pool (the U-Net: 2 x 2 max pools, four
times) are local only on their pooling grid: tile origins then sit on multiples of 2^pools
(``multiple``), so that every tile pools the same 16 x 16 blocks as the whole frame.

Whole-frame statistics (the mean variance that sets the t-statistic's Gaussian width, WSKP's
depth normalisation) are computed once on the frame and handed to every tile.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

from jaxden.errors import JaxdenError


@dataclasses.dataclass(frozen=True)
class Tile:
    """One tile: ``out`` the frame region it writes (rows, columns: (start, stop) each),
    ``src`` the region it reads (``out`` grown by the halo, clipped to the frame, start rounded
    down to the alignment), ``inner`` ``out`` in ``src``'s coordinates."""

    out: tuple[tuple[int, int], tuple[int, int]]
    src: tuple[tuple[int, int], tuple[int, int]]

    @property
    def inner(self) -> tuple[slice, slice]:
        (r0, r1), (c0, c1) = self.out
        (s0, _), (t0, _) = self.src
        return slice(r0 - s0, r1 - s0), slice(c0 - t0, c1 - t0)

    @property
    def out_slices(self) -> tuple[slice, slice]:
        return tuple(slice(a, b) for a, b in self.out)  # type: ignore[return-value]

    @property
    def src_slices(self) -> tuple[slice, slice]:
        return tuple(slice(a, b) for a, b in self.src)  # type: ignore[return-value]

    @property
    def src_shape(self) -> tuple[int, int]:
        return self.src[0][1] - self.src[0][0], self.src[1][1] - self.src[1][0]


@dataclasses.dataclass(frozen=True)
class TileSpec:
    """How a stage may be tiled: ``radius`` its receptive field (pixels, each side),
    ``multiple`` the alignment of tile origins (its pooling grid; 1 for plain convolutions).

    For denoisers with whole-frame statistics, ``constants(config, frame)`` computes them on
    the whole frame and ``apply(packed, config, frame)`` is the denoiser on a tile with
    ``packed = {"params": params, "constants": constants}`` (the same signature as
    :attr:`jaxden.denoise.registry.DenoiserDef.apply`, so that wrappers such as the emission
    separation apply to it unchanged)."""

    radius: int
    multiple: int = 1
    constants: Callable[[Any, Any], Any] | None = None
    apply: Callable[[Any, Any, Any], Any] | None = None


def _round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


def tile_grid(height: int, width: int, tile: int, halo: int, multiple: int = 1) -> list[Tile]:
    """Tiles of side at most ``tile`` (rounded up to ``multiple``; equal along each axis)
    covering a ``height`` x ``width`` frame; each reads its region grown by at least ``halo``
    on every side inside the frame.

    Every tile reads a window of the same size, ``tile + 2 halo`` (or the frame's side when
    smaller): tiles at the frame's edges slide their window inward instead of clipping it, so
    one compiled program serves them all. Window starts are rounded down to a multiple of
    ``multiple`` (pooling grids line up; windows of the last tiles may then be up to
    ``multiple - 1`` larger). One tile when the frame fits in one."""
    if tile < 1 or halo < 0 or multiple < 1:
        raise ValueError(f"tile_grid: tile {tile}, halo {halo}, multiple {multiple}")

    def spans(length: int) -> Iterator[tuple[tuple[int, int], tuple[int, int]]]:
        # As many tiles along the axis as side ``tile`` needs, made equal: 1080 rows in
        # tiles of 512 are three of 360, not 512 + 512 + 56 (whose window would be mostly
        # overlap).
        count = -(-length // _round_up(tile, multiple))
        step = _round_up(-(-length // count), multiple)
        size = min(length, step + 2 * halo)
        for start in range(0, length, step):
            stop = min(start + step, length)
            src_start = min(max(0, start - halo), length - size) // multiple * multiple
            src_stop = min(length, max(src_start + size, stop + halo))
            yield (start, stop), (src_start, src_stop)

    return [Tile(out=(rows, cols), src=(src_rows, src_cols))
            for rows, src_rows in spans(height) for cols, src_cols in spans(width)]


def tile_count(height: int, width: int, tile: int) -> int:
    return -(-height // tile) * -(-width // tile)




# ------------------------------------------------------------------------------- running
#: The tile side tried first and the smallest one tried (pixels, before the overlap).
TILE_START, TILE_MIN = 1024, 64
#: The working set of one tile may take at most this share of the memory limit (the rest
#: holds the frame's arrays, the outputs and the Python process itself) and at most
#: TILE_BUDGET_CAP bytes: tiles beyond ~1024^2 pixels are no faster on a CPU.
TILE_BUDGET_SHARE, TILE_BUDGET_CAP = 0.25, 1 << 30


class MemoryPlanError(JaxdenError):
    """A frame whose own arrays, or whose smallest tile, do not fit the memory limit."""


class TileProgram:
    """``fn(*args_for(tile)) -> {name: (h, w, C) array}`` jitted, compiled once per window
    shape (every tile of :func:`tile_grid` but the aligned last ones shares one), with the
    compiled working set of a tile from XLA's memory analysis."""

    def __init__(self, fn: Callable[..., dict], args_for: Callable[[Tile], tuple]):
        import jax

        self._jitted = jax.jit(fn)
        self._args_for = args_for
        self._compiled: dict[tuple[int, int], Any] = {}

    def compiled(self, tile: Tile):
        shape = tile.src_shape
        if shape not in self._compiled:
            self._compiled[shape] = self._jitted.lower(*self._args_for(tile)).compile()
        return self._compiled[shape]

    def working_bytes(self, tile: Tile) -> int | None:
        """Arguments + outputs + temporaries of ``tile``'s program (None: not reported)."""
        try:
            stats = self.compiled(tile).memory_analysis()
        except Exception:
            return None
        if stats is None:
            return None
        return int(stats.temp_size_in_bytes + stats.argument_size_in_bytes
                   + stats.output_size_in_bytes)

    def forget(self) -> None:
        self._compiled.clear()

    def __call__(self, tile: Tile) -> dict:
        return self.compiled(tile)(*self._args_for(tile))


def tile_budget(limit: int, frame_bytes: int, what: str) -> int:
    """Bytes one tile may use: TILE_BUDGET_SHARE of ``limit``, at most TILE_BUDGET_CAP and
    what the frame's own arrays (``frame_bytes``) leave. Refuses (MemoryPlanError, naming
    ``what``) a frame whose arrays alone exceed the limit."""
    from jaxden.limits import format_bytes

    if frame_bytes > limit:
        raise MemoryPlanError(
            f"{what}: the frame's own arrays need about {format_bytes(frame_bytes)}, more than "
            f"the memory limit {format_bytes(limit)} (JAXDEN_MEMORY_LIMIT or the caller's "
            f"limit sets it)")
    return min(int(limit * TILE_BUDGET_SHARE), TILE_BUDGET_CAP, limit - frame_bytes)


def largest_tile(program: TileProgram, height: int, width: int, halo: int, multiple: int,
                 budget: int, what: str) -> tuple[int, int]:
    """The largest tile side (TILE_START, halved down to TILE_MIN) whose compiled working set
    fits ``budget``, and that working set; MemoryPlanError naming ``what`` when even the
    smallest does not fit."""
    from jaxden.limits import format_bytes

    side = min(TILE_START, max(height, width))
    while True:
        needed = program.working_bytes(tile_grid(height, width, side, halo, multiple)[0])
        if needed is None or needed <= budget:
            return side, needed or 0
        if side <= TILE_MIN:
            raise MemoryPlanError(
                f"{what} on the smallest tile ({TILE_MIN} px + {halo} px overlap) needs about "
                f"{format_bytes(needed)}, more than the {format_bytes(budget)} a tile may use")
        program.forget()
        side = max(TILE_MIN, side // 2)


def run_tiles(program: TileProgram, tiles: list[Tile], outputs: dict, progress: bool = False):
    """Run ``program`` on every tile, writing each tile's centre into ``outputs`` (NumPy
    arrays of the frame, by the names the program returns), with a bar when asked."""
    import numpy as np

    bar = None
    if progress and len(tiles) > 1:
        from tqdm import tqdm

        bar = tqdm(total=len(tiles), desc="tiles", unit="tile", leave=False)
    for tile in tiles:
        produced = program(tile)
        rows, cols = tile.out_slices
        for name, value in produced.items():
            if name in outputs:
                outputs[name][rows, cols] = np.asarray(value)[tile.inner]
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
