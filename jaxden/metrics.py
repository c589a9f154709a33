"""Image error metrics, defined once for all of jaxden (definitions as in REFERENCE-NOTES.md).

Every metric takes ``(estimate, reference)`` of shape (..., H, W, C) (NumPy or JAX arrays) and
returns one value per image, shape (...), i.e. the mean over H, W and C; leading dimensions
are a batch. All but FLIP are jit-able JAX functions (FLIP calls NVIDIA's ``flip_evaluator``:
NumPy in, NumPy out).

=================  =========================================================  ============
metric             definition (x = estimate, y = reference, means over pixels  data
                   and channels)
=================  =========================================================  ============
mse / rmse         mean (x - y)^2 / its square root                            linear HDR
relmse             mean (x - y)^2 / (y^2 + eps), eps = 0.01                    linear HDR
smape              mean |x - y| / (|x| + |y| + eps), eps = 0.01                linear HDR
noise_corrected_   mse(x, y) - mean(var_y): unbiased for E mean (x - truth)^2  linear HDR
  mse              when y is an unbiased, independent estimate of the truth
                   whose variance of the mean is var_y
psnr               10 log10(1 / mse(T(x), T(y)))   (peak 1)                    tone-mapped
ssim               mean SSIM map of T(x), T(y), per channel then averaged      tone-mapped
flip               NVIDIA FLIP mean error (flip_evaluator), HDR or LDR mode    HDR or LDR
=================  =========================================================  ============

Tone map ``T`` (WSKP's "gamma correction"): ``T(v) = clip(v, 0, 1) ** (1 / 2.2)``, per channel,
no exposure scaling. PSNR and SSIM take ``tonemap=False`` for inputs already in display [0, 1].

SSIM: Gaussian window 11 x 11 with sigma 1.5 (normalised to sum 1), K1 = 0.01, K2 = 0.03,
dynamic range L = 1, computed per channel over the *valid* region (no padding: the map is
(H - 10) x (W - 10)) and averaged over that region and the channels, as in Wang et al.'s
reference code; without its automatic downsampling of large images.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import FrameError

EPS = 0.01
GAMMA = 2.2
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1 = 0.01
SSIM_K2 = 0.03
_IMAGE_AXES = (-3, -2, -1)


def _pair(estimate, reference, name: str):
    estimate, reference = jnp.asarray(estimate), jnp.asarray(reference)
    if estimate.ndim < 3 or estimate.shape != reference.shape:
        raise FrameError(
            f"{name}: estimate and reference must have the same shape (..., H, W, C), got "
            f"{estimate.shape} and {reference.shape}"
        )
    dtype = jnp.promote_types(jnp.result_type(estimate, reference), jnp.float32)
    return estimate.astype(dtype), reference.astype(dtype)


# ------------------------------------------------------------------- pixel-wise errors
@jax.jit
def _mse(x, y):
    return jnp.mean(jnp.square(x - y), axis=_IMAGE_AXES)


@jax.jit
def _relmse(x, y, eps):
    return jnp.mean(jnp.square(x - y) / (jnp.square(y) + eps), axis=_IMAGE_AXES)


@jax.jit
def _smape(x, y, eps):
    return jnp.mean(jnp.abs(x - y) / (jnp.abs(x) + jnp.abs(y) + eps), axis=_IMAGE_AXES)


@jax.jit
def _mae(x, y):
    return jnp.mean(jnp.abs(x - y), axis=_IMAGE_AXES)


def mse(estimate, reference):
    """Mean squared error per image: (..., H, W, C) x2 -> (...)."""
    return _mse(*_pair(estimate, reference, "mse"))


def rmse(estimate, reference):
    """Root mean squared error per image (same units as the inputs): -> (...)."""
    return jnp.sqrt(_mse(*_pair(estimate, reference, "rmse")))


def mae(estimate, reference):
    """Mean absolute error per image: -> (...)."""
    return _mae(*_pair(estimate, reference, "mae"))


def relmse(estimate, reference, eps: float = EPS):
    """Relative MSE per image, mean (x - y)^2 / (y^2 + eps) with y the reference: -> (...)."""
    return _relmse(*_pair(estimate, reference, "relmse"), eps)


def smape(estimate, reference, eps: float = EPS):
    """Symmetric MAPE per image, mean |x - y| / (|x| + |y| + eps): -> (...), in [0, 1)."""
    return _smape(*_pair(estimate, reference, "smape"), eps)


def noise_corrected_mse(estimate, reference, reference_variance):
    """MSE against a noisy reference, corrected for the reference's own noise: -> (...).

    ``mse(x, y) - mean(var_y)``, where ``reference_variance`` (..., H, W, C) is the variance of
    the reference's pixel mean. If y = truth + n with E n = 0, Var n = var_y and n independent
    of x, then E[mse(x, y)] = E[mean (x - truth)^2] + mean(var_y): the correction makes the
    estimate unbiased. It can be negative for a single image when x is close to the truth.
    """
    x, y = _pair(estimate, reference, "noise_corrected_mse")
    variance = jnp.asarray(reference_variance, x.dtype)
    if variance.shape != y.shape:
        raise FrameError(
            f"noise_corrected_mse: reference_variance must have the reference's shape "
            f"{y.shape}, got {variance.shape}"
        )
    return _mse(x, y) - jnp.mean(variance, axis=_IMAGE_AXES)


# ------------------------------------------------------------------ tone-mapped metrics
def tonemap(image, gamma: float = GAMMA):
    """Display transform for PSNR/SSIM: clip to [0, 1], then ``** (1 / gamma)``. Any shape."""
    return jnp.power(jnp.clip(jnp.asarray(image), 0.0, 1.0), 1.0 / gamma)


def psnr(estimate, reference, tonemap_inputs: bool = True):
    """Peak signal-to-noise ratio in dB with peak 1, per image: -> (...).

    ``10 log10(1 / mse(T(x), T(y)))`` with ``T`` = :func:`tonemap` (identity if
    ``tonemap_inputs`` is False: inputs already in display [0, 1]). +inf for identical images.
    """
    x, y = _pair(estimate, reference, "psnr")
    if tonemap_inputs:
        x, y = tonemap(x), tonemap(y)
    return -10.0 * jnp.log10(_mse(x, y))


def _gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> np.ndarray:
    offsets = np.arange(size, dtype=np.float64) - size // 2
    window = np.exp(-(offsets**2) / (2 * sigma**2))
    return (window / window.sum()).astype(np.float32)


def _blur_valid(image, window: np.ndarray):
    """Separable 'valid' Gaussian filter of (..., H, W, C) along H and W (no padding)."""
    size = window.shape[0]
    for axis in (-3, -2):
        length = image.shape[axis] - size + 1
        image = sum(
            float(w) * jax.lax.slice_in_dim(image, i, i + length, axis=image.ndim + axis)
            for i, w in enumerate(window)
        )
    return image


@jax.jit
def _ssim(x, y):
    window = _gaussian_window()
    c1, c2 = SSIM_K1**2, SSIM_K2**2  # (K L)^2 with L = 1
    mu_x, mu_y = _blur_valid(x, window), _blur_valid(y, window)
    var_x = _blur_valid(x * x, window) - mu_x * mu_x
    var_y = _blur_valid(y * y, window) - mu_y * mu_y
    cov = _blur_valid(x * y, window) - mu_x * mu_y
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / (
        (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    )
    return jnp.mean(ssim_map, axis=_IMAGE_AXES)


def ssim(estimate, reference, tonemap_inputs: bool = True):
    """Structural similarity per image (module docstring has the exact variant): -> (...).

    Images must be at least 11 x 11. 1 for identical images; symmetric in its arguments.
    """
    x, y = _pair(estimate, reference, "ssim")
    if min(x.shape[-3:-1]) < SSIM_WINDOW:
        raise FrameError(
            f"ssim: images must be at least {SSIM_WINDOW} x {SSIM_WINDOW} (the Gaussian "
            f"window), got {x.shape[-3]} x {x.shape[-2]}"
        )
    if tonemap_inputs:
        x, y = tonemap(x), tonemap(y)
    return _ssim(x, y)


# --------------------------------------------------------------------------------- FLIP
def flip(estimate, reference, dynamic_range: str = "HDR", return_map: bool = False):
    """NVIDIA FLIP error per image via ``flip_evaluator`` (NumPy in and out, not jit-able).

    Args:
      estimate, reference: (..., H, W, 3). HDR mode: linear radiance (linear sRGB), negative
        values are clipped to 0 (FLIP requires >= 0; denoisers can undershoot slightly); the
        exposure range is derived from the reference by FLIP. LDR mode: sRGB-encoded display
        values, clipped to [0, 1].
      dynamic_range: ``"HDR"`` (default: jaxden's data is linear HDR) or ``"LDR"``.
      return_map: also return the per-pixel error maps (..., H, W).

    Returns:
      Mean FLIP error per image, float64 array of shape (...) (a 0-d array for one image),
      and the maps if ``return_map``.
    """
    if dynamic_range not in ("HDR", "LDR"):
        raise FrameError(f"flip: dynamic_range must be 'HDR' or 'LDR', got {dynamic_range!r}")
    x = np.asarray(estimate, np.float32)
    y = np.asarray(reference, np.float32)
    if x.ndim < 3 or x.shape != y.shape or x.shape[-1] != 3:
        raise FrameError(
            f"flip: estimate and reference must have the same shape (..., H, W, 3), got "
            f"{x.shape} and {y.shape}"
        )
    for name, array in (("estimate", x), ("reference", y)):
        if not np.all(np.isfinite(array)):
            count = int((~np.isfinite(array)).sum())
            raise FrameError(f"flip: {name} has {count} non-finite values")
    import flip_evaluator  # deferred: only FLIP needs it

    high = None if dynamic_range == "HDR" else 1.0
    batch = x.shape[:-3]
    means = np.empty(batch, np.float64)
    maps = np.empty(batch + x.shape[-3:-1], np.float32)
    for index in np.ndindex(*batch):
        error_map, mean, _ = flip_evaluator.evaluate(
            np.ascontiguousarray(np.clip(y[index], 0.0, high)),
            np.ascontiguousarray(np.clip(x[index], 0.0, high)),
            dynamic_range,
            applyMagma=False,
        )
        means[index] = mean
        maps[index] = np.asarray(error_map).reshape(x.shape[-3:-1])
    return (means, maps) if return_map else means


# A name -> (function, higher is better) table for experiment code and reports.
METRICS = {
    "mse": (mse, False),
    "rmse": (rmse, False),
    "mae": (mae, False),
    "relmse": (relmse, False),
    "smape": (smape, False),
    "psnr": (psnr, True),
    "ssim": (ssim, True),
    "flip": (flip, False),
}

__all__ = [
    "EPS",
    "GAMMA",
    "METRICS",
    "flip",
    "mae",
    "mse",
    "noise_corrected_mse",
    "psnr",
    "relmse",
    "rmse",
    "smape",
    "ssim",
    "tonemap",
]
