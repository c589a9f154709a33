"""Write the textures of the stress scenes (experiments/scenes/stress/*.xml).

    python experiments/scenes/stress/make_textures.py   # writes experiments/scenes/stress/textures

Deterministic (one fixed seed, no randomness elsewhere): rerunning rewrites the same pixels.
The stress scenes also use the out-of-distribution set's textures (``../ood/textures``:
tiles-height.png, hex-normal.png, marble.png, tint.png; written by
``experiments/scenes/ood/make_textures.py``) and Mitsuba's procedural ``checkerboard``.

- ``dusk.exr``: a small latitude-longitude dusk sky with no sun in it (the sun of
  ``sun-glitter-metal.xml`` is a far, tiny sphere emitter, so its size in pixels and its
  radiance are exact): deep blue zenith, warm horizon, dark ground; 128 x 64, half floats;
- ``glitter-normal.png``: tangent-space normals of square metal flakes (32 a side, 4 texels
  each), each flake tilted at random by up to about 14 degrees, encoded as (N + 1) / 2: on a
  smooth conductor under a tiny sun each flake that happens to face the half-vector flashes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def dusk(width: int = 128, height: int = 64) -> np.ndarray:
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +y (row 0: zenith)
    elevation = 0.5 * np.pi - np.repeat(theta[:, None], width, axis=1)
    zenith = np.array([0.04, 0.08, 0.25])
    horizon = np.array([0.9, 0.55, 0.3])
    ground = np.array([0.05, 0.045, 0.04])
    up = np.clip(elevation / (0.5 * np.pi), 0.0, 1.0)[..., None] ** 0.5
    sky = horizon * (1 - up) + zenith * up
    image = np.where((elevation > 0)[..., None], sky, ground)
    return image.astype(np.float32)


def glitter_normal(n: int = 128, cells: int = 32, seed: int = 34,
                   max_tilt: float = 0.25) -> np.ndarray:
    rng = np.random.default_rng(seed)
    tilt = rng.uniform(-max_tilt, max_tilt, size=(cells, cells, 2))
    per_texel = np.repeat(np.repeat(tilt, n // cells, axis=0), n // cells, axis=1)
    normal = np.concatenate([per_texel, np.ones((n, n, 1))], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return (normal + 1.0) / 2.0


def textures() -> dict[str, np.ndarray]:
    """File name -> what it holds (uint8 for PNG, float32 for EXR)."""
    glitter = np.round(np.clip(glitter_normal(), 0.0, 1.0) * 255.0).astype(np.uint8)
    return {"dusk.exr": dusk(), "glitter-normal.png": glitter}


def main(out: Path = HERE / "textures") -> int:
    from jaxden.render.textures import write_textures

    for path in write_textures(textures(), out):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
