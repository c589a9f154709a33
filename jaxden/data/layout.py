"""Dataset layout on disk: the plan (crops, items, seeds, splits) and ``manifest.json``.

A dataset directory looks like::

    DIR/manifest.json                        the plan, the resolved config, per-item checksums
    DIR/dataset.toml                         the resolved config (rebuild: jaxden dataset build)
    DIR/s000-cornell-box/c000/spp00002.exr   one render of crop 0 of scene 0 at 2 spp
    DIR/s000-cornell-box/c000/reference.exr  the crop's independent reference render
    ...

Everything in the plan is a pure function of the :class:`DatasetConfig` (:func:`plan_dataset`),
so the same config always gives the same crops, seeds and splits, on any machine and in any
build order. Seeds are derived by hashing (base seed, scene id, crop index, spp / 'reference'),
so every render has its own sampler seed: the inputs at different spp are independent of one
another and of the reference (the reference-noise-corrected MSE needs that independence).

Each item's EXR header records ``jaxden.spp``, ``jaxden.seed``, ``jaxden.scene``,
``jaxden.item`` (the item id) and ``jaxden.crop`` ("top,left,height,width" in film pixels).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import math
import os
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np

from jaxden.data.config import SPLIT_NAMES, DatasetConfig
from jaxden.errors import DatasetError
from jaxden.provenance import file_sha256

MANIFEST_NAME = "manifest.json"
CONFIG_NAME = "dataset.toml"  # the resolved config as TOML, for people (the manifest is canonical)
LOCK_NAME = ".build.lock"
MANIFEST_FORMAT = "jaxden-dataset"
MANIFEST_VERSION = 1
REFERENCE_NAME = "reference.exr"
# Features every item must have (variance too when spp > 1): what the denoisers and the
# progressive-denoising mixer read.
ITEM_FEATURES: tuple[str, ...] = ("color", "albedo", "normal", "depth")
# The temporary names jaxden.io.exr uses for atomic writes (".NAME.XXXX.tmp.exr").
TEMP_PATTERN = re.compile(r"^\..*\.tmp(\.exr)?$")

ItemKind = Literal["input", "reference"]


def derive_seed(base_seed: int, *parts: Any) -> int:
    """A 31-bit seed from the base seed and any JSON-able parts (stable across machines and
    Python versions; 31 bits so that any renderer taking an int32 or uint32 accepts it)."""
    digest = hashlib.sha256(json.dumps([int(base_seed), *parts]).encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def required_features(spp: int) -> tuple[str, ...]:
    """The features an item rendered at ``spp`` must have (variance needs >= 2 samples)."""
    return ITEM_FEATURES + (("variance",) if spp > 1 else ())


def _slug(scene: str) -> str:
    if scene.startswith("procedural:"):
        text = "procedural-" + scene.split(":", 1)[1]
    elif scene.lower().endswith(".xml"):
        text = Path(scene).stem
    else:
        text = scene
    return re.sub(r"[^A-Za-z0-9_-]+", "-", text).strip("-")[:40] or "scene"


@dataclasses.dataclass(frozen=True)
class Crop:
    """One crop window of one scene: ``window`` = (top, left, height, width) in film pixels."""

    id: str
    scene: str
    scene_index: int
    crop_index: int
    window: tuple[int, int, int, int]
    split: str


@dataclasses.dataclass
class Item:
    """One render (one EXR file). ``sha256``/``bytes`` are None until it is built."""

    id: str
    crop: str
    path: str  # relative to the dataset directory, '/'-separated
    kind: ItemKind
    spp: int
    seed: int
    sha256: str | None = None
    bytes: int | None = None
    render_seconds: float | None = None

    @property
    def done(self) -> bool:
        return self.sha256 is not None

    def plan_key(self) -> tuple:
        """What must agree between a stored manifest and a fresh plan."""
        return (self.id, self.crop, self.path, self.kind, self.spp, self.seed)


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


@dataclasses.dataclass
class Manifest:
    """The plan of a dataset plus its build state. Saved as ``DIR/manifest.json``."""

    config: dict[str, Any]
    scenes: list[dict[str, Any]]
    crops: list[Crop]
    items: list[Item]
    renderer: str = "jaxden.render.core.render_frame"
    created: str = dataclasses.field(default_factory=_now)
    updated: str = dataclasses.field(default_factory=_now)
    jaxden_version: str = ""
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    # ----------------------------------------------------------------- queries
    @property
    def complete(self) -> bool:
        return all(item.done for item in self.items)

    @property
    def crop_size(self) -> int:
        return int(self.config["crop_size"])

    def crop_by_id(self) -> dict[str, Crop]:
        return {crop.id: crop for crop in self.crops}

    def item_by_id(self) -> dict[str, Item]:
        return {item.id: item for item in self.items}

    def crops_in(self, split: str) -> list[Crop]:
        """Crops of one split ('train', 'val', 'test'), or all for 'all'."""
        if split != "all" and split not in SPLIT_NAMES:
            raise DatasetError(
                f"unknown split {split!r}; choose one of {', '.join(SPLIT_NAMES)} or 'all'"
            )
        return [c for c in self.crops if split == "all" or c.split == split]

    def items_of(self, crop_id: str) -> list[Item]:
        return [item for item in self.items if item.crop == crop_id]

    def split_counts(self) -> dict[str, int]:
        return {name: sum(c.split == name for c in self.crops) for name in SPLIT_NAMES}

    # ----------------------------------------------------------------- (de)serialisation
    def to_json(self) -> dict[str, Any]:
        return {
            "format": MANIFEST_FORMAT,
            "format_version": MANIFEST_VERSION,
            "jaxden_version": self.jaxden_version,
            "renderer": self.renderer,
            "created": self.created,
            "updated": self.updated,
            "complete": self.complete,
            "items_done": sum(item.done for item in self.items),
            "items_total": len(self.items),
            "config": self.config,
            "scenes": self.scenes,
            "crops": [
                {**dataclasses.asdict(c), "window": list(c.window)} for c in self.crops
            ],
            "items": [dataclasses.asdict(item) for item in self.items],
            **({"extra": self.extra} if self.extra else {}),
        }

    @classmethod
    def from_json(cls, data: Any, where: str = MANIFEST_NAME) -> Manifest:
        """The manifest of ``data`` (parsed JSON); DatasetError naming ``where`` and the field
        for anything jaxden could not use: a wrong type, a crop window that is not 4 whole
        numbers, an item of no crop, a crop without its reference, an item path leaving the
        folder."""
        from jaxden.fileio import check_json_fields

        if not isinstance(data, dict) or data.get("format") != MANIFEST_FORMAT:
            raise DatasetError(
                f"{where}: not a jaxden dataset manifest (no format '{MANIFEST_FORMAT}')"
            )
        if data.get("format_version") != MANIFEST_VERSION:
            raise DatasetError(
                f"{where}: manifest format version {data.get('format_version')} is not supported "
                f"(this jaxden reads version {MANIFEST_VERSION})"
            )
        check_json_fields(data, _MANIFEST_FIELDS, where, DatasetError)
        check_json_fields(data["config"], {"crop_size": int}, f"{where}: field 'config'",
                          DatasetError)
        crops = [_crop_from_json(c, f"{where}: crops[{i}]") for i, c in enumerate(data["crops"])]
        by_id = {crop.id: crop for crop in crops}
        items = [_item_from_json(c, f"{where}: items[{i}]") for i, c in enumerate(data["items"])]
        for name, ids in (("crop", [c.id for c in crops]), ("item", [i.id for i in items])):
            if len(set(ids)) < len(ids):
                twice = min(i for i in ids if ids.count(i) > 1)
                raise DatasetError(f"{where}: two {name}s have the id {twice!r}")
        for index, item in enumerate(items):
            if item.crop not in by_id:
                raise DatasetError(f"{where}: items[{index}] ({item.id!r}) names the crop "
                                   f"{item.crop!r}, which is not in 'crops'")
        for crop in crops:
            references = sum(i.crop == crop.id and i.kind == "reference" for i in items)
            if references != 1:
                raise DatasetError(f"{where}: crop {crop.id!r} has {references} reference "
                                   f"items, expected 1")
        return cls(
            config=data["config"],
            scenes=data["scenes"],
            crops=crops,
            items=items,
            renderer=data.get("renderer") or "",
            created=data.get("created") or "",
            updated=data.get("updated") or "",
            jaxden_version=data.get("jaxden_version") or "",
            extra=data.get("extra") or {},
        )

    def save(self, directory: str | os.PathLike) -> Path:
        """Write ``DIR/manifest.json`` atomically (temporary file + rename)."""
        self.updated = _now()
        path = Path(directory) / MANIFEST_NAME
        text = json.dumps(self.to_json(), indent=1)
        from jaxden.fileio import atomic_write_text

        atomic_write_text(path, text)
        return path


_MANIFEST_FIELDS = {"config": dict, "scenes": list, "crops": list, "items": list,
                   "renderer?": str, "created?": str, "updated?": str, "jaxden_version?": str,
                   "extra?": dict}
_CROP_FIELDS = {"id": str, "scene": str, "scene_index": int, "crop_index": int,
                "window": list, "split": str}
_ITEM_FIELDS = {"id": str, "crop": str, "path": str, "kind": str, "spp": int, "seed": int,
                "sha256?": str, "bytes?": int, "render_seconds?": float}


def _crop_from_json(data: Any, where: str) -> Crop:
    from jaxden.fileio import check_json_fields

    check_json_fields(data, _CROP_FIELDS, where, DatasetError)
    window = data["window"]
    if len(window) != 4 or not all(type(v) is int and v >= 0 for v in window) \
            or min(window[2:]) < 1:
        raise DatasetError(f"{where}: field 'window' must be 4 whole numbers (top, left >= 0, "
                           f"height, width >= 1), found {str(window)[:60]}")
    if data["split"] not in SPLIT_NAMES:
        raise DatasetError(f"{where}: field 'split' must be one of {', '.join(SPLIT_NAMES)}, "
                           f"found {data['split'][:20]!r}")
    return Crop(data["id"], data["scene"], data["scene_index"], data["crop_index"],
                tuple(window), data["split"])


def _item_from_json(data: Any, where: str) -> Item:
    from jaxden.fileio import check_json_fields

    check_json_fields(data, _ITEM_FIELDS, where, DatasetError)
    if data["kind"] not in ("input", "reference"):
        raise DatasetError(f"{where}: field 'kind' must be 'input' or 'reference', found "
                           f"{data['kind'][:20]!r}")
    if data["spp"] < 1:
        raise DatasetError(f"{where}: field 'spp' must be >= 1, found {data['spp']}")
    if not inside_folder(data["path"]):
        raise DatasetError(
            f"{where}: item {data['id']!r} has path {data['path']!r}, which leaves the dataset "
            f"folder (item paths must be relative, without '..')")
    return Item(data["id"], data["crop"], data["path"], data["kind"], data["spp"],
                data["seed"], data.get("sha256"), data.get("bytes"), data.get("render_seconds"))


def inside_folder(relative: str) -> bool:
    """Whether a path read from a file stays inside the folder it is relative to: not
    absolute, no '..' part, not empty (names from files never point elsewhere)."""
    path = Path(relative)
    return bool(relative) and not path.is_absolute() and ".." not in path.parts \
        and not str(relative).startswith("~")


def manifest_path(directory: str | os.PathLike) -> Path:
    return Path(directory) / MANIFEST_NAME


def require_manifest(directory, name: str, kind: str, command: str) -> Path:
    """``directory / name``; DatasetError naming ``kind`` ("dataset", "sequence set") when the
    folder is missing or a file, or has no such manifest (``command`` builds one)."""
    directory = Path(directory)
    if not directory.is_dir():
        raise DatasetError(f"{directory} is a file, not a {kind} folder" if directory.exists()
                           else f"{kind} folder {directory} does not exist")
    path = directory / name
    if not path.exists():
        raise DatasetError(f"{directory} is not a jaxden {kind}: it has no {name} "
                           f"(build one with `{command}`)")
    return path


def load_manifest(directory: str | os.PathLike) -> Manifest:
    """Read ``DIR/manifest.json``; DatasetError if the folder or manifest is missing/invalid."""
    path = require_manifest(directory, MANIFEST_NAME, "dataset",
                            f"jaxden dataset build CONFIG --out {directory}")
    from jaxden.fileio import read_json

    data = read_json(path, "the dataset manifest", error=DatasetError)
    return Manifest.from_json(data, where=str(path))


# ----------------------------------------------------------------------------- planning
def _divide(count: int, fractions: dict[str, float]) -> dict[str, int]:
    """Split ``count`` units by fractions (largest remainder); every split with a positive
    fraction gets at least one unit when ``count`` allows, taken from the largest split."""
    raw = {name: count * f for name, f in fractions.items()}
    counts = {name: math.floor(v + 1e-9) for name, v in raw.items()}
    left = count - sum(counts.values())
    by_remainder = sorted(fractions, key=lambda n: -(raw[n] - counts[n]))
    for name in by_remainder[:left]:
        counts[name] += 1
    for name, fraction in fractions.items():
        if fraction > 0 and counts[name] == 0:
            donor = max(counts, key=lambda n: counts[n])
            if counts[donor] > 1:
                counts[donor] -= 1
                counts[name] += 1
    return counts


def _assign_splits(units: list[str], fractions: dict[str, float], seed: int) -> dict[str, str]:
    """Shuffle ``units`` (seeded) and cut them into consecutive runs by fractions."""
    rng = np.random.default_rng(derive_seed(seed, "split"))
    order = [units[i] for i in rng.permutation(len(units))]
    counts = _divide(len(order), fractions)
    assignment, start = {}, 0
    for name in SPLIT_NAMES:
        for unit in order[start : start + counts[name]]:
            assignment[unit] = name
        start += counts[name]
    return assignment


def plan_dataset(config: DatasetConfig) -> Manifest:
    """The full plan for ``config`` (every item with no checksum yet)."""
    from jaxden import __version__
    from jaxden.config import config_to_dict

    scene_ids = config.scene_ids()
    width, height = config.size
    size = config.crop_size
    digits = max(3, len(str(len(scene_ids) - 1)))
    crop_digits = max(3, len(str(config.crops_per_scene - 1)))
    spp_digits = max(5, len(str(max(config.spp))))
    splits = config.splits
    fractions = {"train": splits.train, "val": splits.val, "test": splits.test}
    explicit = {s: "val" for s in splits.val_scenes} | {s: "test" for s in splits.test_scenes}

    scenes, crops, items = [], [], []
    scene_dirs = []
    for index, scene in enumerate(scene_ids):
        scene_dirs.append(f"s{index:0{digits}d}-{_slug(scene)}")
    free_scenes = [s for s in scene_ids if s not in explicit]
    scene_split = dict(explicit)
    if splits.by == "scene":
        scene_split |= _assign_splits(free_scenes, fractions, config.seed)

    crop_ids = []
    for index, scene in enumerate(scene_ids):
        for c in range(config.crops_per_scene):
            crop_ids.append((index, scene, c, f"s{index:0{digits}d}-c{c:0{crop_digits}d}"))
    crop_split = {}
    if splits.by == "crop":
        free_crops = [cid for (_, scene, _, cid) in crop_ids if scene not in explicit]
        crop_split = _assign_splits(free_crops, fractions, config.seed)

    for index, scene in enumerate(scene_ids):
        scenes.append(
            {"index": index, "id": scene, "dir": scene_dirs[index], "split": scene_split.get(scene)}
        )
    # A replica: the same crops and splits, independent samples (only the render seeds differ).
    replica = ("replica", config.replica) if config.replica else ()
    for index, scene, c, crop_id in crop_ids:
        rng = np.random.default_rng(derive_seed(config.seed, "crop", scene, c))
        top = int(rng.integers(0, height - size + 1))
        left = int(rng.integers(0, width - size + 1))
        split = scene_split[scene] if scene in scene_split else crop_split[crop_id]
        crops.append(Crop(crop_id, scene, index, c, (top, left, size, size), split))
        folder = f"{scene_dirs[index]}/c{c:0{crop_digits}d}"
        items.append(
            Item(
                id=f"{crop_id}-ref",
                crop=crop_id,
                path=f"{folder}/{REFERENCE_NAME}",
                kind="reference",
                spp=config.reference_spp,
                seed=derive_seed(config.seed, "render", scene, c, "reference", *replica),
            )
        )
        for spp in config.spp:
            items.append(
                Item(
                    id=f"{crop_id}-spp{spp}",
                    crop=crop_id,
                    path=f"{folder}/spp{spp:0{spp_digits}d}.exr",
                    kind="input",
                    spp=spp,
                    seed=derive_seed(config.seed, "render", scene, c, "spp", spp, *replica),
                )
            )
    for scene in scenes:  # with by='crop' a scene's split is that of its crops, if they agree
        if scene["split"] is None:
            found = {c.split for c in crops if c.scene == scene["id"]}
            scene["split"] = found.pop() if len(found) == 1 else "mixed"
    return Manifest(
        config=config_to_dict(config),
        scenes=scenes,
        crops=crops,
        items=items,
        jaxden_version=__version__,
    )


#: A file's sha256 (hex): the one definition, in :mod:`jaxden.provenance`.
sha256_file = file_sha256
