"""Write the pbrt-v4 fixture of tests/test_exr_falcor.py: ``gbuffer-16spp.exr``, a 16 x 12
frame in the layout of pbrt-v4's ``film "gbuffer"`` at its defaults (16 spp, synthetic values).

What pbrt-v4 writes (its source, mmp/pbrt-v4): GBufferFilm::GetImage makes the channels R, G,
B, Albedo.R/G/B, P.X/Y/Z, dzdx, dzdy, N.X/Y/Z, Ns.X/Y/Z, u, v, Variance.R/G/B and
RelativeVariance.R/G/B, as half floats unless ``"bool savefp16" false``; P, N and Ns are in
camera space unless ``"string coordinatesystem" "world"`` (camera space looks down +z, so P.Z
is the depth); N and Ns are normalised, 0 where no sample hit a surface. Variance is a Welford
estimate of the per-sample variance of the sensor's values (CIE XYZ with the default sensor)
over the samples that hit a surface: 0 on pixels where none did. Image::WriteEXR adds the
attributes renderTimeSeconds, worldToCamera, worldToNDC and samplesPerPixel (an int), with
OpenEXR's default ZIP compression.

    .venv/bin/python tests/data/pbrt/make_fixtures.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
WIDTH, HEIGHT, SPP = 16, 12, 16
SKY_ROWS = 3
FILE = "gbuffer-16spp.exr"


def channels() -> dict[str, np.ndarray]:
    """Channel name -> (H, W) half array, as GBufferFilm writes them."""
    rng = np.random.default_rng(7)
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    u, v = (x + 0.5) / WIDTH * 2 - 1, (y + 0.5) / HEIGHT * 2 - 1
    hit = y >= SKY_ROWS
    depth = np.where(hit, 3.0 + 0.2 * (HEIGHT - y), 0.0)
    position = np.stack([u * 0.6 * depth, -v * 0.45 * depth, depth], axis=-1)
    geometric = np.stack([np.zeros_like(u), np.ones_like(u), -0.3 * np.ones_like(u)], -1)
    shading = geometric + np.stack([0.2 * u, 0.0 * u, 0.1 * v], -1)
    normals = []
    for n in (geometric, shading):
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        normals.append(np.where(hit[..., None], n, 0.0))
    albedo = np.where(hit[..., None], np.stack([0.7 + 0 * x, 0.4 + 0.02 * x, 0.2 + 0.03 * y],
                                               -1), 0.0)
    colour = np.where(hit[..., None], albedo * 0.8, np.array([0.5, 0.7, 1.0]))
    colour = colour * rng.gamma(SPP, 1 / SPP, colour.shape)
    variance = np.where(hit[..., None], 0.05 + 0.1 * rng.random(colour.shape), 0.0)
    luminance_like = np.maximum(colour, 1e-3)
    out = {c: colour[..., i] for i, c in enumerate("RGB")}
    out.update({f"Albedo.{c}": albedo[..., i] for i, c in enumerate("RGB")})
    out.update({f"P.{c}": position[..., i] for i, c in enumerate("XYZ")})
    out.update({"dzdx": np.where(hit, 0.01, 0.0), "dzdy": np.where(hit, 0.2, 0.0)})
    out.update({f"N.{c}": normals[0][..., i] for i, c in enumerate("XYZ")})
    out.update({f"Ns.{c}": normals[1][..., i] for i, c in enumerate("XYZ")})
    out.update({"u": np.where(hit, (x + 0.5) / WIDTH, 0.0), "v": np.where(hit, y / HEIGHT, 0.0)})
    out.update({f"Variance.{c}": variance[..., i] for i, c in enumerate("RGB")})
    out.update({f"RelativeVariance.{c}": variance[..., i] / luminance_like[..., i]
                for i, c in enumerate("RGB")})
    return {name: np.asarray(array, np.float16) for name, array in out.items()}


def main() -> None:
    import OpenEXR

    camera = np.eye(4, dtype=np.float32)
    ndc = np.diag([0.5, 0.5, 1.0, 1.0]).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "renderTimeSeconds": 0.25, "worldToCamera": camera, "worldToNDC": ndc,
              "samplesPerPixel": SPP}
    OpenEXR.File(header, channels()).write(str(HERE / FILE))
    print(f"wrote tests/data/pbrt/{FILE}")


if __name__ == "__main__":
    main()
