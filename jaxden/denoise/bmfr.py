"""BMFR: blockwise multi-order feature regression (Koskela et al., TOG 2019), in pure JAX.

The pipeline per frame, as in the authors' OpenCL code (``bmfr.cl``; docs/departures.md,
"BMFR", lists where jaxden departs from it):

1. **Demodulate** the colour by the albedo (``colour / max(albedo, 0.001)``).
2. **Pre-accumulate** the noisy demodulated colour: the previous frame's history is read at
   ``xy + motion`` with the four bilinear taps, each accepted when inside the image and
   ``|dP|^2 < position_limit_squared`` and ``|dn|^2 < normal_limit_squared`` (world position
   and normal against the previous frame's) and with the same dark albedo channels (below
   ``dark_albedo``); the accepted weights are renormalised, and the blend is ``alpha =
   max(1 / (n + 1), blend_alpha)`` with ``n`` the reprojected sample count.
3. **Fit** per 32 x 32 block and per colour channel the least-squares regression of the
   accumulated colour on the feature basis ``1, n_x, n_y, n_z, P_x, P_y, P_z, P_x^2, P_y^2,
   P_z^2`` (normal ``n``, world position ``P``). The block grid moves every frame by one of 16
   offsets; blocks reaching past the image read it mirrored. The six position features are
   normalised per block by its min and max, every feature but the constant gets a uniform
   perturbation of +-``noise_amount`` (a hash of the row in the block, the feature and the
   frame number: the authors' regularisation); one Householder QR batched over all blocks
   solves them. The fit evaluated per pixel, clamped at 0, is the filtered colour.
4. **Post-accumulate** the filtered colour with the taps accepted in step 2 and
   ``alpha = max(1 / n, filtered_blend_alpha)``; remodulate by the albedo.
5. **TAA**: the previous output, bilinearly resampled, is clamped to the 3 x 3 neighbourhood's
   box in YCoCg and blended with ``taa_blend_alpha``.

``bmfr_step(state, frame, config)`` runs one frame of a sequence, ``bmfr_sequence(frames,
config)`` a list (one compiled step for all frames). The registered denoiser ``bmfr`` applies
the single-frame spatial form (step 3 on the frame's own demodulated colour, remodulated),
pure and differentiable JAX, and carries :func:`bmfr_step` as its temporal form
(``Denoiser.step`` / ``Denoiser.sequence``, ``jaxden denoise --sequence``).

Shapes: images ``(..., H, W, C)`` for the spatial functions (leading batch dimensions
allowed), ``(H, W, C)`` for those that carry history. Units: linear radiance, pixels, world
units for positions. Misses (normal 0), dark albedo channels and directly seen emitters (where
the frame has ``emission``) are kept out of the fit and pass through unfiltered.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp

from jaxden.config import bounded, check_fields
from jaxden.denoise.registry import DenoiserDef, register
from jaxden.denoise.svgf import demodulate, remodulate, shift
from jaxden.denoise.temporal import bilinear_taps
from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.tiling import TileSpec

#: Full float32 products (no TF32 on GPUs: the QR and the fit need the mantissa).
HIGHEST = jax.lax.Precision.HIGHEST
#: The side of a block (pixels); the authors' code supports no other.
BLOCK_SIZE = 32
BLOCK_PIXELS = BLOCK_SIZE * BLOCK_SIZE
#: Per-frame shifts (x, y) of the block grid, used as ``BLOCK_OFFSETS[frame % 16]`` (bmfr.cl).
BLOCK_OFFSETS = ((-14, -14), (4, -6), (-8, 14), (8, 0), (-10, -8), (2, 12), (12, -12), (-10, 0),
                 (12, 14), (-8, -16), (6, 6), (-2, -2), (6, -14), (-16, 12), (14, -4), (-6, 4))
#: Feature columns, in order; the first FEATURES_NOT_SCALED are not normalised per block.
FEATURE_NAMES = ("1", "n_x", "n_y", "n_z", "P_x", "P_y", "P_z", "P_x^2", "P_y^2", "P_z^2")
FEATURE_COUNT = len(FEATURE_NAMES)
FEATURES_NOT_SCALED = 4
#: Columns of the authors' augmented block matrix (features + RGB): the noise hash's stride.
BUFFER_COUNT = FEATURE_COUNT + 3
#: World-position and normal limits per scene of the BMFR dataset (squared distances), as
#: WSKP's NumPy port of the pre-accumulation sets them (BASELINES.md section 0).
WSKP_SCENE_LIMITS: dict[str, tuple[float, float]] = {
    "sponza": (0.0016, 0.25), "classroom": (0.01, 1.0), "living-room": (0.0009, 0.04),
    "san-miguel": (0.0009, 1.0), "sponza-glossy": (0.0016, 0.25),
    "sponza-moving-light": (0.0016, 0.25)}


@dataclasses.dataclass(frozen=True)
class BMFRConfig:
    """BMFR's parameters; the defaults are the authors' OpenCL code (:data:`BMFR_CL`), those
    of WSKP's NumPy port of the pre-accumulation are :data:`BMFR_WSKP`.

    ``noise_amount``: half-width of the uniform perturbation of the non-constant feature
    columns (the fit's regularisation); ``ridge``: a Tikhonov term ``ridge * |beta|^2`` on top
    (tiny: it only keeps blocks without a usable row, e.g. all misses, finite); ``frame_index``:
    the frame number of the single-frame form (picks the block offset and the noise);
    ``pass_through``: keep misses (normal 0), pixels with a dark channel (albedo below
    ``dark_albedo``) and directly seen emitters (``emission`` > 0, when the frame has it) out
    of the fit and return them (those channels) as they are; ``dark_albedo``:
    that threshold, also the reprojection's: a tap must have the same dark channels as the
    pixel (0: no channel is dark, the authors' reprojection);
    ``position_limit_squared`` / ``normal_limit_squared``: the reprojection tests;
    ``blend_alpha`` / ``filtered_blend_alpha`` / ``taa_blend_alpha``: the smallest blend
    factors of the noisy and the filtered accumulation and TAA's factor; ``taa``: run TAA;
    ``sample_count``: ``"integer"`` rounds the reprojected count and saturates it at 255 (the
    authors' uint8 buffer), ``"float"`` keeps it unrounded (WSKP's port).
    """

    noise_amount: float = bounded(1e-2, low=0)
    ridge: float = bounded(1e-6, low=0)
    frame_index: int = bounded(0, low=0)
    pass_through: bool = True
    dark_albedo: float = bounded(0.01, low=0, high=1)
    position_limit_squared: float = bounded(0.01, low=0, low_open=True)
    normal_limit_squared: float = bounded(1.0, low=0, low_open=True)
    blend_alpha: float = bounded(0.2, low=0, low_open=True, high=1)
    filtered_blend_alpha: float = bounded(0.1, low=0, low_open=True, high=1)
    taa_blend_alpha: float = bounded(0.2, low=0, low_open=True, high=1)
    taa: bool = True
    sample_count: Literal["integer", "float"] = "integer"

    def __post_init__(self) -> None:
        check_fields(self)
        if self.noise_amount == 0 and self.ridge == 0:
            raise ConfigError("BMFRConfig: noise_amount and ridge are both 0, so the fit of a "
                              "block with collinear features (a flat wall) has no unique "
                              "solution: set noise_amount > 0 (the authors': 0.01) or ridge > 0")


#: The authors' OpenCL code: noise 0.01, alphas 0.2 / 0.1 / 0.2, an integer sample count
#: saturating at 255, limits 0.01 / 1.0 (gztong's DXR port; WSKP's for classroom).
BMFR_CL = BMFRConfig()
#: WSKP's NumPy port of the pre-accumulation: an unrounded, unbounded sample count.
BMFR_WSKP = BMFRConfig(sample_count="float")
#: Presets by name (the denoiser spec option ``bmfr:preset=NAME``).
BMFR_PRESETS: dict[str, BMFRConfig] = {"bmfr-cl": BMFR_CL, "wskp": BMFR_WSKP}


class BMFRState(NamedTuple):
    """History carried from frame to frame (``(H, W, C)`` arrays; colours demodulated except
    ``output``)."""

    noisy: jax.Array  # (H, W, 3) accumulated noisy colour
    count: jax.Array  # (H, W, 1) samples accumulated in it
    filtered: jax.Array  # (H, W, 3) accumulated filtered colour
    output: jax.Array  # (H, W, 3) the last output (after TAA), linear radiance
    normal: jax.Array  # (H, W, 3) this frame's normal, for the next frame's test
    position: jax.Array  # (H, W, 3) this frame's world position
    dark: jax.Array  # (H, W, 3) 1 where this frame's albedo is below dark_albedo
    frame: jax.Array  # () int32, the number of the next frame (0: no history)


# ------------------------------------------------------------------------------ features
def _finite(array: jax.Array) -> jax.Array:
    return jnp.where(jnp.isfinite(array), array, 0.0)


def feature_basis(normal: jax.Array, position: jax.Array) -> jax.Array:
    """The ten feature columns :data:`FEATURE_NAMES` per pixel, unnormalised; non-finite
    normals and positions read as 0: ``(..., H, W, 3) x 2 -> (..., H, W, 10)``."""
    normal, position = _finite(normal), _finite(position)
    return jnp.concatenate([jnp.ones_like(normal[..., :1]), normal, position, position**2], -1)


def miss_mask(normal: jax.Array) -> jax.Array:
    """Pixels whose camera ray hit nothing (normal 0): ``(..., H, W, 3) -> (..., H, W, 1)``."""
    return jnp.sum(_finite(normal) ** 2, axis=-1, keepdims=True) == 0


def dark_channels(albedo: jax.Array, threshold: float) -> jax.Array:
    """1 where the albedo is below ``threshold`` (``dark_albedo``: there the demodulated
    colour is the colour times more than 1 / threshold, up to 1000 at the demodulation
    guard), else 0: ``(..., H, W, 3) -> (..., H, W, 3)`` float32."""
    return (~(jnp.asarray(albedo) >= threshold)).astype(jnp.float32)


def unfit_mask(normal: jax.Array, albedo: jax.Array, threshold: float,
               emission: jax.Array | None = None) -> jax.Array:
    """Pixel channels passed through unfiltered with ``pass_through``: misses (normal 0), dark
    channels (:func:`dark_channels`) and, given ``emission``, directly seen emitters (any
    channel > 0): a block's least squares would spread their demodulated colour, tens to
    thousands of times their neighbours', over the block. A pixel with any of them takes no
    part in the fit. ``(..., H, W, 3)`` each -> ``(..., H, W, 3)`` bool."""
    unfit = miss_mask(normal) | (dark_channels(albedo, threshold) > 0)
    if emission is not None:
        unfit = unfit | jnp.any(jnp.asarray(emission) > 0, axis=-1, keepdims=True)
    return unfit


def block_offset(frame_index) -> jax.Array:
    """The grid shift ``(x, y)`` of frame ``frame_index`` (int or traced): ``(2,)`` int32."""
    return jnp.asarray(BLOCK_OFFSETS, jnp.int32)[jnp.asarray(frame_index, jnp.int32) % 16]


def block_grid(height: int, width: int) -> tuple[int, int]:
    """Blocks ``(rows, columns)`` of the work area: the image rounded up to whole blocks plus
    one block of margin (the grid's shift moves it by up to half a block either way)."""
    return math.ceil(height / BLOCK_SIZE) + 1, math.ceil(width / BLOCK_SIZE) + 1


def mirror(index: jax.Array, size: int) -> jax.Array:
    """Indices reflected into ``[0, size)`` with the edge repeated (-1 -> 0, size -> size - 1),
    periodically, so any distance out of bounds works."""
    folded = jnp.mod(index, 2 * size)
    return jnp.where(folded >= size, 2 * size - 1 - folded, folded)


def work_area(image: jax.Array, offset: jax.Array) -> jax.Array:
    """The image on the work area of the grid shifted by ``offset``: pixel ``g`` of the work
    area shows image pixel ``mirror(g - 16 + offset)``. ``(H, W, C) -> (32 by, 32 bx, C)``."""
    (height, width), half = image.shape[:2], BLOCK_SIZE // 2
    blocks_y, blocks_x = block_grid(height, width)
    rows = mirror(jnp.arange(blocks_y * BLOCK_SIZE) - half + offset[1], height)
    cols = mirror(jnp.arange(blocks_x * BLOCK_SIZE) - half + offset[0], width)
    return image[rows][:, cols]


def to_blocks(area: jax.Array) -> jax.Array:
    """``(32 by, 32 bx, C) -> (by bx, 1024, C)``, rows of a block in raster order."""
    height, width, channels = area.shape
    blocks = area.reshape(height // BLOCK_SIZE, BLOCK_SIZE, width // BLOCK_SIZE, BLOCK_SIZE, -1)
    return blocks.transpose(0, 2, 1, 3, 4).reshape(-1, BLOCK_PIXELS, channels)


def from_blocks(blocks: jax.Array, height: int, width: int, offset: jax.Array) -> jax.Array:
    """The inverse of :func:`to_blocks` cropped to the image: pixel ``p`` is work-area pixel
    ``p + 16 - offset``. ``(by bx, 1024, C) -> (H, W, C)``."""
    blocks_y, blocks_x = block_grid(height, width)
    channels = blocks.shape[-1]
    area = blocks.reshape(blocks_y, blocks_x, BLOCK_SIZE, BLOCK_SIZE, channels)
    area = area.transpose(0, 2, 1, 3, 4).reshape(blocks_y * BLOCK_SIZE, blocks_x * BLOCK_SIZE,
                                                 channels)
    start = BLOCK_SIZE // 2 - offset
    return jax.lax.dynamic_slice(area, (start[1], start[0], jnp.zeros((), jnp.int32)),
                                 (height, width, channels))


def scale_features(blocks: jax.Array, usable: jax.Array) -> jax.Array:
    """Normalise the position features (columns 4..9) per block by the min and max over its
    usable rows: ``(v - min) / (max - min)`` where ``max - min > 1``, else ``v - min``.
    ``blocks (B, 1024, 10)``, ``usable (B, 1024, 1)`` bool -> ``(B, 1024, 10)``."""
    scaled = blocks[..., FEATURES_NOT_SCALED:]
    low = jnp.min(jnp.where(usable, scaled, jnp.inf), axis=1, keepdims=True)
    high = jnp.max(jnp.where(usable, scaled, -jnp.inf), axis=1, keepdims=True)
    any_usable = jnp.any(usable, axis=1, keepdims=True)
    low, high = jnp.where(any_usable, low, 0.0), jnp.where(any_usable, high, 0.0)
    span = high - low
    wide = span > 1.0
    scaled = jnp.where(wide, (scaled - low) / jnp.where(wide, span, 1.0), scaled - low)
    return jnp.concatenate([blocks[..., :FEATURES_NOT_SCALED], scaled], axis=-1)


# ------------------------------------------------------------------------------ regularisation
def hash_uniform(index: jax.Array) -> jax.Array:
    """A uniform number in [0, 1] per uint32 ``index``: Robert Jenkins' 32-bit integer mix
    (the generator the authors' ``add_random`` uses), divided by 2^32 - 1 in float32."""
    a = jnp.asarray(index, jnp.uint32)
    u = lambda value: jnp.uint32(value)
    a = (a + u(0x7ED55D16)) + (a << 12)
    a = (a ^ u(0xC761C23C)) ^ (a >> 19)
    a = (a + u(0x165667B1)) + (a << 5)
    a = (a + u(0xD3A2646C)) ^ (a << 9)
    a = (a + u(0xFD7046C5)) + (a << 3)
    a = (a ^ u(0xB55A4F09)) ^ (a >> 16)
    return a.astype(jnp.float32) / jnp.float32(2**32 - 1)


def regularisation_noise(frame_index, noise_amount: float) -> jax.Array:
    """The perturbation of the feature columns, the same for every block of a frame:
    ``noise_amount * 2 * (u - 0.5)`` with ``u`` :func:`hash_uniform` of ``row + 1024 feature
    + 1024 * 13 * frame`` (row: raster index in the block); 0 in the constant column.
    ``-> (1024, 10)`` float32."""
    row = jnp.arange(BLOCK_PIXELS, dtype=jnp.uint32)[:, None]
    feature = jnp.arange(FEATURE_COUNT, dtype=jnp.uint32)[None, :]
    frame = jnp.asarray(frame_index).astype(jnp.uint32)
    stride = jnp.uint32(BLOCK_PIXELS)
    index = row + feature * stride + frame * (jnp.uint32(BUFFER_COUNT) * stride)
    noise = jnp.float32(noise_amount) * 2.0 * (hash_uniform(index) - 0.5)
    return noise.at[:, 0].set(0.0)


# ------------------------------------------------------------------------------ the fit
def householder(design: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Householder QR of ``design (..., M, K)`` with its reflections applied to ``target
    (..., M, C)``: ``(R (..., K, K), Q^T target (..., K, C))``. A loop over the K columns with
    masks (static shapes), batched over blocks by broadcasting: ``jnp.linalg.qr`` on the CPU
    costs ~20x more for these tall, thin matrices. The reflectors depend on ``design`` alone,
    so derivatives with respect to ``target`` never pass through their square roots."""
    count, index = design.shape[-1], jnp.arange(design.shape[-2])

    def reflect_column(j, carry):
        design, target = carry
        current = jnp.take(design, j, axis=-1)
        column = jnp.where(index >= j, current, 0.0)
        squared = jnp.sum(column * column, axis=-1)
        norm = jnp.where(squared > 0, jnp.sqrt(jnp.where(squared > 0, squared, 1.0)), 0.0)
        pivot = jnp.take(current, j, axis=-1)
        alpha = jnp.where(pivot < 0, norm, -norm)  # -sign(pivot) |column|: no cancellation
        v = column - jnp.where(index == j, alpha[..., None], 0.0)
        vtv = jnp.sum(v * v, axis=-1)
        scale = jnp.where(vtv > 0, 2.0 / jnp.where(vtv > 0, vtv, 1.0), 0.0)[..., None]
        dot = lambda a: jnp.einsum("...m,...mc->...c", v, a, precision=HIGHEST)
        reflect = lambda a: a - v[..., :, None] * (dot(a) * scale)[..., None, :]
        return reflect(design), reflect(target)

    design, target = jax.lax.fori_loop(0, count, reflect_column, (design, target))
    return design[..., :count, :], target[..., :count, :]


def fit_blocks(design: jax.Array, target: jax.Array, ridge: float = 0.0) -> jax.Array:
    """Least squares per block: ``argmin_b |X b - y|^2 + ridge |b|^2`` for every block and
    channel at once: the Householder QR of ``[X; sqrt(ridge) I]`` (:func:`householder`), then
    back substitution. ``design (B, N, K)``, ``target (B, N, C)`` -> ``(B, K, C)``."""
    count = design.shape[-1]
    root = jnp.sqrt(jnp.asarray(ridge, design.dtype))
    penalty = jnp.broadcast_to(root * jnp.eye(count, dtype=design.dtype),
                               design.shape[:-2] + (count, count))
    stacked = jnp.concatenate([design, penalty], axis=-2)
    zeros = jnp.zeros(target.shape[:-2] + (count, target.shape[-1]), target.dtype)
    padded = jnp.concatenate([target, zeros], axis=-2)
    r, projected = householder(stacked, padded)
    return jax.scipy.linalg.solve_triangular(r, projected, lower=False)


def block_fit(color: jax.Array, normal: jax.Array, position: jax.Array, frame_index,
              config: BMFRConfig = BMFR_CL, unfit: jax.Array | None = None) -> jax.Array:
    """The regression filter of one frame (step 3): per block of the grid of ``frame_index``
    and per channel, ``color`` regressed on the normalised, perturbed feature basis; the fit
    evaluated with the block's normalised (unperturbed) features, clamped at 0. With
    ``pass_through``, pixels with a channel in ``unfit`` (default: the misses) take no part
    in the fit and those channels keep their colour; the position features' min and max are
    taken over the block's hits.

    ``color (H, W, 3)`` (demodulated), ``normal``, ``position (H, W, 3)``, ``unfit (H, W, 1
    or 3)`` bool -> ``(H, W, 3)``.
    """
    height, width, offset = color.shape[0], color.shape[1], block_offset(frame_index)
    blocks = lambda image: to_blocks(work_area(image, offset))
    features = blocks(feature_basis(normal, position))
    target = blocks(_finite(color))
    noise = regularisation_noise(frame_index, config.noise_amount).astype(features.dtype)
    if config.pass_through:
        unfit = jnp.broadcast_to(miss_mask(normal) if unfit is None else unfit, color.shape)
        features = scale_features(features, ~blocks(miss_mask(normal)))
        weight = (~blocks(jnp.any(unfit, axis=-1, keepdims=True))).astype(features.dtype)
        beta = fit_blocks((features + noise) * weight, target * weight, config.ridge)
    else:
        features = scale_features(features, jnp.ones_like(target[..., :1], bool))
        beta = fit_blocks(features + noise, target, config.ridge)
    fitted = jnp.einsum("bnk,bkc->bnc", features, beta, precision=HIGHEST)
    out = jnp.maximum(from_blocks(fitted, height, width, offset), 0.0)
    if config.pass_through:
        out = jnp.where(unfit, color, out)
    return out


def _batched(fn, *images):
    """``fn`` on ``(H, W, C)`` images mapped over the leading dimensions of ``images``."""
    out = jax.vmap(fn)(*[jnp.reshape(image, (-1, *image.shape[-3:])) for image in images])
    return jnp.reshape(out, (*images[0].shape[:-3], *out.shape[1:]))


BMFR_FEATURES = ("albedo", "normal", "position")


def require_features(frame: Frame, who: str) -> None:
    """FrameError naming the missing ones of :data:`BMFR_FEATURES`."""
    frame.require(*BMFR_FEATURES, who=f"{who} (its feature basis is 1, normal, world position "
                                       f"and position^2, and it demodulates by the albedo)")


def bmfr_spatial(frame: Frame, config: BMFRConfig = BMFR_CL) -> jax.Array:
    """Single-frame BMFR: demodulate, the blockwise fit (:func:`block_fit`, grid and noise of
    ``config.frame_index``), remodulate. ``frame`` with colour, albedo, normal, position
    (and, used when present, emission) ``(..., H, W, C)`` -> ``(..., H, W, 3)`` linear
    radiance. Pure and differentiable."""
    require_features(frame, "denoiser 'bmfr'")
    illum = demodulate(frame.color, frame.albedo)
    unfit = unfit_mask(frame.normal, frame.albedo, config.dark_albedo, frame.emission)
    fitted = _batched(lambda c, n, p, u: block_fit(c, n, p, config.frame_index, config, u),
                      illum, jnp.asarray(frame.normal, illum.dtype),
                      jnp.asarray(frame.position, illum.dtype), unfit)
    return remodulate(fitted, frame.albedo)


# ------------------------------------------------------------------------------ reprojection
class Taps(NamedTuple):
    """The bilinear taps of every pixel into the previous frame: ``rows``, ``cols (H, W, 4)``
    int32 (not clipped), ``weights (H, W, 4)`` (0 for rejected taps, not renormalised) and
    ``valid (H, W, 1)`` (some accepted weight > 0)."""

    rows: jax.Array
    cols: jax.Array
    weights: jax.Array
    valid: jax.Array


def _gather(image: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
    """``image (H, W, C)`` at ``rows, cols (H, W, K)`` (clipped) -> ``(H, W, K, C)``."""
    height, width = image.shape[0], image.shape[1]
    return image[jnp.clip(rows, 0, height - 1), jnp.clip(cols, 0, width - 1)]


def reproject(state: BMFRState, normal: jax.Array, position: jax.Array, motion: jax.Array,
              config: BMFRConfig = BMFR_CL, dark: jax.Array | None = None) -> Taps:
    """The taps ``floor(xy + motion) + {0, 1}^2`` into the previous frame, each accepted when
    inside the image, ``|P - P_prev|^2 < position_limit_squared`` and ``|n - n_prev|^2 <
    normal_limit_squared`` and, given ``dark`` (:func:`dark_channels` of this frame), the
    same channels are dark in both (demodulated colours of the two kinds differ by 100x and
    more and must not mix); none on the first frame (``state.frame == 0``).
    ``normal``, ``position (H, W, 3)``, ``motion (H, W, 2)`` (pixels, ``prev_xy = xy +
    motion``)."""
    height, width = normal.shape[0], normal.shape[1]
    rows, cols, weights = bilinear_taps(motion)
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    position, normal = _finite(position), _finite(normal)
    d_position = jnp.sum((_gather(state.position, rows, cols) - position[..., None, :]) ** 2, -1)
    d_normal = jnp.sum((_gather(state.normal, rows, cols) - normal[..., None, :]) ** 2, -1)
    accepted = (inside & (d_position < config.position_limit_squared)
                & (d_normal < config.normal_limit_squared) & (state.frame > 0))
    if dark is not None:
        same = jnp.all(_gather(state.dark, rows, cols) == dark[..., None, :], axis=-1)
        accepted = accepted & same
    weights = jnp.where(accepted, weights, 0.0)
    valid = jnp.sum(weights, axis=-1, keepdims=True) > 0
    return Taps(rows, cols, weights, valid)


def resample(image: jax.Array, taps: Taps) -> jax.Array:
    """``image (H, W, C)`` of the previous frame averaged over the accepted taps with their
    renormalised weights; 0 where none is valid. ``-> (H, W, C)``."""
    total = jnp.sum(taps.weights, axis=-1, keepdims=True)
    mean = jnp.sum(taps.weights[..., None] * _gather(image, taps.rows, taps.cols), axis=-2)
    return jnp.where(taps.valid, mean / jnp.where(taps.valid, total, 1.0), 0.0)


def accumulate_noisy(illum: jax.Array, state: BMFRState, taps: Taps,
                     config: BMFRConfig = BMFR_CL) -> tuple[jax.Array, jax.Array]:
    """Step 2: ``alpha * illum + (1 - alpha) * history`` with ``alpha = max(1 / (n + 1),
    blend_alpha)``, ``n`` the reprojected count (1 where no tap is valid). New count ``n + 1``
    (``"integer"``: ``round(n) + 1``, at most 255), 1 where no tap is valid.
    ``illum (H, W, 3)`` -> ``(colour (H, W, 3), count (H, W, 1))``."""
    previous = resample(state.noisy, taps)
    count = resample(state.count, taps)
    alpha = jnp.where(taps.valid, jnp.maximum(1.0 / (count + 1.0), config.blend_alpha), 1.0)
    if config.sample_count == "integer":
        new_count = jnp.where(count > 254.0, 255.0, jnp.round(count) + 1.0)
    else:
        new_count = count + 1.0
    new_count = jnp.where(taps.valid, new_count, 1.0)
    return alpha * illum + (1.0 - alpha) * previous, new_count


def accumulate_filtered(filtered: jax.Array, state: BMFRState, taps: Taps, count: jax.Array,
                        config: BMFRConfig = BMFR_CL) -> jax.Array:
    """Step 4: the filtered colour blended with its reprojected history (the taps of step 2)
    by ``alpha = max(1 / count, filtered_blend_alpha)`` (``count``: this frame's, from
    :func:`accumulate_noisy`). ``(H, W, 3) -> (H, W, 3)``."""
    previous = resample(state.filtered, taps)
    alpha = jnp.where(taps.valid, jnp.maximum(1.0 / count, config.filtered_blend_alpha), 1.0)
    return alpha * filtered + (1.0 - alpha) * previous


# ------------------------------------------------------------------------------ TAA
def rgb_to_ycocg(rgb: jax.Array) -> jax.Array:
    """Unnormalised YCoCg: ``Y = R + 2G + B, Co = 2R - 2B, Cg = -R + 2G - B``."""
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    return jnp.stack([r + 2 * g + b, 2 * r - 2 * b, -r + 2 * g - b], axis=-1)


def ycocg_to_rgb(ycocg: jax.Array) -> jax.Array:
    """The inverse of :func:`rgb_to_ycocg`."""
    y, co, cg = ycocg[..., 0], ycocg[..., 1], ycocg[..., 2]
    return 0.25 * jnp.stack([y + co - cg, y + cg, y - co - cg], axis=-1)


def taa(image: jax.Array, previous: jax.Array, motion: jax.Array, first,
        config: BMFRConfig = BMFR_CL) -> jax.Array:
    """Step 5: ``taa_blend_alpha * image + (1 - alpha) * clamp(history)``. The history is
    ``previous`` bilinearly read at ``xy + motion`` over the taps inside the image
    (renormalised), clamped in YCoCg to the mean of the 3 x 3 box's and the 5-tap cross's
    min / max around the pixel. ``image`` passes unchanged on the ``first`` frame (bool, may
    be traced) and where ``floor(xy + motion)`` lies left of or above -1 or right of or below
    the last pixel (or no tap is inside). ``(H, W, 3)``; ``motion (H, W, 2)``."""
    height, width = image.shape[0], image.shape[1]
    ycocg = rgb_to_ycocg(image)
    box_lo = box_hi = cross_lo = cross_hi = ycocg
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == dx == 0:
                continue
            value, inside = shift(ycocg, dy, dx)
            lo, hi = jnp.where(inside, value, jnp.inf), jnp.where(inside, value, -jnp.inf)
            box_lo, box_hi = jnp.minimum(box_lo, lo), jnp.maximum(box_hi, hi)
            if dy == 0 or dx == 0:
                cross_lo, cross_hi = jnp.minimum(cross_lo, lo), jnp.maximum(cross_hi, hi)
    low, high = (box_lo + cross_lo) / 2, (box_hi + cross_hi) / 2
    rows, cols, weights = bilinear_taps(motion)
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    weights = jnp.where(inside, weights, 0.0)
    total = jnp.sum(weights, axis=-1, keepdims=True)
    history = jnp.sum(weights[..., None] * _gather(previous, rows, cols), axis=-2)
    history = history / jnp.where(total > 0, total, 1.0)
    clamped = ycocg_to_rgb(jnp.clip(rgb_to_ycocg(history), low, high))
    blended = config.taa_blend_alpha * image + (1.0 - config.taa_blend_alpha) * clamped
    row0, col0 = rows[..., :1], cols[..., :1]
    on_screen = (row0 >= -1) & (col0 >= -1) & (row0 < height) & (col0 < width) & (total > 0)
    return jnp.where(on_screen & ~jnp.asarray(first), blended, image)


# ------------------------------------------------------------------------------ sequences
def initial_state(height: int, width: int) -> BMFRState:
    """The state before the first frame: no history anywhere, frame number 0."""
    zeros = lambda c: jnp.zeros((height, width, c), jnp.float32)
    return BMFRState(noisy=zeros(3), count=zeros(1), filtered=zeros(3), output=zeros(3),
                     normal=zeros(3), position=zeros(3), dark=zeros(3),
                     frame=jnp.zeros((), jnp.int32))


def bmfr_step(state: BMFRState | None, frame: Frame, config: BMFRConfig = BMFR_CL):
    """One frame of a sequence: ``(image (H, W, 3) linear radiance, new state)``.

    ``state``: the previous frame's :class:`BMFRState` (None or :func:`initial_state`: the
    first frame; its ``frame`` numbers the block offset and the noise); ``frame``: colour,
    albedo, normal, position (emission used when present) ``(H, W, C)`` and motion ``(H, W,
    2)`` (pixels to the previous frame; None reads as 0). Pure; jit it with ``config`` static (:func:`bmfr_sequence`
    does)."""
    require_features(frame, "BMFR")
    height, width = frame.color.shape[-3], frame.color.shape[-2]
    if state is None:
        state = initial_state(height, width)
    motion = frame.motion if frame.motion is not None else jnp.zeros((height, width, 2))
    normal = jnp.asarray(frame.normal, jnp.float32)
    position = jnp.asarray(frame.position, jnp.float32)
    illum = demodulate(frame.color, frame.albedo)
    dark = dark_channels(frame.albedo, config.dark_albedo)
    taps = reproject(state, normal, position, motion, config, dark)
    noisy, count = accumulate_noisy(illum, state, taps, config)
    filtered = block_fit(noisy, normal, position, state.frame, config,
                         unfit_mask(normal, frame.albedo, config.dark_albedo, frame.emission))
    accumulated = accumulate_filtered(filtered, state, taps, count, config)
    image = remodulate(accumulated, frame.albedo)
    if config.taa:
        image = taa(image, state.output, motion, state.frame == 0, config)
    return image, BMFRState(noisy=noisy, count=count, filtered=accumulated, output=image,
                            normal=_finite(normal), position=_finite(position), dark=dark,
                            frame=state.frame + 1)


@functools.partial(jax.jit, static_argnames="config")
def _jitted_step(state, frame, config):
    return bmfr_step(state, frame, config)


def bmfr_sequence(frames: list[Frame], config: BMFRConfig = BMFR_CL,
                  state: BMFRState | None = None, return_state: bool = False):
    """BMFR over a sequence: the images ``[(H, W, 3), ...]``, one per frame, by a Python loop
    over the jitted :func:`bmfr_step`, compiled once: every frame is cut to the fields BMFR
    reads (emission where it has one), in float32, with motion 0 where it has none. ``state``: continue from it (None:
    the first frame is frame 0); ``return_state``: return ``(images, last state)``."""
    if not frames:
        return ([], state) if return_state else []
    for frame in frames:
        require_features(frame, "BMFR")
    state = initial_state(frames[0].height, frames[0].width) if state is None else state
    images = []
    for frame in frames:
        f32 = lambda a: jnp.asarray(a, jnp.float32)
        motion = jnp.zeros(frame.color.shape[:-1] + (2,)) if frame.motion is None else frame.motion
        inputs = Frame(color=f32(frame.color), albedo=f32(frame.albedo),
                       normal=f32(frame.normal), position=f32(frame.position),
                       motion=f32(motion),
                       emission=None if frame.emission is None else f32(frame.emission))
        image, state = _jitted_step(state, inputs, config)
        images.append(image)
    return (images, state) if return_state else images


# ------------------------------------------------------------------------------ registration
def bmfr_tile_spec(config: BMFRConfig) -> TileSpec:
    """Tiles on the block grid: a pixel's output depends on its block alone (its features'
    min / max and its fit), which lies within 31 pixels of it. With tile origins on multiples
    of 32 the grid and the noise (both repeat every 32 pixels) fall where they fall on the
    whole frame, and a tile grown by 31 holds the blocks of all its output pixels whole (the
    blocks mirrored at a tile's inner edges serve none of them), so tiles reproduce the whole
    frame."""
    return TileSpec(radius=BLOCK_SIZE - 1, multiple=BLOCK_SIZE)


def _configure(config: BMFRConfig, options: dict[str, str]) -> BMFRConfig:
    return BMFR_PRESETS[options["preset"]] if "preset" in options else config


register(DenoiserDef(
    name="bmfr",
    description="BMFR (Koskela et al. 2019): blockwise regression on normal and world "
                "position features (JAX, no training); one frame alone, or a sequence with "
                "its pre- and post-accumulation and TAA (bmfr:preset=bmfr-cl|wskp)",
    config_cls=BMFRConfig,
    required=lambda config: BMFR_FEATURES,
    optional=lambda config: ("emission",) if config.pass_through else (),
    apply=lambda params, config, frame: bmfr_spatial(frame, config),
    tiling=bmfr_tile_spec,
    options=(("preset", tuple(BMFR_PRESETS)),),
    configure=_configure,
    step=lambda params, config, state, frame: bmfr_step(state, frame, config),
))
