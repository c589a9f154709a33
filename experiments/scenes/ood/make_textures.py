"""Write the textures of the out-of-distribution scenes (experiments/scenes/ood/*.xml).

    python experiments/scenes/ood/make_textures.py        # writes experiments/scenes/ood/textures/

Deterministic (fixed seeds, no randomness elsewhere): rerunning rewrites the same pixels, which
``tests/test_ood_scenes.py`` checks against the committed files. Made with jaxden's texture
tools (``jaxden.render.textures``, ``jaxden.io``) but with parameters the procedural training
generator never draws: tiles far finer than its bump maps, a hexagonal normal map, a studio
environment of rectangular soft boxes instead of a sky, and a conductor tint pattern.

- ``tiles-height.png``: rounded tiles, 24 cells a side, narrow grout (8-bit grey, raw heights);
- ``hex-normal.png``: tangent-space normals of bevelled hexagons encoded as (N + 1) / 2;
- ``marble.png``: veined marble albedo (fBm-warped stripes), sRGB;
- ``tint.png``: a two-metal tint pattern for a conductor's specular reflectance (fine checker
  of gold and steel tones with noise), sRGB;
- ``studio.exr``: latitude-longitude HDR studio: dark grey walls, three rectangular soft boxes
  (one key light 30x the background), a warm floor bounce;
- ``sky.exr``: one sky of ``jaxden.render.textures.environment_map`` (seed 4242).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SIZE = 256


def tiles_height(n: int = SIZE, cells: int = 24, grout: float = 0.06) -> np.ndarray:
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * cells
    fy, fx = np.abs((y % 1.0) - 0.5), np.abs((x % 1.0) - 0.5)
    return np.clip((0.5 - np.maximum(fy, fx)) / grout, 0.0, 1.0)


def hex_normal(n: int = SIZE, cells: int = 10, bevel: float = 0.25) -> np.ndarray:
    """Bevelled hexagons: the normal tilts towards a cell's edge within ``bevel`` of it."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * cells
    # Axial hexagon grid: nearest of the centres of two offset rectangular lattices.
    h = np.sqrt(3.0)
    best = np.full((n, n), np.inf)
    dx = np.zeros((n, n))
    dy = np.zeros((n, n))
    for oy, ox in ((0.0, 0.0), (h / 2, 0.5)):
        cy = np.round((y - oy) / h) * h + oy
        cx = np.round(x - ox) + ox
        d = np.hypot(y - cy, x - cx)
        closer = d < best
        best = np.where(closer, d, best)
        dy = np.where(closer, y - cy, dy)
        dx = np.where(closer, x - cx, dx)
    radius = 0.5
    edge = np.clip((best - (radius - bevel)) / bevel, 0.0, 1.0)
    scale = 0.8 * edge / np.maximum(best, 1e-6)
    normal = np.stack([dx * scale, dy * scale, np.ones_like(best)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return (normal + 1.0) / 2.0


def marble(n: int = SIZE, seed: int = 11) -> np.ndarray:
    from jaxden.render.textures import fbm

    rng = np.random.default_rng(seed)
    warp = fbm((n, n), rng, base_frequency=4, octaves=5)
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    veins = 0.5 + 0.5 * np.sin(2 * np.pi * (3 * x + 2 * y) + 6.0 * warp)
    veins = veins ** 6  # thin dark veins
    base = np.array([0.85, 0.83, 0.78])
    vein = np.array([0.15, 0.17, 0.2])
    return base * (1 - veins[..., None]) + vein * veins[..., None]


def tint(n: int = SIZE, seed: int = 12) -> np.ndarray:
    from jaxden.render.textures import checker, value_noise

    rng = np.random.default_rng(seed)
    mask = checker((n, n), 32)[..., None]
    noise = value_noise((n, n), 16, rng)[..., None]
    gold = np.array([1.0, 0.78, 0.34])
    steel = np.array([0.56, 0.57, 0.58])
    return np.clip((gold * mask + steel * (1 - mask)) * (0.85 + 0.15 * noise), 0.0, 1.0)


def studio(width: int = 512, height: int = 256) -> np.ndarray:
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +y (row 0: zenith)
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    image = np.full((height, width, 3), 0.05, np.float64)
    image[theta > 0.55 * np.pi] = [0.12, 0.09, 0.07]  # warm floor bounce
    boxes = [  # (theta centre, phi centre, half sizes, radiance)
        (0.30 * np.pi, 0.25 * np.pi, 0.10 * np.pi, 0.12 * np.pi, 30.0),
        (0.40 * np.pi, 1.20 * np.pi, 0.08 * np.pi, 0.20 * np.pi, 8.0),
        (0.05 * np.pi, 0.00 * np.pi, 0.05 * np.pi, 1.00 * np.pi, 4.0),
    ]
    for t0, p0, ht, hp, radiance in boxes:
        dphi = np.angle(np.exp(1j * (phi - p0)))
        inside = (np.abs(theta - t0) < ht) & (np.abs(dphi) < hp)
        image[inside] = radiance
    return image.astype(np.float32)


def sky() -> np.ndarray:
    from jaxden.render.textures import environment_map

    return environment_map((128, 256), np.random.default_rng(4242))


def to_uint8(image: np.ndarray, srgb: bool) -> np.ndarray:
    from jaxden.io.png import srgb_encode

    values = srgb_encode(image) if srgb else np.clip(image, 0.0, 1.0)
    return np.round(np.asarray(values) * 255.0).astype(np.uint8)


def textures() -> dict[str, np.ndarray]:
    """File name -> what it holds (uint8 for PNG, float32 for EXR)."""
    return {
        "tiles-height.png": to_uint8(tiles_height(), srgb=False),
        "hex-normal.png": to_uint8(hex_normal(), srgb=False),
        "marble.png": to_uint8(marble(), srgb=True),
        "tint.png": to_uint8(tint(), srgb=True),
        "studio.exr": studio(),
        "sky.exr": sky(),
    }


def main(out: Path = HERE / "textures") -> int:
    from jaxden.render.textures import write_textures

    for path in write_textures(textures(), out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
