"""Procedural textures in NumPy for the random scene generator.

Every function returns a float32 array, is a pure function of its arguments and draws its
randomness only from the ``np.random.Generator`` it is given, so a scene built from
``np.random.default_rng(seed)`` is reproducible bit for bit.

All patterns are *periodic* over the image (lattice frequencies, stripe wave vectors and cell
points wrap around), so the generator can tile them on a surface with Mitsuba's ``to_uv``
scale and ``repeat`` wrap mode without seams; tiling is how the scenes get fine, high-frequency
detail from small bitmaps.

Conventions: ``shape`` is ``(height, width)`` in texels; scalar patterns are ``(H, W)`` in
[0, 1]; colour textures are ``(H, W, 3)`` linear reflectance in [0, 1); the environment map is
``(H, W, 3)`` linear radiance (latitude-longitude, row 0 = zenith, as Mitsuba's ``envmap``).
"""

from __future__ import annotations

import numpy as np

from jaxden.errors import SceneError

#: Kinds of bump-map height fields drawn by :func:`height_map`.
HEIGHT_KINDS: tuple[str, ...] = (
    "fbm", "ridged", "perlin", "cell_edges", "cellular", "stripes", "tiles"
)
#: Names accepted by :func:`pattern` (and drawn by :func:`random_pattern`).
PATTERN_KINDS: tuple[str, ...] = (
    "value",
    "perlin",
    "fbm",
    "ridged",
    "checker",
    "stripes",
    "cellular",
    "cell_edges",
)


# ---------------------------------------------------------------------------- helpers
def _shape(shape, where: str) -> tuple[int, int]:
    try:
        height, width = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise SceneError(f"{where}: shape must be (height, width), got {shape!r}") from None
    if height < 1 or width < 1:
        raise SceneError(f"{where}: shape must be positive, got {shape!r}")
    return height, width


def _positive_int(value, name: str, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise SceneError(f"{where}: {name} must be an integer >= 1, got {value!r}")
    return int(value)


def _grid(height: int, width: int, frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre coordinates in lattice units: x in [0, frequency) along the width."""
    y = (np.arange(height, dtype=np.float64) + 0.5) * (frequency / height)
    x = (np.arange(width, dtype=np.float64) + 0.5) * (frequency / width)
    return np.meshgrid(y, x, indexing="ij")


def _fade(t: np.ndarray) -> np.ndarray:
    # Quintic smoothstep (C2), so bump maps built from noise have continuous curvature.
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


def _normalise(values: np.ndarray) -> np.ndarray:
    lo, hi = float(values.min()), float(values.max())
    if hi - lo < 1e-12:
        return np.full(values.shape, 0.5, dtype=np.float32)
    return ((values - lo) / (hi - lo)).astype(np.float32)


# ---------------------------------------------------------------------------- noise
def value_noise(shape, frequency: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic value noise: random lattice values, quintic interpolation.

    ``frequency`` lattice cells span the image along each axis. Returns (H, W) float32 in [0, 1].
    """
    height, width = _shape(shape, "value_noise")
    frequency = _positive_int(frequency, "frequency", "value_noise")
    lattice = rng.random((frequency, frequency))
    y, x = _grid(height, width, frequency)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    ty, tx = _fade(y - y0), _fade(x - x0)
    y0, x0 = y0 % frequency, x0 % frequency
    y1, x1 = (y0 + 1) % frequency, (x0 + 1) % frequency
    top = lattice[y0, x0] * (1 - tx) + lattice[y0, x1] * tx
    bottom = lattice[y1, x0] * (1 - tx) + lattice[y1, x1] * tx
    return (top * (1 - ty) + bottom * ty).astype(np.float32)


def perlin_noise(shape, frequency: int, rng: np.random.Generator) -> np.ndarray:
    """Periodic gradient (Perlin-style) noise with random unit gradients on the lattice.

    Returns (H, W) float32 in [0, 1] (0.5 + n / sqrt(2); 2-D gradient noise lies in
    [-sqrt(1/2), sqrt(1/2)], so no clipping happens).
    """
    height, width = _shape(shape, "perlin_noise")
    frequency = _positive_int(frequency, "frequency", "perlin_noise")
    angles = rng.uniform(0.0, 2.0 * np.pi, size=(frequency, frequency))
    gy, gx = np.sin(angles), np.cos(angles)
    y, x = _grid(height, width, frequency)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    y0, x0 = y0 % frequency, x0 % frequency
    y1, x1 = (y0 + 1) % frequency, (x0 + 1) % frequency

    def corner(iy, ix, dy, dx):
        return gy[iy, ix] * dy + gx[iy, ix] * dx

    ty, tx = _fade(fy), _fade(fx)
    top = corner(y0, x0, fy, fx) * (1 - tx) + corner(y0, x1, fy, fx - 1) * tx
    bottom = corner(y1, x0, fy - 1, fx) * (1 - tx) + corner(y1, x1, fy - 1, fx - 1) * tx
    noise = top * (1 - ty) + bottom * ty
    return (0.5 + noise / np.sqrt(2.0)).astype(np.float32)


def fbm(
    shape,
    rng: np.random.Generator,
    *,
    base_frequency: int = 4,
    octaves: int = 5,
    gain: float = 0.5,
    basis: str = "perlin",
    ridged: bool = False,
) -> np.ndarray:
    """Fractional Brownian motion: sum of ``octaves`` noise layers, frequency doubling each.

    Lacunarity is fixed at 2 so every octave stays periodic over the image. ``ridged`` folds each
    octave (1 - |2n - 1|), giving sharp creases. Returns (H, W) float32 normalised to [0, 1].
    """
    height, width = _shape(shape, "fbm")
    base_frequency = _positive_int(base_frequency, "base_frequency", "fbm")
    octaves = _positive_int(octaves, "octaves", "fbm")
    if basis not in ("perlin", "value"):
        raise SceneError(f"fbm: basis must be 'perlin' or 'value', got {basis!r}")
    noise_fn = perlin_noise if basis == "perlin" else value_noise
    total = np.zeros((height, width), dtype=np.float64)
    amplitude = 1.0
    for octave in range(octaves):
        layer = noise_fn((height, width), base_frequency * 2**octave, rng).astype(np.float64)
        if ridged:
            layer = 1.0 - np.abs(2.0 * layer - 1.0)
        total += amplitude * layer
        amplitude *= gain
    return _normalise(total)


# ---------------------------------------------------------------------------- regular patterns
def checker(shape, cells: int) -> np.ndarray:
    """Checkerboard with ``cells`` squares along each axis (periodic if ``cells`` is even).

    Returns (H, W) float32 of 0s and 1s.
    """
    height, width = _shape(shape, "checker")
    cells = _positive_int(cells, "cells", "checker")
    y, x = _grid(height, width, cells)
    return ((np.floor(y) + np.floor(x)) % 2).astype(np.float32)


def stripes(
    shape, wave: tuple[int, int], *, duty: float = 0.5, softness: float = 0.0
) -> np.ndarray:
    """Stripes along the integer wave vector ``wave = (ky, kx)`` (periods across the image).

    Integer wave numbers keep the pattern periodic. ``duty`` is the fraction of each period that
    is 1; ``softness`` (in [0, 0.5], fraction of a period) blurs the edges with a linear ramp.
    Returns (H, W) float32 in [0, 1].
    """
    height, width = _shape(shape, "stripes")
    ky, kx = (int(k) for k in wave)
    if ky == 0 and kx == 0:
        raise SceneError("stripes: wave vector must not be (0, 0)")
    if not 0.0 < duty < 1.0 or not 0.0 <= softness <= 0.5:
        raise SceneError(
            f"stripes: need 0 < duty < 1 and 0 <= softness <= 0.5, got {duty}, {softness}"
        )
    y, x = _grid(height, width, 1)
    phase = (ky * y + kx * x) % 1.0
    # Signed distance (in periods) to the nearest stripe edge; positive inside the stripe.
    inside = np.minimum(phase, duty - phase)
    outside = -np.minimum(phase - duty, 1.0 - phase)
    distance = np.where(phase < duty, inside, outside)
    if softness == 0.0:
        return (distance > 0).astype(np.float32)
    return np.clip(0.5 + distance / softness, 0.0, 1.0).astype(np.float32)


def cellular(
    shape, num_points: int, rng: np.random.Generator, *, edges: bool = False
) -> np.ndarray:
    """Worley (cellular) noise on the torus: distance to the nearest of ``num_points`` points.

    ``edges=True`` returns F2 - F1 (thin bright cell borders become dark lines). Distances wrap
    around so the pattern tiles. Returns (H, W) float32 normalised to [0, 1].
    """
    height, width = _shape(shape, "cellular")
    num_points = _positive_int(num_points, "num_points", "cellular")
    points = rng.random((num_points, 2))
    y, x = _grid(height, width, 1)
    dy = np.abs(y[..., None] - points[:, 0])
    dx = np.abs(x[..., None] - points[:, 1])
    dy, dx = np.minimum(dy, 1.0 - dy), np.minimum(dx, 1.0 - dx)
    distance = np.sqrt(dy * dy + dx * dx)
    if edges and num_points >= 2:
        nearest = np.partition(distance, 1, axis=-1)
        return _normalise(nearest[..., 1] - nearest[..., 0])
    return _normalise(distance.min(axis=-1))


# ---------------------------------------------------------------------------- random choices
def pattern(kind: str, shape, rng: np.random.Generator) -> np.ndarray:
    """One scalar pattern of the named kind with randomly drawn parameters, (H, W) in [0, 1]."""
    if kind == "value":
        return value_noise(shape, int(rng.integers(8, 33)), rng)
    if kind == "perlin":
        return perlin_noise(shape, int(rng.integers(8, 33)), rng)
    if kind == "fbm":
        return fbm(shape, rng, base_frequency=int(rng.integers(2, 9)), octaves=5,
                   gain=float(rng.uniform(0.45, 0.7)), basis=str(rng.choice(["perlin", "value"])))
    if kind == "ridged":
        return fbm(shape, rng, base_frequency=int(rng.integers(2, 7)), octaves=5,
                   gain=float(rng.uniform(0.45, 0.65)), ridged=True)
    if kind == "checker":
        return checker(shape, 2 * int(rng.integers(2, 9)))
    if kind == "stripes":
        wave = (int(rng.integers(-6, 7)), int(rng.integers(2, 13)))
        return stripes(shape, wave, duty=float(rng.uniform(0.2, 0.8)),
                       softness=float(rng.choice([0.0, rng.uniform(0.02, 0.2)])))
    if kind == "cellular":
        return cellular(shape, int(rng.integers(8, 40)), rng)
    if kind == "cell_edges":
        return cellular(shape, int(rng.integers(8, 40)), rng, edges=True)
    raise SceneError(
        f"unknown texture pattern {kind!r}; expected one of {', '.join(PATTERN_KINDS)}"
    )


def random_pattern(shape, rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """A random scalar pattern, sometimes modulated by fBm detail. Returns ((H, W), kind)."""
    kind = str(rng.choice(PATTERN_KINDS))
    values = pattern(kind, shape, rng)
    if kind in ("checker", "stripes", "cellular", "cell_edges") and rng.random() < 0.5:
        # Weathering: break up the regular pattern with fine noise.
        detail = fbm(shape, rng, base_frequency=int(rng.integers(4, 17)), octaves=3)
        mix = float(rng.uniform(0.1, 0.4))
        values = _normalise((1 - mix) * values + mix * detail)
    return values, kind


def color_texture(shape, rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """A random colour texture: a pattern mapped between two or three random reflectances.

    Returns ((H, W, 3) float32 linear reflectance in [0.02, 0.9], pattern kind).
    """
    values, kind = random_pattern(shape, rng)
    count = int(rng.integers(2, 4))
    # Brightness spread of at least ~0.15 so the pattern shows in luminance, not only in hue.
    brightness = rng.uniform(0.03, 0.9, size=count)
    brightness[0], brightness[-1] = rng.uniform(0.03, 0.3), rng.uniform(0.45, 0.85)
    chroma = rng.uniform(0.2, 1.0, size=(count, 3))
    colours = brightness[rng.permutation(count), None] * chroma / chroma.mean(axis=1, keepdims=True)
    # Piecewise-linear colour ramp through the chosen colours.
    stops = np.linspace(0.0, 1.0, count)
    texture = np.stack([np.interp(values, stops, colours[:, c]) for c in range(3)], axis=-1)
    return np.clip(texture, 0.02, 0.9).astype(np.float32), kind


def height_map(shape, rng: np.random.Generator) -> tuple[np.ndarray, str]:
    """A random bump-map height field, (H, W) float32 in [0, 1], and its pattern kind.

    Soft-edged patterns only (hard checker/stripe steps would make the bump gradient a few
    texels of enormous slope): stripes get a soft ramp, checkers become rounded tiles.
    """
    kind = str(rng.choice(HEIGHT_KINDS))
    if kind == "stripes":
        wave = (int(rng.integers(-4, 5)), int(rng.integers(3, 17)))
        values = stripes(shape, wave, duty=0.5, softness=0.5)
    elif kind == "tiles":
        cells = 2 * int(rng.integers(2, 9))
        height, width = _shape(shape, "height_map")
        y, x = _grid(height, width, cells)
        # Rounded tiles: 1 in the tile interior, falling to 0 in the grout.
        fy, fx = np.abs((y % 1.0) - 0.5), np.abs((x % 1.0) - 0.5)
        values = np.clip((0.5 - np.maximum(fy, fx)) / 0.08, 0.0, 1.0).astype(np.float32)
    else:
        values = pattern(kind, shape, rng)
    return values.astype(np.float32), kind


def environment_map(shape, rng: np.random.Generator) -> np.ndarray:
    """A random HDR sky in latitude-longitude layout, (H, W, 3) float32 linear radiance.

    A zenith-to-horizon gradient with fBm clouds above the horizon, a darker ground below it,
    and (usually) a small bright sun. Row 0 is the zenith (+y in Mitsuba's ``envmap``).
    The mean over texels is roughly 1 before the caller rescales it.
    """
    height, width = _shape(shape, "environment_map")
    theta = (np.arange(height) + 0.5) / height * np.pi  # polar angle from +y
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    elevation = 0.5 * np.pi - theta
    zenith = rng.uniform(0.1, 1.0, size=3)
    horizon = rng.uniform(0.4, 1.0, size=3)
    ground = rng.uniform(0.02, 0.3, size=3)
    up = np.clip(elevation / (0.5 * np.pi), 0.0, 1.0)[..., None]
    sky = horizon * (1 - up) + zenith * up
    clouds = fbm((height, width), rng, base_frequency=int(rng.integers(2, 6)), octaves=5)
    cover = float(rng.uniform(0.0, 0.8))
    sky = sky * (1 - cover * clouds[..., None]) + cover * clouds[..., None] * rng.uniform(0.7, 1.2)
    image = np.where((elevation > 0)[..., None], sky, ground * (1.0 + 0.3 * clouds[..., None]))
    if rng.random() < 0.8:
        sun_elevation = rng.uniform(0.1, 1.3)
        sun_phi = rng.uniform(0.0, 2.0 * np.pi)
        # Angular distance to the sun direction on the sphere.
        cos_angle = (np.sin(elevation) * np.sin(sun_elevation)
                     + np.cos(elevation) * np.cos(sun_elevation) * np.cos(phi - sun_phi))
        angle = np.arccos(np.clip(cos_angle, -1.0, 1.0))
        size = rng.uniform(0.03, 0.12)
        strength = rng.uniform(20.0, 200.0)
        tint = rng.uniform(0.8, 1.0, size=3)
        image = image + strength * tint * np.exp(-0.5 * (angle / size) ** 2)[..., None]
    image = image / max(float(image.mean()), 1e-6)
    return image.astype(np.float32)


def write_textures(images: dict[str, np.ndarray], out) -> list:
    """Write scene textures into the folder ``out``: ``NAME.png`` as 8-bit PNG (uint8 arrays),
    anything else (``NAME.exr``) as a half-float EXR; what a scene set's make_textures.py
    commits beside its XML files. Returns the paths written."""
    from pathlib import Path

    from jaxden.io.exr import write_image
    from jaxden.io.png import write_png

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, image in images.items():
        if name.endswith(".png"):
            write_png(out / name, image)
        else:
            write_image(out / name, image, half=True)
        written.append(out / name)
    return written
