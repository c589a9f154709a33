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

Identity: a cache is for one dataset, one denoiser
(:func:`jaxden.data.item_cache.denoiser_identity`) and one SURE setting
(:func:`jaxden.progressive.cache_build.cache_settings` of its
:class:`~jaxden.sure.settings.SureSettings`: probes, method, eps, finite-difference scheme,
seed, and the covariance and probe distribution where not the defaults); a rerun with
anything else into the same folder is a DatasetError that names the differences. Items
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

Finite-difference step (``eps`` unset): :func:`jaxden.sure.settings.default_eps`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxden.data.item_cache import (
    DERIVED_DIR,
    CacheKind,
    ItemCacheReader,
    cache_dataset_identity,
    denoiser_slug,
    read_manifest,
)
from jaxden.errors import DatasetError, ExrError, FrameError
from jaxden.sure.denoiser import resolve_denoiser
from jaxden.sure.settings import SureSettings

CACHE_MANIFEST = "sure-cache.json"
CACHE_FORMAT = "jaxden-sure-cache"
CACHE_VERSION = 1
LOCK_NAME = ".sure-cache.lock"
SURE_CHANNELS = ("sure.R", "sure.G", "sure.B")
DIVERGENCE_CHANNELS = ("divergence.R", "divergence.G", "divergence.B")
DENOISED_CHANNELS = ("R", "G", "B")
MEMORY_LIMIT_BYTES = 2 << 30


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


def default_cache_dir(dataset_dir, denoiser, sure: SureSettings | None = None) -> Path:
    """``DATASET/derived/<name>`` (black boxes) or ``DATASET/derived/<name>-<params hash>``
    (:func:`denoiser_slug`), with ``-cov`` for SURE from the colour covariance and
    ``-rademacher`` for Rademacher probes under the SURE settings ``sure`` (None: a mixer's
    defaults): the forms of one denoiser side by side, as a study of them needs; the plain
    form keeps the plain name."""
    covariance = sure is not None and bool(sure.covariance)
    probe_dist = "normal" if sure is None or sure.probe_dist is None else sure.probe_dist
    slug = denoiser_slug(resolve_denoiser(denoiser))
    slug += "-cov" if covariance else ""
    slug += "" if probe_dist == "normal" else f"-{probe_dist}"
    return Path(dataset_dir) / DERIVED_DIR / slug


#: The SURE cache's files (:mod:`jaxden.data.item_cache`).
CACHE_KIND = CacheKind(
    name="SURE", article="a", manifest=CACHE_MANIFEST, lock=LOCK_NAME, format=CACHE_FORMAT,
    version=CACHE_VERSION,
    record_fields={"path": str, "sha256": str, "bytes": int, "source_sha256": str,
                   "seed?": int, "seconds?": float},
    identity_fields={"dataset": dict, "denoiser": dict, "settings": dict},
)


def eligible_items(manifest) -> list:
    """Input items that have a variance (spp >= 2)."""
    return [item for item in manifest.items if item.kind == "input" and item.spp >= 2]


# ------------------------------------------------------------------------------- reading
class SureCache(ItemCacheReader):
    """A built SURE cache, opened for reading (see the module docstring for the layout).

    ``SureCache(dataset_dir, cache_dir)`` checks that the cache was computed from this dataset.
    ``missing`` lists the input items (spp >= 2) without a valid cached file; ``identity`` is
    the recorded denoiser and settings. Decoded items are kept in memory up to
    ``memory_limit`` bytes.
    """

    NAMES = ("denoised", "sure")

    def __init__(self, dataset_dir, cache_dir, *, memory_limit: int = MEMORY_LIMIT_BYTES):
        from jaxden.data.layout import load_manifest

        self.dataset_dir = Path(dataset_dir)
        self.directory = Path(cache_dir)
        self.dataset = load_manifest(self.dataset_dir)
        data = read_manifest(self.directory, CACHE_KIND)
        if data is None:
            raise DatasetError(
                f"{self.directory} holds no SURE cache ({CACHE_MANIFEST} missing): build it with "
                f"`jaxden dataset sure-cache {self.dataset_dir} --denoiser NAME`"
            )
        self.identity = data.get("identity", {})
        self.cache_key = data.get("cache_key")
        dataset_identity = cache_dataset_identity(self.dataset)
        if self.identity.get("dataset") != dataset_identity:
            raise DatasetError(
                f"{self.directory}: the SURE cache was computed from another dataset "
                f"({self.identity.get('dataset')}), not {self.dataset_dir} ({dataset_identity})"
            )
        self.records: dict[str, dict] = data.get("items", {})
        self._items = {item.id: item for item in self.dataset.items}
        crops = self.dataset.crop_by_id()
        self._split = {item.id: crops[item.crop].split for item in self.dataset.items}
        super().__init__(memory_limit)

    @property
    def missing(self) -> list[str]:
        """Eligible items whose record is absent or was computed from another dataset file."""
        return [
            item.id for item in eligible_items(self.dataset)
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

    def crops_for(self, batch) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int, int]]]:
        """The cached denoised image and SURE cut like the loader cut ``batch``.

        ``batch``: a :class:`jaxden.data.loader.Batch` with input colour and variance
        (B, h, w, 3). The loader does not report its crop windows, so each sample's window and
        symmetry are recovered by exact matching of its colour and variance against the item
        (:func:`jaxden.data.item_cache.locate_crop`); the result is a pure function of the
        batch.

        Returns ``(denoised, sure, windows)``: (B, h, w, 3) float32 arrays and
        ``(top, left, symmetry)`` per sample.
        """
        cut, windows = self._cut(batch, "crops_for")
        return cut["denoised"], cut["sure"], windows
