"""The ``njs`` evaluator: a trained neural James-Stein combiner on a held-out dataset and its
replica, beside the combined noisy frame and the base denoiser on it.

Every input item of ``split`` at a level s of the dataset (``--data``) is half A, the same
item of its replica (``--replica``: ``jaxden dataset build ... replica=1``) half B; the
combined frame (2 s samples, :func:`jaxden.denoise.njs_model.combined_frame`) is what the
three images are scored as: ``den_<metric>``, NJS's output
(:func:`jaxden.denoise.njs_model.njs_denoise`: the image-wide bandwidth, clamped at 0);
``mc_<metric>``, the combined noisy colour; ``base_<metric>``, the run's base denoiser on the
combined frame (what NJS is meant to improve on: the same samples, one denoiser). Metrics
are :func:`jaxden.evaluate.denoise.image_errors`' (PSNR and SSIM tone-mapped; relMSE, FLIP,
RMSE and the reference-noise-corrected MSE in linear HDR) against the dataset's reference.
A row: ``{"crop", "scene", "spp": 2 s, "den_*", "mc_*", "base_*"}``.

``jaxden evaluate njs --data SET --replica SET_R1 --denoiser RUN [--split test] [--spp S ...]
--out OUT``: ``--spp`` names the halves' levels s (the dataset's); the rows and tables show
the combination's 2 s.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from jaxden.evaluate.evaluator import Evaluator, dataset_provenance
from jaxden.evaluate.shared import by_spp, denoiser_label, progress_bar

#: The images a row scores, by prefix.
PREFIXES = ("den", "base", "mc")


@dataclasses.dataclass(frozen=True)
class NJSOptions:
    """``denoiser``: an NJS run folder (or checkpoint, weights file); ``replica``: the
    replica of the dataset (the B halves); ``split``; ``spp``: the halves' spp levels (None:
    every level of at least 2)."""

    denoiser: str = dataclasses.field(metadata={"help": "an NJS run folder"})
    replica: str = dataclasses.field(metadata={"help": "the replica of --data (the B halves)"})
    split: str = "test"
    spp: tuple[int, ...] | None = dataclasses.field(
        default=None, metadata={"help": "the halves' spp levels (rows show 2 x)"})

    def __post_init__(self):
        from jaxden.paths import expand_path

        object.__setattr__(self, "replica", expand_path(self.replica))
        object.__setattr__(self, "denoiser", expand_path(self.denoiser))
        if self.spp is not None:
            object.__setattr__(self, "spp", tuple(int(s) for s in self.spp))


def evaluate_njs(dataset_dir, replica_dir, model, *, split: str = "test", spp=None,
                 progress: bool = False) -> list[dict[str, Any]]:
    """One row per (crop, level s >= 2) of ``split``: the errors of NJS's output, of the
    combined noisy colour and of the base on the combined frame (module docstring).
    ``model``: an NJS run folder or :class:`jaxden.denoise.njs_model.NJSModel`."""
    import numpy as np

    from jaxden.data.crops import iter_crops
    from jaxden.data.layout import load_manifest
    from jaxden.denoise.njs_model import as_njs_model, njs_denoise
    from jaxden.denoise.tiled import denoise_frame
    from jaxden.evaluate.denoise import image_errors
    from jaxden.evaluate.shared import crop_count
    from jaxden.io.exr import read_frame
    from jaxden.train.njs_cache import check_replica

    model = as_njs_model(model)
    _, replica = check_replica(dataset_dir, replica_dir)
    replica_paths = {item.id: item.path for item in replica.items}
    manifest = load_manifest(dataset_dir)
    rows = []
    crops = iter_crops(dataset_dir, split, None if spp is None else tuple(spp), min_spp=2)
    for crop, reference, inputs in progress_bar(crops, crop_count(dataset_dir, split),
                                                progress, "NJS"):
        items = {item.spp: item for item in manifest.items_of(crop.id) if item.kind == "input"}
        for level, frame_a in inputs:
            frame_b = read_frame(Path(replica_dir) / replica_paths[items[level].id])
            image, combined = njs_denoise(model, frame_a, frame_b)
            base, _ = denoise_frame(model.base, combined)
            row: dict[str, Any] = {"crop": crop.id, "scene": crop.scene, "spp": 2 * level}
            for prefix, scored in zip(PREFIXES, (image, base, combined.color), strict=True):
                errors = image_errors(np.asarray(scored, np.float32), reference)
                row |= {f"{prefix}_{key}": value for key, value in errors.items()}
            rows.append(row)
    return rows


def summarize_njs(rows, provenance) -> dict:
    """``summary`` (means over every row, :func:`jaxden.evaluate.denoise.summarize`) and
    ``by_spp`` (the same per combined spp)."""
    from jaxden.evaluate.denoise import summarize

    return {"summary": summarize(rows),
            "by_spp": {str(level): summarize(group) for level, group in by_spp(rows).items()}}


def markdown_njs(fields, rows, provenance) -> str:
    """The overall table (NJS, base, MC) and one per combined spp."""
    from jaxden.evaluate.denoise import markdown

    label = denoiser_label(provenance["denoiser"]["spec"])
    parts = [f"All levels ({fields['summary']['count']} images):", "",
             markdown({label: fields["summary"]}, prefixes=PREFIXES)]
    for level, summary in fields.get("by_spp", {}).items():
        parts += ["", f"{level} spp (combined):", "",
                  markdown({label: summary}, prefixes=PREFIXES)]
    return "\n".join(parts)


def njs_provenance(options: NJSOptions) -> dict:
    """The run (its spec; the base and digest its checkpoint records), the replica's build,
    the levels."""
    from jaxden.checkpoint import read_checkpoint_meta
    from jaxden.errors import CheckpointError
    from jaxden.evaluate.shared import weights_identity

    denoiser = weights_identity(options.denoiser)
    try:
        config = read_checkpoint_meta(options.denoiser).get("model_config", {})
        denoiser |= {"base": config.get("base"), "base_sha256": config.get("base_sha256")}
    except (CheckpointError, OSError):
        pass  # the run itself then fails to load, naming why
    return {"denoiser": denoiser,
            "replica": dataset_provenance(options.replica, options.split),
            "spp": None if options.spp is None else list(options.spp)}


EVALUATOR = Evaluator(
    name="njs",
    description="a neural James-Stein combiner run on a dataset and its replica (the two "
                "halves): PSNR, SSIM, relMSE, FLIP, RMSE of NJS, its base and the combined MC "
                "frame per crop and combined spp",
    options=NJSOptions,
    run=lambda data, options, progress=False: evaluate_njs(
        data, options.replica, options.denoiser, split=options.split, spp=options.spp,
        progress=progress),
    summarize=summarize_njs,
    table=markdown_njs,
    provenance=njs_provenance,
    trains="buffer-denoiser",
)

__all__ = ["EVALUATOR", "PREFIXES", "NJSOptions", "evaluate_njs", "markdown_njs",
           "summarize_njs"]
