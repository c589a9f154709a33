"""What a denoiser computes, as a hash: the key that derived data (SURE caches, results) carry
so that a change of the denoiser's code recomputes instead of reusing the old code's output.

Two denoisers with the same name, config and weights but different code must never share a
SURE cache. :func:`code_sha256` hashes:

- for a differentiable JAX denoiser, its lowered computation (the StableHLO text of
  ``apply(params, config, frame)`` traced on a small frame of the fields it reads, with the
  parameters abstract): any change that changes what it computes changes the hash, while
  comments, docstrings, names and line numbers do not; the JAX version is part of it,
  since lowering may differ between versions;
- for a black box (NumPy in, NumPy out), the code of the module that defines its ``apply``
  (every module of a plugin package) as a syntax tree without docstrings and comments, and
  the versions of the libraries it calls (pyoidn for OIDN).

The hash is computed once per (definition, config) and process.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

#: Side of the square frame the computation is traced on (a multiple of every model's
#: pooling grid).
PROBE_SIDE = 64


def _probe_frame(fields: tuple[str, ...], side: int):
    from jaxden.frame import CHANNELS, Frame

    arrays = {}
    for name in ("color", "variance", *fields):
        if name in arrays or name not in CHANNELS:
            continue
        channels = len(CHANNELS[name])
        arrays[name] = jax.ShapeDtypeStruct((side, side, channels), jnp.float32)
    return Frame(**arrays, spp=jax.ShapeDtypeStruct((), jnp.float32))


def _lowered_text(definition, config, params, side: int) -> str:
    """StableHLO of ``apply`` on a ``side`` x ``side`` frame; ``params`` abstract."""
    fields = tuple(dict.fromkeys((*definition.required(config),
                                  *(definition.optional(config) if definition.optional
                                    else ()))))
    frame = _probe_frame(fields, side)
    lowered = jax.jit(lambda p, f: definition.apply(p, config, f)).lower(params, frame)
    return lowered.as_text()


def code_text_sha256(source: str) -> str:
    """sha256 of Python source as code: its syntax tree without docstrings, comments, layout
    or line numbers (so editing documentation does not move what is keyed by it)."""
    import ast

    try:
        tree = ast.parse(source)
    except SyntaxError:
        return hashlib.sha256(source.encode()).hexdigest()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and \
                isinstance(getattr(body[0], "value", None), ast.Constant) and \
                isinstance(body[0].value.value, str):
            node.body = body[1:] or [ast.Pass()]
    return hashlib.sha256(ast.dump(tree).encode()).hexdigest()


def _module_source_sha256(function) -> str:
    """:func:`code_text_sha256` of the module that defines ``function`` (every module of a
    plugin package), or of the function alone when its module has no source."""
    import sys

    function = inspect.unwrap(function)
    module = inspect.getmodule(function)
    package = None if module is None else sys.modules.get(module.__name__.partition(".")[0])
    if package is not None and package.__name__ != "jaxden" and \
            getattr(package, "__path__", None):
        digest = hashlib.sha256()
        for root in package.__path__:
            for path in sorted(Path(root).rglob("*.py")):
                digest.update(str(path.relative_to(root)).encode())
                digest.update(code_text_sha256(path.read_text()).encode())
        return digest.hexdigest()
    try:
        source = inspect.getsource(module if module is not None else function)
    except (OSError, TypeError):
        return hashlib.sha256(repr(function).encode()).hexdigest()
    return code_text_sha256(source)


@functools.lru_cache(maxsize=128)
def _cached(definition, config, params_shapes, kind: str) -> str:
    digest = hashlib.sha256()
    digest.update(f"jax {jax.__version__}\n".encode())
    if kind == "lowered":
        params = jax.tree_util.tree_unflatten(params_shapes[0], [
            jax.ShapeDtypeStruct(shape, np.dtype(dtype)) for shape, dtype in params_shapes[1]])
        digest.update(_lowered_text(definition, config, params, PROBE_SIDE).encode())
    else:
        from jaxden.provenance import package_version

        digest.update(_module_source_sha256(definition.apply).encode())
        for name in ("pyoidn",):
            digest.update(f"{name} {package_version(name)}\n".encode())
    return digest.hexdigest()


def code_sha256(denoiser) -> str:
    """The sha256 of what ``denoiser`` (a :class:`jaxden.denoise.Denoiser`) computes: its
    lowered computation (JAX denoisers) or its module's source (black boxes); see the module
    docstring. Falls back to the source when the computation cannot be traced on a small
    frame."""
    definition, config = denoiser.definition, denoiser.config
    leaves, tree = jax.tree_util.tree_flatten(denoiser.params)
    shapes = (tree, tuple((tuple(np.shape(leaf)), str(np.asarray(leaf).dtype))
                          for leaf in leaves))
    if definition.differentiable:
        with contextlib.suppress(Exception):  # a model that cannot trace on the probe frame
            return _cached(definition, config, shapes, "lowered")
    return _cached(definition, config, shapes, "source")


def source_file(denoiser) -> str | None:
    """The file that defines the denoiser's ``apply`` (for messages and provenance)."""
    try:
        file = inspect.getsourcefile(denoiser.definition.apply)
    except TypeError:
        return None
    return None if file is None else str(Path(file))
