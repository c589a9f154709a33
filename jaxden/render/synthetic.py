"""``synthetic_render``: a Mitsuba-free stand-in for :func:`jaxden.render.core.render_frame`, for
tests, docs and pipeline dry runs (datasets built with it through ``render_fn=``).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def synthetic_render(
    scene: str,
    spp: int,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    *,
    crop: tuple[int, int, int, int] | None = None,
) -> Any:
    """A Mitsuba-free stand-in for ``render_frame``, for tests, docs and pipeline dry runs.

    The "scene" is a smooth analytic image of film coordinates (changing with the scene name);
    each pixel mean is its value plus Gaussian noise of variance ``sigma^2 / spp`` with
    ``sigma = 0.5 * value`` (independent per pixel and channel, seeded by ``seed``), and the
    variance channel is the unbiased sample-variance estimate of the mean, drawn from its
    exact distribution ``(sigma^2 / spp) * chi2(spp - 1) / (spp - 1)`` (None for spp = 1).
    ``position`` holds the film pixel centre (x + 0.5, y + 0.5, 0), so crops can be located;
    ``normal`` is (0, 0, 1), ``depth`` 1, ``albedo`` a smooth pattern. Float32, (h, w, C).
    """
    from jaxden.frame import Frame

    width, height = size if size is not None else (64, 64)
    top, left, crop_height, crop_width = crop if crop is not None else (0, 0, height, width)
    ys, xs = np.mgrid[top : top + crop_height, left : left + crop_width].astype(np.float64)
    ys, xs = ys + 0.5, xs + 0.5
    phase = (int.from_bytes(scene.encode()[:8].ljust(8, b"\0"), "little") % 997) / 997.0
    u, v = xs / width, ys / height
    clean = np.stack(
        [
            1.0 + 0.8 * np.sin(6.0 * u + 6.28 * phase) * np.cos(4.0 * v),
            1.0 + 0.8 * np.cos(5.0 * u * v + 3.0 * phase),
            0.5 + 0.4 * np.sin(3.0 * (u + v) + 1.0),
        ],
        axis=-1,
    )
    rng = np.random.default_rng(seed)
    sigma2 = np.square(0.5 * clean)
    color = clean + rng.standard_normal(clean.shape) * np.sqrt(sigma2 / spp)
    variance = None
    if spp > 1:
        variance = sigma2 / spp * rng.chisquare(spp - 1, clean.shape) / (spp - 1)
    shape = clean.shape[:2]
    albedo = np.stack([0.2 + 0.6 * u, 0.2 + 0.6 * v, np.full(shape, 0.5)], axis=-1)
    return Frame(
        color=color.astype(np.float32),
        variance=None if variance is None else variance.astype(np.float32),
        albedo=albedo.astype(np.float32),
        normal=np.broadcast_to(np.float32([0, 0, 1]), shape + (3,)).copy(),
        depth=np.ones(shape + (1,), np.float32),
        position=np.stack([xs, ys, np.zeros(shape)], axis=-1).astype(np.float32),
        spp=np.float32(spp),
    )
