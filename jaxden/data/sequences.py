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
"""

from __future__ import annotations

import dataclasses
import json
import math
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


def _load_manifest(directory: Path, config_dict: dict) -> dict:
    path = directory / MANIFEST_NAME
    if not path.exists():
        return {"format": FORMAT, "config": config_dict, "sequences": {}}
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"{path}: cannot read the manifest: {error}") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise DatasetError(f"{path}: not a jaxden sequence manifest")
    if manifest.get("config") != config_dict:
        from jaxden.config import config_diff

        changed = "; ".join(config_diff(manifest.get("config") or {}, config_dict))
        raise DatasetError(f"{directory} holds another sequence set ({changed}); use another "
                           f"folder")
    if not isinstance(manifest.get("sequences"), dict):
        raise DatasetError(f"{path}: 'sequences' must be a table")
    return manifest


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
        manifest = _load_manifest(directory, config_dict)
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
            # follow the frame index); finished sequences are kept.
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


def read_manifest(directory) -> dict:
    """The manifest of a built sequence set (DatasetError if there is none or it is broken)."""
    path = Path(directory) / MANIFEST_NAME
    try:
        config = json.loads(path.read_text()).get("config")
    except (OSError, json.JSONDecodeError, AttributeError) as error:
        raise DatasetError(f"{path}: cannot read the sequence manifest: {error}") from None
    return _load_manifest(Path(directory), config)


def load_sequence(directory, key: str):
    """``(frames, references)``: the Frames of one sequence of a built set, in order."""
    from jaxden.io.exr import read_frame

    directory = Path(directory)
    manifest = read_manifest(directory)
    if key not in manifest["sequences"]:
        raise DatasetError(f"{directory}: no sequence {key!r} (has {', '.join(manifest['sequences'])})")
    frames, references = [], []
    for entry in manifest["sequences"][key]["frames"]:
        paths = [directory / key / f["path"] for f in entry["files"]]
        frames.append(read_frame(paths[0]))
        references.append(read_frame(paths[1]))
    return frames, references
