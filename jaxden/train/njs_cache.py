"""The NJS training cache: the neural James-Stein combiner's inputs for every input item of a
dataset and its replica.

NJS trains on (combined colour, its variance, olsA, olsB) -> reference. The cross regressions
are input preparation (the authors' loader computes them once per image), and the base
denoiser is frozen, so they are computed once per item by :func:`build_njs_cache` and read
back by :class:`NJSCache`, as the mixer's SURE cache (:mod:`jaxden.progressive.cache`).

An item of the training dataset at spp level s is half A; the same item of its replica
(``jaxden dataset build ... replica=1``: the same crops, splits and file names, other
seeds) is half B; :func:`jaxden.denoise.njs_model.njs_inputs_from_halves` gives the
combined frame (2 s samples, exact pooled variance), the base on each half and the cross
regressions (with the per-pixel bandwidth by default, as the authors train). The reference
is the dataset's own (the loader reads it with the batch); the replica's is not used.

Layout (default folder ``DATASET/derived/njs-<base>-<key>``, :func:`default_cache_dir`: the
key is the cache's identity, so other settings, another replica or a changed base or code
get another folder)::

    CACHE/njs-cache.json                         identity, per-item checksums
    CACHE/s000-cornell-box/c000/spp00002.exr     one EXR per input item, same relative path

Each item EXR holds, float32, (H, W) of the dataset crop: ``R,G,B`` the combined colour,
``variance.R/G/B`` its variance of the mean, ``olsA.R/G/B``, ``olsB.R/G/B`` the cross
regressions, ``baseA.R/G/B``, ``baseB.R/G/B`` the base on each half. Header attributes:
``jaxden.item``, ``jaxden.cache_key``, ``jaxden.source_sha256`` (half A's file),
``jaxden.replica_sha256`` (half B's), ``jaxden.spp`` (of the combination).

Identity: the two datasets (:func:`jaxden.data.item_cache.cache_dataset_identity` of each
manifest), the base (:func:`jaxden.data.item_cache.denoiser_identity`: name, config,
weights, code) and the settings (bandwidth, window, ridge and the code of
:mod:`jaxden.denoise.njs`). A folder holding another identity is refused, naming the
differences.

Resuming, as the SURE cache: every EXR is written atomically and the manifest saved every few
seconds and at the end; on a rerun an item counts as finished when its file matches the
recorded checksum and both its source files are unchanged, or (finished after the last save)
when its header names this cache's key, the item and both sources and it reads back whole.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.item_cache import (
    CacheKind,
    ItemCacheReader,
    build_items,
    file_record,
    finished,
    item_state,
    read_manifest,
)
from jaxden.errors import DatasetError, ExrError, FrameError
from jaxden.fileio import folder_lock

CACHE_MANIFEST = "njs-cache.json"
CACHE_FORMAT = "jaxden-njs-cache"
CACHE_VERSION = 1
LOCK_NAME = ".njs-cache.lock"
MEMORY_LIMIT_BYTES = 2 << 30
#: The stored images: name -> its three EXR channels.
CHANNELS = {
    "noisy": ("R", "G", "B"),
    "variance": ("variance.R", "variance.G", "variance.B"),
    "ols_a": ("olsA.R", "olsA.G", "olsA.B"),
    "ols_b": ("olsB.R", "olsB.G", "olsB.B"),
    "denoised_a": ("baseA.R", "baseA.G", "baseA.B"),
    "denoised_b": ("baseB.R", "baseB.G", "baseB.B"),
}
#: What a training batch takes of an item (the network's inputs).
NETWORK_INPUTS = ("noisy", "variance", "ols_a", "ols_b")
#: The NJS cache's files (:mod:`jaxden.data.item_cache`).
CACHE_KIND = CacheKind(
    name="NJS", article="an", manifest=CACHE_MANIFEST, lock=LOCK_NAME, format=CACHE_FORMAT,
    version=CACHE_VERSION,
    record_fields={"path": str, "sha256": str, "bytes": int, "source_sha256": str,
                   "replica_sha256": str, "seconds?": float},
)


# ---------------------------------------------------------------------------- the halves
def eligible_items(manifest) -> list:
    """Input items of at least 2 spp (each half needs a variance)."""
    return [item for item in manifest.items if item.kind == "input" and item.spp >= 2]


def check_replica(dataset_dir, replica_dir):
    """``(manifest, replica manifest)`` of two complete datasets that are replicas of one
    another: the same crops (ids, scenes, windows, splits) and input items (ids, paths, spp),
    each input rendered from other seeds. DatasetError naming the first difference."""
    from jaxden.data.layout import load_manifest

    manifests = []
    for folder in (dataset_dir, replica_dir):
        manifest = load_manifest(folder)
        if not manifest.complete:
            done = sum(item.done for item in manifest.items)
            raise DatasetError(f"dataset {folder} is incomplete ({done} of "
                               f"{len(manifest.items)} files built): finish it with `jaxden "
                               f"dataset build` first")
        manifests.append(manifest)
    first, second = manifests
    where = f"{replica_dir} is not a replica of {dataset_dir} (build it from the same config " \
            f"with replica=1)"
    crops = {c.id: c for c in second.crops}
    for crop in first.crops:
        other = crops.get(crop.id)
        if other is None or (other.scene, tuple(other.window), other.split) != (
                crop.scene, tuple(crop.window), crop.split):
            raise DatasetError(f"{where}: crop {crop.id} differs or is missing")
    items = {item.id: item for item in eligible_items(second)}
    for item in eligible_items(first):
        other = items.get(item.id)
        if other is None or (other.path, other.spp) != (item.path, item.spp):
            raise DatasetError(f"{where}: input {item.id} differs or is missing")
        if other.seed == item.seed:
            raise DatasetError(f"{where}: input {item.id} has the same render seed in both "
                               f"(the halves must be independent renders)")
    return first, second


# ------------------------------------------------------------------------------ identity
def cache_identity(manifest, replica, base, *, bandwidth, window, ridge) -> dict[str, Any]:
    """What the cache's content depends on (module docstring)."""
    from jaxden.data.item_cache import cache_dataset_identity, denoiser_identity
    from jaxden.denoise import njs
    from jaxden.denoise.identity import code_text_sha256

    return {
        "dataset": cache_dataset_identity(manifest),
        "replica": cache_dataset_identity(replica),
        "base": denoiser_identity(base),
        "settings": {"bandwidth": bandwidth, "ols_window": int(window),
                     "ols_ridge": float(ridge),
                     "code_sha256": code_text_sha256(inspect.getsource(njs))},
    }


def default_cache_dir(dataset_dir, base, identity: dict) -> Path:
    """``DATASET/derived/njs-<base slug>-<first 8 of the identity key>``."""
    from jaxden.data.item_cache import DERIVED_DIR, denoiser_slug, identity_key

    return (Path(dataset_dir) / DERIVED_DIR
            / f"njs-{denoiser_slug(base)}-{identity_key(identity)[:8]}")


def _settings(config) -> dict[str, Any]:
    return {"bandwidth": config.train_bandwidth, "window": config.ols_window,
            "ridge": config.ols_ridge}


# -------------------------------------------------------------------------------- files
def write_item(path, inputs, attributes: dict) -> None:
    """The arrays of :class:`jaxden.denoise.njs_model.NJSInputs` as one EXR (atomic)."""
    from jaxden import __version__
    from jaxden.io.exr import write_channels

    channels = {}
    for name, names in CHANNELS.items():
        array = np.asarray(getattr(inputs, name), np.float32)
        for index, channel in enumerate(names):
            channels[channel] = array[..., index]
    write_channels(path, channels, attributes={"version": __version__, **attributes})


def read_item(path) -> dict[str, np.ndarray]:
    """``{name: (H, W, 3) float32}`` for every name of :data:`CHANNELS`."""
    from jaxden.io.exr import read_channels

    data, _ = read_channels(path, [c for names in CHANNELS.values() for c in names])
    return {name: np.stack([data[c] for c in names], -1) for name, names in CHANNELS.items()}


# -------------------------------------------------------------------------------- build
def build_njs_cache(dataset_dir, replica_dir, base_spec, out_dir=None, *,
                    bandwidth: str = "pixel", window: int = 51, ridge: float = 0.1,
                    progress: bool = True) -> NJSCache:
    """Compute (or finish) the NJS cache of a dataset and its replica over a base.

    ``base_spec``: a denoiser spec or :class:`jaxden.denoise.Denoiser`; ``out_dir``: the
    cache folder (default :func:`default_cache_dir`); ``bandwidth``, ``window``, ``ridge``:
    of the cross regressions. Resumable and locked (module docstring); returns the opened
    :class:`NJSCache`. DatasetError when a dataset is incomplete, they are not replicas of
    one another, or the folder holds another cache or other files."""
    from jaxden.config import config_diff
    from jaxden.denoise.njs_model import njs_inputs_from_halves
    from jaxden.denoise.registry import as_denoiser
    from jaxden.io.exr import read_frame

    dataset_dir, replica_dir = Path(dataset_dir), Path(replica_dir)
    manifest, replica = check_replica(dataset_dir, replica_dir)
    base = as_denoiser(base_spec, "the NJS base")
    identity = cache_identity(manifest, replica, base, bandwidth=bandwidth, window=window,
                              ridge=ridge)
    from jaxden.data.item_cache import identity_key

    cache_key = identity_key(identity)
    directory = Path(out_dir) if out_dir else default_cache_dir(dataset_dir, base, identity)
    if directory.exists() and not directory.is_dir():
        raise DatasetError(f"{directory} exists and is not a folder")
    directory.mkdir(parents=True, exist_ok=True)
    items = eligible_items(manifest)
    replica_items = replica.item_by_id()

    def state(item, record: dict | None) -> tuple[str, dict | None]:
        sources = {"source_sha256": item.sha256,
                   "replica_sha256": replica_items[item.id].sha256}
        return item_state(directory, item, record, cache_key, sources, read_item)

    if finished(directory, CACHE_KIND, items, identity, state):
        return NJSCache(dataset_dir, replica_dir, directory)

    with folder_lock(directory, LOCK_NAME, "NJS cache build"):
        stored = read_manifest(directory, CACHE_KIND)
        if stored is not None:
            differences = config_diff(stored.get("identity", {}), identity)
            if differences:
                raise DatasetError(
                    f"{directory / CACHE_MANIFEST} holds an NJS cache of other data, base or "
                    f"settings; differences (stored -> given): " + "; ".join(differences)
                    + ". Write into another folder (model_config.cache), or delete it.")

        def compute(item) -> dict[str, Any]:
            other = replica_items[item.id]
            halves = [read_frame(folder / item.path, require=("color", "variance", "albedo",
                                                               "normal", "depth"))
                      for folder in (dataset_dir, replica_dir)]
            try:
                inputs = njs_inputs_from_halves(base, *halves, bandwidth=bandwidth,
                                                window=window, ridge=ridge)
            except FrameError as error:
                raise DatasetError(f"{dataset_dir / item.path} and its replica: "
                                   f"{error}") from None
            path = directory / item.path
            path.parent.mkdir(parents=True, exist_ok=True)
            write_item(path, inputs, {"item": item.id, "cache_key": cache_key,
                                      "source_sha256": item.sha256,
                                      "replica_sha256": other.sha256, "spp": 2 * item.spp})
            return {**file_record(directory, item.path), "source_sha256": item.sha256,
                    "replica_sha256": other.sha256}

        build_items(directory, CACHE_KIND, items, stored, state, compute, {
            "identity": identity, "cache_key": cache_key,
            "base_spec": str(base_spec) if isinstance(base_spec, str) else base.name,
        }, progress=progress, label=f"NJS cache {base.name}")
    return NJSCache(dataset_dir, replica_dir, directory)


def open_njs_cache(dataset_dir, config, *, progress: bool = True) -> NJSCache:
    """The cache an :class:`jaxden.denoise.njs_model.NJSModelConfig` trains on over
    ``dataset_dir`` (its ``replica``, base and cross-regression settings), built or finished
    first when ``config.build_cache``; else it must exist, complete, with this identity."""
    from jaxden.config import config_diff
    from jaxden.denoise.njs_model import checked_base

    if not config.replica:
        raise DatasetError("model_config.replica must name the replica of data.dataset "
                           "(`jaxden dataset build CONFIG replica=1 --out DIR`): NJS trains "
                           "on two independent halves of every item")
    base = checked_base(config)
    if config.build_cache:
        return build_njs_cache(dataset_dir, config.replica, base, config.cache or None,
                               progress=progress, **_settings(config))
    manifest, replica = check_replica(dataset_dir, config.replica)
    identity = cache_identity(manifest, replica, base, **_settings(config))
    directory = (Path(config.cache) if config.cache
                 else default_cache_dir(dataset_dir, base, identity))
    cache = NJSCache(dataset_dir, config.replica, directory)
    if cache.identity != identity:
        raise DatasetError(f"{directory}: the NJS cache was built with other data, base or "
                           f"settings (stored -> wanted): "
                           f"{'; '.join(config_diff(cache.identity, identity))}")
    if not cache.complete:
        raise DatasetError(f"{directory}: the NJS cache lacks {len(cache.missing)} item(s) "
                           f"(e.g. {cache.missing[0]}); set model_config.build_cache = true")
    return cache


# ------------------------------------------------------------------------------ reading
class NJSCache(ItemCacheReader):
    """A built NJS cache, opened for reading: ``missing`` lists the eligible items without a
    valid record, ``identity`` is the recorded one; :meth:`crops_for` cuts a batch's inputs.
    Decoded items are kept in memory up to ``memory_limit`` bytes."""

    NAMES = NETWORK_INPUTS

    def __init__(self, dataset_dir, replica_dir, cache_dir, *,
                 memory_limit: int = MEMORY_LIMIT_BYTES):
        from jaxden.data.item_cache import cache_dataset_identity

        self.dataset_dir, self.replica_dir = Path(dataset_dir), Path(replica_dir)
        self.directory = Path(cache_dir)
        self.dataset, self.replica = check_replica(self.dataset_dir, self.replica_dir)
        data = read_manifest(self.directory, CACHE_KIND)
        if data is None:
            raise DatasetError(f"{self.directory} holds no NJS cache ({CACHE_MANIFEST} "
                               f"missing): train with model_config.build_cache = true")
        self.identity, self.cache_key = data["identity"], data["cache_key"]
        for key, manifest, folder in (("dataset", self.dataset, self.dataset_dir),
                                      ("replica", self.replica, self.replica_dir)):
            if self.identity.get(key) != cache_dataset_identity(manifest):
                raise DatasetError(f"{self.directory}: the NJS cache was computed from another "
                                   f"{key} ({self.identity.get(key)}), not {folder}")
        self.records: dict[str, dict] = data["items"]
        self._items = {item.id: item for item in self.dataset.items}
        self._replica_items = self.replica.item_by_id()
        super().__init__(memory_limit)

    @property
    def missing(self) -> list[str]:
        """Eligible items whose record is absent or was computed from other source files."""
        return [item.id for item in eligible_items(self.dataset)
                if (self.records.get(item.id, {}).get("source_sha256"),
                    self.records.get(item.id, {}).get("replica_sha256"))
                != (item.sha256, self._replica_items[item.id].sha256)]

    @property
    def complete(self) -> bool:
        return not self.missing

    def read(self, item_id: str) -> dict[str, np.ndarray]:
        """Every stored image of one item (:data:`CHANNELS`), (H, W, 3) float32."""
        record = self.records.get(item_id)
        if record is None:
            raise DatasetError(f"{self.directory}: item {item_id} is not in the NJS cache "
                               f"(spp 1, or not built)")
        try:
            return read_item(self.directory / record["path"])
        except ExrError as error:
            raise DatasetError(f"{error} (rebuild the NJS cache to repair it)") from None

    def crops_for(self, batch) -> dict[str, np.ndarray]:
        """The network inputs (:data:`NETWORK_INPUTS`, each (B, h, w, 3) float32) cut like the
        loader cut ``batch`` (its input: half A's colour and variance): each sample's window
        and symmetry are found by exact matching
        (:func:`jaxden.data.item_cache.locate_crop`)."""
        return self._cut(batch, "NJS cache crops_for")[0]


__all__ = [
    "CACHE_MANIFEST",
    "CHANNELS",
    "NETWORK_INPUTS",
    "NJSCache",
    "build_njs_cache",
    "cache_identity",
    "check_replica",
    "default_cache_dir",
    "eligible_items",
    "open_njs_cache",
    "read_item",
    "write_item",
]
