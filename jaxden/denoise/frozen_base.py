"""A frozen base denoiser inside a trained combiner (the Deep Combiner ``dc``, the neural
James-Stein combiner ``njs``): loaded once per process and per version of the file it names,
and identified by a digest of what it computes with, so that a combiner's weights are never run
over another base than the one they were trained over.

``base_sha256`` is recorded in the combiner's config when it is trained; loading the run
later compares it with the base its spec loads now (:func:`check_base`), and a difference is
a :class:`BaseMismatchError` (a ConfigError, which a checkpoint load reports in one line).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from pathlib import Path

from jaxden.denoise.registry import Denoiser, load_denoiser
from jaxden.errors import ConfigError, JaxdenError


class BaseMismatchError(ConfigError):
    """A combiner's recorded base digest differs from the base its config names now."""


def base_sha256(base: Denoiser) -> str:
    """Digest of what a base computes with: its definition's name, its config and its
    weights (paths, dtypes, shapes, bytes; ``None`` for a denoiser without parameters)."""
    from jaxden.config import config_to_dict
    from jaxden.data.item_cache import hash_params

    digest = hashlib.sha256()
    config = (config_to_dict(base.config) if dataclasses.is_dataclass(base.config)
              else repr(base.config))
    digest.update(json.dumps([base.name, config], sort_keys=True, default=str).encode())
    if base.params is not None:
        hash_params(digest, base.params)
    return digest.hexdigest()


def _version(spec: str):
    """What changes when the file or folder a spec names changes (None: a plain name)."""
    from jaxden.denoise.registry import split_spec
    from jaxden.paths import resolve_weights

    path = resolve_weights(split_spec(spec)[0])
    if path is None:
        return None
    stat = Path(path).stat()
    return str(Path(path).resolve()), stat.st_mtime_ns, stat.st_size


@functools.lru_cache(maxsize=8)
def _read(spec: str, version, owner: str) -> tuple[Denoiser, str]:
    try:
        base = load_denoiser(spec)
    except JaxdenError as error:
        raise ConfigError(f"{owner}: base {spec!r} does not load: {error}") from None
    return base, base_sha256(base)


def load_base(spec: str, owner: str) -> tuple[Denoiser, str]:
    """``(base, base_sha256(base))`` for a base spec, read once per process and per version
    of the file it names (a retrained or replaced file is read again). ConfigError naming
    ``owner`` (the combiner) when it does not load."""
    return _read(spec, _version(spec), owner)


def check_base(spec: str, recorded: str, owner: str, combiner: str) -> Denoiser:
    """The base ``spec`` loads now, refused (:class:`BaseMismatchError`, naming ``owner``
    and what to do) unless its digest is ``recorded``; ``combiner``: the model's words for
    itself in that message (e.g. "a Deep Combiner")."""
    base, current = load_base(spec, owner)
    if current != recorded:
        raise mismatch_error(spec, recorded, current, owner, combiner)
    return base


def mismatch_error(spec: str, recorded: str, current: str, owner: str,
                   combiner: str) -> BaseMismatchError:
    """The :class:`BaseMismatchError` of :func:`check_base`."""
    return BaseMismatchError(
        f"{owner}: this combiner was trained over base {spec!r} with base_sha256 "
        f"{recorded[:16]}..., but {spec!r} now loads other weights or config (base_sha256 "
        f"{current[:16]}...); its weights fit only the base it was trained with: restore "
        f"that base, or train {combiner} over this one")
