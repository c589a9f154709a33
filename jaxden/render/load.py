"""load_scene: from a scene spec (built-in name, ``procedural:SEED``, a Mitsuba XML path or a
scene dict) to a Mitsuba scene with jaxden's render overrides (box pixel filter, independent
sampler, film size) applied wherever the sensor is defined, and the sensor source kept for
crops and camera paths.
"""

from __future__ import annotations

import collections
import copy
import math
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.errors import SceneError
from jaxden.render.scene_xml import flatten_scene
from jaxden.render.scenes import (
    ALL_SENSOR_PLUGINS,
    BUILTIN_SCENES,
    DEFAULT_SIZE,
    PROCEDURAL_SPEC,
    SCENE_MEMORY,
    SENSOR_TYPES,
    check_size,
)
from jaxden.render.variant import ensure_variant


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
        if isinstance(value, dict) and value.get("type") in ALL_SENSOR_PLUGINS:
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
    match = PROCEDURAL_SPEC.match(spec)
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
    """Context: put folders first on Mitsuba's file resolver (the first one first), restore
    the resolver after."""

    def __init__(self, folders):
        self.folders = [Path(f) for f in folders]

    def __enter__(self):
        import mitsuba as mi

        self.resolver = mi.file_resolver()
        self.saved = [str(self.resolver[i]) for i in range(len(self.resolver))]
        for folder in reversed(self.folders):
            self.resolver.prepend(str(folder))
        return self

    def __exit__(self, *exc):
        self.resolver.clear()
        for entry in self.saved:
            self.resolver.append(entry)
        return False


@dataclass
class _XmlScene:
    path: Path
    text: str  # the flattened, patched scene XML
    sensor_xml: str  # a scene holding only the first (patched) sensor
    size: tuple[int, int] | None
    search_path: tuple[Path, ...] = ()  # resource folders (jaxden.render.scene_xml)


def _prepare_xml(path, size, parameters=None) -> _XmlScene:
    """Flatten the scene file (includes, defaults, $parameters, paths) and patch every
    top-level sensor, wherever it was defined."""
    flat = flatten_scene(path, parameters)
    root = flat.root
    sensors = root.findall("sensor")
    if not sensors:
        raise SceneError(f"{flat.path}: the scene has no <sensor> (camera) at its top level "
                         f"(also after following its <include>s)")
    for index, sensor in enumerate(sensors):
        if size is None:  # the film's own size gets the same guard as --size
            film = {e.get("name"): e.get("value") for e in sensor.findall("film/integer")}
            try:
                own = (int(film.get("width", 768)), int(film.get("height", 576)))
            except ValueError:
                raise SceneError(f"{flat.path}: sensor {index}: film width/height must be "
                                 f"integers, got {film.get('width')!r} x {film.get('height')!r}")\
                    from None
            check_size(own, f"{flat.path}: sensor {index} film")
        _patch_xml_sensor(sensor, size, f"{flat.path}: sensor {index}")
    sensor_root = ET.Element("scene", dict(root.attrib))
    sensor_root.append(copy.deepcopy(sensors[0]))
    return _XmlScene(path=flat.path, text=ET.tostring(root, encoding="unicode"),
                     sensor_xml=ET.tostring(sensor_root, encoding="unicode"), size=size,
                     search_path=tuple(flat.search_path))


def _load_xml_string(text: str, xml: _XmlScene, what: str):
    import mitsuba as mi

    with _FileResolverDir(xml.search_path or (xml.path.resolve().parent,)):
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
    for every new crop position. Both give the same rays (tested to float round-off);
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


# The SensorSource of each recent scene, keyed by the id of the scene's first sensor and holding
# that sensor: never the scene. Mitsuba scenes take neither attributes nor weak references, and
# holding scenes alive is costly: every live BSDF, shape and emitter of the variant sits in
# Dr.Jit's instance registry, and each symbolic virtual call traces and compiles the code of all
# of them (measured: docs/results.md, "Data"). A held sensor (film, sampler) is not dispatched
# to, and holding it keeps its id from being reused, so ``scene.sensors()[0] is entry[0]``
# identifies the scene exactly.
_loaded: collections.OrderedDict[int, tuple[Any, SensorSource]] = collections.OrderedDict()


def _remember(scene, source: SensorSource) -> None:
    sensor = scene.sensors()[0]
    _loaded[id(sensor)] = (sensor, source)
    _loaded.move_to_end(id(sensor))
    while len(_loaded) > SCENE_MEMORY:
        _loaded.popitem(last=False)


def sensor_source(scene) -> SensorSource | None:
    """The SensorSource of a scene returned by load_scene (the SCENE_MEMORY most recent)."""
    sensors = scene.sensors()
    if not sensors:
        return None
    entry = _loaded.get(id(sensors[0]))
    if entry is not None and entry[0] is sensors[0]:
        _loaded.move_to_end(id(sensors[0]))
        return entry[1]
    return None


def _spec_name(spec) -> str:
    if isinstance(spec, dict):
        return "scene dict"
    return f"scene {os.fspath(spec)!r}" if isinstance(spec, (str, os.PathLike)) else repr(spec)


def load_scene(spec, size: tuple[int, int] | None = None, parameters=None):
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
    if parameters and not _is_path_like(spec):
        raise SceneError(f"{_spec_name(spec)}: parameters (-D) apply to XML scene files only")
    if _is_path_like(spec):
        xml = _prepare_xml(spec, size, parameters)
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
