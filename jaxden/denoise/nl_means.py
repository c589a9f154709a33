"""NL-means weights (Rousselle et al. 2012, as in Tungsten's NFOR code), the NL-means filter and
the NL-means-weighted, *collaborative* first-order regression that NFOR
(:mod:`jaxden.denoise.nfor`) is built from; pure JAX, vectorised over pixels.

Every filter sweeps its ``(2R+1)^2`` window by ``lax.scan`` over the window's offsets, so its
memory is that of its accumulators per pixel (``O(pixels x d^2)`` for a regression on ``d``
columns), never ``O(pixels x window)``; the offsets sweep square blocks of the image in turn
(``lax.map``): 64 x 64 on the CPU, where a block's accumulators stay in cache, the whole image
on accelerators (:func:`block_side`). The result does not depend on the blocks.

Shapes: ``(H, W, C)`` images; offsets ``(dy, dx)`` in pixels, ``q = p + (dy, dx)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

#: Rousselle et al.'s NL-means constants in Tungsten's ``nlMeansWeights``: the denominator's
#: epsilon, the largest per-pixel distance, the least weight of the centre pixel.
NL_MEANS_EPSILON = 1e-7
DISTANCE_CLAMP = 1e4
MIN_CENTRE_WEIGHT = 1e-4
#: Window offsets handled per step of the scans (``lax.scan``'s ``unroll``). 4 saved ~15 % of
#: the regressions' CPU time at 256 x 256 on the CPU but doubled the compile time: 1.
SCAN_UNROLL = 1


# ------------------------------------------------------------------------------ blocks
def window_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(2 radius + 1)^2`` offsets ``(dy, dx)`` of a square window, row by row."""
    span = np.arange(-radius, radius + 1, dtype=np.int32)
    dys, dxs = np.meshgrid(span, span, indexing="ij")
    return dys.ravel(), dxs.ravel()


def block_side(block: int) -> int:
    """The block side the filters work in: ``block``, or for 0 64 pixels on the CPU (a block's
    accumulators stay in cache while the window's offsets sweep over them; measured at 256 x
    256: 32, 64, 128 and whole within 10 % of CPU time, 64 the least temporary memory) and the
    whole image on accelerators (one wide pass per offset, no loop over blocks)."""
    if block:
        return block
    return 64 if jax.default_backend() == "cpu" else 1 << 30


class _Blocks(NamedTuple):
    """A ``height x width`` image cut into ``count_y x count_x`` blocks of ``side_y x side_x``
    (the last ones may reach past the image); ``pad``: how far arrays are zero-padded so that
    any block's window and patches can be sliced from them."""

    height: int
    width: int
    side_y: int
    side_x: int
    count_y: int
    count_x: int
    pad: int


def _blocks(height: int, width: int, block: int, reach: int) -> _Blocks:
    side = block_side(block)
    side_y, side_x = min(side, height), min(side, width)
    count_y, count_x = -(-height // side_y), -(-width // side_x)
    overshoot = max(count_y * side_y - height, count_x * side_x - width)
    return _Blocks(height, width, side_y, side_x, count_y, count_x, reach + overshoot)


def _pad(image: jax.Array, pad: int) -> jax.Array:
    """Zero-pad axes 0 and 1 (rows, columns) of ``(H, W, ...)`` by ``pad``."""
    return jnp.pad(image, [(pad, pad), (pad, pad)] + [(0, 0)] * (image.ndim - 2))


def _slice(padded: jax.Array, pad: int, y, x, height: int, width: int) -> jax.Array:
    """Rows ``[y, y + height)`` and columns ``[x, x + width)`` (image coordinates, may be
    traced) of an image padded by ``pad`` (:func:`_pad`)."""
    start = (pad + y, pad + x) + (0,) * (padded.ndim - 2)
    return jax.lax.dynamic_slice(padded, tuple(jnp.asarray(s, jnp.int32) for s in start),
                                 (height, width) + padded.shape[2:])


def _blockwise(fn: Callable, blocks: _Blocks):
    """``fn(y0, x0)`` (a pytree of ``(side_y, side_x, ...)`` arrays for the block at ``(y0,
    x0)``) over every block by ``lax.map``, reassembled into ``(H, W, ...)`` arrays."""
    ys, xs = np.meshgrid(np.arange(blocks.count_y) * blocks.side_y,
                         np.arange(blocks.count_x) * blocks.side_x, indexing="ij")
    out = jax.lax.map(lambda origin: fn(*origin),
                      (jnp.asarray(ys.ravel(), jnp.int32), jnp.asarray(xs.ravel(), jnp.int32)))

    def assemble(a):
        rest = a.shape[3:]
        a = a.reshape((blocks.count_y, blocks.count_x, blocks.side_y, blocks.side_x) + rest)
        a = jnp.swapaxes(a, 1, 2).reshape((blocks.count_y * blocks.side_y,
                                           blocks.count_x * blocks.side_x) + rest)
        return a[:blocks.height, :blocks.width]

    return jax.tree_util.tree_map(assemble, out)


def _box_valid(image: jax.Array, radius: int) -> jax.Array:
    """Sums over ``(2 radius + 1)^2`` boxes of ``(h + 2 radius, w + 2 radius, ...)`` ->
    ``(h, w, ...)`` (only whole boxes): two separable passes of shifted slices summed directly
    (they fuse with what surrounds them, unlike ``reduce_window`` on the CPU, and avoid the
    float32 round-off of running sums)."""
    for axis in (0, 1):
        size = image.shape[axis] - 2 * radius
        image = sum(jax.lax.slice_in_dim(image, i, i + size, axis=axis)
                    for i in range(2 * radius + 1))
    return image


# ------------------------------------------------------------------------------ NL-means
class _Guide(NamedTuple):
    """A guide and its variance ``(H, W, C)`` and the mask of the image (1 inside), padded."""

    guide: jax.Array
    variance: jax.Array
    mask: jax.Array
    pad: int


def _guide(guide, variance, pad: int) -> _Guide:
    mask = jnp.ones(guide.shape[:2] + (1,), guide.dtype)
    return _Guide(_pad(guide, pad), _pad(variance, pad), _pad(mask, pad), pad)


def _weights(guide: _Guide, y0, x0, dy, dx, side_y: int, side_x: int, patch: int, k,
             variance_scale: float) -> jax.Array:
    """NL-means weights (Tungsten's ``nlMeansWeights``, after Rousselle et al.) of the
    neighbour ``q = p + (dy, dx)`` of the pixels ``p`` of the block at ``(y0, x0)``, per channel:
    ``(side_y, side_x, C)``.

    Per pixel ``r``: ``d(r) = [(g_r - g_{r+delta})^2 - (V_r + min(V_r, V_{r+delta}))] / (1e-7
    + k^2 (V_r + V_{r+delta}))``, ``V = variance_scale * variance``, at most 1e4; its mean over
    the ``(2 patch + 1)^2`` patch around ``p`` (over the pixels ``r`` with ``r`` and ``r + delta``
    in the image); weight ``exp(-max(mean, 0))``, 0 unless ``p`` and ``q`` are in the image, and
    at least 1e-4 at ``delta = 0``. ``dy, dx, y0, x0`` may be traced."""
    height, width = side_y + 2 * patch, side_x + 2 * patch
    at = lambda a, oy, ox: _slice(a, guide.pad, y0 - patch + oy, x0 - patch + ox, height,
                                  width)
    g_r, v_r, m_r = (at(a, 0, 0) for a in guide[:3])
    g_q, v_q, m_q = (at(a, dy, dx) for a in guide[:3])
    v_r, v_q = v_r * variance_scale, v_q * variance_scale
    distance = ((g_r - g_q) ** 2 - (v_r + jnp.minimum(v_r, v_q))) / (
        NL_MEANS_EPSILON + k * k * (v_r + v_q))
    valid = m_r * m_q
    distance = jnp.minimum(distance, DISTANCE_CLAMP) * valid
    mean = _box_valid(distance, patch) / jnp.maximum(_box_valid(valid, patch), 1.0)
    inside = valid[patch:patch + side_y, patch:patch + side_x]
    weight = jnp.exp(-jnp.maximum(mean, 0.0)) * inside
    return jnp.where((dy == 0) & (dx == 0), jnp.maximum(weight, MIN_CENTRE_WEIGHT * inside),
                     weight)


def nl_means_weights(guide, variance, dy: int, dx: int, patch: int, k,
                     variance_scale: float = 1.0) -> jax.Array:
    """The NL-means weights of every pixel's neighbour at the offset ``(dy, dx)`` (0 where it
    is outside the image): ``guide, variance (H, W, C) -> (H, W, C)`` (see :func:`_weights`)."""
    height, width = guide.shape[0], guide.shape[1]
    pad = max(abs(dy), abs(dx)) + patch
    return _weights(_guide(guide, variance, pad), 0, 0, dy, dx, height, width, patch, k,
                    variance_scale)


def nl_means(image, guide, variance, patch: int, window: int, k, variance_scale: float = 1.0,
             block: int = 0) -> jax.Array:
    """NL-means filter (Tungsten's ``nlMeans``): ``out_p = sum_q w_pq image_q / sum_q w_pq``
    over the ``(2 window + 1)^2`` window, with the per-channel weights of
    :func:`nl_means_weights` from ``guide, variance (H, W, C)``. ``image (H, W, C)`` or
    ``(S, H, W, C)`` (S images sharing the weights). ``block``: the side of the blocks it works
    in (:func:`block_side`; the result does not depend on it). Returns the shape of
    ``image``."""
    stacked = image.ndim == 4
    image = jnp.moveaxis(image, 0, 2) if stacked else image[:, :, None]
    blocks = _blocks(guide.shape[0], guide.shape[1], block, window + patch)
    guides = _guide(guide, variance, blocks.pad)
    padded = _pad(image, blocks.pad)
    dys, dxs = window_offsets(window)

    def run(y0, x0):
        def tap(carry, offset):
            dy, dx = offset
            w = _weights(guides, y0, x0, dy, dx, blocks.side_y, blocks.side_x, patch, k,
                         variance_scale)
            image_q = _slice(padded, blocks.pad, y0 + dy, x0 + dx, blocks.side_y,
                             blocks.side_x)
            total, weights = carry
            return (total + w[:, :, None] * image_q, weights + w), None

        shape = (blocks.side_y, blocks.side_x)
        init = (jnp.zeros(shape + image.shape[2:], image.dtype),
                jnp.zeros(shape + guide.shape[2:], guide.dtype))
        (total, weights), _ = jax.lax.scan(tap, init, (jnp.asarray(dys), jnp.asarray(dxs)),
                                           unroll=SCAN_UNROLL)
        return total / jnp.where(weights > 0, weights, 1.0)[:, :, None]

    out = _blockwise(run, blocks)
    return jnp.moveaxis(out, 2, 0) if stacked else out[:, :, 0]


# ------------------------------------------------------------------------------ regression
def _design(features_p, features_q, dy, dx) -> jax.Array:
    """Design rows ``[1, dx, dy, f(q) - f(p)]`` ``(h, w, d)`` (Tungsten's order)."""
    ones = jnp.ones(features_p.shape[:2] + (1,), features_p.dtype)
    return jnp.concatenate([ones, ones * jnp.asarray(dx, ones.dtype),
                            ones * jnp.asarray(dy, ones.dtype), features_q - features_p], -1)


def _system_block(image, guides: _Guide, features, blocks: _Blocks, patch, window, k,
                  variance_scale, y0, x0):
    """:func:`regression_system` of one block (``image``, ``features`` padded by
    ``blocks.pad``)."""
    d = 3 + features.shape[-1]
    upper_i, upper_j = np.triu_indices(d)
    shape = (blocks.side_y, blocks.side_x)
    features_p = _slice(features, blocks.pad, y0, x0, *shape)
    dys, dxs = window_offsets(window)

    def tap(carry, offset):
        dy, dx = offset
        # a scalar weight: the least channel's (Tungsten's convertWeight)
        weight = jnp.min(_weights(guides, y0, x0, dy, dx, *shape, patch, k, variance_scale),
                         axis=-1, keepdims=True)
        design = _design(features_p, _slice(features, blocks.pad, y0 + dy, x0 + dx, *shape),
                         dy, dx)
        color_q = _slice(image, blocks.pad, y0 + dy, x0 + dx, *shape)
        weighted = weight * design
        gram, rhs = carry
        gram = gram + weighted[..., upper_i] * design[..., upper_j]
        rhs = rhs + weighted[..., :, None] * color_q[..., None, :]
        return (gram, rhs), None

    init = (jnp.zeros(shape + (len(upper_i),), image.dtype),
            jnp.zeros(shape + (d, image.shape[-1]), image.dtype))
    (gram, rhs), _ = jax.lax.scan(tap, init, (jnp.asarray(dys), jnp.asarray(dxs)),
                                  unroll=SCAN_UNROLL)
    return gram, rhs


def regression_system(image, guide, features, variance, patch: int, window: int, k,
                      variance_scale: float = 2.0, block: int = 0):
    """Every pixel's weighted normal equations: ``(gram (H, W, T), rhs (H, W, d, 3))``,
    ``gram`` the upper triangle (row-major, ``T = d (d + 1) / 2``) of ``X^T W X`` and ``rhs =
    X^T W Y`` over the ``(2 window + 1)^2`` window (inside the image), rows ``[1, dx, dy, f(q) -
    f(p)]`` (``d = 3 + F`` for ``features (H, W, F)``), ``Y`` the ``image (H, W, 3)`` at ``q``,
    ``W`` the least channel's :func:`nl_means_weights` from ``guide, variance (H, W, C)``."""
    blocks = _blocks(guide.shape[0], guide.shape[1], block, window + patch)
    guides = _guide(guide, variance, blocks.pad)
    image, features = _pad(image, blocks.pad), _pad(features, blocks.pad)
    return _blockwise(lambda y0, x0: _system_block(
        image, guides, features, blocks, patch, window, k, variance_scale, y0, x0), blocks)


def solve_regression(gram: jax.Array, rhs: jax.Array, ridge: float) -> jax.Array:
    """Coefficients ``(..., d, m)`` of every pixel's system ``gram`` (upper triangle,
    ``(..., T)``) ``beta = rhs (..., d, m)``, regularised: with ``S = diag(gram)^(-1/2)`` (0 for a
    zero column), ``(S gram S + ridge I') gamma = S rhs``, ``beta = S gamma``, ``I'`` the
    identity without the intercept's entry; i.e. the least-squares fit plus ``ridge sum_i
    gram_ii beta_i^2`` for every coefficient but the first. Batched Cholesky; a pixel whose
    factorisation fails in float32 (never seen; the scaled system's eigenvalues are >=
    ``ridge`` but for the intercept's) keeps only its intercept, the weighted mean."""
    d = rhs.shape[-2]
    index = np.zeros((d, d), np.int32)
    for t, (i, j) in enumerate(zip(*np.triu_indices(d), strict=True)):
        index[i, j] = index[j, i] = t
    matrix = gram[..., index]
    diagonal = jnp.diagonal(matrix, axis1=-2, axis2=-1)
    scale = jnp.where(diagonal > 1e-30, jax.lax.rsqrt(jnp.maximum(diagonal, 1e-30)), 0.0)
    regulariser = np.full(d, ridge, np.float32)
    regulariser[0] = 0.0
    matrix = matrix * scale[..., :, None] * scale[..., None, :] + jnp.diag(
        jnp.asarray(regulariser, matrix.dtype))
    # an empty column (scale 0) gets a unit diagonal: its coefficient is then 0
    matrix = jnp.where(jnp.eye(d, dtype=bool) & (scale[..., None, :] == 0), 1.0, matrix)
    factor = jnp.linalg.cholesky(matrix)
    gamma = jax.scipy.linalg.cho_solve((factor, True), rhs * scale[..., :, None])
    beta = gamma * scale[..., :, None]
    mean = jnp.zeros_like(beta).at[..., 0, :].set(
        rhs[..., 0, :] / jnp.where(diagonal[..., :1] > 0, diagonal[..., :1], 1.0))
    ok = jnp.all(jnp.isfinite(beta), axis=(-2, -1), keepdims=True)
    return jnp.where(ok, beta, mean)


def regression_coefficients(image, guide, features, variance, patch: int, window: int, k,
                            variance_scale: float = 2.0, ridge: float = 1e-5,
                            block: int = 0) -> jax.Array:
    """Every pixel's fit ``beta (H, W, d, 3)``: :func:`regression_system` solved by
    :func:`solve_regression`, block by block (the normal equations of only one block exist at
    a time)."""
    blocks = _blocks(guide.shape[0], guide.shape[1], block, window + patch)
    guides = _guide(guide, variance, blocks.pad)
    image, features = _pad(image, blocks.pad), _pad(features, blocks.pad)
    return _blockwise(lambda y0, x0: solve_regression(*_system_block(
        image, guides, features, blocks, patch, window, k, variance_scale, y0, x0), ridge),
        blocks)


def collaborate(beta, guide, features, variance, patch: int, window: int, k,
                variance_scale: float = 2.0, block: int = 0) -> jax.Array:
    """The collaborative step: every pixel ``p``'s fit is evaluated at each ``q`` of its window
    and averaged there with the regression weights: ``out_q = sum_p w_pq x_pq . beta_p /
    sum_p w_pq`` ``(H, W, m)`` for ``beta (H, W, d, m)`` (``x_pq = [1, dx, dy, f(q) - f(p)]``,
    ``q = p + (dx, dy)``)."""
    blocks = _blocks(guide.shape[0], guide.shape[1], block, window + patch)
    guides = _guide(guide, variance, blocks.pad)
    features, beta = _pad(features, blocks.pad), _pad(beta, blocks.pad)
    shape = (blocks.side_y, blocks.side_x)
    dys, dxs = window_offsets(window)

    def run(y0, x0):
        features_q = _slice(features, blocks.pad, y0, x0, *shape)

        def tap(carry, offset):
            dy, dx = offset
            # the pixels p = q - delta whose window holds q at offset delta
            weight = jnp.min(_weights(guides, y0 - dy, x0 - dx, dy, dx, *shape, patch, k,
                                      variance_scale), axis=-1, keepdims=True)
            design = _design(_slice(features, blocks.pad, y0 - dy, x0 - dx, *shape),
                             features_q, dy, dx)
            fitted = jnp.einsum("hwd,hwdm->hwm", design,
                                _slice(beta, blocks.pad, y0 - dy, x0 - dx, *shape))
            total, weights = carry
            return (total + weight * fitted, weights + weight), None

        init = (jnp.zeros(shape + beta.shape[-1:], beta.dtype),
                jnp.zeros(shape + (1,), beta.dtype))
        (total, weights), _ = jax.lax.scan(tap, init, (jnp.asarray(dys), jnp.asarray(dxs)),
                                           unroll=SCAN_UNROLL)
        return total / jnp.where(weights > 0, weights, 1.0)

    return _blockwise(run, blocks)


def collaborative_regression(image, guide, features, variance, patch: int, window: int, k,
                             variance_scale: float = 2.0, ridge: float = 1e-5,
                             block: int = 0) -> jax.Array:
    """Tungsten's ``collaborativeRegression``: per-pixel weighted first-order regression of
    ``image (H, W, 3)`` on ``features (H, W, F)`` with weights from ``guide, variance``
    (:func:`regression_coefficients`), then :func:`collaborate`. Returns ``(H, W, 3)``."""
    beta = regression_coefficients(image, guide, features, variance, patch, window, k,
                                   variance_scale, ridge, block)
    return collaborate(beta, guide, features, variance, patch, window, k, variance_scale,
                       block)


# ------------------------------------------------------------------------------ receptive fields
def nl_means_radius(patch: int, window: int, guide_radius: int, image_radius: int) -> int:
    """Receptive field of :func:`nl_means` given those of its guide (and variance) and image."""
    return window + max(patch + guide_radius, image_radius)


def regression_radius(patch: int, window: int, guide_radius: int, image_radius: int,
                      feature_radius: int) -> int:
    """Receptive field of :func:`collaborative_regression`: fits of pixels up to ``window``
    away, each over its window, with weights over patches there."""
    return 2 * window + max(feature_radius, patch + guide_radius, image_radius)
