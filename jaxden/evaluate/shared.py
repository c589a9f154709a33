"""What several evaluators share: rows grouped by spp, a progress bar over a split's crops, how
a denoiser spec is named in tables, and the identity of weights a result used."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path


def by_spp(rows) -> dict[int, list[dict]]:
    """The rows grouped by their ``spp``, in increasing spp order."""
    groups: dict[int, list[dict]] = defaultdict(list)
    for row in rows:
        groups[row["spp"]].append(row)
    return dict(sorted(groups.items()))


def progress_bar(iterable, total: int | None, show: bool, what: str):
    """``iterable`` with a tqdm bar counting crops when ``show``, else itself."""
    if not show:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=what, unit="crop")


def crop_count(dataset_dir, split) -> int:
    """How many crops ``split`` of a dataset has (the progress bar's total)."""
    from jaxden.data.layout import load_manifest

    manifest = load_manifest(dataset_dir)
    return len(manifest.crops_in(split))


def denoiser_label(spec) -> str:
    """How tables, cards and figures name a base denoiser (``MixerConfig.denoiser``, the
    evaluators' ``--denoiser``): ``oidn`` -> OIDN; a shipped or registered name in capitals
    (``wskp-6`` -> WSKP-6); a checkpoint folder or weights file by its own name."""
    spec = str(spec)
    if spec == "oidn":
        return "OIDN"
    path = Path(spec)
    if "/" in spec or path.suffix == ".msgpack" or path.exists():
        return path.stem if path.suffix == ".msgpack" else path.name
    return spec.upper()


def weights_identity(spec: str) -> dict:
    """``{"spec", "file", "sha256"}`` of the weights file a denoiser or mixer spec names (a
    file, or a name shipped in jaxden/weights/), else ``{"spec"}`` (a registered black box,
    a run folder, a closed-form mixer)."""
    from jaxden.paths import resolve_weights
    from jaxden.provenance import file_sha256

    path = resolve_weights(spec)
    if path is not None and path.is_file():
        return {"spec": spec, "file": str(path), "sha256": file_sha256(path)}
    return {"spec": spec}
