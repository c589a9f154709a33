"""Display transforms of the report and the demo's previews: exposure in stops, the sRGB tone
map, false-colour maps of scalar errors, and the automatic exposure of a scene.

The page applies the same tone map in JavaScript (``assets/report.js``: ``2**stops * v``,
clip to [0, 1], the sRGB curve, round to 8 bits) to the linear values it embeds, so that the
exposure can change in the page; :func:`tonemap` is its Python twin (and the tests compare
the two). Previews are for looking at images; the numbers in tables come from the EXR values.
"""

from __future__ import annotations

import numpy as np

from jaxden.io.png import preview

#: Colour maps of the report: FLIP's own (magma) for FLIP, viridis for relative squared
#: error and for alpha maps.
COLORMAPS = ("magma", "viridis")
#: The exposure slider's range in stops.
STOPS_RANGE = (-16.0, 16.0)
#: Rec. 709 luminance weights of linear sRGB.
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def exposure(stops: float) -> float:
    """The linear scale of an exposure in stops: ``2 ** stops``."""
    return float(2.0 ** float(stops))


def auto_stops(reference, key: float = 0.18, step: float = 0.5) -> float:
    """The exposure (stops, a multiple of ``step``, rounded down) that brings the log-average
    luminance of the reference to ``key`` (Reinhard et al.'s "key value": middle grey), so
    that a few very bright pixels (a light source) do not darken the whole view.

    ``reference``: linear (H, W, 3). 0 for a reference without a finite pixel above 0."""
    values = np.asarray(reference, np.float64)
    luminance = values[..., :3] @ LUMINANCE if values.shape[-1] >= 3 else values[..., 0]
    luminance = luminance[np.isfinite(luminance) & (luminance > 0)]
    if not luminance.size:
        return 0.0
    average = float(np.exp(np.mean(np.log(luminance))))
    stops = np.floor(np.log2(key / average) / step + 1e-9) * step  # 1e-9: rounding of exact
    return float(np.clip(stops, *STOPS_RANGE))


def tonemap(image, stops: float = 0.0) -> np.ndarray:
    """Linear HDR (H, W, 3) -> uint8 sRGB after an exposure of ``stops``: the page's tone map.
    Non-finite values are refused (:func:`jaxden.io.png.preview`)."""
    return preview(image, exposure(stops))


def alpha_preview(alpha) -> np.ndarray:
    """A mixer's alpha map (H, W, C) in [0, 1] -> uint8 (H, W, 3): alpha per channel as
    colour, linear (white = all denoised, black = all MC input)."""
    alpha = np.asarray(alpha, np.float64)
    if alpha.ndim == 2:
        alpha = alpha[..., None]
    if alpha.shape[-1] == 1:
        alpha = np.repeat(alpha, 3, axis=-1)
    return np.round(np.clip(np.nan_to_num(alpha), 0.0, 1.0) * 255.0).astype(np.uint8)


def colormap_table(name: str) -> np.ndarray:
    """A matplotlib colour map as a (256, 3) uint8 table (what the page indexes)."""
    from matplotlib import colormaps

    return np.round(colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255.0).astype(np.uint8)


def map_position(values, low: float, high: float, log: bool) -> np.ndarray:
    """Where ``values`` fall on a colour bar from ``low`` to ``high``, in [0, 1]; on a log10
    scale if ``log`` (values <= 0 at the bottom). The page computes the same."""
    values = np.nan_to_num(np.asarray(values, np.float64), nan=0.0, posinf=high, neginf=low)
    if log:
        values = np.log10(np.maximum(values, low * 1e-3))
        low, high = np.log10(low), np.log10(high)
    return np.clip((values - low) / (high - low), 0.0, 1.0)


def false_colour(values, low: float, high: float, log: bool = False,
                 colormap: str = "viridis") -> np.ndarray:
    """Scalar map (H, W) -> uint8 (H, W, 3) through ``colormap`` between ``low`` and ``high``."""
    table = colormap_table(colormap)
    index = np.round(map_position(values, low, high, log) * 255.0).astype(np.int64)
    return table[index]


def log_range(maps, decades: int = 4, percentile: float = 99.0) -> tuple[float, float]:
    """A log colour bar shared by error maps: the top is the power of ten at or above the
    ``percentile`` of all their values, the bottom ``decades`` below it."""
    values = np.concatenate([np.ravel(m) for m in maps]) if maps else np.zeros(1)
    values = values[np.isfinite(values) & (values > 0)]
    high = float(np.percentile(values, percentile)) if values.size else 1.0
    top = 10.0 ** np.ceil(np.log10(high)) if high > 0 else 1.0
    return float(top * 10.0 ** -decades), float(top)


__all__ = ["COLORMAPS", "LUMINANCE", "STOPS_RANGE", "alpha_preview", "auto_stops", "colormap_table",
           "exposure", "false_colour", "log_range", "map_position", "tonemap"]
