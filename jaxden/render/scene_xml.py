"""Mitsuba scene XML, read the way Mitsuba reads it: includes, defaults, parameters, paths.

Published scene collections keep the camera in a shared file (``<include
filename="include/camera.xml"/>``), set parameters with ``<default name="spp" value="64"/>``
and use them as ``$spp``, and add resource folders with ``<path value="textures"/>``. jaxden
must patch the sensor (box filter, independent sampler, film size) wherever it is defined, so
it cannot hand the file to Mitsuba unread: :func:`flatten_scene` resolves all of that into one
``<scene>`` element, following Mitsuba 3's parser (``src/core/xml.cpp``):

- ``$name`` in any attribute value is replaced by the parameter's value. Parameters come from
  the caller (``jaxden render -D name=value``, Mitsuba's ``-D``) and from ``<default>``
  elements, which set a parameter only when it is not set yet, in document order (includes
  included). A ``$name`` that is still undefined where it is used is an error, and so is a
  caller's parameter that the scene never declares or uses (Mitsuba: "Unused parameter").
- ``<path value="DIR"/>``: a relative DIR is taken relative to the folder of the file that
  holds it, else looked up on the search path; it must exist, and is put first on the search
  path (Mitsuba's file resolver).
- ``<include filename="F"/>``: F is looked up on the search path (an absolute F as it is);
  the included file's ``<scene>`` children take the include's place (a file whose root is
  not ``<scene>`` stands for that one element). A missing file, an include cycle and more
  than :data:`MAX_INCLUDE_DEPTH` nested includes are errors.

The search path starts with the folder of the scene file (Mitsuba prepends it when it loads a
file); resources (meshes, textures) are found on the same search path when the flattened
scene is loaded (:mod:`jaxden.render.load`). Errors are :class:`jaxden.errors.SceneError`
with one line naming the file and the element.
"""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from jaxden.errors import SceneError

MAX_INCLUDE_DEPTH = 15  # Mitsuba's MI_XML_INCLUDE_MAX_RECURSION
_NAME = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")
_PARAMETER_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclass
class FlatScene:
    """A scene file with its includes inlined and its parameters substituted.

    ``root``: the ``<scene>`` element (no ``<include>``, ``<default>`` or ``<path>`` left);
    ``search_path``: resource folders, first searched first; ``parameters``: every parameter
    with its value; ``files``: every file read, the scene file first.
    """

    path: Path
    root: ET.Element
    search_path: list[Path]
    parameters: dict[str, str]
    files: list[Path] = field(default_factory=list)


def parse_parameters(definitions) -> dict[str, str]:
    """``["name=value", ...]`` (``-D`` options) -> ``{name: value}``; SceneError on a bad one."""
    parameters: dict[str, str] = {}
    for definition in definitions or ():
        name, equals, value = str(definition).partition("=")
        name = name.strip()
        if not equals or not _PARAMETER_NAME.match(name):
            raise SceneError(f"-D {definition!r}: expected NAME=VALUE with NAME a parameter name "
                             f"(letters, digits, _)")
        if name in parameters and parameters[name] != value:
            raise SceneError(f"-D {name}: given twice ({parameters[name]!r} and {value!r})")
        parameters[name] = value
    return parameters


def _where(path: Path, element: ET.Element) -> str:
    name = element.get("name") or element.get("id") or element.get("filename") or ""
    return f"{path}: <{element.tag}{' ' + repr(name) if name else ''}>"


def _resolve(name: str, search_path: list[Path]) -> Path | None:
    candidate = Path(os.path.expanduser(name))
    if candidate.is_absolute():
        return candidate if candidate.exists() else None
    for folder in search_path:
        if (folder / candidate).exists():
            return (folder / candidate).resolve()
    return None


class _Flattener:
    def __init__(self, parameters: Mapping[str, str]):
        self.parameters = dict(parameters)
        self.given = set(self.parameters)
        self.used: set[str] = set()
        self.search_path: list[Path] = []
        self.files: list[Path] = []

    def substitute(self, element: ET.Element, path: Path, lenient: bool = False) -> None:
        """``lenient``: inside a <sampler>, which jaxden replaces, an undefined name stays."""
        for key, value in element.attrib.items():
            if "$" not in value:
                continue

            def replace(match):
                name = match.group(1)
                # Mitsuba replaces the longest defined name first ($spp2 before $spp).
                for length in range(len(name), 0, -1):
                    if name[:length] in self.parameters:
                        self.used.add(name[:length])
                        return self.parameters[name[:length]] + name[length:]
                if lenient:
                    return match.group(0)
                raise SceneError(
                    f"{_where(path, element)}: {key}={value!r} uses ${name}, which is not "
                    f"defined (no <default name={name!r}> and no -D {name}=...)"
                )

            element.set(key, _NAME.sub(replace, value))

    def children(self, parent: ET.Element, path: Path, stack: list[Path],
                 lenient: bool = False) -> list[ET.Element]:
        """The flattened children of ``parent`` (of file ``path``), in order."""
        out: list[ET.Element] = []
        for child in list(parent):
            if not isinstance(child.tag, str):  # comments, processing instructions
                continue
            inner = lenient or child.tag == "sampler"
            self.substitute(child, path, inner)
            if child.tag == "default":
                name, value = child.get("name"), child.get("value")
                if not name or value is None:
                    raise SceneError(f"{_where(path, child)}: needs name and value")
                self.parameters.setdefault(name, value)
                if name in self.given:
                    self.used.add(name)
            elif child.tag == "path":
                self.add_path(child, path)
            elif child.tag == "include":
                out.extend(self.include(child, path, stack))
            else:
                _check_finite(child, path)
                kept = ET.Element(child.tag, dict(child.attrib))
                kept.text, kept.tail = child.text, child.tail
                kept.extend(self.children(child, path, stack, inner))
                out.append(kept)
        return out

    def add_path(self, element: ET.Element, path: Path) -> None:
        value = element.get("value")
        if not value:
            raise SceneError(f"{_where(path, element)}: needs a value (a folder)")
        folder = Path(os.path.expanduser(value))
        if not folder.is_absolute():
            local = path.parent / folder
            folder = local if local.is_dir() else (_resolve(value, self.search_path) or local)
        if not folder.is_dir():
            raise SceneError(f"{_where(path, element)}: folder {value!r} not found (looked in "
                             f"{path.parent} and on the search path)")
        self.search_path.insert(0, folder.resolve())

    def include(self, element: ET.Element, path: Path, stack: list[Path]) -> list[ET.Element]:
        name = element.get("filename")
        if not name:
            raise SceneError(f"{_where(path, element)}: needs a filename")
        target = _resolve(name, self.search_path)
        if target is None or not target.is_file():
            searched = ", ".join(str(p) for p in self.search_path)
            raise SceneError(f"{_where(path, element)}: included file {name!r} not found "
                             f"(searched {searched})")
        if target in stack:
            chain = " -> ".join(p.name for p in [*stack, target])
            raise SceneError(f"{path}: <include {name!r}> makes a cycle of includes: {chain}")
        if len(stack) > MAX_INCLUDE_DEPTH:
            raise SceneError(f"{path}: more than {MAX_INCLUDE_DEPTH} nested <include>s")
        root = _parse(target)
        self.files.append(target)
        if root.tag == "scene":
            return self.children(root, target, [*stack, target])
        return self.children(_wrap(root), target, [*stack, target])


#: Elements whose numbers place geometry: a NaN or inf there makes Mitsuba drop the shape
#: (or the camera) without a word, so it is refused here.
_GEOMETRY_TAGS = frozenset({"scale", "translate", "rotate", "matrix", "lookat", "point",
                            "vector"})


def _check_finite(element: ET.Element, path: Path) -> None:
    if element.tag not in _GEOMETRY_TAGS:
        return
    for key, value in element.attrib.items():
        if key in ("name", "id", "type"):
            continue
        for token in re.split(r"[\s,]+", value.strip()):
            try:
                number = float(token)
            except ValueError:
                continue
            if not math.isfinite(number):
                raise SceneError(f"{_where(path, element)}: <{element.tag} {key}={value!r}> is "
                                 f"not a finite number; Mitsuba would drop what it places")


def _wrap(element: ET.Element) -> ET.Element:
    holder = ET.Element("holder")
    holder.append(element)
    return holder


def _parse(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as error:
        raise SceneError(f"{path}: invalid XML: {error}") from None
    except OSError as error:
        raise SceneError(f"{path}: cannot read the scene file: {error.strerror or error}") from None


def flatten_scene(path, parameters: Mapping[str, str] | None = None) -> FlatScene:
    """Read the scene file ``path`` with its includes, defaults, ``$`` parameters and paths.

    ``parameters``: ``{name: value}`` given by the caller (they win over ``<default>``).
    Returns a :class:`FlatScene`; raises SceneError (one line) for a missing or invalid file,
    a missing include, a cycle of includes, an undefined ``$name`` and an unused parameter.
    """
    path = Path(os.fspath(path))
    if not path.is_file():
        raise SceneError(f"scene file {path} does not exist" if not path.exists()
                         else f"scene path {path} is not a file")
    root = _parse(path)
    if root.tag != "scene":
        raise SceneError(f"{path}: the root element must be <scene>, got <{root.tag}>")
    flattener = _Flattener(parameters or {})
    flattener.search_path = [path.resolve().parent]
    flattener.files = [path.resolve()]
    flattener.substitute(root, path)
    flat = ET.Element("scene", dict(root.attrib))
    flat.text = root.text
    flat.extend(flattener.children(root, path, [path.resolve()]))
    unused = sorted(flattener.given - flattener.used)
    if unused:
        raise SceneError(f"{path}: parameter(s) {', '.join(unused)} given (-D) but the scene "
                         f"neither declares nor uses them")
    return FlatScene(path=path, root=flat, search_path=flattener.search_path,
                     parameters=flattener.parameters, files=flattener.files)
