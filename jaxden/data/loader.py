"""Batches of (noisy input, reference) crops from a built dataset, with seeded augmentation.

An epoch visits every (crop, input spp) pair of a split once, in an order shuffled by
``(seed, epoch)``; each sample gets a random sub-crop (the same window for input and reference)
and one of the 8 symmetries of the square (the dihedral group D4), also drawn from
``(seed, epoch)``. So the batches are a pure function of (dataset, split, seed, epoch): the same
on every run, independent of caching.

Augmentation acts on every image field alike except ``motion``: motion vectors are pixel
offsets (dx, dy) (x to the right, y down), so a rotation or flip of the image also rotates or
flips the vectors (see :func:`dihedral_motion`). Normals and positions are world-space and stay
unchanged (the camera, not the world, is what the symmetry moves).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.layout import Crop, Item, load_manifest
from jaxden.errors import DatasetError, ExrError
from jaxden.frame import CHANNELS, IMAGE_FIELDS, Frame

DIHEDRAL_COUNT = 8
DEFAULT_FEATURES: tuple[str, ...] = ("color", "variance", "albedo", "normal", "depth")
DEFAULT_REFERENCE_FEATURES: tuple[str, ...] = ("color", "variance")
CACHE_AUTO_LIMIT_BYTES = 2 << 30


# ----------------------------------------------------------------------------- augmentation
def dihedral(image: np.ndarray, index: int) -> np.ndarray:
    """Apply symmetry ``index`` (0..7) of the square to an (..., H, W, C) image.

    ``index % 4`` quarter turns counter-clockwise (``np.rot90`` over the H, W axes), then a
    left-right flip when ``index >= 4``. Index 0 is the identity.
    """
    if not 0 <= index < DIHEDRAL_COUNT:
        raise ValueError(f"dihedral index must be in 0..7, got {index}")
    out = np.rot90(image, k=index % 4, axes=(-3, -2))
    if index >= 4:
        out = np.flip(out, axis=-2)
    return out


def dihedral_motion(motion: np.ndarray, index: int) -> np.ndarray:
    """Transform an (..., H, W, 2) field of (dx, dy) pixel offsets with symmetry ``index``.

    Moves the pixels as :func:`dihedral` does and maps the vectors by the same linear map: a
    counter-clockwise quarter turn (as displayed, y down) sends a pixel at (x, y) to
    (y, W - 1 - x), so (dx, dy) -> (dy, -dx); a left-right flip sends (dx, dy) -> (-dx, dy).
    """
    vectors = np.asarray(motion)
    dx, dy = vectors[..., 0], vectors[..., 1]
    for _ in range(index % 4):
        dx, dy = dy, -dx
    if index >= 4:
        dx = -dx
    return dihedral(np.stack([dx, dy], axis=-1), index)


def dihedral_frame(frame: Frame, index: int) -> Frame:
    """Apply symmetry ``index`` to every image field of ``frame`` (motion vectors transformed,
    world-space normals and positions unchanged)."""
    changes = {}
    for name in IMAGE_FIELDS:
        value = getattr(frame, name)
        if value is None:
            continue
        transform = dihedral_motion if name == "motion" else dihedral
        changes[name] = transform(value, index)
    return frame.replace(**changes)


# ----------------------------------------------------------------------------- loader
@dataclasses.dataclass(frozen=True)
class Batch:
    """One batch: ``input`` and ``reference`` Frames with fields (B, h, w, C) float32 and
    ``spp`` (B,); ``items`` are the input item ids (for debugging and evaluation)."""

    input: Frame
    reference: Frame
    items: tuple[str, ...]


class DatasetLoader:
    """Iterate over batches of one split of a built dataset.

    Args:
      directory: the dataset folder (with ``manifest.json``); must be completely built.
      split: 'train', 'val', 'test' or 'all'.
      batch_size: samples per batch (B).
      crop_size: side h = w of the random sub-crop; None for the stored crop size.
      seed: seeds shuffling, sub-crop positions and symmetries (with the epoch index).
      spp: None for every input spp level, or a list of levels to use.
      features: input features to load (Frame field names); ``reference_features`` likewise
        for the reference.
      augment: draw one of the 8 dihedral symmetries per sample (else identity).
      shuffle: shuffle the samples every epoch (else manifest order).
      drop_last: drop the last incomplete batch (default) or yield it smaller.
      cache: keep decoded EXRs in memory; None (default) caches when the split fits in 2 GiB.
      target_spp: None (default) pairs each input with its crop's reference; an spp level
        instead pairs it with the crop's own input at that level, an independent noisy render
        (another seed), as the target of Noise2Noise training. The level must not be one of
        the inputs', so that no input is its own target.

    ``len(loader)`` is the number of batches per epoch; ``loader.epoch(e)`` yields the batches of
    epoch e; iterating the loader itself yields successive epochs' batches, one epoch per
    ``iter()`` call (epoch 0 first).
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        split: str = "train",
        batch_size: int = 8,
        crop_size: int | None = None,
        seed: int = 0,
        spp: Sequence[int] | None = None,
        features: Sequence[str] = DEFAULT_FEATURES,
        *,
        reference_features: Sequence[str] = DEFAULT_REFERENCE_FEATURES,
        augment: bool = True,
        shuffle: bool = True,
        drop_last: bool = True,
        cache: bool | None = None,
        target_spp: int | None = None,
    ) -> None:
        self.directory = Path(directory)
        manifest = load_manifest(self.directory)
        if not manifest.complete:
            done = sum(item.done for item in manifest.items)
            raise DatasetError(
                f"dataset {self.directory} is incomplete ({done} of {len(manifest.items)} files "
                f"built): run the build again to finish it"
            )
        crops = manifest.crops_in(split)  # checks the split name first
        for name, values in (("features", features), ("reference_features", reference_features)):
            unknown = [f for f in values if f not in CHANNELS]
            if unknown:
                raise DatasetError(
                    f"{name}: unknown feature(s) {', '.join(unknown)}; features are "
                    f"{', '.join(IMAGE_FIELDS)}"
                )
            if "color" not in values:
                raise DatasetError(f"{name} must include 'color'")
        if batch_size < 1:
            raise DatasetError(f"batch_size must be >= 1, got {batch_size}")
        stored = manifest.crop_size
        self.crop_size = stored if crop_size is None else int(crop_size)
        if not 0 < self.crop_size <= stored:
            raise DatasetError(
                f"crop_size {crop_size} must be in 1..{stored} (the dataset's crop size)"
            )
        levels = sorted({item.spp for item in manifest.items if item.kind == "input"})
        if spp is None and target_spp is not None:
            levels = [level for level in levels if level != target_spp]
        if spp is not None:
            missing = [s for s in spp if s not in levels]
            if missing:
                raise DatasetError(
                    f"spp level(s) {missing} are not in {self.directory}; it has {levels} "
                    f"(leave data.spp unset to take every level it has, or name some of these)"
                )
            levels = sorted(set(spp))
        if "variance" in features and 1 in levels:
            raise DatasetError(
                "features include 'variance' but the spp levels include 1 (no variance from one "
                "sample): drop 'variance' or choose spp levels >= 2"
            )
        all_levels = sorted({item.spp for item in manifest.items if item.kind == "input"})
        if target_spp is not None:
            if target_spp not in all_levels:
                raise DatasetError(
                    f"target_spp {target_spp} is not an input spp level of {self.directory}; "
                    f"it has {all_levels}"
                )
            if target_spp in levels:
                raise DatasetError(
                    f"target_spp {target_spp} is also an input level ({list(levels)}): an input "
                    f"would be its own target; choose input levels without it"
                )
        samples: list[tuple[Item, Item]] = []
        for crop in crops:
            items = manifest.items_of(crop.id)
            if target_spp is None:
                reference = next(item for item in items if item.kind == "reference")
            else:
                reference = next(
                    item for item in items if item.kind == "input" and item.spp == target_spp
                )
            for item in sorted(items, key=lambda i: i.spp):
                if item.kind == "input" and item.spp in levels:
                    samples.append((item, reference))
        if not samples:
            raise DatasetError(
                f"split {split!r} of {self.directory} has no samples (crops per split: "
                f"{manifest.split_counts()})"
            )
        if drop_last and len(samples) < batch_size:
            raise DatasetError(
                f"split {split!r} has {len(samples)} samples, fewer than batch_size {batch_size} "
                f"(pass drop_last=False or a smaller batch)"
            )
        self.split = split
        self.batch_size = int(batch_size)
        self.seed = int(seed)
        self.spp_levels = tuple(levels)
        self.target_spp = target_spp
        self.features = tuple(features)
        self.reference_features = tuple(reference_features)
        self.augment = augment
        self.shuffle = shuffle
        self.drop_last = drop_last
        self.samples = samples
        self.crops: dict[str, Crop] = manifest.crop_by_id()
        self.stored_crop_size = stored
        if cache is None:
            fields = set(self.features) | set(self.reference_features)
            channels = sum(len(CHANNELS[f]) for f in fields)
            files = len({item.id for pair in samples for item in pair})
            cache = files * stored * stored * channels * 4 <= CACHE_AUTO_LIMIT_BYTES
        self.cache_enabled = bool(cache)
        self._cache: dict[tuple[str, tuple[str, ...]], Frame] = {}
        self._next_epoch = 0

    def __len__(self) -> int:
        count = len(self.samples) / self.batch_size
        return math.floor(count) if self.drop_last else math.ceil(count)

    def __iter__(self) -> Iterator[Batch]:
        epoch = self._next_epoch
        self._next_epoch += 1
        return self.epoch(epoch)

    def _read(self, item: Item, features: tuple[str, ...]) -> Frame:
        key = (item.id, features)
        frame = self._cache.get(key)
        if frame is not None:
            return frame
        from jaxden.io.exr import read_frame

        path = self.directory / item.path
        try:
            full = read_frame(path, require=features)
        except ExrError as error:
            raise DatasetError(
                f"{error} (run `jaxden dataset verify {self.directory}` to check the dataset)"
            ) from None
        frame = Frame(
            **{name: getattr(full, name) for name in features},
            spp=np.float32(item.spp),
        )
        if self.cache_enabled:
            self._cache[key] = frame
        return frame

    def plan_epoch(self, epoch: int) -> list[tuple[int, int, int, int]]:
        """The epoch's draws: (sample index, top, left, symmetry) per sample, in visit order."""
        rng = np.random.default_rng([self.seed, int(epoch)])
        count = len(self.samples)
        order = rng.permutation(count) if self.shuffle else np.arange(count)
        room = self.stored_crop_size - self.crop_size + 1
        tops = rng.integers(0, room, size=count)
        lefts = rng.integers(0, room, size=count)
        symmetries = (
            rng.integers(0, DIHEDRAL_COUNT, size=count) if self.augment else np.zeros(count, int)
        )
        return [
            (int(order[i]), int(tops[i]), int(lefts[i]), int(symmetries[i])) for i in range(count)
        ]

    def batch_draws(self, epoch: int) -> Iterator[list[tuple[int, int, int, int]]]:
        """The draws of each batch of epoch ``epoch`` (:meth:`plan_epoch` cut into batches; the
        last one shorter unless ``drop_last``)."""
        draws = self.plan_epoch(epoch)
        for start in range(0, len(draws), self.batch_size):
            chunk = draws[start : start + self.batch_size]
            if len(chunk) < self.batch_size and self.drop_last:
                return
            yield chunk

    def read(self, draws) -> Batch:
        """The batch of ``draws`` (sample index, top, left, symmetry), in their order: any
        subset of an epoch's draws reads the same crops and symmetries as the whole (several
        training processes each read their rows of a batch)."""
        inputs, references, ids = [], [], []
        size = self.crop_size
        for index, top, left, symmetry in draws:
            item, reference = self.samples[index]
            for frame_list, source, features in (
                (inputs, item, self.features),
                (references, reference, self.reference_features),
            ):
                frame = self._read(source, features).crop(top, left, size, size)
                frame_list.append(dihedral_frame(frame, symmetry))
            ids.append(item.id)
        return Batch(_stack(inputs), _stack(references), tuple(ids))

    def epoch(self, epoch: int) -> Iterator[Batch]:
        """The batches of epoch ``epoch`` (a pure function of the seed and the epoch)."""
        for draws in self.batch_draws(epoch):
            yield self.read(draws)


def _stack(frames: list[Frame]) -> Frame:
    fields: dict[str, Any] = {}
    for name in frames[0].features():
        fields[name] = np.ascontiguousarray(
            np.stack([getattr(f, name) for f in frames]), dtype=np.float32
        )
    fields["spp"] = np.asarray([f.spp for f in frames], dtype=np.float32)
    return Frame(**fields)
