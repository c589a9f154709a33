"""Animated sequences: camera paths through static scenes, rendered frame by frame with motion
vectors and per-frame references, for temporal accumulation and real-time denoisers.

Example config (``experiments/configs/sequences-rt-test.toml``)::

    name = "rt-seq"
    scenes = []                  # built-in names, "procedural:SEED" or XML paths
    size = [128, 128]            # film (width, height), pixels
    frames = 16                  # frames per sequence
    spp = 1                      # samples per pixel of the input frames
    reference_spp = 512          # an independent reference render per frame
    seed = 0                     # path and sampler seeds
    path = "random"              # camera path: "random" (seeded, smooth) or "orbit"
    translation = 0.05           # random path: origin / target moves, x the target distance
    rotation_deg = 8.0           # random path: orbit angle per keyframe; orbit path: total
    [procedural]
    count = 4
    seed = 9000

Layout: ``DIR/sequences.json`` (the config, and per sequence its scene and frame files with
SHA-256 checksums), ``DIR/s000-<scene>/f000.exr`` (input: colour, variance when spp > 1,
features, ``motion.X/Y``) and ``.../f000.ref.exr`` (reference, its own motion). Resumable: a
frame whose files are listed with a matching checksum is not rendered again; files are
written atomically and the manifest after every frame; a lock keeps two builds out of one
folder. Frame ``t`` of sequence ``i`` renders with seed ``sequence_seed(seed + i, t)``, the
reference with the reference purpose, so a rebuild gives the same files.

The manifest is read through :func:`jaxden.fileio.read_json` and checked field by field
(types; the sequences, scenes and frame count the config gives; each frame's index and its
two file names inside the sequence's folder; SHA-256s): a broken one is one DatasetError
naming the file and the field, for a resumed build as for the readers. The readers
(:func:`read_manifest`, :func:`load_sequence`) also refuse an unfinished set, and
:func:`load_sequence` a frame file that does not match its checksum or the config's size.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Literal

from jaxden.config import bounded
from jaxden.data.config import ProceduralConfig
from jaxden.errors import ConfigError, DatasetError

MANIFEST_NAME = "sequences.json"
LOCK_NAME = ".sequences.lock"
FORMAT = "jaxden-sequences"


@dataclasses.dataclass(frozen=True)
class SequenceConfig:
    """A set of camera-path sequences (see the module docstring for the fields)."""

    name: str = "sequences"
    scenes: tuple[str, ...] = ()
    procedural: ProceduralConfig = ProceduralConfig()
    size: tuple[int, int] = bounded((128, 128), low=1, high=16384, unit='pixels')
    frames: int = bounded(16, low=2, high=100_000)
    spp: int = bounded(1, low=1, high=2**24)
    reference_spp: int = bounded(512, low=1, high=2**26)
    seed: int = bounded(0, low=0, high=4294967295)
    path: Literal["random", "orbit"] = "random"
    translation: float = bounded(0.05, low=0, high=100)
    rotation_deg: float = bounded(8.0, low=0, high=360)

    def __post_init__(self) -> None:
        if not self.scenes and self.procedural.count == 0:
            raise ConfigError("the sequence set has no scenes: give `scenes` and/or "
                              "`procedural.count`")
        width, height = self.size
        if width <= 0 or height <= 0:
            raise ConfigError(f"size must be positive (width, height), got {list(self.size)}")
        for name, value, low in (("frames", self.frames, 2), ("spp", self.spp, 1),
                                 ("reference_spp", self.reference_spp, 1), ("seed", self.seed, 0)):
            if value < low:
                raise ConfigError(f"{name} must be >= {low}, got {value}")
        if self.reference_spp < self.spp:
            raise ConfigError(f"reference_spp ({self.reference_spp}) must be >= spp ({self.spp})")
        for name in ("translation", "rotation_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"{name} must be a finite number >= 0, got {value}")

    def scene_ids(self) -> list[str]:
        generated = [f"procedural:{self.procedural.seed + i}" for i in range(self.procedural.count)]
        return list(self.scenes) + generated


def load_sequence_config(source, overrides=()) -> SequenceConfig:
    from jaxden.config import load_config

    return load_config(source, SequenceConfig, overrides)


def _slug(scene: str) -> str:
    base = Path(scene).stem if scene.lower().endswith(".xml") else scene
    return "".join(c if c.isalnum() or c in "-_" else "-" for c in base)


def sequence_cameras(config: SequenceConfig, index: int, scene: str):
    """The camera of every frame of sequence ``index`` (seeded by config.seed + index)."""
    from jaxden.render import camera
    from jaxden.render.load import load_scene

    start = camera.from_scene(load_scene(scene, tuple(config.size)))
    if config.path == "orbit":
        return camera.orbit_path(start, config.frames, config.rotation_deg)
    return camera.random_path(start, config.frames, config.seed + index,
                              translation=config.translation, rotation_deg=config.rotation_deg)


_RECORD_FIELDS = {"scene": str, "frames": list}
_FRAME_FIELDS = {"frame": int, "files": list}
_FILE_FIELDS = {"path": str, "sha256": str}
#: What temporal accumulation reads from an input frame (jaxden.denoise.temporal).
_INPUT_FEATURES = ("color", "motion", "position", "normal", "depth")


def _sequence_key(index: int, scene: str) -> str:
    return f"s{index:03d}-{_slug(scene)}"


def _frame_files(t: int) -> tuple[str, str]:
    """The names of frame ``t``'s input and reference, inside the sequence's folder."""
    return f"f{t:03d}.exr", f"f{t:03d}.ref.exr"


def _read_manifest_file(path: Path) -> dict:
    """``path`` parsed, with its top-level fields checked (DatasetError naming the field)."""
    from jaxden.fileio import check_json_fields, read_json

    data = read_json(path, "the sequence manifest", error=DatasetError)
    if data.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a jaxden sequence manifest (no format '{FORMAT}')")
    check_json_fields(data, {"config": dict, "sequences": dict}, f"{path}: the sequence "
                      f"manifest", DatasetError)
    return data


def _check_sequences(data: dict, config: SequenceConfig, path: Path, *, complete: bool) -> None:
    """Check every sequence record of ``data`` against ``config``: its name is one the config
    gives (a folder inside the set), its scene is that sequence's, it lists at most
    ``config.frames`` frames (exactly, with ``complete``) in order, each with its input and
    reference file under the names the build gives them and a SHA-256. DatasetError naming
    ``path``, the sequence and the field otherwise."""
    from jaxden.data.layout import inside_folder
    from jaxden.fileio import check_json_fields

    expected = {_sequence_key(i, scene): scene for i, scene in enumerate(config.scene_ids())}
    sequences = data["sequences"]
    for key, record in sequences.items():
        here = f"{path}: sequence {key[:60]!r}"
        if not inside_folder(key) or len(Path(key).parts) != 1:
            raise DatasetError(f"{here}: the name is not a folder inside the sequence set "
                               f"(no '/', '..' or absolute paths)")
        if key not in expected:
            raise DatasetError(f"{here}: not one of the sequences of the set's config (those "
                               f"are {', '.join(expected)})")
        check_json_fields(record, _RECORD_FIELDS, here, DatasetError)
        if record["scene"] != expected[key]:
            raise DatasetError(f"{here}: field 'scene' must be {expected[key]!r}, found "
                               f"{record['scene'][:60]!r}")
        frames = record["frames"]
        if len(frames) > config.frames or (complete and len(frames) < config.frames):
            unfinished = " (its build did not finish: run `jaxden dataset sequences` on the " \
                         "folder again)" if len(frames) < config.frames else ""
            raise DatasetError(f"{here}: lists {len(frames)} frames, the set's config gives "
                               f"{config.frames}{unfinished}")
        for t, entry in enumerate(frames):
            at = f"{here}: frames[{t}]"
            check_json_fields(entry, _FRAME_FIELDS, at, DatasetError)
            if entry["frame"] != t:
                raise DatasetError(f"{at}: field 'frame' must be {t} (its place in the list), "
                                   f"found {str(entry['frame'])[:20]}")
            files = entry["files"]
            if len(files) != 2:
                raise DatasetError(f"{at}: field 'files' must list 2 files (the input and its "
                                   f"reference), found {len(files)}")
            for f, (item, name) in enumerate(zip(files, _frame_files(t))):
                where = f"{at}: files[{f}]"
                check_json_fields(item, _FILE_FIELDS, where, DatasetError)
                if not inside_folder(item["path"]):
                    raise DatasetError(f"{where}: path {item['path'][:60]!r} leaves the sequence "
                                       f"folder {key} (paths must be relative, without '..')")
                if item["path"] != name:
                    kind = "reference" if f else "input"
                    raise DatasetError(f"{where}: field 'path' must be {name!r} (the {kind} of "
                                       f"frame {t}), found {item['path'][:60]!r}")
                if re.fullmatch(r"[0-9a-f]{64}", item["sha256"]) is None:
                    raise DatasetError(f"{where}: field 'sha256' must be 64 hex digits, found "
                                       f"{item['sha256'][:20]!r}")
    if complete:
        missing = [key for key in expected if key not in sequences]
        if missing:
            raise DatasetError(f"{path}: sequence {missing[0]!r} is not built yet (its build "
                               f"did not finish: run `jaxden dataset sequences` on the folder "
                               f"again)")


def _load_manifest(directory: Path, config: SequenceConfig, config_dict: dict) -> dict:
    """The manifest to resume a build of ``config`` from (a new one if there is none);
    DatasetError for a manifest of another config or a broken one."""
    path = directory / MANIFEST_NAME
    if not path.exists():
        return {"format": FORMAT, "config": config_dict, "sequences": {}}
    manifest = _read_manifest_file(path)
    if manifest["config"] != config_dict:
        from jaxden.config import config_diff

        changed = "; ".join(config_diff(manifest["config"], config_dict))
        raise DatasetError(f"{directory} holds another sequence set ({changed}); use another "
                           f"folder")
    _check_sequences(manifest, config, path, complete=False)
    return manifest


def _check_writable(folder: Path, frames: int) -> None:
    """DatasetError if ``folder`` or one of its frame files is in the way of a build."""
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: is a file, where the build writes that sequence's "
                           f"frames; move it away")
    for t in range(frames):
        for name in _frame_files(t):
            if (folder / name).is_dir():
                raise DatasetError(f"{folder / name}: is a folder, where the build writes a "
                                   f"frame; move it away")


def build_sequences(config: SequenceConfig, out_dir, *, progress: bool = True) -> dict:
    """Render every sequence of ``config`` into ``out_dir`` (resumable); returns the manifest."""
    from tqdm import tqdm

    from jaxden.config import config_to_dict
    from jaxden.data.layout import sha256_file
    from jaxden.fileio import atomic_write_text, folder_lock
    from jaxden.io.exr import write_frame
    from jaxden.render.sequence import iter_sequence

    directory = Path(out_dir)
    if directory.exists() and not directory.is_dir():
        raise DatasetError(f"{directory} exists and is not a folder")
    directory.mkdir(parents=True, exist_ok=True)
    config_dict = config_to_dict(config)
    scenes = config.scene_ids()
    total = len(scenes) * config.frames
    with folder_lock(directory, LOCK_NAME, "sequence build"):
        manifest = _load_manifest(directory, config, config_dict)
        bar = tqdm(total=total, desc=f"sequences {config.name}", unit="frame",
                   disable=not progress)
        for index, scene in enumerate(scenes):
            key = f"s{index:03d}-{_slug(scene)}"
            record = manifest["sequences"].setdefault(key, {"scene": scene, "frames": []})
            frames = record["frames"]

            if len(frames) == config.frames and all(
                    (directory / key / f["path"]).is_file()
                    and sha256_file(directory / key / f["path"]) == f["sha256"]
                    for entry in frames for f in entry["files"]):
                bar.update(config.frames)
                continue
            # A partial sequence is rendered again from its first frame (seeds and motion
            # follow the frame index); finished sequences are kept. Nothing is dropped from
            # the manifest before it is sure that every file can be written.
            _check_writable(directory / key, config.frames)
            del frames[:]
            cameras = sequence_cameras(config, index, scene)
            (directory / key).mkdir(exist_ok=True)
            pairs = iter_sequence(scene, cameras, config.spp, config.seed + index,
                                  tuple(config.size), config.reference_spp)
            for t, (frame, reference) in enumerate(pairs):
                files = []
                for suffix, image in (("", frame), (".ref", reference)):
                    name = f"f{t:03d}{suffix}.exr"
                    write_frame(directory / key / name, image, attributes={
                        "scene": scene, "sequence": key, "frame": t,
                        "seed": config.seed + index})
                    files.append({"path": name, "sha256": sha256_file(directory / key / name)})
                frames.append({"frame": t, "files": files})
                atomic_write_text(directory / MANIFEST_NAME, json.dumps(manifest, indent=1))
                bar.update(1)
        bar.close()
        atomic_write_text(directory / MANIFEST_NAME, json.dumps(manifest, indent=1))
    return manifest


def _read_set(directory) -> tuple[dict, SequenceConfig, Path]:
    """``(manifest, config, manifest path)`` of a complete sequence set, checked."""
    from jaxden.data.layout import require_manifest

    directory = Path(directory)
    path = require_manifest(directory, MANIFEST_NAME, "sequence set",
                            f"jaxden dataset sequences CONFIG --out {directory}")
    manifest = _read_manifest_file(path)
    try:
        config = load_sequence_config(manifest["config"])
    except ConfigError as error:
        raise DatasetError(f"{path}: field 'config': {error}") from None
    _check_sequences(manifest, config, path, complete=True)
    return manifest, config, path


def read_manifest(directory) -> dict:
    """The manifest of a built sequence set, checked (:func:`_check_sequences`): DatasetError
    naming the file and the field if there is none, it is broken or the build did not
    finish."""
    return _read_set(directory)[0]


def _read_file(path: Path, sha256: str, manifest: Path, require: tuple[str, ...],
               size: tuple[int, int]):
    """The Frame in ``path``, which must match its checksum and the set's frame size."""
    from jaxden.data.layout import sha256_file
    from jaxden.io.exr import read_frame

    again = "run `jaxden dataset sequences` on the folder again to render it"
    if not path.exists():
        raise DatasetError(f"{path}: missing (listed in {manifest}); {again}")
    if not path.is_file():
        raise DatasetError(f"{path}: not a regular file (listed in {manifest} as a frame)")
    try:
        digest = sha256_file(path)
    except OSError as error:
        raise DatasetError(f"{path}: cannot read: {error.strerror or error}") from None
    if digest != sha256:
        raise DatasetError(f"{path}: does not match its checksum in {manifest} (changed or "
                           f"damaged since the build); {again}")
    frame = read_frame(path, require=require)
    width, height = size
    if tuple(frame.color.shape[:2]) != (height, width):
        raise DatasetError(f"{path}: the frame is {frame.color.shape[1]}x{frame.color.shape[0]}"
                           f" pixels, the set's config gives {width}x{height}")
    return frame


def load_sequence(directory, key: str):
    """``(frames, references)``: the Frames of one sequence of a built set, in order. Every
    file must match its checksum in the manifest; inputs carry what temporal accumulation
    reads (motion, position, normal, depth)."""
    directory = Path(directory)
    manifest, config, path = _read_set(directory)
    if key not in manifest["sequences"]:
        raise DatasetError(f"{directory}: no sequence {key!r} (has "
                           f"{', '.join(manifest['sequences'])})")
    frames, references = [], []
    for entry in manifest["sequences"][key]["frames"]:
        (input_, reference) = entry["files"]
        frames.append(_read_file(directory / key / input_["path"], input_["sha256"], path,
                                 _INPUT_FEATURES, config.size))
        references.append(_read_file(directory / key / reference["path"],
                                     reference["sha256"], path, ("color",), config.size))
    return frames, references
