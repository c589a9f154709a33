"""Scene library and scene loading with the film settings denoising data needs.

A *scene spec* is one of:

* a built-in name (:func:`list_scenes`): ``cornell-box``, ``texture-bump``, ``glossy-glass``,
  ``env-sun``, ``small-lights``;
* ``procedural:SEED`` (SEED a decimal integer >= 0): a random scene from
  :func:`jaxden.render.procedural.generate_scene`;
* a path to a Mitsuba 3 XML scene file (str or os.PathLike);
* a Mitsuba scene dict (``{"type": "scene", "sensor": {...}, ...}``).

Whatever the spec says, every sensor gets an ``hdrfilm`` with a **box** reconstruction filter
(other filters spread one sample over several pixels, which correlates neighbours and breaks the
per-pixel variance), RGB float32 pixels, and an **independent** sampler (so samples of a pixel
are i.i.d. and the sample variance estimates the variance); ``size`` = (width, height) overrides
the film size. The spp comes from the render call, never from the scene.

:func:`load_scene` returns an ``mi.Scene`` and remembers how to rebuild its sensor at another
size or with a film crop (for :func:`jaxden.render.render_frame`) for the most recent
``SCENE_MEMORY`` scenes it loaded. The memory holds each scene's first sensor, never the
scene (a held scene would stay in Dr.Jit's instance registry and slow every later render; see
``jaxden.render.load``), so a scene is freed as soon as its caller drops it.

:func:`prepare_scene` is the dict-level step: the patched scene dict, not loaded, for every
spec but XML files (those are patched as XML text and loaded by :func:`load_scene`).

All built-in scenes are small (spheres, rectangles, cubes, cylinders, disks), need no files,
and draw their textures from NumPy with fixed seeds, so they are identical everywhere.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from jaxden.errors import SceneError
from jaxden.limits import check_render_size

DEFAULT_SIZE: tuple[int, int] = (256, 256)
MAX_SIDE = 16384  # pixels; a larger film is a typo, not a render
MAX_PIXELS = 1 << 27
SCENE_MEMORY = 16
SENSOR_TYPES = frozenset({"perspective", "thinlens", "orthographic", "telecentric"})
# Every Mitsuba sensor plugin: found as sensors, then rejected unless in SENSOR_TYPES.
ALL_SENSOR_PLUGINS = SENSOR_TYPES | {"batch", "radiancemeter", "irradiancemeter", "distant"}
PROCEDURAL_SPEC = re.compile(r"^procedural:(\d+)$")


# ---------------------------------------------------------------------------- validation
def check_size(size, where: str = "size") -> tuple[int, int]:
    """(width, height) as ints, or SceneError: both in [1, MAX_SIDE], product <= MAX_PIXELS."""
    try:
        width, height = size
    except (TypeError, ValueError):
        raise SceneError(f"{where}: size must be (width, height), got {size!r}") from None
    for value in (width, height):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise SceneError(f"{where}: size must be two integers (width, height), got {size!r}")
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise SceneError(f"{where}: size must be >= 1 pixel each way, got {width}x{height}")
    if width > MAX_SIDE or height > MAX_SIDE or width * height > MAX_PIXELS:
        raise SceneError(
            f"{where}: size {width}x{height} is too large (at most {MAX_SIDE} per side and "
            f"{MAX_PIXELS} pixels)"
        )
    check_render_size(width, height, where, SceneError)
    return width, height


# ---------------------------------------------------------------------------- small helpers
def _transform():
    import mitsuba as mi

    return mi.ScalarTransform4f()


def _look_at(origin, target, up=(0.0, 1.0, 0.0)):
    return _transform().look_at(origin=list(origin), target=list(target), up=list(up))


def _sensor(origin, target, fov: float, size=DEFAULT_SIZE, up=(0.0, 1.0, 0.0)) -> dict:
    return {
        "type": "perspective",
        "fov": float(fov),
        "fov_axis": "x",
        "to_world": _look_at(origin, target, up),
        "film": {"type": "hdrfilm", "width": size[0], "height": size[1],
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": 16},
    }


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _bitmap_texture(array: np.ndarray, tiles: float = 1.0, *, raw: bool = False,
                    nearest: bool = False) -> dict:
    import mitsuba as mi

    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(array, dtype=np.float32)),
        "raw": raw,
        "filter_type": "nearest" if nearest else "bilinear",
        "wrap_mode": "repeat",
        "to_uv": _transform().scale([tiles, tiles, 1.0]),
    }


def _diffuse(value) -> dict:
    return {"type": "diffuse", "reflectance": _rgb(value) if not isinstance(value, dict) else value}


def _rectangle(to_world, bsdf: dict, emitter: dict | None = None) -> dict:
    shape = {"type": "rectangle", "to_world": to_world, "bsdf": bsdf}
    if emitter is not None:
        shape["emitter"] = emitter
    return shape


def _value_noise(rng: np.random.Generator, n: int, cells: int) -> np.ndarray:
    """Smooth periodic value noise in [0, 1], shape (n, n): bilinear blend of a cells^2 grid."""
    grid = rng.random((cells, cells))
    coords = np.arange(n) * cells / n
    i0 = np.floor(coords).astype(int)
    f = coords - i0
    f = f * f * (3 - 2 * f)
    i1 = (i0 + 1) % cells
    rows0 = grid[i0][:, i0] * (1 - f)[None, :] + grid[i0][:, i1] * f[None, :]
    rows1 = grid[i1][:, i0] * (1 - f)[None, :] + grid[i1][:, i1] * f[None, :]
    return rows0 * (1 - f)[:, None] + rows1 * f[:, None]


def _fine_albedo_texture(n: int = 512) -> np.ndarray:
    """High-frequency colour texture, (n, n, 3) in [0.05, 0.9]: a checker of 8-texel cells,
    thin stripes (period 5 texels) and noise. Tiled once over the texture-bump floor, a texel is
    about a third of a pixel at 256 x 256, so the stripes sit near the pixel scale and the
    checker cells span a few pixels: the fine detail denoisers must keep."""
    rng = np.random.default_rng(1234)
    y, x = np.mgrid[0:n, 0:n]
    checker = ((x // 8 + y // 8) % 2).astype(np.float64)
    stripes = (np.sin(2 * np.pi * (x + 0.5 * y) / 5.0) > 0.3).astype(np.float64)
    noise = _value_noise(rng, n, 64)
    a = np.stack([
        0.15 + 0.6 * checker * (0.6 + 0.4 * noise),
        0.1 + 0.35 * stripes + 0.3 * noise,
        0.1 + 0.5 * (1 - checker) * stripes + 0.15 * noise,
    ], axis=-1)
    return np.clip(a, 0.05, 0.9)


def _ripple_height(n: int = 256, rings: int = 12) -> np.ndarray:
    """Bump height field (n, n, 1): concentric ripples plus fine noise, values in [0, 1]."""
    rng = np.random.default_rng(99)
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n
    r = np.hypot(x - 0.5, y - 0.5)
    h = 0.5 + 0.35 * np.sin(2 * np.pi * rings * r) + 0.15 * (_value_noise(rng, n, 32) - 0.5)
    return np.clip(h, 0.0, 1.0)[..., None]


def _brick_normal_map(n: int = 256, bricks: int = 4) -> np.ndarray:
    """Tangent-space normal map (n, n, 3) of bevelled bricks, encoded as (N + 1) / 2."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * bricks
    x = x + 0.5 * (np.floor(y) % 2)  # running bond
    fx, fy = x - np.floor(x) - 0.5, y - np.floor(y) - 0.5
    bevel = 0.36
    nx = np.where(np.abs(fx) > bevel, np.sign(fx) * 0.7, 0.0)
    ny = np.where(np.abs(fy) > bevel, np.sign(fy) * 0.7, 0.0)
    normal = np.stack([nx, ny, np.ones_like(nx)], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return (normal + 1.0) / 2.0


def _sky(width: int = 256, height: int = 128, sun_elevation_deg: float = 35.0,
         sun_azimuth_deg: float = 60.0, sun_radiance: float = 4000.0) -> np.ndarray:
    """Equirectangular HDR sky (height, width, 3): blue zenith, pale horizon, dark ground,
    and a sun of ~2.2 degrees diameter (a few texels) with ``sun_radiance``."""
    v = (np.arange(height) + 0.5) / height  # 0 at the zenith (Mitsuba's envmap: +Y up)
    u = (np.arange(width) + 0.5) / width
    theta = v * np.pi
    phi = u * 2 * np.pi
    elevation = np.pi / 2 - theta[:, None] + 0 * phi[None, :]
    up = np.clip(np.sin(elevation), 0.0, 1.0)
    zenith, horizon, ground = np.array([0.25, 0.45, 1.0]), np.array([1.0, 0.95, 0.9]), \
        np.array([0.12, 0.1, 0.08])
    t = up[..., None] ** 0.5
    sky = (1 - t) * horizon + t * zenith
    sky = np.where((elevation > 0)[..., None], sky * 1.2, ground)
    # Direction of each texel and of the sun, in the envmap's frame.
    dirs = np.stack([np.sin(theta)[:, None] * np.cos(phi)[None, :],
                     np.cos(theta)[:, None] * np.ones_like(phi)[None, :],
                     np.sin(theta)[:, None] * np.sin(phi)[None, :]], axis=-1)
    se, sa = math.radians(sun_elevation_deg), math.radians(sun_azimuth_deg)
    sun = np.array([math.cos(se) * math.cos(sa), math.sin(se), math.cos(se) * math.sin(sa)])
    angle = np.arccos(np.clip(dirs @ sun, -1.0, 1.0))
    sky = sky + np.where((angle < math.radians(1.1))[..., None],
                         sun_radiance * np.array([1.0, 0.93, 0.8]), 0.0)
    return sky.astype(np.float32)


# ---------------------------------------------------------------------------- built-in scenes
def _cornell_box() -> dict:
    import mitsuba as mi

    scene = mi.cornell_box()
    scene["sensor"]["film"]["rfilter"] = {"type": "box"}
    return scene


def _room(bsdf_floor: dict, bsdf_walls: dict, half: float = 2.0, height: float = 3.0) -> dict:
    """Floor (y = 0), back wall (z = -half) and left/right walls of a box room."""
    t = _transform
    return {
        "floor": _rectangle(t().rotate([1, 0, 0], -90).scale([half, half, 1]), bsdf_floor),
        "back": _rectangle(t().translate([0, height / 2, -half]).scale([half, height / 2, 1]),
                           bsdf_walls),
        "left": _rectangle(t().translate([-half, height / 2, 0]).rotate([0, 1, 0], 90)
                           .scale([half, height / 2, 1]), bsdf_walls),
        "right": _rectangle(t().translate([half, height / 2, 0]).rotate([0, 1, 0], -90)
                            .scale([half, height / 2, 1]), bsdf_walls),
    }


def _texture_bump() -> dict:
    t = _transform
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 6},
        "sensor": _sensor([0.0, 1.6, 4.2], [0.0, 0.8, 0.0], 50.0),
    }
    scene.update(_room(_diffuse(_bitmap_texture(_fine_albedo_texture(), tiles=1.0, nearest=True)),
                       _diffuse([0.6, 0.6, 0.6])))
    # The back wall carries a bump map (ripples): flat geometry, varying shading normals.
    scene["back"]["bsdf"] = {
        "type": "bumpmap",
        "arbitrary": _bitmap_texture(_ripple_height(), tiles=2.0, raw=True),
        "scale": 1.0,
        "bsdf": _diffuse([0.7, 0.65, 0.55]),
    }
    scene["brick_cube"] = {
        "type": "cube",
        "to_world": t().translate([0.9, 0.5, 0.2]).rotate([0, 1, 0], 25).scale(0.5),
        "bsdf": {"type": "normalmap",
                 "normalmap": _bitmap_texture(_brick_normal_map(), raw=True),
                 "bsdf": _diffuse([0.55, 0.25, 0.15])},
    }
    scene["bumpy_sphere"] = {
        "type": "sphere", "center": [-0.8, 0.6, 0.3], "radius": 0.6,
        "bsdf": {"type": "bumpmap",
                 "arbitrary": _bitmap_texture(_ripple_height(128), tiles=4.0, raw=True),
                 "scale": 0.5,
                 "bsdf": _diffuse([0.3, 0.5, 0.7])},
    }
    scene["light"] = _rectangle(
        t().translate([0.0, 2.99, 0.5]).rotate([1, 0, 0], 90).scale([0.6, 0.4, 1]),
        _diffuse([0.0, 0.0, 0.0]),
        {"type": "area", "radiance": _rgb([40.0, 37.0, 32.0])},
    )
    scene["ambient"] = {"type": "constant", "radiance": _rgb([0.05, 0.05, 0.06])}
    return scene


def _glossy_glass() -> dict:
    t = _transform
    checker = {"type": "checkerboard", "color0": _rgb([0.75, 0.75, 0.72]),
               "color1": _rgb([0.2, 0.2, 0.22]), "to_uv": t().scale([6, 6, 1])}
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 12},
        "sensor": _sensor([0.0, 1.5, 4.5], [0.0, 0.55, 0.0], 45.0),
        "floor": _rectangle(t().rotate([1, 0, 0], -90).scale([3, 3, 1]), _diffuse(checker)),
        "back": _rectangle(t().translate([0, 1.5, -2.0]).scale([3, 1.5, 1]),
                           {"type": "roughplastic", "diffuse_reflectance": _rgb([0.5, 0.5, 0.55]),
                            "alpha": 0.3}),
        "gold_sphere": {"type": "sphere", "center": [-1.2, 0.5, 0.0], "radius": 0.5,
                        "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.12}},
        "glass_sphere": {"type": "sphere", "center": [0.0, 0.55, 0.6], "radius": 0.55,
                         "bsdf": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0}},
        "plastic_cube": {
            "type": "cube",
            "to_world": t().translate([1.25, 0.45, -0.2]).rotate([0, 1, 0], 30).scale(0.45),
            "bsdf": {"type": "roughplastic", "diffuse_reflectance": _rgb([0.1, 0.25, 0.6]),
                     "alpha": 0.08},
        },
        "copper_cylinder": {
            "type": "cylinder", "radius": 0.25, "p0": [0.55, 0.0, -1.0], "p1": [0.55, 1.3, -1.0],
            "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.25},
        },
        "light": _rectangle(
            t().translate([0.5, 3.0, 1.0]).rotate([1, 0, 0], 90).scale([1.0, 0.6, 1]),
            _diffuse([0.0, 0.0, 0.0]),
            {"type": "area", "radiance": _rgb([9.0, 8.5, 8.0])},
        ),
        "ambient": {"type": "constant", "radiance": _rgb([0.15, 0.16, 0.2])},
    }
    return scene


def _env_sun() -> dict:
    import mitsuba as mi

    t = _transform
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": _sensor([0.0, 1.2, 5.0], [0.0, 0.9, 0.0], 55.0),
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(_sky()), "scale": 1.0},
        "ground": {"type": "disk", "to_world": t().rotate([1, 0, 0], -90).scale(12.0),
                   "bsdf": _diffuse([0.35, 0.32, 0.28])},
        "sphere": {"type": "sphere", "center": [-1.0, 0.7, 0.0], "radius": 0.7,
                   "bsdf": _diffuse([0.8, 0.2, 0.15])},
        "cube": {"type": "cube",
                 "to_world": t().translate([0.9, 0.5, -0.3]).rotate([0, 1, 0], -20).scale(0.5),
                 "bsdf": {"type": "roughplastic", "diffuse_reflectance": _rgb([0.7, 0.7, 0.65]),
                          "alpha": 0.2}},
        "pillar": {"type": "cylinder", "radius": 0.2, "p0": [0.0, 0.0, -1.5],
                   "p1": [0.0, 2.2, -1.5],
                   "bsdf": {"type": "roughconductor", "material": "Al", "alpha": 0.3}},
    }


def _small_lights() -> dict:
    t = _transform
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": _sensor([0.0, 1.4, 4.3], [0.0, 0.9, 0.0], 50.0),
    }
    scene.update(_room({"type": "roughconductor", "material": "Al", "alpha": 0.08},
                       _diffuse([0.55, 0.55, 0.55])))
    scene["statue"] = {"type": "sphere", "center": [0.0, 0.6, -0.3], "radius": 0.6,
                       "bsdf": _diffuse([0.7, 0.7, 0.7])}
    scene["shelf"] = {"type": "cube",
                      "to_world": t().translate([-1.1, 0.35, -0.9]).scale([0.5, 0.35, 0.5]),
                      "bsdf": {"type": "roughplastic",
                               "diffuse_reflectance": _rgb([0.6, 0.3, 0.1]), "alpha": 0.15}}
    # Tiny, very bright sphere lights: a few pixels on screen, the rest of the scene lit only
    # by them, so most paths miss them and a few find them: the classic firefly source.
    bulbs = [([-1.4, 1.9, -1.2], [400.0, 250.0, 120.0]), ([1.3, 1.2, -0.8], [120.0, 200.0, 420.0]),
             ([0.4, 2.4, 0.3], [350.0, 350.0, 330.0]), ([-0.6, 0.15, 0.9], [300.0, 60.0, 60.0])]
    for index, (centre, radiance) in enumerate(bulbs):
        scene[f"bulb_{index}"] = {
            "type": "sphere", "center": centre, "radius": 0.035,
            "emitter": {"type": "area", "radiance": _rgb(radiance)},
        }
    return scene


@dataclass(frozen=True)
class _BuiltIn:
    description: str
    build: Callable[[], dict]


BUILTIN_SCENES: dict[str, _BuiltIn] = {
    "cornell-box": _BuiltIn(
        "Mitsuba's Cornell box: diffuse walls and boxes, one visible ceiling area light.",
        _cornell_box),
    "texture-bump": _BuiltIn(
        "Room with a high-frequency NumPy-textured floor, a bump-mapped wall and sphere and a "
        "normal-mapped brick cube; ceiling area light.", _texture_bump),
    "glossy-glass": _BuiltIn(
        "Rough gold sphere, glass sphere, rough-plastic cube and rough copper cylinder on a "
        "checker floor; area light plus dim ambient.", _glossy_glass),
    "env-sun": _BuiltIn(
        "Outdoor objects lit only by a NumPy HDR sky envmap with a small bright sun (sky "
        "visible on misses).", _env_sun),
    "small-lights": _BuiltIn(
        "Dark room with a glossy metal floor lit only by four tiny, very bright sphere lights "
        "(firefly-prone).", _small_lights),
}


def list_scenes() -> dict[str, str]:
    """Built-in scene names -> one-line descriptions."""
    return {name: entry.description for name, entry in BUILTIN_SCENES.items()}
