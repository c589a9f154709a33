"""Building a SURE cache (build_sure_cache: resumable, locked, checksummed) and opening the one a
mixer's training needs (open_training_cache: found, finished or built).
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import Any

import jax

from jaxden.data.item_cache import (
    build_items,
    cache_dataset_identity,
    denoiser_identity,
    file_record,
    finished,
    identity_key,
    item_state,
    read_manifest,
)
from jaxden.errors import DatasetError
from jaxden.fileio import folder_lock
from jaxden.progressive.cache import (
    CACHE_KIND,
    CACHE_MANIFEST,
    LOCK_NAME,
    SureCache,
    default_cache_dir,
    eligible_items,
    item_seed,
    read_sure_exr,
    write_sure_exr,
)
from jaxden.sure.denoiser import denoise_with_sure, for_denoiser, resolve_denoiser
from jaxden.sure.settings import SureSettings, resolve_settings


def _lock(directory: Path):
    return folder_lock(directory, LOCK_NAME, "SURE cache build")


#: Fields of the SURE settings that do not change a cache's maps (probe_batch: memory only;
#: the chunks sum the same probes), left out of its identity.
NOT_IN_IDENTITY = ("probe_batch",)


def cache_settings(settings: SureSettings, denoiser, half: bool = False) -> dict[str, Any]:
    """The ``settings`` entry of a SURE cache's identity: the resolved SURE settings for
    ``denoiser`` (:func:`jaxden.sure.denoiser.for_denoiser`) in the cache's keys
    (``num_probes``, ``method``, ``eps``, ``fd_scheme`` (None for jvp), ``seed``, ``half``),
    plus every other field that changes the maps where it is not a mixer's default
    (``covariance``, ``probe_dist``, and an option added later): absent when off, so caches
    built before a field existed keep their key."""
    from jaxden.progressive.mixer_config import MIXER_SURE

    settings = for_denoiser(resolve_settings(settings, MIXER_SURE), denoiser)
    identity: dict[str, Any] = {
        "num_probes": settings.probes,
        "method": settings.method,
        "eps": settings.eps,
        "fd_scheme": settings.fd_scheme if settings.method == "fd" else None,
        "seed": settings.seed,
        "half": bool(half),
    }
    named = ("probes", "method", "eps", "fd_scheme", "seed", *NOT_IN_IDENTITY)
    for name, value in settings.given().items():
        if name not in named and value != getattr(MIXER_SURE, name):
            identity[name] = value
    return identity


def build_sure_cache(dataset_dir, denoiser_spec, out_dir=None, *,
                     sure: SureSettings | None = None, half: bool = False,
                     progress: bool = True, **options) -> SureCache:
    """Compute (or finish) the SURE cache of ``denoiser_spec`` over a built dataset.

    Args:
      dataset_dir: a complete dataset folder (``jaxden dataset build``).
      denoiser_spec: ``"oidn"``, a checkpoint folder / .msgpack of a trained denoiser, or a
        :class:`jaxden.denoise.Denoiser`.
      out_dir: cache folder; default :func:`default_cache_dir` (``DATASET/derived/<name>``).
      sure: the :class:`~jaxden.sure.settings.SureSettings`; unset fields are a mixer's
        (:data:`jaxden.progressive.mixer_config.MIXER_SURE`: 4 probes, ``auto``, the measured
        step, seed 0, per channel). The older keywords ``options`` (``num_probes=``,
        ``method=``, ``eps=``, ``seed=``, ``fd_scheme=``, ``probe_batch=``, ``covariance=``,
        ``probe_dist=``) override it where given. Item i uses
        ``PRNGKey(item_seed(seed, i))``; with ``covariance`` every item must carry a colour
        covariance.
      half: store float16 channels (the authors' choice; float32 by default so the cache
        equals a direct computation bit for bit).
      progress: show a tqdm bar.

    Returns the opened :class:`SureCache`. Raises DatasetError when the dataset is incomplete,
    the folder holds a cache of another dataset / denoiser / setting (naming the
    differences) or unrelated files; ConfigError for bad options.
    """
    from jaxden.config import config_diff
    from jaxden.data.layout import load_manifest
    from jaxden.io.exr import read_frame
    from jaxden.progressive.mixer_config import MIXER_SURE

    settings = resolve_settings(sure, MIXER_SURE, **options)
    dataset_dir = Path(dataset_dir)
    manifest = load_manifest(dataset_dir)
    if not manifest.complete:
        done = sum(item.done for item in manifest.items)
        raise DatasetError(
            f"dataset {dataset_dir} is incomplete ({done} of {len(manifest.items)} files built): "
            f"finish it with `jaxden dataset build` before computing SURE"
        )
    denoiser = resolve_denoiser(denoiser_spec)
    settings = for_denoiser(settings, denoiser)
    identity = {
        "dataset": cache_dataset_identity(manifest),
        "denoiser": denoiser_identity(denoiser),
        "settings": cache_settings(settings, denoiser, half),
    }
    cache_key = identity_key(identity)
    directory = (Path(out_dir) if out_dir is not None
                 else default_cache_dir(dataset_dir, denoiser, settings))
    if directory.exists() and not directory.is_dir():
        raise DatasetError(f"{directory} exists and is not a folder")
    directory.mkdir(parents=True, exist_ok=True)
    items = eligible_items(manifest)

    def state(item, record: dict | None) -> tuple[str, dict | None]:
        return item_state(directory, item, record, cache_key, {"source_sha256": item.sha256},
                          read_sure_exr, lambda header: {"seed": header.get("seed"),
                                                         "seconds": None})

    if finished(directory, CACHE_KIND, items, identity, state):
        # Only read: no lock, so runs sharing a finished cache (a sweep) never block each other.
        return SureCache(dataset_dir, directory)

    with _lock(directory):
        stored = read_manifest(directory, CACHE_KIND)
        if stored is not None:
            differences = config_diff(stored.get("identity", {}), identity)
            if differences and not config_diff(_without_code(stored.get("identity", {})),
                                               _without_code(identity)):
                # Same denoiser, weights and settings, other code: what the old code computed
                # is not this denoiser's output. Recompute in place: without the records,
                # each file is judged by its header's cache key, the old code's.
                print(f"jaxden: note: {directory}: the denoiser's code changed since this SURE "
                      f"cache was built; recomputing it", file=sys.stderr)
                differences = []
                stored = {**stored, "items": {}}
            if differences:
                raise DatasetError(
                    f"{directory / CACHE_MANIFEST} holds a SURE cache of another dataset, "
                    f"denoiser or setting; differences (stored -> given): "
                    + "; ".join(differences)
                    + ". Write into another folder (out_dir / --out), or delete it to rebuild."
                )
        skipped = [item.id for item in manifest.items if item.kind == "input" and item.spp < 2]

        def compute(item) -> dict[str, Any]:
            frame = read_frame(dataset_dir / item.path, require=("color", "variance"))
            if settings.covariance and frame.covariance is None:
                raise DatasetError(
                    f"{dataset_dir / item.path}: no colour covariance (channels "
                    f"covariance.RG/GB/BR), which SURE from the covariance needs "
                    f"(sure.covariance = true); rebuild the dataset with this jaxden, "
                    f"which records it, or turn sure.covariance off")
            seed_i = item_seed(settings.seed, item.id)
            result, _ = denoise_with_sure(
                denoiser, frame, jax.random.PRNGKey(seed_i), sure=settings,
                where=str(dataset_dir / item.path),
            )
            path = directory / item.path
            path.parent.mkdir(parents=True, exist_ok=True)
            write_sure_exr(path, result, half=half, attributes={
                "item": item.id, "cache_key": cache_key, "source_sha256": item.sha256,
                "denoiser": denoiser.name, "probes": settings.probes,
                "method": settings.method,
                "eps": -1.0 if settings.eps is None else float(settings.eps),
                "seed": seed_i, "spp": item.spp,
            })
            return {**file_record(directory, item.path), "source_sha256": item.sha256,
                    "seed": seed_i}

        build_items(directory, CACHE_KIND, items, stored, state, compute, {
            "identity": identity, "cache_key": cache_key,
            "info": _runtime_info(denoiser, denoiser_spec), "skipped_no_variance": skipped,
        }, progress=progress, label=f"SURE cache {denoiser.name}")
    return SureCache(dataset_dir, directory)


def _without_code(identity: dict) -> dict:
    """A cache identity without the denoiser's code hash (what stays equal when only the
    denoiser's code changed)."""
    denoiser = {k: v for k, v in dict(identity.get("denoiser") or {}).items()
                if k != "code_sha256"}
    return {**identity, "denoiser": denoiser}


def _runtime_info(denoiser, spec) -> dict[str, Any]:
    """Recorded, not compared: where the denoiser came from and library versions."""
    from importlib import metadata

    info: dict[str, Any] = {"spec": str(spec) if isinstance(spec, (str, os.PathLike)) else None,
                            "jax": jax.__version__}
    if not denoiser.differentiable:
        with contextlib.suppress(metadata.PackageNotFoundError):
            info["pyoidn"] = metadata.version("pyoidn")
    return info


def open_training_cache(dataset_dir, config) -> SureCache:
    """The SURE cache a :class:`jaxden.progressive.MixerConfig` asks for (its ``denoiser``
    and ``sure`` settings), built or finished first when ``config.build_cache`` (a complete
    cache costs one checksum pass to confirm)."""
    denoiser = resolve_denoiser(config.denoiser)
    directory = (Path(config.cache) if config.cache
                 else default_cache_dir(dataset_dir, denoiser, config.sure))
    if config.build_cache:
        return build_sure_cache(dataset_dir, denoiser, directory, sure=config.sure)
    cache = SureCache(dataset_dir, directory)
    settings = cache.identity.get("settings", {})
    wanted = {"denoiser": denoiser_identity(denoiser),
              **{k: v for k, v in cache_settings(config.sure, denoiser).items() if k != "half"}}
    stored = {"denoiser": cache.identity.get("denoiser"),
              **{k: v for k, v in settings.items() if k != "half"}}
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
