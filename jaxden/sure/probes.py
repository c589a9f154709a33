"""SURE's probes: the random directions b whose products b (J b) estimate the divergence term.

Probe k of a key is ``b_k = sqrt(var) * n_k`` (or ``L n_k`` with the colour covariance's
Cholesky factor L, :func:`colour_factor`) with ``n_k`` standard normal from
``split(key, K)[k]``, or the signs of those normals for Rademacher probes (:func:`unit_probes`).
Every path that draws them (the jitted estimator in chunks, a tile's window of the frame, the
NumPy black box one probe at a time) gets the same values for the same key: the math is in
:mod:`jaxden.sure.stein`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import FrameError
from jaxden.sure.settings import ProbeDist


def probe_normal(key, shape, dtype):
    """Standard normal draws of ``shape`` from ``key``: ``normal(key, shape)``."""
    # Drawn flat and reshaped: the same values as normal(key, shape) (counter-based threefry
    # indexes the flat array), but XLA:CPU compiles the flat draw several times faster.
    return jax.random.normal(key, (math.prod(shape),), dtype).reshape(shape)


def unit_probes(normals, dist: ProbeDist, xp=jnp):
    """Standard normal draws as probes of ``dist`` (zero mean, identity covariance): the
    normals themselves, or their signs (+1 where ``n >= 0``, -1 elsewhere: never 0)."""
    if dist == "normal":
        return normals
    return xp.where(normals >= 0, 1.0, -1.0).astype(normals.dtype)


def probe_normals(keys, shape, dtype, dist: ProbeDist = "normal"):
    """:func:`probe_normal` for each of ``keys`` (K, ...), as probes of ``dist``
    (:func:`unit_probes`): (K, *shape)."""
    # lax.map, not vmap: a sequential draw per key equals the unbatched draw for every key
    # implementation (vmap of rbg keys does not), so probe k is the same at any probe_batch.
    return jax.lax.map(lambda k: unit_probes(probe_normal(k, shape, dtype), dist), keys)


def window_normal(key, frame_shape, origin, shape):
    """The (rows, cols, C) window at ``origin`` (row, column; traced) of
    ``probe_normal(key, frame_shape, float32)`` for a frame of ``frame_shape`` (H, W, C),
    computed without drawing the rest: with JAX's partitionable threefry (the default) the
    value at flat index i is threefry2x32(key, (0, i)), turned into a normal as
    ``jax.random.normal`` does (a uniform in (-1, 1) from the top 23 bits, then
    sqrt(2) erfinv). Equal bit for bit to the slice of the whole draw (tested), so a tile's
    SURE probes are the whole frame's."""
    from jax.extend.random import threefry2x32_p

    height, width, channels = frame_shape
    if height * width * channels >= 2**32:
        raise FrameError(f"SURE probes over tiles: a {height}x{width} frame is too large "
                         f"(2^32 values at most)")
    origin = jnp.asarray(origin, jnp.uint32)
    rows = origin[0] + jnp.arange(shape[0], dtype=jnp.uint32)
    cols = origin[1] + jnp.arange(shape[1], dtype=jnp.uint32)
    chans = jnp.arange(channels, dtype=jnp.uint32)
    low = (rows[:, None, None] * jnp.uint32(width) + cols[None, :, None]) * jnp.uint32(
        channels) + chans[None, None, :]
    data = jax.random.key_data(key) if jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key) \
        else key
    bits1, bits2 = threefry2x32_p.bind(jnp.broadcast_to(data[0], low.shape),
                                       jnp.broadcast_to(data[1], low.shape),
                                       jnp.zeros_like(low), low)
    mantissa = jax.lax.shift_right_logical(bits1 ^ bits2, jnp.uint32(32 - 23))
    one = jnp.uint32(np.array(1.0, np.float32).view(np.uint32))
    floats = jax.lax.bitcast_convert_type(mantissa | one, jnp.float32) - jnp.float32(1.0)
    low_value = np.nextafter(np.float32(-1.0), np.float32(0.0), dtype=np.float32)
    uniform = jnp.maximum(low_value, floats * (np.float32(1.0) - low_value) + low_value)
    return np.float32(np.sqrt(2.0)) * jax.lax.erf_inv(uniform)


def window_normals(keys, frame_shape, origin, shape, dist: ProbeDist = "normal"):
    """:func:`window_normal` for each of ``keys`` (K, ...), as probes of ``dist``
    (:func:`unit_probes`): (K, rows, cols, C)."""
    return jax.lax.map(
        lambda k: unit_probes(window_normal(k, frame_shape, origin, shape), dist), keys)


def colour_factor(variance, covariance, xp=jnp):
    """Per pixel, the lower-triangular L with L L^T = Sigma, the 3 x 3 covariance of the pixel
    mean (``variance`` on the diagonal, ``covariance`` = (R, G), (G, B), (B, R) off it), as
    its six entries (l00, l10, l11, l20, l21, l22), each (..., H, W).

    A closed-form Cholesky that tolerates singular and round-off-indefinite Sigma: a zero
    pivot zeroes its column (a channel without variance gets no noise) and negative Schur
    complements are clipped at 0. With zero covariance L = diag(sqrt(var)), so the probes
    ``L n`` equal ``sqrt(var) * n`` exactly. ``xp``: ``jnp`` (traced) or ``np`` (float64)."""
    v = xp.maximum(variance, 0.0)
    c_rg, c_gb, c_br = covariance[..., 0], covariance[..., 1], covariance[..., 2]

    def over(a, pivot):
        return xp.where(pivot > 0, a / xp.where(pivot > 0, pivot, 1.0), 0.0)

    l00 = xp.sqrt(v[..., 0])
    l10, l20 = over(c_rg, l00), over(c_br, l00)
    l11 = xp.sqrt(xp.maximum(v[..., 1] - l10 * l10, 0.0))
    l21 = over(c_gb - l20 * l10, l11)
    l22 = xp.sqrt(xp.maximum(v[..., 2] - l20 * l20 - l21 * l21, 0.0))
    return l00, l10, l11, l20, l21, l22


def colour_probes(normals, factor, xp=jnp):
    """``L n`` per pixel for standard normals (..., H, W, 3) and :func:`colour_factor`'s L."""
    l00, l10, l11, l20, l21, l22 = factor
    n0, n1, n2 = normals[..., 0], normals[..., 1], normals[..., 2]
    return xp.stack([l00 * n0, l10 * n0 + l11 * n1, l20 * n0 + l21 * n1 + l22 * n2], axis=-1)


def draw_probes(key, variance, num_probes: int, covariance=None,
                dist: ProbeDist = "normal") -> jax.Array:
    """The probes ``sure(..., key, num_probes)`` uses: shape (num_probes, *variance.shape).

    ``b_k = sqrt(var) * n_k`` with ``n_k = normal(split(key, num_probes)[k])``, so the draw of
    probe k does not depend on the chunking (``probe_batch``), for any key implementation
    (threefry, rbg). With ``covariance`` (``Frame.covariance``) ``b_k = L n_k``, L the
    per-pixel Cholesky factor of the colour covariance (:func:`colour_factor`): the same
    ``n_k``, so zero covariance gives the same probes. ``dist="rademacher"``: ``n_k``
    replaced by its signs (:func:`unit_probes`). Exposed so that tests and experiments can
    reproduce the exact probes (common random numbers).
    """
    variance = jnp.asarray(variance)
    keys = jax.random.split(key, num_probes)
    normals = probe_normals(keys, variance.shape, variance.dtype, dist)
    if covariance is None:
        return jnp.sqrt(variance) * normals
    return colour_probes(normals, colour_factor(variance, jnp.asarray(covariance, variance.dtype)))


@functools.partial(jax.jit, static_argnames=("num_probes", "dist"))
def draw_probes_compiled(key, variance, num_probes: int, covariance=None, dist="normal"):
    """:func:`draw_probes` compiled once per shape (called eagerly it retraces its
    ``lax.map`` on every call); the same values."""
    return draw_probes(key, variance, num_probes, covariance, dist)


@functools.partial(jax.jit, static_argnames=("dist",))
def draw_probe(key, variance, covariance=None, dist="normal"):
    """Probe k of :func:`draw_probes` alone (``key`` = ``split(key, K)[k]``): the same values."""
    normals = unit_probes(probe_normal(key, variance.shape, variance.dtype), dist)
    if covariance is None:
        return jnp.sqrt(variance) * normals
    return colour_probes(normals, colour_factor(variance, jnp.asarray(covariance,
                                                                      variance.dtype)))
