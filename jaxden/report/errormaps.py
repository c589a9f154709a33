"""Per-pixel error maps and per-image metrics of the report.

- :func:`relative_squared_error`: ``mean_c (x - r)^2 / (r^2 + eps)`` per pixel, eps = 0.01;
  its image mean is :func:`jaxden.metrics.relmse`.
- :func:`flip_map`: NVIDIA FLIP's per-pixel error in HDR mode (``flip_evaluator``, through
  :func:`jaxden.metrics.flip`); its image mean is the FLIP metric.
- :func:`image_metrics`: relMSE, SMAPE, RMSE (linear HDR), FLIP (HDR), PSNR and SSIM (on the
  tone map of :func:`jaxden.metrics.tonemap`), all from :mod:`jaxden.metrics`.

Images are (H, W, 3) linear radiance; maps are (H, W).
"""

from __future__ import annotations

import numpy as np

from jaxden.errors import FrameError

#: Metrics of the report's tables, in column order, with their display names.
METRIC_NAMES = {"relmse": "relMSE", "smape": "SMAPE", "rmse": "RMSE", "flip": "FLIP",
                "psnr": "PSNR (dB)", "ssim": "SSIM", "rmse_nc": "RMSE (noise-corr.)",
                "mse_nc": "MSE (noise-corr.)", "mse": "MSE", "mae": "MAE"}
#: Higher is better for these; lower for the others.
HIGHER_IS_BETTER = ("psnr", "ssim")


def _pair(image, reference) -> tuple[np.ndarray, np.ndarray]:
    image = np.asarray(image, np.float64)
    reference = np.asarray(reference, np.float64)
    if image.ndim != 3 or image.shape != reference.shape:
        raise FrameError(f"error map: image and reference must be (H, W, C) of the same "
                         f"shape, got {image.shape} and {reference.shape}")
    return image, reference


def relative_squared_error(image, reference, eps: float | None = None) -> np.ndarray:
    """(H, W, C) x2 -> (H, W) float64: ``mean over C of (x - r)^2 / (r^2 + eps)``."""
    from jaxden.metrics import EPS

    image, reference = _pair(image, reference)
    eps = EPS if eps is None else eps
    return np.mean(np.square(image - reference) / (np.square(reference) + eps), axis=-1)


def flip_map(image, reference) -> tuple[float, np.ndarray]:
    """HDR-FLIP of ``image`` against ``reference``: (mean, per-pixel map (H, W) float32)."""
    from jaxden.metrics import flip

    mean, error_map = flip(np.asarray(image, np.float32), np.asarray(reference, np.float32),
                           "HDR", return_map=True)
    return float(mean), np.asarray(error_map, np.float32)


def image_metrics(image, reference, flip_mean: float | None = None) -> dict[str, float]:
    """Every metric of the report for one image (``flip_mean``: FLIP if already computed).
    SSIM is left out for images under 11 x 11 pixels (its window)."""
    from jaxden import metrics

    image = np.asarray(image, np.float32)
    reference = np.asarray(reference, np.float32)
    values = {
        "relmse": float(metrics.relmse(image, reference)),
        "smape": float(metrics.smape(image, reference)),
        "rmse": float(metrics.rmse(image, reference)),
        "flip": float(metrics.flip(image, reference, "HDR")) if flip_mean is None
        else float(flip_mean),
        "psnr": float(metrics.psnr(image, reference)),
    }
    if min(image.shape[:2]) >= metrics.SSIM_WINDOW:
        values["ssim"] = float(metrics.ssim(image, reference))
    return values


def best_methods(rows: list[dict], metric: str) -> dict[int, str]:
    """Per spp, the method with the best ``metric`` among ``rows`` (ties: the first)."""
    best: dict[int, tuple[float, str]] = {}
    sign = -1.0 if metric in HIGHER_IS_BETTER else 1.0
    for row in rows:
        value = row.get(metric)
        if value is None or not np.isfinite(value):
            continue
        if row["spp"] not in best or sign * value < sign * best[row["spp"]][0]:
            best[row["spp"]] = (value, row["method"])
    return {spp: method for spp, (_, method) in best.items()}


__all__ = ["HIGHER_IS_BETTER", "METRIC_NAMES", "best_methods", "flip_map", "image_metrics",
           "relative_squared_error"]
