"""SURE cache: the denoised image and its SURE map for every input item of a dataset.

The progressive-denoising mixer is trained on (noisy x, variance, denoised y, SURE of y). The
denoiser is fixed while the mixer trains, so y and SURE are computed once per dataset item by
:func:`build_sure_cache` and read back by :class:`SureCache` (the authors' pipeline does the
same: an inference pass writes the denoised image and its SURE, then PDNet trains on them).

Layout (default folder ``DATASET/derived/<denoiser>``, see :func:`default_cache_dir`)::

    CACHE/sure-cache.json                        identity, settings, per-item checksums
    CACHE/s000-cornell-box/c000/spp00002.exr     one EXR per input item, same relative path

Each item EXR holds, float32 (or half with ``half=True``), all (H, W) of the dataset crop:

    R, G, B                    y, the denoised image (linear radiance; what a viewer shows)
    sure.R, sure.G, sure.B     per-pixel SURE of y (radiance^2; may be negative)
    divergence.R/G/B           var * dy/dx, the probe estimate of the divergence term

(``(y - x)^2`` is not stored: it follows from y and the dataset's x; SURE = (y - x)^2 - var +
2 divergence up to float32 rounding of the stored parts.) Header attributes: ``jaxden.item``,
``jaxden.cache_key``, ``jaxden.source_sha256`` (the dataset file it was computed from),
``jaxden.denoiser``, ``jaxden.probes``, ``jaxden.method``, ``jaxden.eps``, ``jaxden.seed`` (the
item's probe seed).

Identity: a cache is for one dataset, one denoiser (name, config and a SHA-256 of its
parameters) and one setting (probes, method, eps, finite-difference scheme, seed); a rerun
with anything else into the same folder is a DatasetError that names the differences. Items
with spp = 1 have no variance and are skipped (SURE needs it; the mixer loader refuses them).

Resuming: every EXR is written atomically and the manifest is saved every few seconds and at
the end. On rerun an item counts as finished when its file matches the recorded checksum and
the dataset file it came from is unchanged, or (finished after the last manifest save) when its
header carries this cache's key, the item id and the source checksum and it reads back whole.
Everything else is computed again.

Probes: item ``i`` uses ``key_i = PRNGKey(item_seed(seed, i))`` and the probes
``draw_probes(key_i, var, K)``, for JAX denoisers (through :func:`jaxden.sure.sure`) and for
black boxes (the same probes handed to :func:`jaxden.sure.sure_blackbox`), so a cached map
equals a direct call with that key.

Finite-difference step (``eps=None`` picks :func:`default_eps`): the authors use 1e-4, which
in float32 is dominated by round-off. Measured on OIDN (pyoidn 2.5, 'high', Cornell box 64 x 64,
4 common probes, relative L2 error of the divergence term against the mean of central
differences at 3e-3 and 1e-2): forward eps = 1e-4: 5 % (4 spp), 12 % (64 spp), 30 % (1024 spp);
1e-3: 2 %, 2 %, 5 %; 1e-2: 1.9 %, 0.9 %, 1.1 %; 3e-2: 4 %, 2 %, 1 %. So black boxes get
1e-2 (the error floor is OIDN's own float32 output). JAX denoisers use jvp (exact) unless
``method='fd'``, for which 1e-3 (the float32 optimum measured in tests/test_sure_properties.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import os
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxden.fileio import atomic_write_text, folder_lock
from jaxden.errors import ConfigError, DatasetError, ExrError, FrameError
from jaxden.frame import Frame

__all__ = [
    "CACHE_MANIFEST",
    "SureCache",
    "build_sure_cache",
    "default_cache_dir",
    "default_eps",
    "denoise_with_sure",
    "denoiser_identity",
    "inverse_dihedral",
    "item_seed",
    "locate_crop",
    "open_training_cache",
    "read_sure_exr",
    "resolve_denoiser",
    "write_sure_exr",
]

CACHE_MANIFEST = "sure-cache.json"
CACHE_FORMAT = "jaxden-sure-cache"
CACHE_VERSION = 1
LOCK_NAME = ".sure-cache.lock"
SAVE_INTERVAL_S = 5.0
DERIVED_DIR = "derived"
#: Finite-difference steps chosen from measurements (module docstring).
FD_EPS_BLACKBOX = 1e-2
FD_EPS_JAX = 1e-3
SURE_CHANNELS = ("sure.R", "sure.G", "sure.B")
DIVERGENCE_CHANNELS = ("divergence.R", "divergence.G", "divergence.B")
DENOISED_CHANNELS = ("R", "G", "B")
MEMORY_LIMIT_BYTES = 2 << 30


# ------------------------------------------------------------------------------- denoisers
def resolve_denoiser(denoiser):
    """A :class:`jaxden.denoisers.Denoiser` from a Denoiser or a spec for ``load_denoiser``."""
    from jaxden.denoisers import Denoiser, load_denoiser

    if isinstance(denoiser, Denoiser):
        return denoiser
    if isinstance(denoiser, (str, os.PathLike)):
        return load_denoiser(denoiser)
    raise ConfigError(
        f"denoiser must be a name, a checkpoint path or a Denoiser, got {type(denoiser).__name__}"
    )


def params_sha256(params: Any) -> str | None:
    """SHA-256 over the parameter pytree (paths, dtypes, shapes, bytes); None for no params."""
    if params is None:
        return None
    digest = hashlib.sha256()
    leaves = jax.tree_util.tree_leaves_with_path(params)
    for path, leaf in sorted(leaves, key=lambda pair: jax.tree_util.keystr(pair[0])):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(jax.tree_util.keystr(path).encode())
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _plain(value: Any) -> Any:
    from jaxden.config import config_to_dict

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return config_to_dict(value)
    return repr(value)


def denoiser_identity(denoiser) -> dict[str, Any]:
    """What makes two denoisers the same for the cache: name, config and parameters."""
    return {
        "name": denoiser.name,
        "config": _plain(denoiser.config),
        "params_sha256": params_sha256(denoiser.params),
    }


def denoiser_slug(denoiser) -> str:
    """Folder name for a denoiser: its name, plus a parameter hash for trained weights."""
    digest = params_sha256(denoiser.params)
    return denoiser.name if digest is None else f"{denoiser.name}-{digest[:10]}"


def default_eps(method: str, differentiable: bool) -> float | None:
    """The finite-difference step used when none is given (see the module docstring):
    None for ``jvp``; 1e-2 for black boxes, 1e-3 for JAX denoisers with ``fd``."""
    if method == "jvp":
        return None
    return FD_EPS_JAX if differentiable else FD_EPS_BLACKBOX


def resolve_method(method: str, denoiser) -> str:
    if method not in ("auto", "jvp", "fd"):
        raise ConfigError(f"SURE method must be 'auto', 'jvp' or 'fd', got {method!r}")
    if method == "auto":
        return "jvp" if denoiser.differentiable else "fd"
    if method == "jvp" and not denoiser.differentiable:
        raise ConfigError(
            f"denoiser '{denoiser.name}' is a black box (no derivatives): SURE needs method 'fd' "
            f"(or 'auto')"
        )
    return method


@functools.partial(jax.jit, static_argnames=("num_probes",))
def _draw_probes(key, variance, num_probes: int):
    """:func:`jaxden.sure.draw_probes` compiled once per shape (called eagerly it retraces
    its ``lax.map`` on every call, ~0.7 s each on the project machine); the same values."""
    from jaxden.sure import draw_probes

    return draw_probes(key, variance, num_probes)


@functools.lru_cache(maxsize=64)
def _apply_fn(definition, config):
    """A stable ``(params, frame) -> image`` per (definition, config): :func:`jaxden.sure.sure`
    compiles per function object, so the same object must come back every call."""
    return lambda params, frame: definition.apply(params, config, frame)


def denoise_with_sure(
    denoiser,
    frame: Frame,
    key,
    *,
    num_probes: int = 4,
    method: str = "auto",
    eps: float | None = None,
    fd_scheme: str = "forward",
    probe_batch: int | None = None,
    nonfinite: str = "error",
    where: str = "sure",
):
    """Denoise ``frame`` and estimate the per-pixel SURE of the result.

    ``method``: ``auto`` = ``jvp`` for JAX denoisers (exact J b, :func:`jaxden.sure.sure`) and
    ``fd`` for black boxes (:func:`jaxden.sure.sure_blackbox` with the probes of
    :func:`jaxden.sure.draw_probes`, so both paths use the same probes for the same key).
    ``eps`` None: :func:`default_eps`. ``probe_batch``: probes per jvp pass (memory; JAX only).

    Returns ``(SureResult, frame)``: fields (..., H, W, 3) (JAX arrays for JAX denoisers, NumPy
    for black boxes) and the validated (possibly repaired, ``nonfinite='zero'``) NumPy frame.
    Raises FrameError when the frame has no variance (naming SURE and the variance), bad
    values, or lacks a feature the denoiser needs.
    """
    from jaxden.sure import sure, sure_blackbox

    denoiser = resolve_denoiser(denoiser)
    if not isinstance(frame, Frame):
        raise FrameError(f"{where}: expected a jaxden Frame, got {type(frame).__name__}")
    if frame.variance is None:
        raise FrameError(
            f"{where}: SURE needs the variance of the pixel mean (EXR channels variance.R/G/B: "
            f"sample variance / spp), but the frame has only {', '.join(frame.features())}"
        )
    if nonfinite not in ("error", "zero"):
        raise ConfigError(f"{where}: nonfinite must be 'error' or 'zero', got {nonfinite!r}")
    frame = frame.numpy().validated(where=where, nonfinite=nonfinite)
    denoiser.check_frame(frame)
    method = resolve_method(method, denoiser)
    if eps is None:
        eps = default_eps(method, denoiser.differentiable) or 1e-4  # ignored by jvp
    if denoiser.differentiable:
        result = sure(
            _apply_fn(denoiser.definition, denoiser.config), frame, key, num_probes, method, eps,
            params=denoiser.params, fd_scheme=fd_scheme, probe_batch=probe_batch,
        )
    else:
        probes = np.asarray(_draw_probes(key, frame.variance, num_probes), np.float64)
        result = sure_blackbox(
            denoiser.function(), frame, probes=probes, eps=eps, fd_scheme=fd_scheme
        )
    return result, frame


# ------------------------------------------------------------------------------- files
def write_sure_exr(path, result, *, half: bool = False, attributes: dict | None = None) -> None:
    """Write a SureResult of one image (H, W, 3) as an EXR (atomic): R,G,B = denoised,
    sure.R/G/B, divergence.R/G/B (see the module docstring)."""
    from jaxden.io.exr import write_channels

    channels = {}
    for names, array in (
        (DENOISED_CHANNELS, result.denoised),
        (SURE_CHANNELS, result.sure),
        (DIVERGENCE_CHANNELS, result.divergence_term),
    ):
        array = np.asarray(array, np.float32)
        if array.ndim != 3 or array.shape[-1] != 3:
            raise FrameError(f"{path}: SURE images must be (H, W, 3), got {array.shape}")
        for index, name in enumerate(names):
            channels[name] = array[..., index]
    from jaxden import __version__

    write_channels(path, channels, half=half,
                   attributes={"version": __version__, **(attributes or {})})


def read_sure_exr(path) -> dict[str, np.ndarray]:
    """``{"denoised", "sure", "divergence"}`` (H, W, 3) float32 from a SURE EXR."""
    from jaxden.io.exr import read_channels

    data, _ = read_channels(path, DENOISED_CHANNELS + SURE_CHANNELS + DIVERGENCE_CHANNELS)
    return {
        "denoised": np.stack([data[c] for c in DENOISED_CHANNELS], -1),
        "sure": np.stack([data[c] for c in SURE_CHANNELS], -1),
        "divergence": np.stack([data[c] for c in DIVERGENCE_CHANNELS], -1),
    }


def item_seed(seed: int, item_id: str) -> int:
    """The probe seed of one dataset item (independent of build order and of other items)."""
    from jaxden.data.layout import derive_seed

    return derive_seed(int(seed), "sure", item_id)


def default_cache_dir(dataset_dir, denoiser) -> Path:
    """``DATASET/derived/<name>`` (black boxes) or ``DATASET/derived/<name>-<params hash>``."""
    return Path(dataset_dir) / DERIVED_DIR / denoiser_slug(resolve_denoiser(denoiser))


def _dataset_identity(manifest) -> dict[str, Any]:
    text = json.dumps(manifest.config, sort_keys=True)
    return {"name": manifest.config.get("name"),
            "config_sha256": hashlib.sha256(text.encode()).hexdigest()}


def _cache_key(identity: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:20]


def _save_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=1))


def _load_cache_manifest(directory: Path) -> dict[str, Any] | None:
    path = directory / CACHE_MANIFEST
    if not path.exists():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise DatasetError(f"{path}: cannot be read as JSON: {error}") from None
    if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT:
        raise DatasetError(f"{path}: not a jaxden SURE cache manifest (no format '{CACHE_FORMAT}')")
    if data.get("format_version") != CACHE_VERSION:
        raise DatasetError(
            f"{path}: SURE cache format version {data.get('format_version')} is not supported "
            f"(this jaxden reads version {CACHE_VERSION}); rebuild into another folder"
        )
    return data


def _lock(directory: Path):
    return folder_lock(directory, LOCK_NAME, "SURE cache build")


def _eligible_items(manifest) -> list:
    """Input items that have a variance (spp >= 2)."""
    return [item for item in manifest.items if item.kind == "input" and item.spp >= 2]


def _item_state(path: Path, record: dict | None, item, cache_key: str) -> tuple[str, dict | None]:
    """('done' | 'recovered' | 'pending', record) for one cached item."""
    from jaxden.data.layout import sha256_file

    if not path.is_file():
        return "pending", None
    if record is not None:
        if (record.get("source_sha256") == item.sha256
                and path.stat().st_size == record.get("bytes")
                and sha256_file(path) == record.get("sha256")):
            return "done", record
        return "pending", None
    from jaxden.io.exr import read_header

    try:
        header = read_header(path)
        if (header.get("item") != item.id or header.get("cache_key") != cache_key
                or header.get("source_sha256") != item.sha256):
            return "pending", None
        read_sure_exr(path)
    except ExrError:
        return "pending", None
    return "recovered", {
        "path": item.path, "sha256": sha256_file(path), "bytes": path.stat().st_size,
        "source_sha256": item.sha256, "seed": header.get("seed"), "seconds": None,
    }


def build_sure_cache(
    dataset_dir,
    denoiser_spec,
    out_dir=None,
    *,
    num_probes: int = 4,
    method: str = "auto",
    eps: float | None = None,
    seed: int = 0,
    fd_scheme: str = "forward",
    probe_batch: int | None = None,
    half: bool = False,
    progress: bool = True,
) -> SureCache:
    """Compute (or finish) the SURE cache of ``denoiser_spec`` over a built dataset.

    Args:
      dataset_dir: a complete dataset folder (``jaxden dataset build``).
      denoiser_spec: ``"oidn"``, a checkpoint folder / .msgpack of a trained denoiser, or a
        :class:`jaxden.denoisers.Denoiser`.
      out_dir: cache folder; default :func:`default_cache_dir` (``DATASET/derived/<name>``).
      num_probes: K probes per item (4, as the authors).
      method: ``auto`` (jvp for JAX denoisers, fd for black boxes), ``jvp`` or ``fd``.
      eps: finite-difference step; None: :func:`default_eps` (1e-2 black box, 1e-3 JAX fd,
        measured; the authors' 1e-4 is dominated by float32 round-off, module docstring).
      seed: base seed; item i uses ``PRNGKey(item_seed(seed, i))``.
      fd_scheme: ``forward`` (authors, K + 1 denoiser calls) or ``central`` (2K + 1).
      probe_batch: probes per jvp pass; 1 bounds the memory to one jvp for big images.
      half: store float16 channels (the authors' choice; float32 by default so the cache
        equals a direct computation bit for bit).
      progress: show a tqdm bar.

    Returns the opened :class:`SureCache`. Raises DatasetError when the dataset is incomplete,
    the folder holds a cache of another dataset / denoiser / setting (naming the
    differences) or unrelated files; ConfigError for bad options.
    """
    from jaxden import __version__
    from jaxden.config import config_diff
    from jaxden.data.layout import load_manifest, sha256_file
    from jaxden.io.exr import read_frame

    dataset_dir = Path(dataset_dir)
    manifest = load_manifest(dataset_dir)
    if not manifest.complete:
        done = sum(item.done for item in manifest.items)
        raise DatasetError(
            f"dataset {dataset_dir} is incomplete ({done} of {len(manifest.items)} files built): "
            f"finish it with `jaxden dataset build` before computing SURE"
        )
    if not isinstance(num_probes, int) or isinstance(num_probes, bool) or num_probes < 1:
        raise ConfigError(f"num_probes must be an integer >= 1, got {num_probes!r}")
    if fd_scheme not in ("forward", "central"):
        raise ConfigError(f"fd_scheme must be 'forward' or 'central', got {fd_scheme!r}")
    denoiser = resolve_denoiser(denoiser_spec)
    method = resolve_method(method, denoiser)
    if eps is None:
        eps = default_eps(method, denoiser.differentiable)
    elif method == "jvp":
        eps = None  # not used; keep it out of the identity
    settings = {
        "num_probes": num_probes,
        "method": method,
        "eps": None if eps is None else float(eps),
        "fd_scheme": fd_scheme if method == "fd" else None,
        "seed": int(seed),
        "half": bool(half),
    }
    identity = {
        "dataset": _dataset_identity(manifest),
        "denoiser": denoiser_identity(denoiser),
        "settings": settings,
    }
    cache_key = _cache_key(identity)
    directory = Path(out_dir) if out_dir is not None else default_cache_dir(dataset_dir, denoiser)
    if directory.exists() and not directory.is_dir():
        raise DatasetError(f"{directory} exists and is not a folder")
    directory.mkdir(parents=True, exist_ok=True)

    with _lock(directory):
        stored = _load_cache_manifest(directory)
        if stored is not None:
            differences = config_diff(stored.get("identity", {}), identity)
            if differences:
                raise DatasetError(
                    f"{directory / CACHE_MANIFEST} holds a SURE cache of another dataset, "
                    f"denoiser or setting; differences (stored -> given): "
                    + "; ".join(differences)
                    + ". Write into another folder (out_dir / --out), or delete it to rebuild."
                )
            records = dict(stored.get("items", {}))
            created = stored.get("created")
        else:
            foreign = [p.name for p in directory.iterdir()
                       if p.name != LOCK_NAME and not p.name.startswith(".")]
            if foreign:
                raise DatasetError(
                    f"{directory} is not empty ({', '.join(sorted(foreign)[:5])}) and has no "
                    f"{CACHE_MANIFEST}: refusing to write a SURE cache into it"
                )
            records, created = {}, None
        created = created or time.strftime("%Y-%m-%dT%H:%M:%S%z")
        items = _eligible_items(manifest)
        skipped = [item.id for item in manifest.items if item.kind == "input" and item.spp < 2]
        new_records: dict[str, dict] = {}
        pending = []
        for item in items:
            state, record = _item_state(
                directory / item.path, records.get(item.id), item, cache_key
            )
            if state == "pending":
                (directory / item.path).unlink(missing_ok=True)
                pending.append(item)
            else:
                new_records[item.id] = record
        records = new_records

        def save() -> None:
            _save_json(directory / CACHE_MANIFEST, {
                "format": CACHE_FORMAT,
                "format_version": CACHE_VERSION,
                "jaxden_version": __version__,
                "identity": identity,
                "cache_key": cache_key,
                "info": _runtime_info(denoiser, denoiser_spec),
                "created": created,
                "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                "complete": len(records) == len(items),
                "items_done": len(records),
                "items_total": len(items),
                "skipped_no_variance": skipped,
                "items": {item.id: records[item.id] for item in items if item.id in records},
            })

        save()
        bar = None
        if progress and pending:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(items), initial=len(items) - len(pending), unit=" items",
                       desc=f"SURE cache {denoiser.name}", dynamic_ncols=True)
        last_save = time.monotonic()
        try:
            for item in pending:
                start = time.perf_counter()
                frame = read_frame(dataset_dir / item.path, require=("color", "variance"))
                seed_i = item_seed(seed, item.id)
                result, _ = denoise_with_sure(
                    denoiser, frame, jax.random.PRNGKey(seed_i), num_probes=num_probes,
                    method=method, eps=eps, fd_scheme=fd_scheme, probe_batch=probe_batch,
                    where=str(dataset_dir / item.path),
                )
                path = directory / item.path
                path.parent.mkdir(parents=True, exist_ok=True)
                write_sure_exr(path, result, half=half, attributes={
                    "item": item.id, "cache_key": cache_key, "source_sha256": item.sha256,
                    "denoiser": denoiser.name, "probes": num_probes, "method": method,
                    "eps": -1.0 if eps is None else float(eps), "seed": seed_i, "spp": item.spp,
                })
                records[item.id] = {
                    "path": item.path, "sha256": sha256_file(path), "bytes": path.stat().st_size,
                    "source_sha256": item.sha256, "seed": seed_i,
                    "seconds": round(time.perf_counter() - start, 4),
                }
                if bar is not None:
                    bar.update(1)
                if time.monotonic() - last_save > SAVE_INTERVAL_S:
                    save()
                    last_save = time.monotonic()
        finally:
            if bar is not None:
                bar.close()
            save()
    return SureCache(dataset_dir, directory)


def _runtime_info(denoiser, spec) -> dict[str, Any]:
    """Recorded, not compared: where the denoiser came from and library versions."""
    from importlib import metadata

    info: dict[str, Any] = {"spec": str(spec) if isinstance(spec, (str, os.PathLike)) else None,
                            "jax": jax.__version__}
    if not denoiser.differentiable:
        with contextlib.suppress(metadata.PackageNotFoundError):
            info["pyoidn"] = metadata.version("pyoidn")
    return info


# ------------------------------------------------------------------------------- reading
def inverse_dihedral(image: np.ndarray, index: int) -> np.ndarray:
    """Undo :func:`jaxden.data.loader.dihedral` (flip back, then turn back)."""
    out = np.asarray(image)
    if index >= 4:
        out = np.flip(out, axis=-2)
    return np.rot90(out, k=-(index % 4), axes=(-3, -2))


def locate_crop(full: np.ndarray, crop: np.ndarray, where: str = "crop") -> tuple[int, int, int]:
    """Find ``(top, left, symmetry)`` with ``dihedral(full[top:top+h, left:left+w], symmetry)
    == crop`` exactly; ``full`` (H, W, C), ``crop`` (h, w, C).

    Candidates are screened on a 5 x 5 grid of pixels, then checked in full. Symmetries are
    tried in order 0..7 and positions in row-major order; the first exact match wins. Only a
    crop whose window is repeated exactly elsewhere in the item (a constant, noise-free region,
    all C channels equal) can match more than one window; those windows then hold identical
    inputs. Raises DatasetError when nothing matches (the data changed under the cache).
    """
    full = np.asarray(full)
    crop = np.asarray(crop)
    height, width = full.shape[:2]
    for symmetry in range(8):
        window = inverse_dihedral(crop, symmetry)
        h, w = window.shape[:2]
        if h > height or w > width:
            continue
        rows, cols = height - h + 1, width - w + 1
        ok = np.ones((rows, cols), bool)
        for dy in np.unique(np.linspace(0, h - 1, 5).astype(int)):
            for dx in np.unique(np.linspace(0, w - 1, 5).astype(int)):
                ok &= np.all(full[dy : dy + rows, dx : dx + cols] == window[dy, dx], axis=-1)
            if not ok.any():
                break
        for top, left in np.argwhere(ok):
            if np.array_equal(full[top : top + h, left : left + w], window):
                return int(top), int(left), symmetry
    raise DatasetError(
        f"{where}: the batch crop is not a window of the dataset item (did the dataset change "
        f"since the loader read it?)"
    )


class SureCache:
    """A built SURE cache, opened for reading (see the module docstring for the layout).

    ``SureCache(dataset_dir, cache_dir)`` checks that the cache was computed from this dataset.
    ``missing`` lists the input items (spp >= 2) without a valid cached file; ``identity`` is
    the recorded denoiser and settings. Decoded items are kept in memory up to
    ``memory_limit`` bytes.
    """

    def __init__(self, dataset_dir, cache_dir, *, memory_limit: int = MEMORY_LIMIT_BYTES):
        from jaxden.data.layout import load_manifest

        self.dataset_dir = Path(dataset_dir)
        self.directory = Path(cache_dir)
        self.dataset = load_manifest(self.dataset_dir)
        data = _load_cache_manifest(self.directory)
        if data is None:
            raise DatasetError(
                f"{self.directory} holds no SURE cache ({CACHE_MANIFEST} missing): build it with "
                f"`jaxden dataset sure-cache {self.dataset_dir} --denoiser NAME`"
            )
        self.identity = data.get("identity", {})
        self.cache_key = data.get("cache_key")
        dataset_identity = _dataset_identity(self.dataset)
        if self.identity.get("dataset") != dataset_identity:
            raise DatasetError(
                f"{self.directory}: the SURE cache was computed from another dataset "
                f"({self.identity.get('dataset')}), not {self.dataset_dir} ({dataset_identity})"
            )
        self.records: dict[str, dict] = data.get("items", {})
        self._items = {item.id: item for item in self.dataset.items}
        crops = self.dataset.crop_by_id()
        self._split = {item.id: crops[item.crop].split for item in self.dataset.items}
        self.memory_limit = memory_limit
        self._memory: dict[str, dict[str, np.ndarray]] = {}
        self._bytes = 0

    @property
    def missing(self) -> list[str]:
        """Eligible items whose record is absent or was computed from another dataset file."""
        return [
            item.id for item in _eligible_items(self.dataset)
            if self.records.get(item.id, {}).get("source_sha256") != item.sha256
        ]

    @property
    def complete(self) -> bool:
        return not self.missing

    def in_split(self, item_id: str, split: str) -> bool:
        """Whether a dataset item belongs to ``split`` ('all' matches every item)."""
        return split == "all" or self._split.get(item_id) == split

    def read(self, item_id: str) -> dict[str, np.ndarray]:
        """``{"denoised", "sure", "divergence"}`` (H, W, 3) of one item, float32."""
        record = self.records.get(item_id)
        if record is None:
            raise DatasetError(
                f"{self.directory}: item {item_id} is not in the SURE cache (spp 1, or not built: "
                f"run `jaxden dataset sure-cache` again)"
            )
        try:
            return read_sure_exr(self.directory / record["path"])
        except ExrError as error:
            raise DatasetError(f"{error} (rebuild the SURE cache to repair it)") from None

    def _full(self, item_id: str) -> dict[str, np.ndarray]:
        """The whole item: ``key`` (colour and variance from the dataset, (H, W, 6)), the cached
        ``denoised`` and ``sure``."""
        found = self._memory.get(item_id)
        if found is not None:
            return found
        from jaxden.io.exr import read_frame

        item = self._items.get(item_id)
        if item is None:
            raise DatasetError(f"{self.dataset_dir}: no item {item_id!r} in the dataset")
        frame = read_frame(self.dataset_dir / item.path, require=("color", "variance"))
        cached = self.read(item_id)
        entry = {
            "key": np.concatenate([frame.color, frame.variance], axis=-1),
            "denoised": cached["denoised"],
            "sure": cached["sure"],
        }
        size = sum(a.nbytes for a in entry.values())
        if self._bytes + size <= self.memory_limit:
            self._memory[item_id] = entry
            self._bytes += size
        return entry

    def crops_for(self, batch) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, int]]]:
        """The cached denoised image and SURE cut like the loader cut ``batch``.

        ``batch``: a :class:`jaxden.data.loader.Batch` with input colour and variance
        (B, h, w, 3). The loader does not report its crop windows, so each sample's window and
        symmetry are recovered by exact matching of its colour and variance against the item
        (:func:`locate_crop`); the result is a pure function of the batch.

        Returns ``(denoised, sure, windows)``: (B, h, w, 3) float32 arrays and
        ``(top, left, symmetry)`` per sample.
        """
        from jaxden.data.loader import dihedral

        color = np.asarray(batch.input.color)
        variance = batch.input.variance
        if variance is None:
            raise FrameError("crops_for: the batch has no input variance")
        variance = np.asarray(variance)
        denoised, sure_maps, windows = [], [], []
        for index, item_id in enumerate(batch.items):
            entry = self._full(item_id)
            crop = np.concatenate([color[index], variance[index]], axis=-1)
            top, left, symmetry = locate_crop(entry["key"], crop, where=f"item {item_id}")
            h, w = crop.shape[:2] if symmetry % 2 == 0 else crop.shape[1::-1]
            for out, name in ((denoised, "denoised"), (sure_maps, "sure")):
                out.append(dihedral(entry[name][top : top + h, left : left + w], symmetry))
            windows.append((top, left, symmetry))
        return (
            np.ascontiguousarray(np.stack(denoised), np.float32),
            np.ascontiguousarray(np.stack(sure_maps), np.float32),
            windows,
        )


def open_training_cache(dataset_dir, config) -> SureCache:
    """The SURE cache a :class:`jaxden.progressive.MixerConfig` asks for, built or finished
    first when ``config.build_cache`` (a complete cache costs one checksum pass to confirm)."""
    denoiser = resolve_denoiser(config.denoiser)
    directory = Path(config.cache) if config.cache else default_cache_dir(dataset_dir, denoiser)
    options = dict(num_probes=config.sure_probes, method=config.sure_method, eps=config.sure_eps,
                   seed=config.sure_seed)
    if config.build_cache:
        return build_sure_cache(dataset_dir, denoiser, directory, **options)
    cache = SureCache(dataset_dir, directory)
    method = resolve_method(config.sure_method, denoiser)
    eps = config.sure_eps
    if eps is None:
        eps = default_eps(method, denoiser.differentiable)
    wanted = {"denoiser": denoiser_identity(denoiser), "num_probes": config.sure_probes,
              "method": method, "eps": None if method == "jvp" else eps, "seed": config.sure_seed}
    stored = {"denoiser": cache.identity.get("denoiser"),
              **{k: cache.identity.get("settings", {}).get(k) for k in
                 ("num_probes", "method", "eps", "seed")}}
    if stored != wanted:
        from jaxden.config import config_diff

        raise DatasetError(
            f"{directory}: the SURE cache was built with another denoiser or setting (stored -> "
            f"wanted): {'; '.join(config_diff(stored, wanted))}"
        )
    if not cache.complete:
        raise DatasetError(
            f"{directory}: the SURE cache lacks {len(cache.missing)} item(s) (e.g. "
            f"{cache.missing[0]}); run `jaxden dataset sure-cache {dataset_dir} --denoiser "
            f"{config.denoiser}` or set model_config.build_cache = true"
        )
    return cache
