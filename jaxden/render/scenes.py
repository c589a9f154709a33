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
``SCENE_MEMORY`` scenes it loaded (Mitsuba scenes accept neither attributes nor weak
references, so the memory holds them alive; it is bounded to keep memory bounded).

:func:`prepare_scene` is the dict-level step: the patched scene dict, not loaded, for every
spec but XML files (those are patched as XML text and loaded by :func:`load_scene`).

All built-in scenes are small (spheres, rectangles, cubes, cylinders, disks), need no files,
and draw their textures from NumPy with fixed seeds, so they are identical everywhere.
"""

from __future__ import annotations

import collections
import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.errors import SceneError
from jaxden.render.variant import ensure_variant

DEFAULT_SIZE: tuple[int, int] = (256, 256)
MAX_SIDE = 16384  # pixels; a larger film is a typo, not a render
MAX_PIXELS = 1 << 27
SCENE_MEMORY = 8
SENSOR_TYPES = frozenset({"perspective", "thinlens", "orthographic", "telecentric"})
# Every Mitsuba sensor plugin: found as sensors, then rejected unless in SENSOR_TYPES.
_ALL_SENSOR_PLUGINS = SENSOR_TYPES | {"batch", "radiancemeter", "irradiancemeter", "distant"}
_PROCEDURAL = re.compile(r"^procedural:(\d+)$")


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


# ---------------------------------------------------------------------------- dict patching
def _copy_tree(value):
    """Copy nested dicts and lists; Mitsuba objects (Bitmap, Transform) are shared, not copied."""
    if isinstance(value, dict):
        return {k: _copy_tree(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_copy_tree(v) for v in value]
    return value


def patch_sensor_dict(sensor: dict, size: tuple[int, int] | None, where: str) -> dict:
    """A copy of a Mitsuba sensor dict with hdrfilm + box filter + independent sampler.

    ``size`` (width, height) overrides the film size; the film's crop is removed (crops are
    set per render). Raises SceneError for sensors jaxden cannot render images with.
    """
    if not isinstance(sensor, dict):
        raise SceneError(f"{where}: the sensor must be a dict, got {type(sensor).__name__}")
    sensor = _copy_tree(sensor)
    kind = sensor.get("type")
    if kind not in SENSOR_TYPES:
        raise SceneError(
            f"{where}: sensor type {kind!r} is not supported; use one of {sorted(SENSOR_TYPES)}"
        )
    film = sensor.get("film", {"type": "hdrfilm"})
    if not isinstance(film, dict):
        raise SceneError(f"{where}: the sensor's film must be a dict, got {type(film).__name__}")
    if film.get("type", "hdrfilm") != "hdrfilm":
        raise SceneError(f"{where}: film type {film.get('type')!r} is not supported; use hdrfilm")
    film = dict(film)
    for key in ("crop_offset_x", "crop_offset_y", "crop_width", "crop_height"):
        film.pop(key, None)
    film.update(type="hdrfilm", rfilter={"type": "box"}, pixel_format="rgb",
                component_format="float32")
    if size is not None:
        film["width"], film["height"] = check_size(size, where)
    else:
        film.setdefault("width", DEFAULT_SIZE[0])
        film.setdefault("height", DEFAULT_SIZE[1])
        check_size((film["width"], film["height"]), f"{where}: film")
    sensor["film"] = film
    sampler = sensor.get("sampler")
    count = sampler.get("sample_count", 16) if isinstance(sampler, dict) else 16
    sensor["sampler"] = {"type": "independent",
                         "sample_count": int(count) if isinstance(count, (int, np.integer)) else 16}
    return sensor


def _sensor_keys(scene: dict, where: str) -> list[str]:
    import mitsuba as mi

    keys = []
    for key, value in scene.items():
        if isinstance(value, dict) and value.get("type") in _ALL_SENSOR_PLUGINS:
            keys.append(key)
        elif isinstance(value, mi.Sensor):
            raise SceneError(
                f"{where}: entry {key!r} is an instantiated mi.Sensor; give it as a dict so "
                f"jaxden can set its film and sampler"
            )
    if not keys:
        raise SceneError(f"{where}: the scene has no sensor (camera); add e.g. a 'perspective' "
                         f"entry with a film")
    return keys


def _patch_scene_dict(scene: dict, size, where: str) -> dict:
    if not isinstance(scene, dict):
        raise SceneError(f"{where}: a scene dict must be a dict, got {type(scene).__name__}")
    if scene.get("type") != "scene":
        raise SceneError(f"{where}: a scene dict needs type 'scene', got {scene.get('type')!r}")
    scene = _copy_tree(scene)
    for key in _sensor_keys(scene, where):
        scene[key] = patch_sensor_dict(scene[key], size, f"{where}: sensor {key!r}")
    return scene


def _procedural(spec: str, size) -> dict:
    match = _PROCEDURAL.match(spec)
    if match is None:
        raise SceneError(
            f"scene spec {spec!r} is malformed: procedural scenes are 'procedural:SEED' with "
            f"SEED a decimal integer >= 0, e.g. 'procedural:7'"
        )
    seed = int(match.group(1))
    try:
        from jaxden.render.procedural import generate_scene
    except ImportError as error:
        raise SceneError(f"procedural scenes are unavailable: {error}") from error
    return _patch_scene_dict(generate_scene(seed), size, f"scene {spec!r}")


def _is_path_like(spec) -> bool:
    """Whether a spec names a file: PathLike, or a str that is not a built-in or procedural
    name and ends in .xml, contains a path separator or names an existing file."""
    if isinstance(spec, os.PathLike):
        return True
    if not isinstance(spec, str) or spec in BUILTIN_SCENES or spec.startswith("procedural"):
        return False
    return spec.lower().endswith(".xml") or os.sep in spec or os.path.isfile(spec)


def prepare_scene(spec, size: tuple[int, int] | None = None) -> dict:
    """The patched Mitsuba scene dict of a built-in name, ``procedural:SEED`` or a scene dict.

    Box filter, independent sampler and ``size`` = (width, height) are applied to every sensor
    (see the module docstring); the dict is a copy (bitmaps and transforms are shared) and is
    not loaded. XML files are not dicts: load them with :func:`load_scene`. Raises SceneError.
    """
    ensure_variant()  # built-in dicts hold Mitsuba objects of the variant
    if size is not None:
        size = check_size(size, "size")
    if isinstance(spec, dict):
        return _patch_scene_dict(spec, size, "scene dict")
    if _is_path_like(spec):
        raise SceneError(
            f"prepare_scene works on dict scenes; load the XML file {os.fspath(spec)} with "
            f"load_scene"
        )
    if not isinstance(spec, str):
        raise SceneError(
            f"a scene spec must be a name, 'procedural:SEED', a path or a dict, got "
            f"{type(spec).__name__}"
        )
    if spec.startswith("procedural"):
        return _procedural(spec, size)
    if spec not in BUILTIN_SCENES:
        raise SceneError(
            f"unknown scene {spec!r}; built-in scenes: {', '.join(BUILTIN_SCENES)} (or "
            f"'procedural:SEED', a Mitsuba XML file, a scene dict)"
        )
    return _patch_scene_dict(BUILTIN_SCENES[spec].build(), size, f"scene {spec!r}")


# ---------------------------------------------------------------------------- XML patching
def _xml_set_param(parent: ET.Element, tag: str, name: str, value: str) -> None:
    for child in list(parent):
        if child.get("name") == name:
            parent.remove(child)
    ET.SubElement(parent, tag, {"name": name, "value": value})


def _patch_xml_sensor(sensor: ET.Element, size, where: str) -> None:
    if sensor.get("type") not in SENSOR_TYPES:
        raise SceneError(
            f"{where}: sensor type {sensor.get('type')!r} is not supported; use one of "
            f"{sorted(SENSOR_TYPES)}"
        )
    films = sensor.findall("film")
    if not films:
        films = [ET.SubElement(sensor, "film", {"type": "hdrfilm"})]
    film = films[0]
    if film.get("type") != "hdrfilm":
        raise SceneError(f"{where}: film type {film.get('type')!r} is not supported; use hdrfilm")
    for child in list(film):
        if child.tag == "rfilter" or child.get("name", "").startswith("crop_"):
            film.remove(child)
    ET.SubElement(film, "rfilter", {"type": "box"})
    _xml_set_param(film, "string", "pixel_format", "rgb")
    _xml_set_param(film, "string", "component_format", "float32")
    if size is not None:
        _xml_set_param(film, "integer", "width", str(size[0]))
        _xml_set_param(film, "integer", "height", str(size[1]))
    count = "16"
    for sampler in sensor.findall("sampler"):
        for child in sampler:
            if child.get("name") == "sample_count" and (child.get("value") or "").isdigit():
                count = child.get("value")
        sensor.remove(sampler)
    sampler = ET.SubElement(sensor, "sampler", {"type": "independent"})
    ET.SubElement(sampler, "integer", {"name": "sample_count", "value": count})


def _one_line(message: str) -> str:
    return " ".join(part.strip() for part in str(message).splitlines() if part.strip())


class _FileResolverDir:
    """Context: put a folder first on Mitsuba's file resolver, restore the resolver after."""

    def __init__(self, folder: Path):
        self.folder = folder

    def __enter__(self):
        import mitsuba as mi

        self.resolver = mi.file_resolver()
        self.saved = [str(self.resolver[i]) for i in range(len(self.resolver))]
        self.resolver.prepend(str(self.folder))
        return self

    def __exit__(self, *exc):
        self.resolver.clear()
        for entry in self.saved:
            self.resolver.append(entry)
        return False


@dataclass
class _XmlScene:
    path: Path
    text: str  # the patched scene XML
    sensor_xml: str  # a scene holding only the defaults and the first (patched) sensor
    size: tuple[int, int] | None


def _prepare_xml(path, size) -> _XmlScene:
    path = Path(os.fspath(path))
    if not path.is_file():
        raise SceneError(f"scene file {path} does not exist" if not path.exists()
                         else f"scene path {path} is not a file")
    try:
        tree = ET.parse(path)
    except ET.ParseError as error:
        raise SceneError(f"{path}: invalid XML: {error}") from None
    except OSError as error:
        raise SceneError(f"{path}: cannot read the scene file: {error}") from None
    root = tree.getroot()
    if root.tag != "scene":
        raise SceneError(f"{path}: the root element must be <scene>, got <{root.tag}>")
    sensors = root.findall("sensor")
    if not sensors:
        raise SceneError(f"{path}: the scene has no <sensor> (camera) at its top level")
    for index, sensor in enumerate(sensors):
        _patch_xml_sensor(sensor, size, f"{path}: sensor {index}")
    # The first sensor on its own, with the scene's <default> parameters so $names resolve.
    sensor_root = ET.Element("scene", dict(root.attrib))
    for element in root.findall("default"):
        sensor_root.append(element)
    sensor_root.append(sensors[0])
    return _XmlScene(path=path, text=ET.tostring(root, encoding="unicode"),
                     sensor_xml=ET.tostring(sensor_root, encoding="unicode"), size=size)


def _load_xml_string(text: str, xml: _XmlScene, what: str):
    import mitsuba as mi

    with _FileResolverDir(xml.path.resolve().parent):
        try:
            return mi.load_string(text)
        except Exception as error:  # noqa: BLE001 - Mitsuba raises RuntimeError and others
            raise SceneError(f"{xml.path}: Mitsuba could not load the {what}: "
                             f"{_one_line(error)}") from None


# ---------------------------------------------------------------------------- sensor sources
_PROJECTION_KEYS = ("x_fov", "principal_point_offset_x", "principal_point_offset_y")


def crop_projection(x_fov_deg: float, principal_point: tuple[float, float],
                    size: tuple[int, int], crop: tuple[int, int, int, int]):
    """(x_fov, (ppo_x, ppo_y)) of a camera whose (crop width x crop height) film sees exactly
    the crop (top, left, height, width) of a ``size`` = (W, H) film of the given camera.

    Mitsuba's perspective camera maps film coordinates s in [0, 1]^2 to camera-space slopes
    X/Z = t (1 - 2 s_x - 2 ppo_x) and Y/Z = (t / aspect) (1 - 2 s_y - 2 ppo_y), with
    t = tan(x_fov / 2) (measured with sample_ray). A crop is s = offset / size + s' * crop /
    size; matching both maps gives t' = t * width / W and
    ppo' = (1 - (1 - 2 offset / size - 2 ppo) * size / crop) / 2 per axis.
    """
    top, left, height, width = crop
    full_width, full_height = size
    t = math.tan(math.radians(x_fov_deg) / 2.0)
    x_fov = 2.0 * math.degrees(math.atan(t * width / full_width))
    ppo_x = (1.0 - (1.0 - 2.0 * left / full_width - 2.0 * principal_point[0])
             * full_width / width) / 2.0
    ppo_y = (1.0 - (1.0 - 2.0 * top / full_height - 2.0 * principal_point[1])
             * full_height / height) / 2.0
    return x_fov, (ppo_x, ppo_y)


@dataclass
class SensorSource:
    """How to build the sensor of a loaded scene at any size, with an optional crop.

    Crops of perspective cameras are rendered by a camera with a crop-sized film and a
    narrower, off-centre projection (:func:`crop_projection`), set through ``mi.traverse``:
    those parameters are opaque to Dr.Jit, so every crop of one size reuses the compiled
    kernels. Mitsuba's own film crop would bake the crop offset into the kernel and recompile
    (~1 s) for every new crop position. Both give the same rays (tested to float round-off);
    other sensor types fall back to the film crop.
    """

    name: str
    size: tuple[int, int]  # the scene's own film size (width, height)
    sensor_dict: dict | None = None
    xml: _XmlScene | None = None
    _cache: collections.OrderedDict = field(default_factory=collections.OrderedDict)

    def _load(self, size: tuple[int, int], film_crop=None):
        if self.sensor_dict is not None:
            return build_sensor(self.sensor_dict, size, film_crop, self.name)
        root = ET.fromstring(self.xml.sensor_xml)
        film = root.find("sensor").find("film")
        _xml_set_param(film, "integer", "width", str(size[0]))
        _xml_set_param(film, "integer", "height", str(size[1]))
        if film_crop is not None:
            top, left, height, width = film_crop
            for name, value in (("crop_offset_x", left), ("crop_offset_y", top),
                                ("crop_width", width), ("crop_height", height)):
                _xml_set_param(film, "integer", name, str(value))
        scene = _load_xml_string(ET.tostring(root, encoding="unicode"), self.xml, "sensor")
        return scene.sensors()[0]

    def _cached(self, key, make):
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        sensor = self._cache[key] = make()
        while len(self._cache) > 6:
            self._cache.popitem(last=False)
        return sensor

    def build(self, size: tuple[int, int], crop: tuple[int, int, int, int] | None):
        """An mi.Sensor at ``size`` (w, h), rendering only ``crop`` (top, left, h, w) if given.

        A crop sensor is shared between crops of one size and re-aimed by each call: use it
        before asking for the next crop.
        """
        import mitsuba as mi

        size = tuple(size)
        full = self._cached(("full", size), lambda: self._load(size))
        if crop is None:
            return full
        params = mi.traverse(full)
        if not all(key in params.keys() for key in _PROJECTION_KEYS):
            return self._cached(("film-crop", size, tuple(crop)),
                                lambda: self._load(size, film_crop=crop))
        crop_size = (crop[3], crop[2])
        sensor = self._cached(("crop", crop_size), lambda: self._load(crop_size))
        x_fov, (ppo_x, ppo_y) = crop_projection(
            float(params["x_fov"][0]),
            (float(params["principal_point_offset_x"][0]),
             float(params["principal_point_offset_y"][0])),
            size, crop)
        crop_params = mi.traverse(sensor)
        crop_params["x_fov"] = x_fov
        crop_params["principal_point_offset_x"] = ppo_x
        crop_params["principal_point_offset_y"] = ppo_y
        crop_params.update()
        return sensor


def build_sensor(sensor_dict: dict, size: tuple[int, int],
                 crop: tuple[int, int, int, int] | None, where: str):
    """Load an mi.Sensor from a sensor dict at ``size`` with an optional Mitsuba film crop.

    The dict is patched first (hdrfilm, box filter, independent sampler). To render crops
    without recompiling kernels, use ``SensorSource(...).build`` instead.
    """
    import mitsuba as mi

    sensor_dict = patch_sensor_dict(sensor_dict, size, where)
    if crop is not None:
        top, left, height, width = crop
        sensor_dict["film"].update(crop_offset_x=left, crop_offset_y=top, crop_width=width,
                                   crop_height=height)
    try:
        return mi.load_dict(sensor_dict)
    except Exception as error:  # noqa: BLE001
        raise SceneError(
            f"{where}: Mitsuba could not load the sensor: {_one_line(error)}"
        ) from None


_loaded: collections.OrderedDict[int, tuple[Any, SensorSource]] = collections.OrderedDict()


def _remember(scene, source: SensorSource) -> None:
    _loaded[id(scene)] = (scene, source)  # holding the scene keeps its id from being reused
    _loaded.move_to_end(id(scene))
    while len(_loaded) > SCENE_MEMORY:
        _loaded.popitem(last=False)


def sensor_source(scene) -> SensorSource | None:
    """The SensorSource of a scene returned by load_scene (the SCENE_MEMORY most recent)."""
    entry = _loaded.get(id(scene))
    if entry is not None and entry[0] is scene:
        _loaded.move_to_end(id(scene))
        return entry[1]
    return None


def _spec_name(spec) -> str:
    if isinstance(spec, dict):
        return "scene dict"
    return f"scene {os.fspath(spec)!r}" if isinstance(spec, (str, os.PathLike)) else repr(spec)


def load_scene(spec, size: tuple[int, int] | None = None):
    """Load a scene spec (see the module docstring) as an ``mi.Scene``.

    Every sensor renders with an hdrfilm, a box filter and an independent sampler; ``size`` =
    (width, height) in pixels overrides the film size. XML files load with their own folder
    first on Mitsuba's file resolver, so relative mesh and texture paths work; their
    ``<default>`` parameters keep working (a size override replaces ``$resx``-style values of
    the film by numbers). Raises SceneError for an unknown name, a missing or invalid file, a
    scene without sensor, a bad size.
    """
    import mitsuba as mi

    ensure_variant()
    if size is not None:
        size = check_size(size, "size")
    if _is_path_like(spec):
        xml = _prepare_xml(spec, size)
        scene = _load_xml_string(xml.text, xml, "scene")
        if not scene.sensors():
            raise SceneError(f"{xml.path}: the scene has no sensor")
        film_size = tuple(int(v) for v in scene.sensors()[0].film().size())
        _remember(scene, SensorSource(name=str(xml.path), size=film_size, xml=xml))
        return scene
    scene_dict = prepare_scene(spec, size)
    name = _spec_name(spec)
    first_sensor = scene_dict[_sensor_keys(scene_dict, name)[0]]
    try:
        scene = mi.load_dict(scene_dict)
    except Exception as error:  # noqa: BLE001
        raise SceneError(f"{name}: Mitsuba could not load the scene: {_one_line(error)}") from None
    film = first_sensor["film"]
    _remember(scene, SensorSource(name=name, size=(int(film["width"]), int(film["height"])),
                                  sensor_dict=first_sensor))
    return scene
