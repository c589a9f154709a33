"""Per-item caches on disk: one file per dataset item (same relative path) beside a JSON
manifest, built resumably (the SURE cache :mod:`jaxden.progressive.cache`, the NJS cache
:mod:`jaxden.train.njs_cache`).

Manifest: ``format``, ``format_version``, ``jaxden_version``, the cache's ``identity`` and
``cache_key`` (and fields of its own), ``created``, ``updated``, ``complete``, ``items_done``,
``items_total`` and ``items``: item id -> record ``{path, sha256, bytes, <source checksums>,
..., seconds}``.

Resuming: every item file is written atomically and the manifest is saved every
:data:`SAVE_INTERVAL_S` seconds and at the end. On rerun an item counts as finished when its
file matches the recorded checksum and the files it came from are unchanged, or (finished
after the last manifest save) when its header carries the cache's key, the item id and the
source checksums and it reads back whole (:func:`item_state`). Everything else is computed
again.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.errors import DatasetError, ExrError, FrameError
from jaxden.fileio import atomic_write_text

SAVE_INTERVAL_S = 5.0
#: Fields of a cache manifest that jaxden reads (checked on load; ``?``: optional).
MANIFEST_FIELDS = {"format": str, "format_version": int, "identity": dict, "cache_key": str,
                   "items": dict, "complete?": bool, "created?": str}
_TIME_FORMAT = "%Y-%m-%dT%H:%M:%S%z"


@dataclasses.dataclass(frozen=True)
class CacheKind:
    """One kind of item cache: ``name`` for messages ("SURE": "the SURE cache manifest",
    with ``article``: "a SURE cache"), the ``manifest`` and ``lock`` file names, the manifest's
    ``format`` and ``format_version`` (``version``), and the fields checked on load of each
    item record and (None: unchecked) of the identity
    (:func:`jaxden.fileio.check_json_fields`'s form)."""

    name: str
    article: str
    manifest: str
    lock: str
    format: str
    version: int
    record_fields: dict
    identity_fields: dict | None = None


def save_manifest(path: Path, data: dict) -> None:
    """Write a cache manifest (atomic)."""
    atomic_write_text(path, json.dumps(data, indent=1))


def read_manifest(directory: Path, kind: CacheKind) -> dict[str, Any] | None:
    """The cache manifest of ``directory`` (None when there is none); DatasetError naming the
    file and the field when it is unreadable, malformed, wrongly typed or of another format."""
    from jaxden.data.layout import inside_folder
    from jaxden.fileio import check_json_fields, read_json

    path = directory / kind.manifest
    if not path.exists():
        return None
    what = f"the {kind.name} cache manifest"
    data = read_json(path, what, error=DatasetError)
    if data.get("format") != kind.format:
        raise DatasetError(f"{path}: not a jaxden {kind.name} cache manifest (no format "
                           f"'{kind.format}'); delete it to rebuild the cache")
    check_json_fields(data, MANIFEST_FIELDS, f"{path}: {what}", DatasetError)
    if data["format_version"] != kind.version:
        raise DatasetError(
            f"{path}: {kind.name} cache format version {data['format_version']} is not "
            f"supported (this jaxden reads version {kind.version}); rebuild into another folder"
        )
    if kind.identity_fields is not None:
        check_json_fields(data["identity"], kind.identity_fields,
                          f"{path}: {what}, field 'identity'", DatasetError)
    for item_id, record in data["items"].items():
        where = f"{path}: {what}, item {item_id!r}"
        check_json_fields(record, kind.record_fields, where, DatasetError)
        if not inside_folder(record["path"]):
            raise DatasetError(f"{where}: path {record['path']!r} leaves the cache folder (item "
                               f"paths must be relative, without '..')")
    return data


def file_record(directory: Path, relative: str) -> dict[str, Any]:
    """The start of an item's record: ``{path, sha256, bytes}`` of ``directory/relative``."""
    from jaxden.data.layout import sha256_file

    path = directory / relative
    return {"path": relative, "sha256": sha256_file(path), "bytes": path.stat().st_size}


def item_state(directory: Path, item, record: dict | None, cache_key: str, sources: dict,
               read: Callable, extra: Callable | None = None) -> tuple[str, dict | None]:
    """('done' | 'recovered' | 'pending', record) of the file ``directory/item.path``.

    Done: the file matches ``record`` (its ``sources``, field -> checksum of a file it was
    computed from, its size and its checksum). Without a record: recovered when its header
    names ``item.id``, ``cache_key`` and ``sources`` and ``read(path)`` reads it whole; the
    new record (:func:`file_record`, ``sources``) gets ``extra(header)`` too."""
    from jaxden.data.layout import sha256_file

    path = directory / item.path
    if not path.is_file():
        return "pending", None
    if record is not None:
        if (all(record.get(name) == value for name, value in sources.items())
                and path.stat().st_size == record.get("bytes")
                and sha256_file(path) == record.get("sha256")):
            return "done", record
        return "pending", None
    from jaxden.io.exr import read_header

    try:
        header = read_header(path)
        if ((header.get("item"), header.get("cache_key")) != (item.id, cache_key)
                or any(header.get(name) != value for name, value in sources.items())):
            return "pending", None
        read(path)
    except ExrError:
        return "pending", None
    return "recovered", {**file_record(directory, item.path), **sources,
                         **(extra(header) if extra else {})}


def finished(directory: Path, kind: CacheKind, items: list, identity: dict,
             state: Callable) -> bool:
    """Whether ``directory`` holds the cache of ``identity``, complete, every item ``done``
    by ``state(item, record)`` (:func:`item_state`). Read only: a writer replaces files
    atomically, so this never sees half a file, and runs sharing a finished cache never
    take its lock."""
    from jaxden.config import config_diff

    stored = read_manifest(directory, kind)
    if stored is None or not stored.get("complete") or config_diff(
            stored.get("identity", {}), identity):
        return False
    records = stored["items"]
    return all(state(item, records.get(item.id))[0] == "done" for item in items)


def build_items(directory: Path, kind: CacheKind, items: list, stored: dict | None,
                state: Callable, compute: Callable, fields: dict, *, progress: bool,
                label: str) -> None:
    """Compute the unfinished ``items`` of a cache in ``directory`` (under its lock),
    keeping the manifest current.

    ``stored``: the folder's manifest, checked by the caller, whose records and ``created``
    carry over (None: there is none; then the folder must hold nothing but hidden files).
    ``state(item, record)`` sorts the items (:func:`item_state`); a pending item's file is
    deleted and ``compute(item)`` writes it and returns its record (:func:`file_record` and
    the cache's fields; ``seconds`` is added). The manifest (``fields`` after the format
    fields: ``identity``, ``cache_key``, the cache's own) is saved first, then every
    :data:`SAVE_INTERVAL_S` seconds and at the end, also when ``compute`` raises or the run is
    interrupted. ``label``: the tqdm bar's, shown when ``progress`` and items are pending."""
    from jaxden import __version__

    if stored is None:
        foreign = [p.name for p in directory.iterdir()
                   if p.name != kind.lock and not p.name.startswith(".")]
        if foreign:
            raise DatasetError(
                f"{directory} is not empty ({', '.join(sorted(foreign)[:5])}) and has no "
                f"{kind.manifest}: refusing to write {kind.article} {kind.name} cache into it"
            )
        records, created = {}, None
    else:
        records, created = dict(stored["items"]), stored.get("created")
    created = created or time.strftime(_TIME_FORMAT)
    kept, pending = {}, []
    for item in items:
        status, record = state(item, records.get(item.id))
        if status == "pending":
            (directory / item.path).unlink(missing_ok=True)
            pending.append(item)
        else:
            kept[item.id] = record
    records = kept

    def save() -> None:
        save_manifest(directory / kind.manifest, {
            "format": kind.format, "format_version": kind.version,
            "jaxden_version": __version__, **fields,
            "created": created, "updated": time.strftime(_TIME_FORMAT),
            "complete": len(records) == len(items), "items_done": len(records),
            "items_total": len(items),
            "items": {item.id: records[item.id] for item in items if item.id in records},
        })

    save()
    bar = None
    if progress and pending:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(items), initial=len(items) - len(pending), unit=" items",
                   desc=label, dynamic_ncols=True)
    last_save = time.monotonic()
    try:
        for item in pending:
            start = time.perf_counter()
            record = compute(item)
            records[item.id] = {**record, "seconds": round(time.perf_counter() - start, 4)}
            if bar is not None:
                bar.update(1)
            if time.monotonic() - last_save > SAVE_INTERVAL_S:
                save()
                last_save = time.monotonic()
    finally:
        if bar is not None:
            bar.close()
        save()


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


class ItemCacheReader:
    """What the readers of item caches share: each item's stored images ``NAMES`` and its
    ``key`` (the dataset item's colour and variance), kept in memory up to ``memory_limit``
    bytes, and batch crops cut out of them. A subclass sets ``dataset_dir``, ``_items`` (id
    -> dataset item) and ``NAMES`` and defines ``read(item_id)`` (the stored images)."""

    NAMES: tuple[str, ...] = ()

    def __init__(self, memory_limit: int):
        self.memory_limit = memory_limit
        self._memory: dict[str, dict[str, np.ndarray]] = {}
        self._bytes = 0

    def _full(self, item_id: str) -> dict[str, np.ndarray]:
        """The whole item: ``key`` ((H, W, 6), from the dataset) and the stored ``NAMES``."""
        found = self._memory.get(item_id)
        if found is not None:
            return found
        from jaxden.io.exr import read_frame

        item = self._items.get(item_id)
        if item is None:
            raise DatasetError(f"{self.dataset_dir}: no item {item_id!r} in the dataset")
        frame = read_frame(self.dataset_dir / item.path, require=("color", "variance"))
        cached = self.read(item_id)
        entry = {"key": np.concatenate([frame.color, frame.variance], axis=-1),
                 **{name: cached[name] for name in self.NAMES}}
        size = sum(a.nbytes for a in entry.values())
        if self._bytes + size <= self.memory_limit:
            self._memory[item_id] = entry
            self._bytes += size
        return entry

    def _cut(self, batch, where: str) -> tuple[dict[str, np.ndarray], list[tuple[int, int, int]]]:
        """The stored ``NAMES`` cut like the loader cut ``batch`` (whose input colour and
        variance (B, h, w, 3) are matched against each item, :func:`locate_crop`): ``({name:
        (B, h, w, 3) float32}, [(top, left, symmetry) per sample])``. ``where``: the caller,
        for the message when the batch has no variance."""
        from jaxden.data.loader import dihedral

        if batch.input.variance is None:
            raise FrameError(f"{where}: the batch has no input variance")
        color, variance = np.asarray(batch.input.color), np.asarray(batch.input.variance)
        out: dict[str, list] = {name: [] for name in self.NAMES}
        windows = []
        for index, item_id in enumerate(batch.items):
            entry = self._full(item_id)
            crop = np.concatenate([color[index], variance[index]], axis=-1)
            top, left, symmetry = locate_crop(entry["key"], crop, where=f"item {item_id}")
            h, w = crop.shape[:2] if symmetry % 2 == 0 else crop.shape[1::-1]
            for name in self.NAMES:
                out[name].append(dihedral(entry[name][top : top + h, left : left + w], symmetry))
            windows.append((top, left, symmetry))
        return ({name: np.ascontiguousarray(np.stack(images), np.float32)
                 for name, images in out.items()}, windows)


# --------------------------------------------------------------------------- identities
#: The folder of a dataset that holds its derived caches (``DATASET/derived/<slug>``).
DERIVED_DIR = "derived"


def params_sha256(params: Any) -> str | None:
    """SHA-256 over the parameter pytree (paths, dtypes, shapes, bytes); None for no params."""
    if params is None:
        return None
    digest = hashlib.sha256()
    hash_params(digest, params)
    return digest.hexdigest()


def hash_params(digest, params: Any) -> None:
    """Feed ``params`` into the hashlib object ``digest``: each leaf's path, dtype, shape and
    bytes, in path order."""
    import jax

    leaves = jax.tree_util.tree_leaves_with_path(params)
    for path, leaf in sorted(leaves, key=lambda pair: jax.tree_util.keystr(pair[0])):
        array = np.ascontiguousarray(np.asarray(leaf))
        digest.update(jax.tree_util.keystr(path).encode())
        digest.update(f"{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())


def _plain(value: Any) -> Any:
    from jaxden.config import config_to_dict

    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return config_to_dict(value)
    return repr(value)


def denoiser_identity(denoiser) -> dict[str, Any]:
    """What makes two denoisers the same for the cache: name, config, parameters and code
    (:func:`jaxden.denoise.identity.code_sha256`: a changed denoiser never reuses what the
    old code computed)."""
    from jaxden.denoise.identity import code_sha256

    return {
        "name": denoiser.name,
        "config": _plain(denoiser.config),
        "params_sha256": params_sha256(denoiser.params),
        "code_sha256": code_sha256(denoiser),
    }


def denoiser_slug(denoiser) -> str:
    """Folder name for a denoiser: its name, plus a parameter hash for trained weights, plus a
    config hash for a denoiser with spec options run with other than its default config
    (``oidn:quality=fast``, ``oidn-jax:precision=bfloat16``: another output, another cache;
    the default config keeps the plain name)."""
    slug = denoiser.name
    definition = getattr(denoiser, "definition", None)
    if definition is not None and definition.options and \
            denoiser.config != definition.config_cls():
        text = json.dumps(_plain(denoiser.config), sort_keys=True, default=str)
        slug += "-c" + hashlib.sha256(text.encode()).hexdigest()[:8]
    digest = params_sha256(denoiser.params)
    return slug if digest is None else f"{slug}-{digest[:10]}"


def cache_dataset_identity(manifest) -> dict[str, Any]:
    text = json.dumps(manifest.config, sort_keys=True)
    return {"name": manifest.config.get("name"),
            "config_sha256": hashlib.sha256(text.encode()).hexdigest()}


def identity_key(identity: dict[str, Any]) -> str:
    return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:20]
