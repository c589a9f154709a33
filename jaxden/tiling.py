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
    """Tiles of side ``tile`` (rounded up to ``multiple``) covering a ``height`` x ``width``
    frame; each reads its region grown by at least ``halo`` on every side inside the frame.

    Every tile reads a window of the same size, ``tile + 2 halo`` (or the frame's side when
    smaller): tiles at the frame's edges slide their window inward instead of clipping it, so
    one compiled program serves them all. Window starts are rounded down to a multiple of
    ``multiple`` (pooling grids line up; windows of the last tiles may then be up to
    ``multiple - 1`` larger). One tile when the frame fits in one."""
    if tile < 1 or halo < 0 or multiple < 1:
        raise ValueError(f"tile_grid: tile {tile}, halo {halo}, multiple {multiple}")
    tile = _round_up(tile, multiple)

    def spans(length: int) -> Iterator[tuple[tuple[int, int], tuple[int, int]]]:
        size = min(length, tile + 2 * halo)
        for start in range(0, length, tile):
            stop = min(start + tile, length)
            src_start = min(max(0, start - halo), length - size) // multiple * multiple
            src_stop = min(length, max(src_start + size, stop + halo))
            yield (start, stop), (src_start, src_stop)

    return [Tile(out=(rows, cols), src=(src_rows, src_cols))
            for rows, src_rows in spans(height) for cols, src_cols in spans(width)]


def tile_count(height: int, width: int, tile: int) -> int:
    return -(-height // tile) * -(-width // tile)


