"""Small synthetic frames with a known clean image, and Monte Carlo noise around them: the data
of jaxden's property checks and strategies (NumPy, seeded; no renderer).

A clean frame (:func:`synthetic_frame`) holds the true image ``mu`` as its colour and the
variance of the pixel mean that a render at ``spp`` samples would have, so that
:func:`monte_carlo_noise` can draw noisy frames whose error against ``mu`` is known.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

NoiseKind = Literal["gaussian", "gamma"]
NOISE_KINDS = ("gaussian", "gamma")


def _smooth_field(rng: np.random.Generator, height: int, width: int, cells: int,
                  channels: int) -> np.ndarray:
    """A (height, width, channels) field in [0, 1]: a random (cells + 1)^2 grid, bilinearly
    interpolated (smooth, with structure at the scale of height / cells)."""
    grid = rng.uniform(0.0, 1.0, (cells + 1, cells + 1, channels))
    rows = np.linspace(0.0, cells, height)
    cols = np.linspace(0.0, cells, width)
    r0 = np.minimum(rows.astype(int), cells - 1)
    c0 = np.minimum(cols.astype(int), cells - 1)
    fr = (rows - r0)[:, None, None]
    fc = (cols - c0)[None, :, None]
    top = grid[r0][:, c0] * (1 - fc) + grid[r0][:, c0 + 1] * fc
    bottom = grid[r0 + 1][:, c0] * (1 - fc) + grid[r0 + 1][:, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def synthetic_frame(seed: int = 0, height: int = 16, width: int = 16, *,
                    radiance: tuple[float, float] = (0.05, 2.0),
                    relative_std: tuple[float, float] = (0.05, 0.5),
                    spp: float = 16.0, miss_fraction: float = 0.0,
                    correlation: float | None = None) -> Frame:
    """A clean frame (H, W) with every feature a render has, float32 NumPy, seeded.

    - ``color`` (the clean image mu): albedo times a smooth shading field whose log is
      uniform over ``radiance`` (linear radiance, min > 0), times a per-pixel texture in
      [0.7, 1.3]: heterogeneous at every scale, no two neighbours equal.
    - ``variance`` (of the pixel mean): ``(r mu)^2``, the relative standard deviation of the
      mean ``r`` log-uniform over ``relative_std`` per pixel and channel, half of its log
      following the image's brightness (darker pixels are noisier relative to their value,
      as in a render).
    - ``albedo`` in [0.1, 0.9] (smooth patches), ``normal`` unit length, ``depth`` in [1, 10];
      a ``miss_fraction`` of the pixels are misses (normal and depth 0, albedo 0, the colour
      an environment value).
    - ``spp`` the scalar sample count the variance is said to come from (recorded only: it
      sets the sample count of ``"gamma"`` noise and the error guard's degrees of freedom);
      ``covariance`` (R, G), (G, B), (B, R) with correlation
      ``correlation`` per pair when given (in [0, 1); None: no covariance field).
    """
    if not (isinstance(height, (int, np.integer)) and isinstance(width, (int, np.integer))
            and height >= 1 and width >= 1):
        raise ConfigError(f"synthetic_frame: height and width must be integers >= 1, got "
                          f"{height!r} x {width!r}")
    low, high = (float(v) for v in radiance)
    r_low, r_high = (float(v) for v in relative_std)
    if not 0 < low <= high or not 0 < r_low <= r_high:
        raise ConfigError(f"synthetic_frame: radiance and relative_std must be ranges (low, "
                          f"high) with 0 < low <= high, got {radiance!r}, {relative_std!r}")
    if not spp > 0:
        raise ConfigError(f"synthetic_frame: spp must be > 0, got {spp!r}")
    if correlation is not None and not 0 <= correlation < 1:
        raise ConfigError(f"synthetic_frame: correlation must be in [0, 1), got {correlation!r}")
    rng = np.random.default_rng(seed)
    cells = max(1, min(height, width) // 4)
    albedo = 0.1 + 0.8 * _smooth_field(rng, height, width, cells, 3)
    shading = np.exp(np.log(low) + (np.log(high) - np.log(low))
                     * _smooth_field(rng, height, width, cells, 1))
    texture = rng.uniform(0.7, 1.3, (height, width, 3))
    clean = np.clip(albedo * shading * texture, low * 0.1, None)
    miss = rng.random((height, width, 1)) < miss_fraction
    clean = np.where(miss, low + (high - low) * _smooth_field(rng, height, width, 1, 3), clean)
    brightness = np.log(clean / clean.min()) / max(np.log(clean.max() / clean.min()), 1e-9)
    level = 0.5 * rng.uniform(0.0, 1.0, clean.shape) + 0.5 * (1.0 - brightness)
    relative = np.exp(np.log(r_low) + (np.log(r_high) - np.log(r_low)) * level)
    variance = np.square(relative * clean)
    normal = rng.standard_normal((height, width, 3)) * 0.3 + np.array([0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    depth = 1.0 + 9.0 * _smooth_field(rng, height, width, cells, 1)
    covariance = None
    if correlation is not None:
        covariance = correlation * np.sqrt(variance * np.roll(variance, -1, axis=-1))
    f32 = np.float32
    return Frame(
        color=clean.astype(f32), variance=variance.astype(f32),
        albedo=np.where(miss, 0.0, albedo).astype(f32),
        normal=np.where(miss, 0.0, normal).astype(f32),
        depth=np.where(miss, 0.0, depth).astype(f32),
        spp=f32(spp),
        covariance=None if covariance is None else covariance.astype(f32),
    )


def monte_carlo_noise(frame: Frame, seed: int | np.random.Generator = 0,
                      kind: NoiseKind = "gaussian", spp: int | None = None) -> Frame:
    """A noisy frame around the clean frame ``frame`` (colour mu, variance of the mean var).

    ``kind``:
      ``"gaussian"``: x = mu + e, e ~ N(0, var) per pixel and channel, or N(0, Sigma) per
        pixel with the frame's ``covariance`` (Sigma's Cholesky factor as SURE's probes use,
        :func:`jaxden.sure.stein.colour_factor`); the variance stays the exact one. What
        Stein's SURE assumes.
      ``"gamma"``: a render's pixel mean: ``spp`` non-negative samples per pixel and channel
        (independent), each mu times a Gamma variable of mean 1 and variance ``spp var /
        mu^2``, so the mean x is >= 0 with E[x] = mu and Var[x] = var, skewed (heavy right
        tail where the noise is large relative to mu); the variance becomes the unbiased
        sample estimate (sample variance / spp) and ``spp`` the count. Pixels with mu <= 0
        or var 0 get x = mu. ``spp`` None: the frame's (>= 2 needed).

    ``seed``: an int or a ``np.random.Generator``. Other fields are kept. Returns a Frame of
    float32 NumPy arrays with the leading dims of ``frame``.
    """
    if kind not in NOISE_KINDS:
        raise ConfigError(f"monte_carlo_noise: kind must be one of {', '.join(NOISE_KINDS)}, "
                          f"got {kind!r}")
    if frame.variance is None:
        raise FrameError("monte_carlo_noise: the clean frame needs its variance of the pixel "
                         "mean (Frame.variance)")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    mu = np.asarray(frame.color, np.float64)
    var = np.maximum(np.asarray(frame.variance, np.float64), 0.0)
    if kind == "gaussian":
        normals = rng.standard_normal(mu.shape)
        if frame.covariance is None:
            noise = np.sqrt(var) * normals
        else:
            from jaxden.sure.stein import colour_factor, colour_probes

            factor = colour_factor(var, np.asarray(frame.covariance, np.float64), xp=np)
            noise = colour_probes(normals, factor, xp=np)
        return frame.replace(color=(mu + noise).astype(np.float32))
    count = spp if spp is not None else frame.spp
    if count is None or np.ndim(count) != 0 or int(count) != count or int(count) < 2:
        raise ConfigError(f"monte_carlo_noise: gamma noise needs an integer spp >= 2 (the "
                          f"argument or a scalar Frame.spp), got {count!r}")
    count = int(count)
    noisy = (mu > 0) & (var > 0)
    # One sample: mu * G, G ~ Gamma(k, 1 / k), mean 1, variance 1 / k = spp var / mu^2.
    shape_k = np.where(noisy, np.square(mu) / np.where(noisy, count * var, 1.0), 1.0)
    gammas = rng.gamma(shape_k[..., None], 1.0 / shape_k[..., None], mu.shape + (count,))
    samples = np.where(noisy[..., None], mu[..., None] * gammas, mu[..., None])
    return frame.replace(
        color=samples.mean(-1).astype(np.float32),
        variance=(samples.var(-1, ddof=1) / count).astype(np.float32),
        covariance=None, spp=np.float32(count), variance_dof=None)
