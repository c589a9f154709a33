"""SVGF: spatiotemporal variance-guided filtering (Schied et al., HPG 2017), in pure JAX.

The pipeline per frame, as in Falcor's ``SVGFPass`` (docs/departures.md, "SVGF", lists where
jaxden departs from it and from the paper):

1. **Demodulate** the colour by the albedo: ``illum = colour / max(albedo, 0.001)``.
2. **Reproject** the previous frame's filtered illumination, luminance moments and history
   length to this frame with the motion vectors (``prev_xy = xy + motion``), four bilinear taps,
   each tested for depth and normal consistency; failed taps are dropped and the weights of the
   rest renormalised; with none left, a 3 x 3 neighbourhood is tried, then history resets.
3. **Accumulate** colour and moments ``(l, l^2)`` by an exponential moving average with
   ``max(alpha, 1 / history)``; variance ``max(0, m2 - m1^2)``.
4. Where the history is short (``< history_threshold``), **estimate the variance spatially**
   from the moments under a 7 x 7 bilateral filter (which also filters the colour there).
5. **A-trous wavelet iterations**: a 5 x 5 B3-spline kernel at step ``2^i`` with edge-stopping
   weights on luminance (scaled by the 3 x 3 Gaussian-prefiltered standard deviation), normal and
   depth; the variance is filtered alongside with squared weights. The output of iteration
   ``feedback_iteration`` becomes the next frame's colour history.
6. **Remodulate**: ``out = max(albedo, 0.001) * filtered``.

``svgf_step(state, frame, config)`` runs one frame of a sequence, ``svgf_sequence(frames,
config)`` a list, and the registered denoiser ``svgf`` is the single-frame spatial form (no
history: spatial variance estimate and the a-trous iterations), pure and differentiable JAX:
``make_denoiser("svgf")``, ``load_denoiser("svgf:preset=falcor")``.

Shapes: images are ``(..., H, W, C)`` for the spatial functions (leading batch dimensions
allowed) and ``(H, W, C)`` for those that carry history (reprojection, step, sequence).
Units: linear radiance, pixels, depth in the frame's own units (distance along the ray; 0 on
misses).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxden.config import bounded, check_fields
from jaxden.denoise.nn.wskp import safe_albedo
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.denoise.temporal import bilinear_taps
from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.tiling import TileSpec

#: Rec. 709 luminance weights (Falcor ColorHelpers.slang).
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
#: The albedo below which demodulation stops dividing (Falcor SVGFReproject).
ALBEDO_GUARD = 1e-3
#: Separable a-trous weights indexed by |offset| (B3 spline {1/16, 1/4, 3/8, 1/4, 1/16} / (3/8)).
ATROUS_WEIGHTS = (1.0, 2.0 / 3.0, 1.0 / 6.0)
#: 3 x 3 Gaussian prefilter of the variance indexed by (|dy|, |dx|).
GAUSS3_WEIGHTS = ((1 / 4, 1 / 8), (1 / 8, 1 / 16))
_VARIANCE_EPS = 1e-10
_DEPTH_EPS = 1e-8


@dataclasses.dataclass(frozen=True)
class SVGFConfig:
    """SVGF's parameters; the defaults are the paper's (:data:`SVGF_PAPER`), Falcor's are
    :data:`SVGF_FALCOR` (BASELINES.md section 1).

    ``alpha_color`` / ``alpha_moments``: blend factors of the temporal moving averages (the
    blend is ``max(alpha, 1 / history)``); ``phi_color`` / ``phi_normal`` / ``phi_depth``: the
    edge-stopping sigmas; ``iterations``: a-trous passes (steps 1, 2, 4, ...);
    ``feedback_iteration``: the pass whose output is the next frame's colour history (-1: the
    unfiltered accumulated colour); ``history_threshold``: below this history length the
    variance comes from the spatial estimate (radius ``spatial_radius``); ``history_cap``: the
    largest history length; ``depth_tolerance`` / ``normal_tolerance``: the reprojection tests
    ``|z - z_prev| / (dz + 0.01) <= depth_tolerance`` and ``|n - n_prev| / (fwidth n + 0.01) <=
    normal_tolerance``; ``variance_prefilter``: blur the variance 3 x 3 before each pass;
    ``reprojection_fallback``: try a 3 x 3 neighbourhood when no bilinear tap is valid;
    ``albedo_floor``: the albedo (de)modulation divides by WSKP's safe albedo
    (:func:`jaxden.denoise.nn.wskp.safe_albedo`: the albedo from this floor up, a ramp to 1
    below it), so no pixel's illumination is amplified more than 1 / floor; 0: Falcor's
    ``max(albedo, 0.001)`` (docs/departures.md, "SVGF": dark albedo amplified up to 1000x
    spreads into the neighbours' history).
    """

    alpha_color: float = bounded(0.2, low=0, low_open=True, high=1)
    alpha_moments: float = bounded(0.2, low=0, low_open=True, high=1)
    phi_color: float = bounded(4.0, low=0, low_open=True)
    phi_normal: float = bounded(128.0, low=0)
    phi_depth: float = bounded(1.0, low=0, low_open=True)
    iterations: int = bounded(5, low=0, high=10)
    feedback_iteration: int = bounded(0, low=-1, high=9)
    history_threshold: float = bounded(4.0, low=0)
    history_cap: float = bounded(32.0, low=1)
    spatial_radius: int = bounded(3, low=0, high=16)
    depth_tolerance: float = bounded(10.0, low=0, low_open=True)
    normal_tolerance: float = bounded(16.0, low=0, low_open=True)
    variance_prefilter: bool = True
    reprojection_fallback: bool = True
    albedo_floor: float = bounded(0.05, low=0, high=1)

    def __post_init__(self) -> None:
        check_fields(self)
        if self.feedback_iteration >= max(self.iterations, 1) and self.iterations > 0:
            raise ConfigError(
                f"SVGFConfig: feedback_iteration {self.feedback_iteration} needs at least "
                f"{self.feedback_iteration + 1} iterations, got iterations = {self.iterations}")
        if self.iterations == 0 and self.feedback_iteration >= 0:
            raise ConfigError("SVGFConfig: with iterations = 0 the history can only be the "
                              "unfiltered colour: set feedback_iteration = -1")


#: The paper's parameters: alpha 0.2, phi 4 / 128 / 1, 5 iterations, feedback from the first.
SVGF_PAPER = SVGFConfig()
#: Falcor's SVGFPass defaults: alpha 0.05 (colour) and 0.2 (moments), phi_color 10,
#: 4 iterations, feedback from the second (step 2).
SVGF_FALCOR = SVGFConfig(alpha_color=0.05, alpha_moments=0.2, phi_color=10.0, iterations=4,
                         feedback_iteration=1)
#: Presets by name (the denoiser spec option ``svgf:preset=NAME``).
SVGF_PRESETS: dict[str, SVGFConfig] = {"paper": SVGF_PAPER, "falcor": SVGF_FALCOR}


class SVGFState(NamedTuple):
    """History carried from frame to frame (all ``(H, W, C)``; demodulated units)."""

    color: jax.Array  # (H, W, 3) filtered illumination (the feedback iteration's output)
    moments: jax.Array  # (H, W, 2) accumulated luminance moments (l, l^2)
    history: jax.Array  # (H, W, 1) history length in frames (0: none)
    depth: jax.Array  # (H, W, 1) this frame's depth, for the next frame's test
    normal: jax.Array  # (H, W, 3) this frame's normal


# ------------------------------------------------------------------------------ helpers
def luminance(color: jax.Array) -> jax.Array:
    """Rec. 709 luminance: ``(..., H, W, 3) -> (..., H, W, 1)``."""
    return color @ jnp.asarray(LUMINANCE_WEIGHTS, color.dtype)[:, None]


def shift(image: jax.Array, dy: int, dx: int) -> tuple[jax.Array, jax.Array]:
    """``image[y + dy, x + dx]`` for every pixel, 0 outside: ``(..., H, W, C)`` and the mask
    ``inside (H, W, 1)`` (bool) of pixels whose source lies in the image."""
    height, width = image.shape[-3], image.shape[-2]
    pad = [(0, 0)] * (image.ndim - 3) + [(abs(dy), abs(dy)), (abs(dx), abs(dx)), (0, 0)]
    padded = jnp.pad(image, pad)
    out = padded[..., abs(dy) + dy: abs(dy) + dy + height, abs(dx) + dx: abs(dx) + dx + width, :]
    ys = jnp.arange(height)[:, None, None] + dy
    xs = jnp.arange(width)[None, :, None] + dx
    inside = (ys >= 0) & (ys < height) & (xs >= 0) & (xs < width)
    return out, inside


def _split(stack: jax.Array, sizes: tuple[int, ...]) -> list[jax.Array]:
    """``stack (..., C)`` cut into consecutive channel groups of ``sizes``."""
    bounds = [sum(sizes[:i]) for i in range(len(sizes) + 1)]
    return [stack[..., a:b] for a, b in itertools.pairwise(bounds)]


def neighbour_scan(tap, init, images, offsets, with_index: bool = False):
    """Fold ``tap`` over the neighbours ``p + (dy, dx)`` of every pixel, for ``offsets`` a
    static list of ``(dy, dx)``, by ``lax.scan`` (one compiled body, however many taps).

    ``images``: ``(..., H, W, C_k)`` arrays; the body sees them at the neighbour concatenated
    along channels, followed by one channel ``inside`` (1 where the neighbour lies in the image,
    0 outside, where the values are 0): ``tap(carry, q, distance[, index]) -> carry``,
    ``distance = |(dy, dx)|``."""
    stack = jnp.concatenate([*images, jnp.ones_like(images[0][..., :1])], axis=-1)
    height, width = stack.shape[-3], stack.shape[-2]
    pad = max(max(abs(dy), abs(dx)) for dy, dx in offsets)
    padded = jnp.pad(stack, [(0, 0)] * (stack.ndim - 3) + [(pad, pad), (pad, pad), (0, 0)])
    lead = (0,) * (stack.ndim - 3)
    size = stack.shape[:-3] + (height, width, stack.shape[-1])
    dys = jnp.asarray([dy for dy, _ in offsets], jnp.int32)
    dxs = jnp.asarray([dx for _, dx in offsets], jnp.int32)
    distances = jnp.asarray([(dy * dy + dx * dx) ** 0.5 for dy, dx in offsets], stack.dtype)

    def body(carry, xs):
        dy, dx, distance, index = xs
        start = (*lead, pad + dy, pad + dx, 0)  # one index type, also under x64
        q = jax.lax.dynamic_slice(padded, tuple(jnp.asarray(i, jnp.int32) for i in start), size)
        args = (distance, index) if with_index else (distance,)
        return tap(carry, q, *args), None

    carry, _ = jax.lax.scan(body, init, (dys, dxs, distances, jnp.arange(len(offsets))))
    return carry


def _one_sided_min(image: jax.Array, axis: int) -> jax.Array:
    """Per pixel, the smaller (by norm over channels) of the forward and backward differences
    along ``axis`` (-3: y, -2: x); one-sided at the image's edges. ``(..., H, W, C)``."""
    dy, dx = (1, 0) if axis == -3 else (0, 1)
    forward, inside_f = shift(image, dy, dx)
    backward, inside_b = shift(image, -dy, -dx)
    forward = jnp.where(inside_f, forward - image, jnp.inf)
    backward = jnp.where(inside_b, image - backward, jnp.inf)
    size = image.shape[axis]
    if size == 1:
        return jnp.zeros_like(image)
    norm_f = jnp.sum(forward * forward, axis=-1, keepdims=True)
    norm_b = jnp.sum(backward * backward, axis=-1, keepdims=True)
    return jnp.where(norm_f <= norm_b, forward, backward)


def depth_slope(depth: jax.Array) -> jax.Array:
    """Screen-space depth slope ``max(|dz/dx|, |dz/dy|)`` per pixel, each derivative the
    smaller one-sided difference (the slope of the surface the pixel lies on, not of a depth
    jump beside it): ``(..., H, W, 1) -> (..., H, W, 1)``, depth units per pixel."""
    return jnp.maximum(jnp.abs(_one_sided_min(depth, -2)), jnp.abs(_one_sided_min(depth, -3)))


def normal_width(normal: jax.Array) -> jax.Array:
    """``length(fwidth(normal))`` with ``fwidth = |d/dx| + |d/dy|`` (one-sided differences as
    :func:`depth_slope`): ``(..., H, W, 3) -> (..., H, W, 1)``."""
    width = jnp.abs(_one_sided_min(normal, -2)) + jnp.abs(_one_sided_min(normal, -3))
    return jnp.sqrt(jnp.sum(width * width, axis=-1, keepdims=True) + 1e-30)


def guarded_albedo(albedo: jax.Array, floor: float = 0.0) -> jax.Array:
    """The albedo SVGF divides by: WSKP's safe albedo above ``floor`` > 0
    (:func:`jaxden.denoise.nn.wskp.safe_albedo`), Falcor's ``max(albedo, 0.001)`` for 0."""
    return safe_albedo(albedo, floor) if floor > 0 else jnp.maximum(albedo, ALBEDO_GUARD)


def demodulate(color: jax.Array, albedo: jax.Array, floor: float = 0.0) -> jax.Array:
    """Untextured illumination ``color / guarded_albedo(albedo, floor)`` (``floor`` 0:
    ``max(albedo, 0.001)``), NaN set to 0: ``(..., H, W, 3), (..., H, W, 3) -> (..., H, W, 3)``."""
    illum = color / guarded_albedo(albedo, floor)
    return jnp.where(jnp.isnan(illum), 0.0, illum)


def remodulate(illum: jax.Array, albedo: jax.Array, floor: float = 0.0) -> jax.Array:
    """``guarded_albedo(albedo, floor) * illum``, the inverse of :func:`demodulate`:
    ``(..., H, W, 3) -> (..., H, W, 3)``."""
    return illum * guarded_albedo(albedo, floor)


def edge_weight(depth_p, depth_q, phi_z, normal_p, normal_q, phi_normal, lum_p, lum_q, phi_l,
                centre=False):
    """SVGF's edge-stopping weight (Falcor ``computeWeight``), broadcasting ``(..., H, W, 1)``
    depths, luminances and scales and ``(..., H, W, 3)`` normals -> ``(..., H, W, 1)``:
    ``exp(-|l_p - l_q| / phi_l - |z_p - z_q| / phi_z) * max(0, n_p . n_q)^phi_normal``;
    ``centre`` (a bool, may be traced) drops the depth term (the tap at distance 0, where
    ``phi_z`` is 0)."""
    cosine = jnp.clip(jnp.sum(normal_p * normal_q, axis=-1, keepdims=True), 0.0, 1.0)
    w_normal = cosine ** phi_normal
    a_lum = jnp.abs(lum_p - lum_q) / phi_l
    safe_phi_z = jnp.where(centre, 1.0, phi_z)
    a_depth = jnp.where(centre, 0.0, jnp.abs(depth_p - depth_q) / safe_phi_z)
    return jnp.exp(-a_lum - a_depth) * w_normal


# ------------------------------------------------------------------------------ reprojection
def _gather(image: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
    """``image (H, W, C)`` at ``rows, cols (H, W, K)`` (clipped) -> ``(H, W, K, C)``."""
    height, width = image.shape[0], image.shape[1]
    return image[jnp.clip(rows, 0, height - 1), jnp.clip(cols, 0, width - 1)]


def _tap_valid(state: SVGFState, rows, cols, depth, slope, normal, nwidth, config):
    """Which taps ``(H, W, K)`` pass: inside the image, with a history, depth and normal
    consistent with the current pixel (Falcor ``isReprjValid``)."""
    height, width = depth.shape[0], depth.shape[1]
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    prev_depth = _gather(state.depth, rows, cols)[..., 0]
    prev_normal = _gather(state.normal, rows, cols)
    has_history = _gather(state.history, rows, cols)[..., 0] > 0
    depth_ok = (jnp.abs(prev_depth - depth) / (slope + 1e-2)) <= config.depth_tolerance
    normal_distance = jnp.sqrt(jnp.sum((prev_normal - normal[..., None, :]) ** 2, axis=-1))
    normal_ok = normal_distance / (nwidth + 1e-2) <= config.normal_tolerance
    return inside & has_history & depth_ok & normal_ok


def reproject(state: SVGFState, depth: jax.Array, normal: jax.Array, motion: jax.Array,
              config: SVGFConfig = SVGF_PAPER):
    """The previous frame's history sampled at ``xy + motion``.

    ``state``: :class:`SVGFState` of the previous frame (``(H, W, C)`` fields); ``depth
    (H, W, 1)``, ``normal (H, W, 3)``, ``motion (H, W, 2)`` (pixels, ``prev_xy = xy + motion``)
    of this frame. The four bilinear taps at ``floor(xy + motion) + {0, 1}^2`` are each kept
    when inside the image, holding a history, and consistent: ``|z - z_prev| / (dz + 0.01)
    <= depth_tolerance`` and ``|n - n_prev| / (fwidth n + 0.01) <= normal_tolerance`` (dz and
    fwidth of this frame); the kept weights are renormalised and used when they sum to at least
    0.01. Else (``reprojection_fallback``) the valid pixels of the 3 x 3 neighbourhood of the
    first tap are averaged. Returns ``(color (H, W, 3), moments (H, W, 2), history (H, W, 1),
    valid (H, W, 1) bool)``; where not valid the history is 0 and colour and moments are 0.
    """
    slope = depth_slope(depth)
    nwidth = normal_width(normal)
    rows, cols, weights = bilinear_taps(motion)
    valid_taps = _tap_valid(state, rows, cols, depth, slope, normal, nwidth, config)
    w = jnp.where(valid_taps, weights, 0.0)
    total = jnp.sum(w, axis=-1, keepdims=True)
    bilinear_ok = total >= 0.01
    w = w / jnp.where(bilinear_ok, total, 1.0)

    def combine(w, rows, cols):
        return tuple(jnp.sum(w[..., None] * _gather(field, rows, cols), axis=-2)
                     for field in (state.color, state.moments, state.history))

    color, moments, history = combine(w, rows, cols)
    valid = bilinear_ok
    if config.reprojection_fallback:
        offsets = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        rows_k = rows[..., :1] + jnp.asarray([o[0] for o in offsets], jnp.int32)
        cols_k = cols[..., :1] + jnp.asarray([o[1] for o in offsets], jnp.int32)
        ok = _tap_valid(state, rows_k, cols_k, depth, slope, normal, nwidth, config)
        count = jnp.sum(ok, axis=-1, keepdims=True).astype(color.dtype)
        w9 = ok / jnp.maximum(count, 1.0)
        color9, moments9, history9 = combine(w9, rows_k, cols_k)
        use9 = ~bilinear_ok & (count > 0)
        color = jnp.where(use9, color9, color)
        moments = jnp.where(use9, moments9, moments)
        history = jnp.where(use9, history9, history)
        valid = bilinear_ok | use9
    zero = lambda a: jnp.where(valid, a, 0.0)
    return zero(color), zero(moments), zero(history), valid


# ------------------------------------------------------------------------------ accumulation
def accumulate(illum, prev_color, prev_moments, prev_history, valid,
               config: SVGFConfig = SVGF_PAPER):
    """Temporal integration of this frame's illumination with the reprojected history.

    ``illum (H, W, 3)`` this frame's demodulated colour; ``prev_* , valid`` from
    :func:`reproject`. History ``h = min(history_cap, h_prev + 1)`` where valid, else 1; colour
    and moments ``(l, l^2)`` blend with ``max(alpha, 1 / h)`` (1 on a reset). Returns ``(color
    (H, W, 3), moments (H, W, 2), variance (H, W, 1) = max(0, m2 - m1^2), history (H, W, 1))``.
    """
    history = jnp.where(valid, jnp.minimum(config.history_cap, prev_history + 1.0), 1.0)
    alpha_c = jnp.where(valid, jnp.maximum(config.alpha_color, 1.0 / history), 1.0)
    alpha_m = jnp.where(valid, jnp.maximum(config.alpha_moments, 1.0 / history), 1.0)
    lum = luminance(illum)
    current = jnp.concatenate([lum, lum * lum], axis=-1)
    moments = alpha_m * current + (1.0 - alpha_m) * prev_moments
    color = alpha_c * illum + (1.0 - alpha_c) * prev_color
    variance = jnp.maximum(0.0, moments[..., 1:2] - moments[..., 0:1] ** 2)
    return color, moments, variance, history


# ------------------------------------------------------------------------------ spatial variance
def spatial_variance(color, moments, variance, history, depth, normal,
                     config: SVGFConfig = SVGF_PAPER):
    """Where ``history < history_threshold``: a ``(2r+1)^2`` bilateral filter (r =
    ``spatial_radius``, box weights, edge-stopping with ``phi_z = 3 * dz * |offset|``,
    ``phi_normal`` and luminance scale ``phi_color`` unscaled by the variance) of the colour and
    the moments; the variance ``max(0, m2 - m1^2) * history_threshold / history`` of the
    filtered moments (Falcor's boost of the first frames). Elsewhere, and on misses (depth <= 0),
    colour and variance pass through.

    ``color (..., H, W, 3)``, ``moments (..., H, W, 2)``, ``variance``, ``history``, ``depth``
    ``(..., H, W, 1)``, ``normal (..., H, W, 3)`` -> ``(color (..., H, W, 3), variance
    (..., H, W, 1))``.
    """
    radius = config.spatial_radius
    lum = luminance(color)
    phi_z = jnp.maximum(depth_slope(depth), _DEPTH_EPS) * 3.0
    offsets = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]

    def tap(carry, q, distance):
        sum_w, sum_color, sum_moments = carry
        color_q, moments_q, depth_q, normal_q, inside = _split(q, (3, 2, 1, 3, 1))
        w = edge_weight(depth, depth_q, phi_z * distance, normal, normal_q, config.phi_normal,
                        lum, luminance(color_q), config.phi_color, centre=distance == 0)
        w = w * inside
        return sum_w + w, sum_color + w * color_q, sum_moments + w * moments_q

    init = (jnp.zeros_like(lum), jnp.zeros_like(color), jnp.zeros_like(moments))
    sum_w, sum_color, sum_moments = neighbour_scan(
        tap, init, [color, moments, depth, normal], offsets)
    sum_w = jnp.maximum(sum_w, 1e-6)
    filtered_color = sum_color / sum_w
    filtered_moments = sum_moments / sum_w
    boost = config.history_threshold / jnp.maximum(history, 1.0)
    filtered_variance = jnp.maximum(
        0.0, filtered_moments[..., 1:2] - filtered_moments[..., 0:1] ** 2) * boost
    use = (history < config.history_threshold) & (depth > 0)
    return (jnp.where(use, filtered_color, color), jnp.where(use, filtered_variance, variance))


# ------------------------------------------------------------------------------ a-trous
def prefilter_variance(variance: jax.Array) -> jax.Array:
    """3 x 3 Gaussian (1/4 centre, 1/8 edges, 1/16 corners) of ``variance (..., H, W, 1)``,
    zero outside the image as Falcor's loads."""
    out = jnp.zeros_like(variance)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out = out + GAUSS3_WEIGHTS[abs(dy)][abs(dx)] * shift(variance, dy, dx)[0]
    return out


def atrous_iteration(color, variance, depth, normal, step: int,
                     config: SVGFConfig = SVGF_PAPER):
    """One a-trous pass at ``step`` pixels: taps ``p + step * (x, y)``, ``x, y in [-2, 2]``,
    kernel ``h[|x|] h[|y|]`` (:data:`ATROUS_WEIGHTS`), edge-stopping :func:`edge_weight` with
    ``phi_l = phi_color * sqrt(g3x3(var) + 1e-10)``, ``phi_z = phi_depth * max(dz, 1e-8) *
    step * |(x, y)|``; the centre enters with weight 1; taps outside the image are skipped.
    ``c' = (c_p + sum w c_q) / (1 + sum w)``, ``v' = (v_p + sum w^2 v_q) / (1 + sum w)^2``.
    Misses (depth <= 0) pass through.

    ``color (..., H, W, 3)``, ``variance, depth (..., H, W, 1)``, ``normal (..., H, W, 3)`` ->
    ``(color (..., H, W, 3), variance (..., H, W, 1))``.
    """
    lum = luminance(color)
    var_center = prefilter_variance(variance) if config.variance_prefilter else variance
    phi_l = config.phi_color * jnp.sqrt(jnp.maximum(0.0, _VARIANCE_EPS + var_center))
    phi_z = config.phi_depth * jnp.maximum(depth_slope(depth), _DEPTH_EPS) * step
    offsets = [(y * step, x * step) for y in range(-2, 3) for x in range(-2, 3)
               if (x, y) != (0, 0)]
    kernel = jnp.asarray([ATROUS_WEIGHTS[abs(dx) // step] * ATROUS_WEIGHTS[abs(dy) // step]
                          for dy, dx in offsets], color.dtype)

    def tap(carry, q, distance, index):
        sum_w, sum_color, sum_variance = carry
        color_q, variance_q, depth_q, normal_q, inside = _split(q, (3, 1, 1, 3, 1))
        w = edge_weight(depth, depth_q, phi_z * distance / step, normal, normal_q,
                        config.phi_normal, lum, luminance(color_q), phi_l)
        w = w * inside * kernel[index]
        return sum_w + w, sum_color + w * color_q, sum_variance + w * w * variance_q

    init = (jnp.ones_like(lum), color, variance)
    sum_w, sum_color, sum_variance = neighbour_scan(
        tap, init, [color, variance, depth, normal], offsets, with_index=True)
    hit = depth > 0
    return (jnp.where(hit, sum_color / sum_w, color),
            jnp.where(hit, sum_variance / (sum_w * sum_w), variance))


def atrous(color, variance, depth, normal, config: SVGFConfig = SVGF_PAPER):
    """All ``config.iterations`` passes (steps 1, 2, 4, ...). Returns ``(color (..., H, W, 3),
    variance (..., H, W, 1), feedback (..., H, W, 3))``: the last pass's output and the output
    of pass ``feedback_iteration`` (the input colour when it is -1)."""
    feedback = color
    for i in range(config.iterations):
        color, variance = atrous_iteration(color, variance, depth, normal, 2**i, config)
        if i == config.feedback_iteration:
            feedback = color
    return color, variance, feedback


# ------------------------------------------------------------------------------ the filter
def svgf_spatial(frame: Frame, config: SVGFConfig = SVGF_PAPER) -> jax.Array:
    """Single-frame SVGF (no history: history 1 everywhere): demodulate, spatial variance
    estimate from the frame's own moments, a-trous, remodulate. ``frame`` with colour,
    albedo, normal, depth ``(..., H, W, C)`` -> ``(..., H, W, 3)`` linear radiance. Pure and
    differentiable."""
    frame.require("albedo", "normal", "depth", who="denoiser 'svgf'")
    illum = demodulate(frame.color, frame.albedo, config.albedo_floor)
    lum = luminance(illum)
    moments = jnp.concatenate([lum, lum * lum], axis=-1)
    history = jnp.ones_like(lum)
    color, variance = spatial_variance(illum, moments, jnp.zeros_like(lum), history,
                                       frame.depth, frame.normal, config)
    color, _, _ = atrous(color, variance, frame.depth, frame.normal, config)
    return remodulate(color, frame.albedo, config.albedo_floor)


def initial_state(height: int, width: int) -> SVGFState:
    """The state before the first frame: no history anywhere."""
    zeros = lambda c: jnp.zeros((height, width, c), jnp.float32)
    return SVGFState(color=zeros(3), moments=zeros(2), history=zeros(1), depth=zeros(1),
                     normal=zeros(3))


def svgf_step(state: SVGFState | None, frame: Frame, config: SVGFConfig = SVGF_PAPER):
    """One frame of a sequence: ``(image (H, W, 3), new state)``.

    ``state``: the previous frame's :class:`SVGFState` (None or :func:`initial_state`: the
    first frame); ``frame``: colour, albedo, normal, depth ``(H, W, C)`` and motion
    ``(H, W, 2)`` (pixels to the previous frame; may be None for the first frame). Pure; jit it
    with ``config`` static (:func:`svgf_sequence` does)."""
    frame.require("albedo", "normal", "depth", who="SVGF")
    height, width = frame.color.shape[-3], frame.color.shape[-2]
    if state is None:
        state = initial_state(height, width)
    motion = frame.motion if frame.motion is not None else jnp.zeros((height, width, 2))
    illum = demodulate(frame.color, frame.albedo, config.albedo_floor)
    prev_color, prev_moments, prev_history, valid = reproject(
        state, frame.depth, frame.normal, motion, config)
    color, moments, variance, history = accumulate(
        illum, prev_color, prev_moments, prev_history, valid, config)
    color, variance = spatial_variance(color, moments, variance, history, frame.depth,
                                       frame.normal, config)
    filtered, _, feedback = atrous(color, variance, frame.depth, frame.normal, config)
    new_state = SVGFState(color=feedback, moments=moments, history=history,
                          depth=jnp.asarray(frame.depth, jnp.float32),
                          normal=jnp.asarray(frame.normal, jnp.float32))
    return remodulate(filtered, frame.albedo, config.albedo_floor), new_state


@functools.partial(jax.jit, static_argnames="config")
def _jitted_step(state, frame, config):
    return svgf_step(state, frame, config)


def svgf_sequence(frames: list[Frame], config: SVGFConfig = SVGF_PAPER) -> list[jax.Array]:
    """SVGF over a sequence: the filtered images ``[(H, W, 3), ...]``, one per frame, by a
    Python loop over the jitted :func:`svgf_step` (frames may differ in which fields they
    carry, e.g. the first without motion)."""
    if not frames:
        return []
    state = initial_state(frames[0].height, frames[0].width)
    images = []
    for frame in frames:
        if frame.motion is None:
            frame = frame.replace(motion=jnp.zeros(frame.color.shape[:-1] + (2,), jnp.float32))
        image, state = _jitted_step(state, frame, config)
        images.append(image)
    return images


# ------------------------------------------------------------------------------ registration
def svgf_radius(config: SVGFConfig) -> int:
    """The single-frame form's receptive field (pixels, each side): ``sum_i 2 * 2^i`` over the
    a-trous passes (their 3 x 3 variance prefilter lies inside each pass's taps) plus the
    spatial variance estimate's radius."""
    return sum(2 * 2**i for i in range(config.iterations)) + config.spatial_radius


def _configure(config: SVGFConfig, options: dict[str, str]) -> SVGFConfig:
    return SVGF_PRESETS[options["preset"]] if "preset" in options else config


register(DenoiserDef(
    name="svgf",
    description="SVGF (Schied et al. 2017), single-frame spatial form: spatial variance "
                "estimate + a-trous (JAX, no training; svgf:preset=paper|falcor)",
    config_cls=SVGFConfig,
    required=lambda config: ("albedo", "normal", "depth"),
    apply=lambda params, config, frame: svgf_spatial(frame, config),
    tiling=lambda config: TileSpec(radius=svgf_radius(config)),
    options=(("preset", tuple(SVGF_PRESETS)),),
    configure=_configure,
    step=lambda params, config, state, frame: svgf_step(state, frame, config),
))
