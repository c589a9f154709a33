"""Seeded random Mitsuba scenes, in the spirit of the progressive-denoising paper's data.

Firmino et al. (2022, Sec. 5.2) train on 504 crops of "randomly generated scenes rendered in
mitsuba" besides pbrt scenes; the paper does not describe the generator. This one builds, from a
single integer seed, a Mitsuba 3 scene dict with:

* a ground plane, sometimes one or two walls behind or beside the content;
* 3-10 objects (sphere, cube, cylinder (open or capped), rectangle and disk panels) resting on
  the ground or floating, with random placement, size and rotation;
* random materials: diffuse, plastic, roughplastic, conductor, roughconductor (a named metal
  or random eta/k), dielectric, roughdielectric, thindielectric; procedural high-frequency
  colour textures, roughness textures and bump maps from :mod:`jaxden.render.textures`,
  passed as ``mi.Bitmap`` objects (no files) and tiled on the surfaces;
* random lighting: rectangle and disk area lights, small very bright sphere lights (the
  firefly sources denoisers must cope with), and a constant or HDR envmap environment;
* a random perspective camera looking at the content, with an ``hdrfilm`` (box filter) and an
  ``independent`` sampler. No integrator: the renderer chooses it.

Exposure: light strengths are set from a target irradiance at the content (area lights by
E ~= L A / d^2, the environment by E = pi L), times a random exposure factor, so that renders
land at a mean radiance of roughly 0.05-2 for most seeds (measured numbers in the tests).

Determinism: all randomness comes from ``np.random.default_rng(seed)``; the same seed gives an
identical dict (same numbers, same bitmaps) on every call and machine with the same NumPy.
Geometry is static: animation (jaxden.render.sequence) moves only the camera.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from jaxden.errors import SceneError
from jaxden.render import textures
from jaxden.render.camera import Camera, film_size_pair
from jaxden.render.variant import ensure_variant

SHAPE_KINDS: tuple[str, ...] = ("sphere", "cube", "cylinder", "rectangle", "disk")
MATERIAL_KINDS: tuple[str, ...] = (
    "diffuse",
    "plastic",
    "roughplastic",
    "conductor",
    "roughconductor",
    "dielectric",
    "roughdielectric",
    "thindielectric",
)
LIGHT_KINDS: tuple[str, ...] = ("area_rectangle", "area_disk", "area_sphere", "constant", "envmap")
#: Named conductors of Mitsuba 3 that load in every variant.
CONDUCTORS: tuple[str, ...] = (
    "Ag", "Al", "Au", "Cu", "Cr", "W", "Mo", "Rh", "Ir", "Be", "TiN", "Ta"
)

_MATERIAL_WEIGHTS = np.array([0.28, 0.08, 0.14, 0.07, 0.17, 0.09, 0.09, 0.08])
_SHAPE_WEIGHTS = np.array([0.27, 0.25, 0.2, 0.14, 0.14])
_TEXTURE_RESOLUTION = 128
_ENVMAP_HEIGHT = 64


# ---------------------------------------------------------------------------- small helpers
def _check_seed(seed) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise SceneError(f"generate_scene: seed must be an integer >= 0, got {seed!r}")
    if seed < 0:
        raise SceneError(f"generate_scene: seed must be >= 0, got {seed}")
    return int(seed)


def _transform(matrix: np.ndarray):
    import mitsuba as mi

    return mi.ScalarTransform4f(np.asarray(matrix, dtype=np.float64))


def _affine(translation=(0.0, 0.0, 0.0), rotation=None, scale=(1.0, 1.0, 1.0)) -> np.ndarray:
    """4x4 matrix of translate @ rotate @ scale."""
    matrix = np.eye(4)
    rotation = np.eye(3) if rotation is None else np.asarray(rotation)
    matrix[:3, :3] = rotation @ np.diag(np.asarray(scale, dtype=np.float64))
    matrix[:3, 3] = translation
    return matrix


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly distributed rotation (3, 3) from a normalised Gaussian quaternion."""
    quaternion = rng.normal(size=4)
    w, x, y, z = quaternion / np.linalg.norm(quaternion)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _face_towards(normal: np.ndarray) -> np.ndarray:
    """A rotation (3, 3) taking local +z to the unit vector ``normal``."""
    z = normal / np.linalg.norm(normal)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _direction(azimuth: float, elevation: float) -> np.ndarray:
    """Unit vector (3,) at ``azimuth`` around +y (from +x towards +z) and ``elevation``."""
    return np.array([
        math.cos(elevation) * math.cos(azimuth),
        math.sin(elevation),
        math.cos(elevation) * math.sin(azimuth),
    ])


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _rgb(values) -> dict:
    return {"type": "rgb", "value": [float(v) for v in values]}


# ---------------------------------------------------------------------------- textures
def _bitmap(array: np.ndarray, tiles: float, *, raw: bool = False) -> dict:
    import mitsuba as mi

    texture = {
        "type": "bitmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(array, dtype=np.float32)),
        "filter_type": "bilinear",
        "wrap_mode": "repeat",
        "to_uv": _transform(_affine(scale=(tiles, tiles, 1.0))),
    }
    if raw:
        texture["raw"] = True
    return texture


def _tiles(rng: np.random.Generator, uv_length: float, scene_radius: float) -> float:
    """Integer texture repeats over one uv unit, for a tile of ~0.15-0.8 scene radii."""
    tile_world = scene_radius * rng.uniform(0.15, 0.8)
    return float(max(1, round(uv_length / tile_world)))


def _colour(rng, uv_length, radius, probability) -> tuple[Any, bool]:
    if rng.random() < probability:
        array, _ = textures.color_texture((_TEXTURE_RESOLUTION, _TEXTURE_RESOLUTION), rng)
        return _bitmap(array, _tiles(rng, uv_length, radius)), True
    return _rgb(rng.uniform(0.03, 0.85, size=3)), False


def _roughness(rng, uv_length, radius, lo, hi) -> Any:
    """A roughness alpha: a constant, or (30%) a texture ranging over [lo, hi]."""
    if rng.random() < 0.3:
        values, _ = textures.random_pattern((_TEXTURE_RESOLUTION, _TEXTURE_RESOLUTION), rng)
        alpha = lo + (hi - lo) * values
        return _bitmap(alpha[..., None], _tiles(rng, uv_length, radius), raw=True)
    return _log_uniform(rng, lo, hi)


# ---------------------------------------------------------------------------- materials
def _material(rng: np.random.Generator, uv_length: float, radius: float, kind: str | None = None):
    """A random BSDF dict. ``uv_length`` is the world length of one uv unit on the shape."""
    if kind is None:
        kind = str(rng.choice(MATERIAL_KINDS, p=_MATERIAL_WEIGHTS / _MATERIAL_WEIGHTS.sum()))
    bsdf: dict[str, Any] = {"type": kind}
    if kind == "diffuse":
        bsdf["reflectance"], _ = _colour(rng, uv_length, radius, 0.75)
    elif kind in ("plastic", "roughplastic"):
        bsdf["diffuse_reflectance"], _ = _colour(rng, uv_length, radius, 0.6)
        bsdf["int_ior"] = float(rng.uniform(1.3, 1.8))
        bsdf["nonlinear"] = bool(rng.random() < 0.3)
        if kind == "roughplastic":
            # Mitsuba's roughplastic takes a scalar alpha only (no texture).
            bsdf["alpha"] = _log_uniform(rng, 0.02, 0.4)
            bsdf["distribution"] = str(rng.choice(["beckmann", "ggx"]))
    elif kind in ("conductor", "roughconductor"):
        if rng.random() < 0.65:
            bsdf["material"] = str(rng.choice(CONDUCTORS))
        else:
            bsdf["eta"] = _rgb(rng.uniform(0.1, 2.5, size=3))
            bsdf["k"] = _rgb(rng.uniform(1.0, 5.0, size=3))
        if rng.random() < 0.25:
            tint, _ = _colour(rng, uv_length, radius, 0.7)
            bsdf["specular_reflectance"] = tint
        if kind == "roughconductor":
            bsdf["alpha"] = _roughness(rng, uv_length, radius, 0.02, 0.5)
            bsdf["distribution"] = str(rng.choice(["beckmann", "ggx"]))
    else:  # dielectrics
        bsdf["int_ior"] = float(rng.uniform(1.3, 1.9))
        if rng.random() < 0.4:
            bsdf["specular_transmittance"] = _rgb(rng.uniform(0.6, 1.0, size=3))
        if kind == "roughdielectric":
            bsdf["alpha"] = _roughness(rng, uv_length, radius, 0.01, 0.3)
            bsdf["distribution"] = str(rng.choice(["beckmann", "ggx"]))
    transmissive = kind in ("dielectric", "roughdielectric", "thindielectric")
    if rng.random() < (0.15 if transmissive else 0.35):
        bsdf = _bump(rng, bsdf, uv_length, radius)
    if not transmissive:
        # Panels and walls are seen from both sides; Mitsuba cannot wrap transmissive BSDFs.
        bsdf = {"type": "twosided", "bsdf": bsdf}
    return bsdf


def _bump(rng: np.random.Generator, bsdf: dict, uv_length: float, radius: float) -> dict:
    """Wrap ``bsdf`` in a bump map whose mean slope is 0.05-0.6 (normals tilt ~3-30 degrees).

    Mitsuba's bumpmap offsets the surface by ``scale * height`` world units along the normal
    (measured: the gradient includes the ``to_uv`` tiling), so the slope is
    scale * |grad height| / (world length per uv unit).
    """
    size = _TEXTURE_RESOLUTION
    height, _ = textures.height_map((size, size), rng)
    tiles = _tiles(rng, uv_length, radius)
    gy, gx = np.gradient(height.astype(np.float64))
    mean_gradient = float(np.mean(np.hypot(gx, gy))) * size * tiles / uv_length  # per world unit
    slope = rng.uniform(0.05, 0.6)
    scale = slope / max(mean_gradient, 1e-6)
    return {
        "type": "bumpmap",
        "arbitrary": _bitmap(height[..., None], tiles, raw=True),
        "scale": float(scale),
        "bsdf": bsdf,
    }


# ---------------------------------------------------------------------------- geometry
def _object(rng: np.random.Generator, index: int, radius: float) -> dict[str, dict]:
    """One random object (a few Mitsuba shapes for a capped cylinder), keyed by name."""
    kind = str(rng.choice(SHAPE_KINDS, p=_SHAPE_WEIGHTS / _SHAPE_WEIGHTS.sum()))
    angle, distance = rng.uniform(0, 2 * math.pi), radius * math.sqrt(rng.random())
    x, z = distance * math.cos(angle), distance * math.sin(angle)
    size = radius * rng.uniform(0.12, 0.42)
    floating = rng.random() < 0.25
    lift = radius * rng.uniform(0.3, 1.2) if floating else 0.0
    name = f"object_{index:02d}"
    shapes: dict[str, dict] = {}
    if kind == "sphere":
        matrix = _affine((x, size + lift, z), _random_rotation(rng), (size, size, size))
        uv_length = 2 * math.pi * size
        shapes[name] = {"type": "sphere", "to_world": _transform(matrix)}
    elif kind == "cube":
        half = size * rng.uniform(0.5, 1.2, size=3)
        rotation = _random_rotation(rng) if floating else _rot_y(rng.uniform(0, 360))
        # Resting cubes stand on the ground; floating ones tumble (corners may dip into it).
        matrix = _affine((x, half[1] + lift, z), rotation, half)
        uv_length = 2 * float(half.mean())
        shapes[name] = {"type": "cube", "to_world": _transform(matrix)}
    elif kind == "cylinder":
        cylinder_radius = size * rng.uniform(0.3, 0.8)
        length = size * rng.uniform(1.0, 3.0)
        if floating or rng.random() < 0.3:
            rotation = _random_rotation(rng)
            base = np.array([x, lift + cylinder_radius, z]) - rotation @ [0, 0, length / 2]
        else:
            rotation = _rot_y(rng.uniform(0, 360)) @ _rot_x(-90.0)  # local z -> world +y
            base = np.array([x, 0.0, z])
        matrix = _affine(base, rotation, (cylinder_radius, cylinder_radius, length))
        uv_length = 2 * math.pi * cylinder_radius
        shapes[name] = {"type": "cylinder", "to_world": _transform(matrix)}
        if rng.random() < 0.5:
            for cap, height in (("cap0", 0.0), ("cap1", 1.0)):
                cap_matrix = matrix @ _affine((0.0, 0.0, height))
                shapes[f"{name}_{cap}"] = {"type": "disk", "to_world": _transform(cap_matrix)}
    else:  # rectangle or disk panel
        if floating or rng.random() < 0.3:
            rotation = _random_rotation(rng)
            centre_y = lift + size
        else:
            # A panel standing upright (possibly leaning) on the ground.
            rotation = _rot_y(rng.uniform(0, 360)) @ _rot_x(rng.uniform(-20, 20))
            centre_y = size
        aspect = rng.uniform(0.5, 1.5) if kind == "rectangle" else 1.0
        matrix = _affine((x, centre_y, z), rotation, (size * aspect, size, 1.0))
        uv_length = 2 * size if kind == "rectangle" else 2 * math.pi * size
        shapes[name] = {"type": kind, "to_world": _transform(matrix)}
    bsdf = _material(rng, uv_length, radius)
    for shape in shapes.values():
        shape["bsdf"] = bsdf
    return shapes


def _environment(rng: np.random.Generator, total: float) -> tuple[dict | None, str | None]:
    """Environment light with irradiance share ``total`` on an up-facing, unoccluded surface."""
    import mitsuba as mi

    kind = str(rng.choice(["none", "constant", "envmap"], p=[0.2, 0.35, 0.45]))
    if kind == "none" or total <= 0:
        return None, None
    radiance_level = total / math.pi  # E = pi L for a uniform sky over the hemisphere
    if kind == "constant":
        tint = rng.uniform(0.6, 1.0, size=3)
        tint = tint / tint.mean()
        return {"type": "constant", "radiance": _rgb(radiance_level * tint)}, kind
    image = textures.environment_map((_ENVMAP_HEIGHT, 2 * _ENVMAP_HEIGHT), rng)
    # The map has mean ~1 over texels; the upper half dominates what reaches the content.
    upper = float(image[: _ENVMAP_HEIGHT // 2].mean())
    scale = radiance_level / max(upper, 1e-6)
    rotation = _affine(rotation=_rot_y(rng.uniform(0, 360)))
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(image)),
        "scale": float(scale),
        "to_world": _transform(rotation),
    }, kind


def _area_light(rng: np.random.Generator, index: int, radius: float, irradiance: float) -> dict:
    """An area light above the content delivering ~``irradiance`` to the scene centre."""
    kind = str(rng.choice(["area_rectangle", "area_disk", "area_sphere"], p=[0.4, 0.25, 0.35]))
    azimuth = rng.uniform(0, 2 * math.pi)
    elevation = math.radians(rng.uniform(30, 80))
    distance = radius * rng.uniform(1.5, 4.0)
    position = distance * _direction(azimuth, elevation)
    tint = rng.uniform(0.5, 1.0, size=3)
    tint = tint / tint.mean()
    if kind == "area_sphere":
        # Small and very bright: at most ~0.1 scene radii, often far smaller.
        light_radius = radius * _log_uniform(rng, 0.01, 0.12)
        area_term = math.pi * light_radius**2  # projected area seen from the content
        shape = {"type": "sphere", "center": [float(v) for v in position],
                 "radius": float(light_radius)}
    else:
        half = radius * rng.uniform(0.15, 0.8, size=2)
        if kind == "area_disk":
            half[1] = half[0]
        aim = -position + rng.normal(size=3) * 0.2 * radius  # roughly at the content
        rotation = _face_towards(aim)
        area_term = 4 * half[0] * half[1] if kind == "area_rectangle" else math.pi * half[0] ** 2
        shape = {
            "type": "rectangle" if kind == "area_rectangle" else "disk",
            "to_world": _transform(_affine(position, rotation, (half[0], half[1], 1.0))),
        }
    radiance = irradiance * distance**2 / area_term
    shape["emitter"] = {"type": "area", "radiance": _rgb(radiance * tint)}
    # Light shapes are black to the eye except for their emission.
    shape["bsdf"] = {"type": "diffuse", "reflectance": _rgb([0.0, 0.0, 0.0])}
    return shape


def _camera(rng: np.random.Generator, radius: float) -> Camera:
    fov = rng.uniform(35.0, 75.0)
    azimuth = rng.uniform(0, 2 * math.pi)
    elevation = math.radians(rng.uniform(5.0, 45.0))
    # Far enough that the content (radius ~R, objects up to 0.42 R) fits and never contains it.
    distance = max(radius * rng.uniform(0.7, 1.3) / math.tan(math.radians(fov) / 2), 2.3 * radius)
    target = radius * np.array(
        [rng.uniform(-0.3, 0.3), rng.uniform(0.0, 0.5), rng.uniform(-0.3, 0.3)]
    )
    origin = target + distance * _direction(azimuth, elevation)
    roll = math.radians(rng.uniform(-10, 10)) if rng.random() < 0.3 else 0.0
    # Roll tilts up towards the horizontal direction perpendicular to the view.
    up = np.array(
        [-math.sin(roll) * math.sin(azimuth), math.cos(roll), math.sin(roll) * math.cos(azimuth)]
    )
    return Camera(origin=origin, target=target, up=up, fov_deg=fov)


# ---------------------------------------------------------------------------- the generator
def generate_scene(seed: int, *, size: tuple[int, int] = (256, 256)) -> dict:
    """A random Mitsuba scene dict for ``seed`` (an int >= 0), with a film of ``size``.

    ``size`` is (width, height) in pixels. The dict has ``type: scene``, a ``sensor`` (see
    :class:`jaxden.render.camera.Camera`), shapes named ``ground``, ``wall_*``, ``object_*``,
    ``light_*`` and possibly an ``environment`` emitter; no integrator. Load it with
    ``mi.load_dict``. Same seed -> identical dict; the module docstring lists what it contains.
    Raises SceneError for a bad seed or size.
    """
    seed = _check_seed(seed)
    width, height = film_size_pair(size, "generate_scene")
    ensure_variant()
    rng = np.random.default_rng(seed)
    radius = float(rng.uniform(1.5, 3.5))  # half-extent of the content region, world units
    camera = _camera(rng, radius)
    scene: dict[str, Any] = {"type": "scene", "sensor": camera.to_sensor_dict((width, height))}

    ground_half = 30.0 * radius
    scene["ground"] = {
        "type": "rectangle",
        "to_world": _transform(
            _affine(rotation=_rot_x(-90.0), scale=(ground_half, ground_half, 1.0))
        ),
        "bsdf": _material(rng, 2 * ground_half, radius,
                          kind=str(rng.choice(["diffuse", "roughplastic", "roughconductor"],
                                              p=[0.7, 0.2, 0.1]))),
    }
    # Walls stand behind the content as seen from the camera (and one may flank it).
    view_azimuth = math.atan2(
        camera.origin[2] - camera.target[2], camera.origin[0] - camera.target[0]
    )
    num_walls = int(rng.choice([0, 1, 2], p=[0.4, 0.4, 0.2]))
    for wall in range(num_walls):
        azimuth = view_azimuth + math.pi + (0.0 if wall == 0 else rng.choice([-1, 1]) * math.pi / 2)
        azimuth += rng.uniform(-0.3, 0.3)
        outward = np.array([math.cos(azimuth), 0.0, math.sin(azimuth)])
        distance = radius * rng.uniform(1.4, 2.2)
        half_width, half_height = radius * rng.uniform(2.5, 5.0), radius * rng.uniform(1.0, 3.0)
        rotation = _face_towards(-outward)  # the wall faces the content
        centre = outward * distance + np.array([0.0, half_height, 0.0])
        scene[f"wall_{wall}"] = {
            "type": "rectangle",
            "to_world": _transform(_affine(centre, rotation, (half_width, half_height, 1.0))),
            "bsdf": _material(rng, 2 * half_width, radius,
                              kind=str(rng.choice(["diffuse", "roughplastic"], p=[0.75, 0.25]))),
        }

    for index in range(int(rng.integers(3, 11))):
        scene.update(_object(rng, index, radius))

    # Lighting: the target irradiance at the content, split between environment and lamps.
    exposure = _log_uniform(rng, 0.4, 2.5)
    irradiance = 2.5 * exposure  # a white diffuse surface then reflects ~0.8 * exposure
    environment_share = float(rng.uniform(0.2, 1.0))
    environment, _ = _environment(rng, irradiance * environment_share)
    if environment is not None:
        scene["environment"] = environment
        lamp_irradiance = irradiance * (1.0 - environment_share)
        num_lights = int(rng.integers(0, 4))
    else:
        lamp_irradiance = irradiance
        num_lights = int(rng.integers(1, 4))
    weights = rng.uniform(0.2, 1.0, size=num_lights)
    for index in range(num_lights):
        share = lamp_irradiance * weights[index] / weights.sum()
        scene[f"light_{index}"] = _area_light(rng, index, radius, share)
    return scene


# ---------------------------------------------------------------------------- introspection
def _unwrap_bsdf(bsdf: dict) -> tuple[str, bool, list[dict]]:
    """(material kind, has bump map, textures) of a generated BSDF dict."""
    bump = False
    found: list[dict] = []
    while bsdf["type"] in ("twosided", "bumpmap"):
        if bsdf["type"] == "bumpmap":
            bump = True
        bsdf = bsdf["bsdf"]
    for value in bsdf.values():
        if isinstance(value, dict) and value.get("type") == "bitmap":
            found.append(value)
    return bsdf["type"], bump, found


def scene_summary(scene: dict) -> dict[str, Any]:
    """Counts of what a generated scene dict contains (for tests, logs and dataset manifests).

    Returns a dict with Counters ``shapes`` (object shape kinds, caps not counted),
    ``materials`` (BSDF kinds of objects, ground and walls), ``lights`` (LIGHT_KINDS) and ints
    ``textures`` (bitmap textures in materials), ``bump_maps``, ``walls``.
    """
    shapes: Counter = Counter()
    materials: Counter = Counter()
    lights: Counter = Counter()
    texture_count = bump_count = walls = 0
    for key, value in scene.items():
        if not isinstance(value, dict):
            continue
        if key == "environment":
            lights[value["type"]] += 1
        elif key.startswith("light_"):
            lights[f"area_{value['type']}"] += 1
        elif key == "ground" or key.startswith(("wall_", "object_")):
            if key.startswith("wall_"):
                walls += 1
            if key.startswith("object_") and "_cap" not in key:
                shapes[value["type"]] += 1
            if "_cap" in key:
                continue
            kind, bump, found = _unwrap_bsdf(value["bsdf"])
            materials[kind] += 1
            bump_count += int(bump)
            texture_count += len(found)
    return {
        "shapes": shapes,
        "materials": materials,
        "lights": lights,
        "textures": texture_count,
        "bump_maps": bump_count,
        "walls": walls,
    }
