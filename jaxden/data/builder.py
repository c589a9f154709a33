"""Build a dataset: render every planned item to EXR, resumably and in parallel.

``build_dataset(config, out_dir)`` plans the dataset (:func:`jaxden.data.layout.plan_dataset`),
skips the items already built, renders the rest through an executor
(:mod:`jaxden.executor`) and records each item's SHA-256 in ``manifest.json``.

Resuming: the manifest is rewritten (atomically) every few seconds and at the end, and every
EXR is written atomically (temporary name + rename), so a build killed at any moment can be
rerun with the same command. On rerun an item counts as finished when its file is present and
matches the recorded checksum, or, for a file finished after the last manifest save, when it
reads back as a complete frame whose header names this item, seed and spp. Anything else
(missing, corrupt, foreign) is rendered again; leftover temporary files are removed. A rerun
with a different config, or a different renderer, into the same folder is a DatasetError that
names the differences.

Parallelism: one Mitsuba ``llvm`` render already uses every core, so the default is one
worker process per 8 CPUs (:func:`jaxden.executor.default_workers`); on a cluster use Ray
(``executor='ray'``). Work is handed out one crop at a time (:class:`CropTask`), because
Mitsuba compiles a kernel per crop window, and the build time is mostly that compilation
(build times by executor and worker count: docs/results.md, "Data").
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.config import DatasetConfig, load_dataset_config
from jaxden.data.layout import (
    CONFIG_NAME,
    LOCK_NAME,
    MANIFEST_NAME,
    TEMP_PATTERN,
    Item,
    Manifest,
    load_manifest,
    plan_dataset,
    required_features,
    sha256_file,
)
from jaxden.errors import DatasetError, SceneError
from jaxden.render.scene_cache import render_cached

SAVE_INTERVAL_S = 5.0

RenderFn = Callable[..., Any]


@dataclasses.dataclass(frozen=True)
class RenderTask:
    """Everything needed to render and write one item (picklable)."""

    item_id: str
    path: str
    spp: int
    seed: int


@dataclasses.dataclass(frozen=True)
class CropTask:
    """The pending items of one crop, rendered one after another by one worker.

    Grouping by crop matters for speed: Mitsuba compiles its kernels with the film's crop
    window baked in (a new crop costs an LLVM compile, more than rendering it at low spp:
    docs/results.md, "Data"), and every later render of the same crop reuses the kernel.
    """

    directory: str
    scene: str
    size: tuple[int, int]  # full film (width, height)
    window: tuple[int, int, int, int]  # (top, left, height, width)
    half: bool
    dataset: str
    items: tuple[RenderTask, ...]
    render_fn: RenderFn | None = None
    threads: int | None = None  # Dr.Jit worker threads for this process (None: all cores)
    aux: str = "first-hit"  # DatasetConfig.aux; passed to the renderer only when not default
    feature_spp: int = 16  # DatasetConfig.feature_spp; passed only when not the default 16
    statistics: bool = False  # DatasetConfig.statistics; passed only when True
    parameters: tuple[tuple[str, str], ...] = ()  # DatasetConfig.scene_parameters (XML scenes)
    scene_file: str = ""  # an XML scene's absolute path (workers may run in another folder)


def _feature_options(aux: str, feature_spp: int, statistics: bool = False) -> dict[str, Any]:
    """The feature keywords a dataset passes to its renderer: only those off their defaults,
    so render functions written before they existed keep working on ordinary datasets."""
    options: dict[str, Any] = {"statistics": True} if statistics else {}
    if aux != "first-hit":
        options["aux"] = aux
    if feature_spp != 16:
        options["feature_spp"] = feature_spp
    return options


def _missing_keywords(render_fn: RenderFn, names) -> list[str]:
    import inspect

    try:
        parameters = inspect.signature(render_fn).parameters.values()
    except (TypeError, ValueError):
        return []  # cannot tell (a builtin); let the call decide
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return []
    return [name for name in names if name not in {p.name for p in parameters}]


def renderer_name(render_fn: RenderFn | None) -> str:
    """What a manifest records as the renderer of ``render_fn`` (``module.qualname``; None:
    jaxden's Mitsuba renderer): a rerun with another renderer is refused."""
    if render_fn is None:
        return "jaxden.render.core.render_frame"
    name = getattr(render_fn, "__qualname__", None) or type(render_fn).__qualname__
    return f"{getattr(render_fn, '__module__', '?')}.{name}"


def render_crop(task: CropTask) -> list[dict[str, Any]]:
    """Render, check and atomically write every item of one crop; return checksum records.

    Runs in a worker process. The render function is called as
    ``render_fn(scene, spp, seed=seed, size=(width, height), crop=(top, left, height, width))``
    (plus ``aux=`` / ``feature_spp=`` when the dataset's differ from ``"first-hit"`` / 16, and
    ``statistics=True`` when the dataset asks for them)
    and must return a :class:`jaxden.frame.Frame` of the crop's size with the dataset features.
    """
    render = task.render_fn or render_cached
    if task.threads is not None:
        import drjit as dr

        if dr.thread_count() != task.threads:
            dr.set_thread_count(task.threads)
    records: list[dict[str, Any]] = []
    try:
        for item in task.items:
            records.append(_render_one(task, item, render))
    except Exception as error:
        # Hand the items finished before the failure back with the error (exceptions pickle
        # their __dict__), so the manifest records them even from another process.
        error.jaxden_finished = records  # type: ignore[attr-defined]
        raise
    return records


def _render_one(task: CropTask, item: RenderTask, render: RenderFn) -> dict[str, Any]:
    from jaxden.io.exr import write_frame

    top, left, height, width = task.window
    start = time.perf_counter()
    extra = _feature_options(task.aux, task.feature_spp, task.statistics)
    if task.parameters:
        extra["parameters"] = dict(task.parameters)
    frame = render(task.scene_file or task.scene, item.spp, seed=item.seed, size=task.size,
                   crop=task.window, **extra)
    seconds = time.perf_counter() - start
    _check_render(frame, task, item)
    if frame.spp is None:
        frame = frame.replace(spp=np.float32(item.spp))
    path = Path(task.directory) / item.path
    attributes = {
        "seed": item.seed,
        "scene": task.scene,
        "item": item.item_id,
        "crop": f"{top},{left},{height},{width}",
        "dataset": task.dataset,
    }
    if task.render_fn is None:  # jaxden's renderer: the features it made (data.features)
        from jaxden.render.core import feature_attributes

        attributes.update(feature_attributes(item.spp, task.aux, task.feature_spp))
    write_frame(path, frame, half=task.half, attributes=attributes)
    return {
        "id": item.item_id,
        "sha256": sha256_file(path),
        "bytes": path.stat().st_size,
        "render_seconds": round(seconds, 4),
    }


def _check_render(frame: Any, task: CropTask, item: RenderTask) -> None:
    from jaxden.frame import Frame

    who = f"{renderer_name(task.render_fn)} for item {item.item_id} ({task.scene}, {item.spp} spp)"
    if not isinstance(frame, Frame):
        raise DatasetError(f"{who} returned {type(frame).__name__}, not a Frame")
    height, width = task.window[2], task.window[3]
    if tuple(np.shape(frame.color)) != (height, width, 3):
        raise DatasetError(
            f"{who} returned colour of shape {np.shape(frame.color)}, expected the crop's "
            f"({height}, {width}, 3)"
        )
    missing = [f for f in required_features(item.spp) + (("boxcox",) if task.statistics else ())
               if getattr(frame, f) is None]
    if missing:
        raise DatasetError(f"{who} returned a frame without {', '.join(missing)}")
    if frame.spp is not None and float(np.asarray(frame.spp)) != float(item.spp):
        raise DatasetError(f"{who} returned a frame with spp {frame.spp}, expected {item.spp}")


# ----------------------------------------------------------------------------- checks
def check_scenes(scene_ids: list[str], parameters: dict[str, str] | None = None) -> None:
    """Raise SceneError for a scene the renderer cannot know (before any rendering starts);
    XML files are read with their includes and ``parameters`` (missing includes, cycles,
    undefined ``$names`` fail here)."""
    from difflib import get_close_matches

    from jaxden.render.scenes import list_scenes

    names = list(list_scenes())
    for scene in scene_ids:
        if scene.startswith("procedural:"):
            continue
        if scene.lower().endswith(".xml"):
            if not Path(scene).is_file():
                raise SceneError(f"scene file {scene} does not exist (relative to {os.getcwd()})")
            from jaxden.render.scene_xml import flatten_scene

            flatten_scene(scene, parameters)
            continue
        if scene not in names:
            close = get_close_matches(scene, names, 1)
            hint = f"; did you mean '{close[0]}'?" if close else ""
            raise SceneError(
                f"unknown scene {scene!r}{hint} Built-in scenes: {', '.join(names)}; or use "
                f"'procedural:SEED' or a path to a Mitsuba .xml file"
            )


def _item_state(directory: Path, item: Item, window: tuple[int, int, int, int]) -> str:
    """'done', 'missing', 'corrupt' (checksum mismatch or unreadable) or 'recovered'
    (finished after the last manifest save; its checksum is filled into ``item``)."""
    path = directory / item.path
    if not path.is_file():
        return "missing"
    if item.sha256 is not None:
        if path.stat().st_size == item.bytes and sha256_file(path) == item.sha256:
            return "done"
        return "corrupt"
    from jaxden.data.verify import check_item_file

    if check_item_file(path, item, window):
        return "corrupt"
    item.sha256 = sha256_file(path)
    item.bytes = path.stat().st_size
    return "recovered"


def _clean_temporaries(directory: Path) -> int:
    removed = 0
    for root, _, files in os.walk(directory):
        for name in files:
            if TEMP_PATTERN.match(name):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(root, name))
                    removed += 1
    return removed


def _build_lock(directory: Path):
    from jaxden.fileio import folder_lock

    return folder_lock(directory, LOCK_NAME, "build")


def config_with_defaults(stored_config: dict[str, Any]) -> dict[str, Any]:
    """A stored dataset config with the fields added since it was written at their defaults
    (e.g. ``aux``), so that an older dataset still resumes under the same config."""
    from jaxden.config import config_to_dict
    from jaxden.errors import ConfigError

    try:
        return config_to_dict(load_dataset_config(stored_config))
    except (ConfigError, TypeError, ValueError):  # unreadable today: compare it as it is
        return stored_config


def _reconcile(stored: Manifest, planned: Manifest, directory: Path) -> Manifest:
    """Check a stored manifest against a fresh plan; return the plan with stored checksums."""
    from jaxden.config import config_diff

    where = directory / MANIFEST_NAME
    if not any(item.done for item in stored.items) and not any(directory.rglob("*.exr")):
        return planned  # nothing was built yet (e.g. the first render failed): start afresh
    differences = config_diff(config_with_defaults(stored.config), planned.config)
    if differences:
        raise DatasetError(
            f"{where} was built from a different config; differences (stored -> given): "
            + "; ".join(differences)
            + f". Build into another folder, or delete {directory} to rebuild it."
        )
    if stored.renderer != planned.renderer:
        raise DatasetError(
            f"{where} was built with the renderer {stored.renderer}, not {planned.renderer}; "
            f"build into another folder"
        )
    if [i.plan_key() for i in stored.items] != [i.plan_key() for i in planned.items] or [
        c.window for c in stored.crops
    ] != [c.window for c in planned.crops]:
        raise DatasetError(
            f"{where}: the same config now gives a different plan (crops, seeds or file names); "
            f"it was made by jaxden {stored.jaxden_version or '?'}: rebuild into another folder"
        )
    for item, old in zip(planned.items, stored.items):
        item.sha256, item.bytes, item.render_seconds = old.sha256, old.bytes, old.render_seconds
    planned.created = stored.created
    planned.extra = stored.extra
    return planned


# ----------------------------------------------------------------------------- build
def build_dataset(
    config: DatasetConfig | str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    executor: str = "local",
    workers: int | None = None,
    render_fn: RenderFn | None = None,
    progress: bool = True,
    ray_address: str | None = None,
) -> Manifest:
    """Render every item of the dataset into ``out_dir`` and return the complete manifest.

    ``config``: a DatasetConfig (or a TOML path). ``executor``: 'local' (spawned processes),
    'serial' (this process) or 'ray'; ``workers``: parallel renders (default: see
    :func:`jaxden.executor.default_workers`). ``render_fn``: the renderer, called as
    ``render_fn(scene, spp, seed=, size=(w, h), crop=(top, left, h, w)) -> Frame``; default
    ``jaxden.render.core.render_frame``. With a process pool it must be picklable (a
    module-level function). ``progress``: show a tqdm bar (in samples rendered).
    ``ray_address``: the Ray cluster of ``executor='ray'`` (None: ``RAY_ADDRESS``; see
    :class:`jaxden.executor.RayExecutor`). Paths reach the workers absolute.

    Safe to interrupt and rerun (see the module docstring). Raises DatasetError when the folder
    holds another dataset or something else, SceneError for an unknown scene (checked before
    any rendering), and re-raises the first failing render's error after saving the progress.
    """
    from jaxden.executor import make_executor

    if not isinstance(config, DatasetConfig):
        config = load_dataset_config(config)
    options = _feature_options(config.aux, config.feature_spp, config.statistics)
    missing = _missing_keywords(render_fn, options) if render_fn is not None else []
    if missing:
        raise DatasetError(
            "the dataset's " + ", ".join(f"{name} = {options[name]!r}" for name in missing)
            + " needs a renderer that takes "
            + ", ".join(f"`{name}=`" for name in missing)
            + f"; {renderer_name(render_fn)} does not")
    directory = Path(out_dir)
    if directory.exists() and not directory.is_dir():
        raise DatasetError(f"{directory} exists and is not a folder")
    planned = plan_dataset(config)
    planned.renderer = renderer_name(render_fn)
    if render_fn is None:  # before the output folder exists: nothing left behind
        try:
            check_scenes(config.scene_ids(), config.scene_parameters)
        except SceneError as error:
            raise SceneError(f"dataset config 'scenes': {error}") from None
    # Join the executor (a Ray cluster) before anything is written: a cluster that cannot
    # be reached leaves no folder behind.
    pool = make_executor(executor, workers, ray_address=ray_address)
    try:
        return _build(config, directory, planned, pool, executor=executor, workers=workers,
                      render_fn=render_fn, progress=progress)
    finally:
        pool.close()


def _build(config: DatasetConfig, directory: Path, planned: Manifest, pool: Any, *,
           executor: str, workers: int | None, render_fn: RenderFn | None,
           progress: bool) -> Manifest:
    """The body of :func:`build_dataset` once the executor is there."""
    directory.mkdir(parents=True, exist_ok=True)

    with _build_lock(directory):
        manifest_file = directory / MANIFEST_NAME
        if manifest_file.exists():
            manifest = _reconcile(load_manifest(directory), planned, directory)
        else:
            foreign = [
                p.name
                for p in directory.iterdir()
                if p.name != LOCK_NAME and not TEMP_PATTERN.match(p.name)
            ]
            if foreign:
                raise DatasetError(
                    f"{directory} is not empty ({', '.join(sorted(foreign)[:5])}...) and has no "
                    f"{MANIFEST_NAME}: refusing to build a dataset into it"
                )
            manifest = planned
        _clean_temporaries(directory)
        windows = {crop.id: crop.window for crop in manifest.crops}
        crops = manifest.crop_by_id()
        pending: list[Item] = []
        for item in manifest.items:
            state = _item_state(directory, item, windows[item.crop])
            if state in ("missing", "corrupt"):
                if state == "corrupt":
                    (directory / item.path).unlink(missing_ok=True)
                item.sha256 = item.bytes = item.render_seconds = None
                pending.append(item)
        if render_fn is None and pending:  # the renderer's files carry covariance, emission
            from jaxden.data.verify import check_renderer_fields_recorded

            check_renderer_fields_recorded(directory, manifest.items, skip=pending)
        for item in pending:
            (directory / item.path).parent.mkdir(parents=True, exist_ok=True)
        manifest.save(directory)
        from jaxden.config import save_config

        save_config(
            config,
            directory / CONFIG_NAME,
            header=f"Resolved config of this dataset (jaxden {planned.jaxden_version})",
        )
        if not pending:
            return manifest

        threads = _threads_per_worker(executor, workers) if render_fn is None else None
        tasks = []
        for crop_id in dict.fromkeys(item.crop for item in pending):  # plan order
            crop_items = sorted((i for i in pending if i.crop == crop_id), key=lambda i: -i.spp)
            tasks.append(
                CropTask(
                    directory=str(directory.absolute()),
                    scene=crops[crop_id].scene,
                    size=tuple(config.size),
                    window=windows[crop_id],
                    half=config.half,
                    dataset=config.name,
                    items=tuple(RenderTask(i.id, i.path, i.spp, i.seed) for i in crop_items),
                    render_fn=render_fn,
                    threads=threads,
                    aux=config.aux,
                    feature_spp=config.feature_spp,
                    statistics=config.statistics,
                    parameters=tuple(sorted(config.scene_parameters.items())),
                    scene_file=_scene_file(crops[crop_id].scene),
                )
            )
        by_id = manifest.item_by_id()
        pixels = config.crop_size**2
        bar = _progress_bar(manifest, pixels, enabled=progress, name=config.name)
        last_save = time.monotonic()

        def record(records: list[dict[str, Any]]) -> None:
            for entry in records:
                item = by_id[entry["id"]]
                item.sha256, item.bytes = entry["sha256"], entry["bytes"]
                item.render_seconds = entry["render_seconds"]
                if bar is not None:
                    bar.update(item.spp * pixels)

        try:
            try:
                results = pool.map_unordered(render_crop, tasks)
                for records in results:
                    record(records)
                    if bar is not None:
                        bar.set_postfix_str(
                            f"{sum(i.done for i in manifest.items)}/{len(manifest.items)} files"
                        )
                    if time.monotonic() - last_save > SAVE_INTERVAL_S:
                        manifest.save(directory)
                        last_save = time.monotonic()
            except Exception as error:
                record(getattr(error, "jaxden_finished", []))
                raise
        finally:
            if bar is not None:
                bar.close()
            manifest.save(directory)
        return manifest


def _scene_file(scene: str) -> str:
    return str(Path(scene).absolute()) if scene.lower().endswith(".xml") else ""


def _threads_per_worker(executor: str, workers: int | None) -> int | None:
    """Share the cores between local worker processes (each Mitsuba render would otherwise
    start a thread per core in every process); a Ray task renders on the one CPU Ray gave it."""
    if executor == "ray":
        return 1
    if executor != "local":
        return None
    from jaxden.executor import default_workers

    count = default_workers() if workers is None else workers
    return max(1, (os.cpu_count() or 1) // max(1, count)) if count > 1 else None


def _progress_bar(manifest: Manifest, pixels: int, *, enabled: bool, name: str):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    total = sum(item.spp for item in manifest.items) * pixels
    done = sum(item.spp for item in manifest.items if item.done) * pixels
    return tqdm(
        total=total,
        initial=done,
        unit=" samples",
        unit_scale=True,
        desc=f"build {name}",
        dynamic_ncols=True,
    )
