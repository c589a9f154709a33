"""Reading a finished dataset crop by crop: the reference and the inputs of every crop of a
split, as Frames (for reports that score methods against the references)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from jaxden.errors import DatasetError


def iter_crops(dataset_dir, split: str = "test", spp: tuple[int, ...] | None = None,
               *, min_spp: int = 2) -> Iterator[tuple[Any, Any, list[tuple[int, Any]]]]:
    """``(crop, reference_frame, [(spp, input_frame), ...])`` for every crop of ``split``
    (``all``: every crop) of a complete dataset, inputs of at least ``min_spp`` samples in spp
    order (default 2: the inputs that have a variance, as SURE needs), restricted to ``spp``
    when given."""
    from jaxden.data.layout import load_manifest
    from jaxden.io.exr import read_frame

    dataset_dir = Path(dataset_dir)
    manifest = load_manifest(dataset_dir)
    if not manifest.complete:
        raise DatasetError(f"{dataset_dir}: the dataset is not complete; finish `jaxden dataset "
                           f"build` first")
    crops = manifest.crops_in(split)
    if not crops:
        raise DatasetError(f"{dataset_dir}: no crops in split {split!r} "
                           f"(splits: {manifest.split_counts()})")
    for crop in crops:
        items = manifest.items_of(crop.id)
        references = [item for item in items if item.kind == "reference"]
        if len(references) != 1:
            raise DatasetError(f"{dataset_dir}: crop {crop.id} has {len(references)} references")
        inputs = sorted((item for item in items if item.kind == "input" and item.spp >= min_spp
                         and (spp is None or item.spp in tuple(spp))), key=lambda item: item.spp)
        reference = read_frame(dataset_dir / references[0].path)
        yield crop, reference, [(item.spp, read_frame(dataset_dir / item.path))
                                for item in inputs]
