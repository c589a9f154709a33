"""refeature_dataset: copy a finished dataset, re-rendering only its features (albedo, normal,
depth, position) with other settings; colour, variance and references are copied byte for byte.
"""

from __future__ import annotations

import os
from pathlib import Path

from jaxden.data.builder import build_dataset, config_with_defaults, renderer_name
from jaxden.data.config import load_dataset_config
from jaxden.data.layout import (
    Manifest,
    load_manifest,
)
from jaxden.errors import DatasetError
from jaxden.render.scene_cache import render_cached

# -------------------------------------------------------------------------- refeature
#: The config keys `refeature` may change: they touch only the feature pass.
FEATURE_KEYS: tuple[str, ...] = ("aux", "feature_spp", "name")


class ColourFrom:
    """A dataset renderer that keeps the colour and variance of another dataset's items and
    renders only their features (``render_frame(colour=...)``). Items are found by their
    render seed, which the builder derives from the config's seed, scene and crop, so a
    refeatured item equals what a full build of the new config renders."""

    def __init__(self, source: str | os.PathLike) -> None:

        self.source = str(source)
        manifest = load_manifest(source)
        self.items = {item.seed: (item.path, item.spp, item.id) for item in manifest.items}
        if len(self.items) != len(manifest.items):
            raise DatasetError(f"{source}: two items share a render seed; cannot refeature it")

    def __call__(self, scene, spp, seed=0, size=None, *, crop=None, aux="first-hit",
                 feature_spp=16):
        from jaxden.io.exr import read_frame

        if seed not in self.items:
            raise DatasetError(f"{self.source}: no item was rendered with seed {seed}")
        path, item_spp, item_id = self.items[seed]
        if item_spp != spp:
            raise DatasetError(f"{self.source}: item {item_id} has {item_spp} spp, not {spp}")
        colour = read_frame(Path(self.source) / path, require=("color",))
        return render_cached(scene, spp, seed=seed, size=size, crop=crop, aux=aux,
                             feature_spp=feature_spp, colour=colour)


def refeature_dataset(
    source: str | os.PathLike,
    out_dir: str | os.PathLike,
    overrides=(),
    *,
    executor: str = "local",
    workers: int | None = None,
    progress: bool = True,
) -> Manifest:
    """A copy of a complete dataset with its features re-rendered under new feature settings
    (``aux``, ``feature_spp``; ``key=value`` overrides of the source's config) and its colour
    and variance kept. The colour pass does not depend on the feature settings, so the result
    is what ``jaxden dataset build`` of the new config would render, at the cost of the
    feature passes alone. Resumable like a build (rerun the same command)."""
    from jaxden.config import config_diff, config_to_dict

    manifest = load_manifest(source)
    if not manifest.complete:
        raise DatasetError(f"{source}: the dataset is not complete; finish its build first")
    if manifest.renderer != renderer_name(None):
        raise DatasetError(f"{source}: built by {manifest.renderer}; refeature needs a dataset "
                           f"rendered by {renderer_name(None)}")
    base = config_with_defaults(manifest.config)
    config = load_dataset_config(base, overrides)
    changed = [line.split(":", 1)[0] for line in config_diff(base, config_to_dict(config))]
    other = [key for key in changed if key not in FEATURE_KEYS]
    if other:
        raise DatasetError(f"refeature can change only {', '.join(FEATURE_KEYS)}; "
                           f"{', '.join(other)} would change the colour renders: build a new "
                           f"dataset instead")
    if Path(out_dir).resolve() == Path(source).resolve():
        raise DatasetError(f"refeature writes a new dataset: out_dir must not be the source "
                           f"{source}")
    return build_dataset(config, out_dir, executor=executor, workers=workers,
                         render_fn=ColourFrom(source), progress=progress)
