"""Write the Falcor frame-capture fixtures of tests/test_exr_falcor.py: two captures (base
filenames ``Mogwai`` and ``Mogwai-run1``, frame 256) of a 16 x 12 synthetic frame, one file per
render-graph output, in the layout Falcor's Mogwai writes.

What Falcor writes (its source, NVIDIAGameWorks/Falcor): FrameCapture names a file
``<outputDir>/<baseFilename>.<pass>.<output>.<frame>.<ext>`` (CaptureTrigger::
getOutputNamePrefix, FrameCapture::captureOutput); the extension follows the texture format
(Bitmap::getFileExtFromResourceFormat: float formats -> exr, 8-bit unorm -> png). EXR goes
through FreeImage with no flags: channels R, G, B (no alpha unless captured with the RGBA mask)
as half floats, PIZ-compressed, no other attributes. The outputs imitated:

    AccumulatePass.output   RGBA32Float  colour accumulated over frames       -> exr
    PathTracer.color        RGBA32Float  one frame's colour                   -> exr
    PathTracer.albedo       RGBA8Unorm   diffuse albedo (linear, 8 bits)      -> png (RGB)
    PathTracer.guideNormal  RGBA16Float  world-space guide normal             -> exr
    GBufferRT.linearZ       RG32Float    view depth, its slope; 1e8 on misses -> exr: R = z,
                                         G = slope, B = 0; 1e8 overflows half to +inf

The top three rows are sky (camera rays that miss): the path tracer writes the compressed
background radiance as albedo and minus the ray direction as guide normal there.

    .venv/bin/python tests/data/falcor/make_fixtures.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
WIDTH, HEIGHT, FRAME = 16, 12, 256
SKY_ROWS = 3
CAPTURES = {"Mogwai": 1, "Mogwai-run1": 2}  # base filename -> seed of its noise


def scene() -> dict[str, np.ndarray]:
    """The noise-free frame: radiance, albedo, normal, linear z, ray direction (H, W, 3|1)."""
    y, x = np.mgrid[0:HEIGHT, 0:WIDTH].astype(np.float64)
    u, v = (x + 0.5) / WIDTH * 2 - 1, (y + 0.5) / HEIGHT * 2 - 1
    direction = np.stack([u * 0.6, -v * 0.45, -np.ones_like(u)], axis=-1)
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    sky = (y < SKY_ROWS)[..., None]
    background = np.array([0.6, 0.8, 1.4]) * (1.2 - 0.2 * v[..., None])
    albedo = np.stack([0.2 + 0.6 * (x / WIDTH), 0.5 + 0.3 * np.sin(y), 0.3 + 0.0 * x], -1)
    normal = np.stack([0.3 * u, np.ones_like(u), 0.2 * v], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    shading = np.clip(normal @ np.array([0.3, 0.9, 0.3]), 0, None)[..., None]
    radiance = np.where(sky, background, albedo * (0.2 + 1.5 * shading))
    compressed = (background / (background + 1)) ** 0.454545  # PathTracer's background albedo
    return {"radiance": radiance,
            "albedo": np.where(sky, compressed, albedo),
            "normal": np.where(sky, -direction, normal),
            "linear_z": np.where(sky[..., 0], 1e8, 2.0 + 0.25 * (HEIGHT - y))[..., None],
            "sky": sky[..., 0]}


def capture(seed: int) -> dict[str, dict[str, np.ndarray]]:
    """Output name -> {channel: stored array} of one capture (half floats, uint8 for PNG)."""
    truth, rng = scene(), np.random.default_rng(seed)
    accumulated = truth["radiance"] * rng.gamma(64.0, 1 / 64.0, truth["radiance"].shape)
    one_frame = truth["radiance"] * rng.gamma(2.0, 1 / 2.0, truth["radiance"].shape)
    z = truth["linear_z"][..., 0]
    slope = np.where(truth["sky"], 0.0, 0.25)

    def rgb(image) -> dict[str, np.ndarray]:
        return {c: np.asarray(image[..., i], np.float16) for i, c in enumerate("RGB")}

    return {
        "AccumulatePass.output": rgb(accumulated),
        "PathTracer.color": rgb(one_frame),
        "PathTracer.albedo": {"png": np.round(np.clip(truth["albedo"], 0, 1) * 255)
                              .astype(np.uint8)},
        "PathTracer.guideNormal": rgb(truth["normal"]),
        "GBufferRT.linearZ": {"R": z.astype(np.float16),  # 1e8 -> +inf, as FreeImage stores it
                              "G": slope.astype(np.float16),
                              "B": np.zeros_like(z, np.float16)},
    }


def file_name(base: str, output: str) -> str:
    ext = "png" if output == "PathTracer.albedo" else "exr"
    return f"{base}.{output}.{FRAME}.{ext}"


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.PIZ_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {name: array.copy() for name, array in channels.items()}).write(
        str(path))


def write_png(path: Path, rgb8: np.ndarray) -> None:
    from PIL import Image

    Image.fromarray(rgb8, "RGB").save(path)  # libpng-style adaptive row filters


def main() -> None:
    with np.errstate(over="ignore"):  # linear z 1e8 overflows half, as in Falcor's files
        for base, seed in CAPTURES.items():
            for output, channels in capture(seed).items():
                path = HERE / file_name(base, output)
                if "png" in channels:
                    write_png(path, channels["png"])
                else:
                    write_exr(path, channels)
                print(f"wrote {path.relative_to(HERE.parent.parent.parent)}")


if __name__ == "__main__":
    main()
