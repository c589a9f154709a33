"""The James-Stein combination of the neural James-Stein combiner (Gu, Iglesias-Guitian, Moon,
SIGGRAPH Asia 2022; :mod:`jaxden.denoise.njs` is the whole combiner): the network's weighted
average of the per-pixel variance, the shrinkage factor and the shrunk image, in pure JAX.

Per pixel and channel, with the network's 225 weights ``w`` over the 15 x 15 window (row-major,
image borders mirrored without repeating the edge, :func:`mirror_pad`) and its ``alpha``:

    sigma^2 = sum_q w_q Var(q) / max(sum_q w_q, 1e-5)              (:func:`weighted_variance`)
    z       = alpha olsA + (1 - alpha) olsB
    rho     = max(0, 1 - (K^2 - 2) sigma^2 / max(sum_15x15 (y - z)^2, 1e-5)),  K^2 - 2 = 223
                                                                   (:func:`shrinkage`)
    out     = z + mean_15x15(rho) (y - z)                          (:func:`james_stein`)

(:func:`js_combine` does all of it; at test time the authors clamp ``out`` at 0.) Shapes
``(..., H, W, C)``; linear radiance.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from jaxden.denoise.nn.njs import KERNEL_SIZE
from jaxden.errors import ConfigError, FrameError

#: The floor of the weight sum and of the squared-error sum in the combination (``JS_EP``).
JS_EPS = 1e-5


def check_window(window, what: str) -> int:
    if isinstance(window, bool) or not isinstance(window, int) or window < 1 or window % 2 == 0:
        raise ConfigError(f"{what}: the window must be an odd int >= 1, got {window!r}")
    return window // 2


def check_mirror(height: int, width: int, radius: int, what: str) -> None:
    """The authors mirror once (``2 W - 2 - x``): a window reaching more than one image side
    past the border has no defined mirror pixel."""
    if radius > height - 1 or radius > width - 1:
        raise FrameError(f"{what}: a {2 * radius + 1} x {2 * radius + 1} window needs an image "
                         f"of at least {radius + 1} x {radius + 1} pixels (its borders are "
                         f"mirrored once), got {height} x {width}")


def mirror_pad(image: jax.Array, radius: int) -> jax.Array:
    """Pad axes -3, -2 by ``radius``, mirrored without repeating the edge (``x -> -x``,
    ``x -> 2 (W - 1) - x``, the authors' ``getImgIdx``)."""
    pad = [(0, 0)] * (image.ndim - 3) + [(radius, radius), (radius, radius), (0, 0)]
    return jnp.pad(image, pad, mode="reflect")



def _box_sum(image: jax.Array, kernel_size: int) -> jax.Array:
    """Sums over the mirrored ``kernel_size`` square around each pixel: (..., H, W, C)."""
    radius = kernel_size // 2
    padded = mirror_pad(image, radius)
    for axis, size in ((-3, image.shape[-3]), (-2, image.shape[-2])):
        padded = sum(jax.lax.slice_in_dim(padded, i, i + size, axis=padded.ndim + axis)
                     for i in range(kernel_size))
    return padded


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _window_average(values, weights, kernel_size: int):
    """``sum_n w_n values(q_n) / max(sum_n w_n, 1e-5)``, row-major mirrored window: a scan
    over the window's rows (one row of shifted neighbours at a time), rematerialised in
    reverse mode."""
    radius = kernel_size // 2
    width = values.shape[-2]
    axis = values.ndim - 3
    padded = mirror_pad(values, radius)
    rows = weights.reshape(*weights.shape[:-1], kernel_size, kernel_size)
    rows = jnp.moveaxis(rows, -2, 0)

    @jax.checkpoint
    def step(total, xs):
        dy, row_weights = xs
        band = jax.lax.dynamic_slice_in_dim(padded, dy, values.shape[-3], axis=axis)
        shifted = jnp.stack([band[..., dx:dx + width, :] for dx in range(kernel_size)], -2)
        return total + jnp.einsum("...k,...kc->...c", row_weights, shifted), None

    total, _ = jax.lax.scan(step, jnp.zeros(values.shape, values.dtype),
                            (jnp.arange(kernel_size), rows))
    return total / jnp.maximum(jnp.sum(weights, -1, keepdims=True), JS_EPS)


def _check_image(name: str, value, shape, what: str) -> jax.Array:
    value = jnp.asarray(value, jnp.float32)
    if value.shape != tuple(shape):
        raise FrameError(f"{what}: {name} must have shape {tuple(shape)}, got {value.shape}")
    return value


def weighted_variance(variance, weights, kernel_size: int = KERNEL_SIZE) -> jax.Array:
    """The network's variance estimate (the authors' ``weight_avg``): ``sum_n w_pn Var(q_n) /
    max(sum_n w_pn, 1e-5)`` over the mirrored ``kernel_size`` window, ``n`` row-major (channel
    ``n`` of ``weights`` for the offset ``divmod(n, k) - (k // 2, k // 2)``).
    ``variance (..., H, W, C)``, ``weights (..., H, W, k * k)`` -> (..., H, W, C)."""
    radius = check_window(kernel_size, "weighted_variance")
    variance = jnp.asarray(variance, jnp.float32)
    if variance.ndim < 3:
        raise FrameError(f"weighted_variance: variance must be (..., H, W, C), got "
                         f"{variance.shape}")
    weights = _check_image("weights", weights, (*variance.shape[:-1], kernel_size ** 2),
                           "weighted_variance")
    check_mirror(variance.shape[-3], variance.shape[-2], radius, "weighted_variance")
    return _window_average(variance, weights, kernel_size)


def shrinkage(noisy, biased, variance_estimate, kernel_size: int = KERNEL_SIZE) -> jax.Array:
    """The James-Stein shrinkage factor (the authors' ``calc_shrinkage``), per pixel and
    channel: ``max(0, 1 - (k^2 - 2) var_hat(p) / max(sum_q (y(q) - z(q))^2, 1e-5))`` over the
    mirrored ``k x k`` window. ``noisy`` y, ``biased`` z, ``variance_estimate`` var_hat, each
    (..., H, W, C) -> (..., H, W, C) in [0, 1] (for var_hat >= 0)."""
    radius = check_window(kernel_size, "shrinkage")
    noisy = jnp.asarray(noisy, jnp.float32)
    biased = _check_image("biased", biased, noisy.shape, "shrinkage")
    variance_estimate = _check_image("variance_estimate", variance_estimate, noisy.shape,
                                     "shrinkage")
    check_mirror(noisy.shape[-3], noisy.shape[-2], radius, "shrinkage")
    return _shrinkage(noisy, biased, variance_estimate, kernel_size)


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _shrinkage(noisy, biased, variance_estimate, kernel_size: int):
    squared_error = _box_sum(jnp.square(noisy - biased), kernel_size)
    degrees = kernel_size * kernel_size - 2
    return jnp.maximum(0.0, 1.0 - degrees * variance_estimate
                       / jnp.maximum(squared_error, JS_EPS))


def james_stein(noisy, biased, rho, kernel_size: int = KERNEL_SIZE) -> jax.Array:
    """The combination (the authors' ``combiner``): ``z + mean_q rho(q) (y - z)`` with the mean
    over the mirrored ``k x k`` window; (..., H, W, C) each -> (..., H, W, C)."""
    radius = check_window(kernel_size, "james_stein")
    noisy = jnp.asarray(noisy, jnp.float32)
    biased = _check_image("biased", biased, noisy.shape, "james_stein")
    rho = _check_image("rho", rho, noisy.shape, "james_stein")
    check_mirror(noisy.shape[-3], noisy.shape[-2], radius, "james_stein")
    return _james_stein(noisy, biased, rho, kernel_size)


@functools.partial(jax.jit, static_argnames=("kernel_size",))
def _james_stein(noisy, biased, rho, kernel_size: int):
    mean_rho = _box_sum(rho, kernel_size) / (kernel_size * kernel_size)
    return biased + mean_rho * (noisy - biased)


def js_combine(noisy, variance, ols_a, ols_b, weights, alpha, kernel_size: int = KERNEL_SIZE,
               clamp: bool = False) -> jax.Array:
    """The whole combination after the network: the variance estimate, ``z = alpha olsA + (1
    - alpha) olsB``, the shrinkage and the combination (module docstring); ``clamp``: the
    result clamped at 0 (the authors' test step). ``noisy``, ``variance`` (of the mean),
    ``ols_a``, ``ols_b`` (..., H, W, 3); ``weights`` (..., H, W, k * k) > 0; ``alpha``
    (..., H, W, 1) in [0, 1]. Returns (..., H, W, 3)."""
    noisy = jnp.asarray(noisy, jnp.float32)
    shape = noisy.shape
    ols_a = _check_image("ols_a", ols_a, shape, "js_combine")
    ols_b = _check_image("ols_b", ols_b, shape, "js_combine")
    alpha = _check_image("alpha", alpha, (*shape[:-1], 1), "js_combine")
    variance_estimate = weighted_variance(_check_image("variance", variance, shape,
                                                       "js_combine"), weights, kernel_size)
    biased = alpha * ols_a + (1.0 - alpha) * ols_b
    rho = shrinkage(noisy, biased, variance_estimate, kernel_size)
    out = james_stein(noisy, biased, rho, kernel_size)
    return jnp.maximum(out, 0.0) if clamp else out


