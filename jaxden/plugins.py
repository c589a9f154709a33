"""Plugins: outside modules that fill jaxden's registries, imported before any name resolves.

A plugin is an ordinary Python module (a file ``my_filter.py`` or an installed package) that
registers what it brings at import time: a denoiser (:func:`jaxden.denoise.register`, or
:meth:`jaxden.denoise.Denoiser.from_function`), a trainable model, a mixer, a loss, an
evaluator. jaxden imports it, in every process it starts, when it is named by any of:

- ``--plugin MODULE`` on any ``jaxden`` command (repeatable);
- ``JAXDEN_PLUGINS=mod_a,mod_b`` in the environment (comma- or ``os.pathsep``-separated);
- ``plugins = ["mod_a"]`` at the top of a train or sweep config;
- the entry-point group ``jaxden.plugins`` of an installed package
  (``[project.entry-points."jaxden.plugins"] mine = "my_package.jaxden_plugin"``).

``MODULE`` is a module name importable from the current folder or ``sys.path``
(``my_filter``, ``lab.denoisers``), or the path of a ``.py`` file (``~/src/my_filter.py``,
imported as module ``my_filter``). Every module loaded is written back into
``JAXDEN_PLUGINS`` (files as absolute paths), so processes that jaxden spawns (the local
executor's workers, ``jax.distributed`` processes) import the same modules; Ray tasks carry
the list and, for single-file plugins, the source itself (:func:`worker_payload`), so a node
without the file still imports the same code.

A module that fails to import is one line (:class:`PluginError`: which module, named where,
the error and the plugin's own file and line); a name that clashes with a built-in or with
another plugin's is one line (:class:`jaxden.registry.PluginClashError`).

What a plugin contributes is recorded: results' provenance lists every loaded plugin (module
name and the sha256 of its source, :func:`provenance`), and SURE caches are keyed by the
denoiser's own code (:func:`jaxden.denoise.identity.code_identity`), so a changed plugin never
reuses what its old code computed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import importlib.util
import os
import re
import sys
import traceback
from collections.abc import Iterable
from pathlib import Path

from jaxden.errors import ConfigError

#: The environment variable naming plugins (and, once loaded, every plugin this process has).
ENV = "JAXDEN_PLUGINS"
#: The entry-point group of installed packages' plugins.
ENTRY_POINT_GROUP = "jaxden.plugins"


class PluginError(ConfigError):
    """A plugin module cannot be found or fails to import."""


@dataclasses.dataclass(frozen=True)
class Plugin:
    """A loaded plugin: ``spec`` as it was named, ``module`` its ``__name__``, ``file`` its
    source file (None for a namespace package), ``sha256`` of its source (every ``.py`` file
    of a package), ``origin`` where it was named (``--plugin``, ``JAXDEN_PLUGINS``, a config
    file, an entry point)."""

    spec: str
    module: str
    file: str | None
    sha256: str
    origin: str

    def record(self) -> dict:
        """What provenance records of it."""
        return {"module": self.module, "sha256": self.sha256, "file": self.file}


_LOADED: dict[str, Plugin] = {}  # module name -> Plugin
_ENTRY_POINTS_DONE = False


# ----------------------------------------------------------------------------------- naming
def split_specs(text: str | None) -> list[str]:
    """The plugin specs of a ``JAXDEN_PLUGINS`` value (comma- or ``os.pathsep``-separated)."""
    if not text:
        return []
    return [part.strip() for part in re.split(f"[,{re.escape(os.pathsep)}]", text)
            if part.strip()]


def _is_file_spec(spec: str) -> bool:
    return spec.endswith(".py") or os.sep in spec or (os.altsep or "\0") in spec


def source_sha256(module) -> tuple[str | None, str]:
    """``(file, sha256)`` of a module's source: its file's bytes, or for a package every
    ``.py`` file under it (sorted by relative path, each path hashed with its bytes)."""
    file = getattr(module, "__file__", None)
    digest = hashlib.sha256()
    paths = list(getattr(module, "__path__", []) or [])
    if paths:
        for root in paths:
            for path in sorted(Path(root).rglob("*.py")):
                digest.update(str(path.relative_to(root)).encode())
                digest.update(path.read_bytes())
    elif file and Path(file).is_file():
        digest.update(Path(file).read_bytes())
    else:
        digest.update(repr(module).encode())
    return file, digest.hexdigest()


def _failure(spec: str, origin: str, error: BaseException) -> PluginError:
    """One line: the plugin, where it was named, the error, and the last frame of the
    traceback inside the plugin's own code (file and line), when there is one."""
    where = ""
    frames = traceback.extract_tb(error.__traceback__)
    own = [f for f in frames if "importlib" not in f.filename and
           not f.filename.endswith(("jaxden/plugins.py",))]
    if isinstance(error, SyntaxError) and error.filename:
        where = f" ({error.filename}, line {error.lineno})"
    elif own:
        where = f" ({own[-1].filename}, line {own[-1].lineno})"
    message = str(error).strip().splitlines()[0] if str(error).strip() else ""
    what = f"{type(error).__name__}: {message}" if message else type(error).__name__
    return PluginError(f"plugin {spec!r} (from {origin}) failed to import: {what}{where}")


def _import_file(spec: str, origin: str):
    path = Path(spec).expanduser()
    if not path.is_file():
        raise PluginError(f"plugin {spec!r} (from {origin}): no such file")
    name = path.stem
    if not name.isidentifier():
        raise PluginError(f"plugin {spec!r} (from {origin}): the file name must be a Python "
                          f"module name (letters, digits, _), got {name!r}")
    resolved = path.resolve()
    existing = sys.modules.get(name)
    if existing is not None:
        if Path(getattr(existing, "__file__", "") or "").resolve() == resolved:
            return existing
        raise PluginError(f"plugin {spec!r} (from {origin}): module name {name!r} is taken by "
                          f"{getattr(existing, '__file__', None) or 'a built-in module'}; "
                          f"rename the file")
    return _exec_module(name, importlib.util.spec_from_file_location(name, resolved), spec,
                        origin)


def _exec_module(name, module_spec, spec, origin, source: str | None = None):
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module
    try:
        if source is None:
            module_spec.loader.exec_module(module)
        else:
            exec(compile(source, module_spec.origin or name, "exec"), module.__dict__)  # noqa: S102 - the user's own plugin, carried to a worker
    except BaseException as error:
        sys.modules.pop(name, None)
        if isinstance(error, (KeyboardInterrupt, SystemExit)):
            raise
        if isinstance(error, ConfigError) and not isinstance(error, PluginError):
            raise  # a name clash or a bad registration: already one line naming the module
        raise _failure(spec, origin, error) from None
    return module


def _import_name(spec: str, origin: str):
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as error:
        top = spec.split(".")[0]
        if error.name not in (spec, top) and not spec.startswith(f"{error.name}."):
            raise _failure(spec, origin, error) from None  # the plugin's own import failed
        here = os.getcwd()
        if here in sys.path or not (Path(here) / f"{top}.py").exists() and not (
                Path(here) / top).is_dir():
            raise PluginError(
                f"plugin {spec!r} (from {origin}): no module named {spec!r} (not on sys.path "
                f"nor in {here}); give the path of its .py file or install it") from None
        sys.path.insert(0, here)  # as `python -m` would: the user's own folder
        return _import_name(spec, origin)
    except (KeyboardInterrupt, SystemExit, ConfigError):
        raise  # a ConfigError (a clash, a bad registration) is already its own one line
    except BaseException as error:  # noqa: BLE001 - any failure of the user's code
        raise _failure(spec, origin, error) from None


# ---------------------------------------------------------------------------------- loading
def load(specs: Iterable[str], origin: str = "--plugin") -> list[Plugin]:
    """Import the plugins ``specs`` names (module names or ``.py`` paths), once each, and
    record them; returns their :class:`Plugin` records. ``origin``: where they were named
    (for messages and provenance)."""
    out = []
    for spec in specs:
        spec = str(spec).strip()
        if not spec:
            continue
        module = _import_file(spec, origin) if _is_file_spec(spec) else _import_name(spec, origin)
        out.append(_remember(spec, module, origin))
    _export_env()
    return out


def _remember(spec: str, module, origin: str) -> Plugin:
    name = module.__name__
    if name in _LOADED:
        return _LOADED[name]
    file, digest = source_sha256(module)
    plugin = Plugin(spec=spec, module=name, file=file, sha256=digest, origin=origin)
    _LOADED[name] = plugin
    return plugin


def _export_env() -> None:
    """``JAXDEN_PLUGINS`` = every loaded plugin (files by absolute path), for child
    processes."""
    specs = [p.file if p.file and _is_file_spec(p.spec) else p.module for p in _LOADED.values()
             if not (p.file and _is_file_spec(p.spec)) or Path(p.file).is_file()]
    current = split_specs(os.environ.get(ENV))
    merged = list(dict.fromkeys([*current, *specs]))
    if merged:
        os.environ[ENV] = ",".join(merged)
    # a module found in the current folder: children may start elsewhere (Ray), so its folder
    # travels on PYTHONPATH too
    folders = {str(Path(p.file).parent) for p in _LOADED.values()
               if p.file and not _is_file_spec(p.spec) and "." not in p.module}
    if folders:
        path = [f for f in os.environ.get("PYTHONPATH", "").split(os.pathsep) if f]
        os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys([*path, *sorted(folders)]))


def entry_point_specs() -> list[tuple[str, object]]:
    """``(name, entry point)`` of the installed ``jaxden.plugins`` entry points."""
    from importlib.metadata import entry_points

    return [(ep.name, ep) for ep in entry_points(group=ENTRY_POINT_GROUP)]


def load_entry_points() -> list[Plugin]:
    """Import every installed package's ``jaxden.plugins`` entry point (a module, or a
    ``module:function`` that is called with no arguments)."""
    out = []
    for name, ep in entry_point_specs():
        origin = f"entry point {name!r} of group {ENTRY_POINT_GROUP}"
        try:
            target = ep.load()
        except ConfigError:
            raise
        except Exception as error:  # noqa: BLE001
            raise _failure(ep.value, origin, error) from None
        if callable(target) and not isinstance(target, type(sys)):
            target()
        module = sys.modules[ep.value.partition(":")[0]]
        out.append(_remember(ep.value, module, origin))
    return out


def load_ambient() -> None:
    """The plugins ``JAXDEN_PLUGINS`` names (those not imported yet) and, once per process,
    the installed entry points. Every registry lookup of a missing name calls this, so a
    spawned worker that only calls library functions resolves a plugin's names too."""
    global _ENTRY_POINTS_DONE
    load(split_specs(os.environ.get(ENV)), origin=ENV)
    if not _ENTRY_POINTS_DONE:
        load_entry_points()
        _ENTRY_POINTS_DONE = True


def load_all(specs: Iterable[str] = (), origin: str = "--plugin") -> list[Plugin]:
    """:func:`load_ambient`, then ``specs``: what a command does before parsing names."""
    load_ambient()
    load(specs, origin)
    return loaded()


def loaded() -> list[Plugin]:
    """Every plugin this process imported, in load order."""
    return list(_LOADED.values())


def provenance() -> list[dict]:
    """What a result records of the plugins: module name, sha256 of its source, file."""
    return [plugin.record() for plugin in _LOADED.values()]


# ---------------------------------------------------------------------------- other workers
def worker_payload() -> list[tuple[str, str, str | None]]:
    """``(spec, module name, source or None)`` of each loaded plugin, for a worker on another
    machine: single-file plugins carry their source, so a node without the file imports the
    same code; packages must be installed there."""
    out = []
    for plugin in _LOADED.values():
        source = None
        if plugin.file and Path(plugin.file).is_file() and \
                Path(plugin.file).name != "__init__.py":
            source = Path(plugin.file).read_text()
        spec = plugin.file if plugin.file and _is_file_spec(plugin.spec) else plugin.module
        out.append((spec, plugin.module, source))
    return out


def load_payload(payload: Iterable[tuple[str, str, str | None]]) -> None:
    """In a worker: import each plugin of :func:`worker_payload` that is not imported yet,
    from its file or module name when this machine has it, else from the carried source."""
    load_ambient()
    for spec, name, source in payload:
        if name in _LOADED or name in sys.modules:
            continue
        try:
            load([spec], origin="the calling process")
            continue
        except PluginError:
            if source is None:
                raise
        module_spec = importlib.util.spec_from_loader(name, loader=None, origin=spec)
        module = _exec_module(name, module_spec, spec, "the calling process", source)
        module.__file__ = spec
        _LOADED[name] = Plugin(spec, name, spec, hashlib.sha256(source.encode()).hexdigest(),
                               "the calling process")


# --------------------------------------------------------------------------- command lines
def take_plugin_options(argv: list[str]) -> tuple[list[str], list[str]]:
    """``(plugin specs, argv without them)``: ``--plugin X`` and ``--plugin=X`` anywhere in a
    command line (they must be imported before the parser is built, since commands list
    registered names)."""
    specs, rest = [], []
    words = iter(argv)
    for word in words:
        if word == "--":
            rest.append(word)
            rest.extend(words)
            break
        if word == "--plugin":
            value = next(words, None)
            if value is None or value.startswith("-"):
                raise PluginError("--plugin needs a module name or a .py file")
            specs.append(value)
        elif word.startswith("--plugin="):
            specs.append(word.partition("=")[2])
        else:
            rest.append(word)
    return specs, rest


def load_config_plugins(data: dict, where: str) -> list[Plugin]:
    """Import the plugins a config file's top-level ``plugins = [...]`` names (relative file
    paths are relative to the config's folder); ConfigError for a malformed list."""
    names = data.get("plugins", [])
    if names is None:
        return []
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise ConfigError(f"{where}: plugins must be a list of module names or .py paths, "
                          f"got {names!r}")
    base = Path(where).parent if where else Path(".")
    specs = [str((base / n).resolve()) if _is_file_spec(n) and not Path(n).is_absolute()
             else n for n in names]
    load_ambient()
    return load(specs, origin=str(where))
