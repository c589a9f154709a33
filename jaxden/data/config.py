"""DatasetConfig: what a dataset contains, validated from a TOML file.

A dataset is a set of *crops* (a square window of a scene's full film) and, for every crop, one
render at each input sample count plus one independent high-spp reference render. Example
(``experiments/configs/dataset-tiny.toml``)::

    name = "tiny"
    scenes = ["cornell-box"]          # built-in names, "procedural:SEED", or XML paths
    size = [64, 64]                   # full film, (width, height) in pixels
    crop_size = 32                    # square crops, pixels
    crops_per_scene = 1
    spp = [2, 8, 32]                  # input sample counts
    reference_spp = 256
    seed = 0

    [procedural]                      # generated scenes "procedural:SEED" added to `scenes`
    count = 1                         # SEED = procedural.seed + i for i < count
    seed = 1000

    [splits]                          # by scene (default) or by crop; fractions sum to 1
    train = 0.5
    val = 0.5
    test = 0.0
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

from jaxden.config import bounded
from jaxden.errors import ConfigError
from jaxden.render.integrators import AUX_MODES

SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test")
#: The features of a dataset config without ``aux`` / ``feature_spp``: those of every dataset
#: built before the options existed. Not render_frame's (specular-chain at 1024): changing them
#: would change what the configs that leave them out build, and the identity of the datasets
#: already built from them. A model records its training data's settings instead, and a frame
#: of other features is named when it meets the model (:mod:`jaxden.data.features`).
DEFAULT_AUX = "first-hit"
DEFAULT_FEATURE_SPP = 16


@dataclasses.dataclass(frozen=True)
class ProceduralConfig:
    """Procedurally generated scenes: ``count`` scenes ``procedural:SEED`` with
    SEED = ``seed`` + i, i = 0..count-1."""

    count: int = bounded(0, low=0, high=100_000)
    seed: int = bounded(0, low=0, high=4294967295)

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ConfigError(f"procedural.count must be >= 0, got {self.count}")
        if self.seed < 0:
            raise ConfigError(f"procedural.seed must be >= 0, got {self.seed}")


@dataclasses.dataclass(frozen=True)
class SplitConfig:
    """How scenes (or crops) are divided into train / val / test.

    Scenes named in ``val_scenes`` / ``test_scenes`` go to that split; the rest are shuffled
    (seeded by the dataset seed) and divided by the fractions ``train : val : test`` (largest
    remainder rounding; a split with a positive fraction gets at least one unit when there are
    enough). ``by = "scene"`` (default) keeps all crops of a scene in one split, so validation
    never sees a training scene; ``by = "crop"`` divides crops instead (what the progressive
    denoising paper does with its 5 % validation set), and then the explicit scene lists
    still assign whole scenes.
    """

    train: float = 0.9
    val: float = 0.1
    test: float = 0.0
    by: Literal["scene", "crop"] = "scene"
    val_scenes: tuple[str, ...] = ()
    test_scenes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        fractions = {"train": self.train, "val": self.val, "test": self.test}
        for name, value in fractions.items():
            if not (0.0 <= value <= 1.0) or math.isnan(value):
                raise ConfigError(f"splits.{name} must be a fraction in [0, 1], got {value}")
        total = sum(fractions.values())
        if abs(total - 1.0) > 1e-6:
            raise ConfigError(
                f"splits.train + splits.val + splits.test must sum to 1, got "
                f"{self.train} + {self.val} + {self.test} = {total:g}"
            )
        both = set(self.val_scenes) & set(self.test_scenes)
        if both:
            raise ConfigError(
                f"scene(s) {', '.join(sorted(both))} are in both splits.val_scenes and "
                f"splits.test_scenes"
            )
        for name in ("val_scenes", "test_scenes"):
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ConfigError(f"splits.{name} lists a scene twice: {list(values)}")


def _powers_of_two(low: int, high: int) -> tuple[int, ...]:
    powers = (2**k for k in range(high.bit_length()))
    return tuple(p for p in powers if low <= p <= high)


@dataclasses.dataclass(frozen=True)
class DatasetConfig:
    """A dataset of crops x (input spp levels + one reference).

    Fields (units: pixels, samples per pixel):

    - ``name``: a label stored in the manifest.
    - ``scenes``: built-in scene names (``jaxden.render.scenes.list_scenes()``),
      ``"procedural:SEED"``, or paths to Mitsuba XML files (relative to the working directory).
    - ``procedural``: adds ``count`` generated scenes (see :class:`ProceduralConfig`).
    - ``size``: the full film (width, height) the crops are placed in.
    - ``crop_size``: side of the square crops; each crop is rendered on its own (the renderer's
      crop window), so the film size sets the field of view, not the cost.
    - ``crops_per_scene``: crops per scene, placed uniformly at random (seeded) in the film;
      they may overlap.
    - ``spp``: input sample counts, distinct, each rendered independently (own seed).
    - ``reference_spp``: the reference's sample count (>= max(spp)), an independent render.
    - ``seed``: base seed for crop placement, split shuffling and every render's sampler seed.
    - ``half``: store EXR channels as float16 (half the disk space; float32 by default).
    - ``aux``: how the albedo and normal features are rendered: ``"first-hit"`` (default;
      every dataset before this option) or ``"specular-chain"`` (from the first non-delta
      surface behind mirrors and smooth glass, as OIDN recommends;
      :func:`jaxden.render.core.render_frame`).
    - ``feature_spp``: the feature pass (albedo, normal, depth, position) averages
      ``min(spp, feature_spp)`` samples per pixel; 16 (default) is what every dataset before
      this option used. More samples give OIDN cleaner features (docs/results.md, "OIDN's
      auxiliary features"); set it >= the largest spp to average as many samples as the colour.
      Both defaults differ from ``jaxden render``'s (specular-chain at 1024); a model trained
      on the dataset records them, and running it on a frame of other features prints a
      warning (:mod:`jaxden.data.features`).
    - ``statistics``: also render each item's per-pixel sample statistics (``Frame.boxcox``:
      the Box-Cox(0.5) mean and central moments StatMC's test reads; 9 float32 channels more
      per file, same samples as the colour); False by default.
    - ``replica``: 0 (default) or the number of an independent replica of the dataset: the
      same crops, splits and file names, every render from other seeds. Two replicas of a
      dataset are the two independent halves of each item that cross-validating methods
      (the neural James-Stein combiner, NFOR) train and run on: their exact combination
      (:func:`jaxden.data.merge.combine_buffers`) is one render of twice the samples.
    - ``scene_parameters``: ``$name`` values for the XML scenes, as Mitsuba's ``-D``
      (``[scene_parameters]`` table, e.g. ``spp = "64"``); empty by default.
    - ``splits``: see :class:`SplitConfig`.
    """

    name: str = "dataset"
    scenes: tuple[str, ...] = ()
    procedural: ProceduralConfig = ProceduralConfig()
    size: tuple[int, int] = bounded((256, 256), low=1, high=16384, unit='pixels')
    crop_size: int = bounded(128, low=1, high=16384, unit='pixels')
    crops_per_scene: int = bounded(4, low=1, high=100_000)
    spp: tuple[int, ...] = bounded(_powers_of_two(2, 4096), low=1, high=2**24)
    reference_spp: int = bounded(16384, low=1, high=2**26)
    seed: int = bounded(0, low=0, high=4294967295)
    half: bool = False
    aux: str = DEFAULT_AUX
    feature_spp: int = bounded(DEFAULT_FEATURE_SPP, low=1, high=2**24)
    statistics: bool = False
    replica: int = bounded(0, low=0, high=1_000_000)
    scene_parameters: dict[str, str] = dataclasses.field(default_factory=dict)
    splits: SplitConfig = SplitConfig()

    def __post_init__(self) -> None:
        if not self.scenes and self.procedural.count == 0:
            raise ConfigError("the dataset has no scenes: give `scenes` and/or `procedural.count`")
        for scene in self.scenes:
            if not scene.strip():
                raise ConfigError("scenes: a scene name is empty")
            if scene.startswith("procedural:"):
                tail = scene.split(":", 1)[1]
                if not tail.isdigit():
                    raise ConfigError(
                        f"scenes: {scene!r} must be 'procedural:SEED' with SEED a non-negative "
                        f"integer"
                    )
        all_scenes = self.scene_ids()
        duplicates = sorted({s for s in all_scenes if all_scenes.count(s) > 1})
        if duplicates:
            last = self.procedural.seed + self.procedural.count - 1
            raise ConfigError(
                f"scenes: {', '.join(duplicates)} appear(s) twice (check `scenes` against the "
                f"procedural seeds {self.procedural.seed}..{last})"
            )
        width, height = self.size
        if width <= 0 or height <= 0:
            raise ConfigError(f"size must be positive (width, height), got {list(self.size)}")
        if self.crop_size <= 0:
            raise ConfigError(f"crop_size must be > 0, got {self.crop_size}")
        if self.crop_size > min(width, height):
            raise ConfigError(
                f"crop_size {self.crop_size} does not fit in the film size {width}x{height} "
                f"(width x height)"
            )
        if self.crops_per_scene <= 0:
            raise ConfigError(f"crops_per_scene must be > 0, got {self.crops_per_scene}")
        if not self.spp:
            raise ConfigError("spp: give at least one input sample count")
        if any(s <= 0 for s in self.spp):
            raise ConfigError(f"spp: every sample count must be > 0, got {list(self.spp)}")
        if len(set(self.spp)) != len(self.spp):
            raise ConfigError(f"spp: sample counts must be distinct, got {list(self.spp)}")
        if self.reference_spp <= 0:
            raise ConfigError(f"reference_spp must be > 0, got {self.reference_spp}")
        if self.reference_spp < max(self.spp):
            raise ConfigError(
                f"reference_spp ({self.reference_spp}) must be >= the largest input spp "
                f"({max(self.spp)})"
            )
        if self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")
        if self.feature_spp <= 0:
            raise ConfigError(f"feature_spp must be > 0, got {self.feature_spp}")
        if self.aux not in AUX_MODES:
            raise ConfigError(f"aux must be one of {', '.join(AUX_MODES)}, got {self.aux!r}")
        if self.scene_parameters:
            if not all(isinstance(k, str) and isinstance(v, (str, int, float))
                       and not isinstance(v, bool) for k, v in self.scene_parameters.items()):
                raise ConfigError("scene_parameters: expected a table of name = value (strings "
                                  "or numbers)")
            object.__setattr__(self, "scene_parameters",
                               {k: str(v) for k, v in self.scene_parameters.items()})
            if not any(s.lower().endswith(".xml") for s in self.scenes):
                raise ConfigError("scene_parameters: set, but the dataset has no XML scene file "
                                  "(they are the values of $name in Mitsuba XML scenes)")
        for name in ("val_scenes", "test_scenes"):
            unknown = [s for s in getattr(self.splits, name) if s not in all_scenes]
            if unknown:
                raise ConfigError(
                    f"splits.{name}: {', '.join(unknown)} is not one of the dataset's scenes "
                    f"({', '.join(all_scenes)})"
                )

    def scene_ids(self) -> list[str]:
        """Every scene of the dataset in order: ``scenes`` then the procedural ones."""
        generated = [
            f"procedural:{self.procedural.seed + i}" for i in range(self.procedural.count)
        ]
        return list(self.scenes) + generated


def load_dataset_config(source, overrides=()) -> DatasetConfig:
    """Load a DatasetConfig from a TOML file / dict with ``key=value`` overrides."""
    from jaxden.config import load_config

    return load_config(source, DatasetConfig, overrides)
