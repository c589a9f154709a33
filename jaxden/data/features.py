"""Which auxiliary features a frame carries, recorded where features are made and compared
where a trained model meets a frame.

Two settings make the albedo, normal, depth and position of a render (:mod:`jaxden.render.core`):
``aux`` (albedo and normal of the first hit, ``"first-hit"``, or of the first non-delta surface
behind mirrors and glass, ``"specular-chain"``) and ``feature_spp`` (the feature pass averages
``min(spp, feature_spp)`` samples). Their defaults differ on purpose: a dataset config without
them builds first-hit features at 16 spp (every dataset built before the options existed keeps
its identity), while ``jaxden render`` and ``render_frame`` give specular-chain at 1024 (what
OIDN does best with). So a model trained on a dataset of the defaults and run on a frame of
``jaxden render`` sees other features than it was trained on.

The settings are therefore recorded: a dataset's in its manifest (its config), a trained
model's in its checkpoint meta record (``trained_features``: those of its training dataset,
written by :mod:`jaxden.train.loop`), an EXR frame's in its header (``jaxden.aux``,
``jaxden.feature_spp``: :func:`jaxden.render.core.feature_attributes`). :func:`feature_mismatch`
says how two records differ, and :func:`warn_feature_mismatch` prints that on one line, once
per process for each pair of records.

A record compares the samples the features really average: a frame of 8 spp has features of
8 samples whether ``feature_spp`` was 16 or 1024, as did the 8-spp inputs the model was trained
on. An imported dataset (another renderer's files) has no record: its features are the source
renderer's, which these settings do not describe.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from collections.abc import Iterable, Mapping
from typing import Any

from jaxden.data.config import DEFAULT_AUX, DEFAULT_FEATURE_SPP

#: The key of a checkpoint meta record that holds the training data's record.
META_KEY = "trained_features"
#: The frame fields the settings change (aux: albedo and normal; feature_spp: all four).
FEATURE_FIELDS: tuple[str, ...] = ("albedo", "normal", "depth", "position")

#: The (trained, found) pairs warned about in this process.
_warned: set[tuple[Any, Any]] = set()


@dataclasses.dataclass(frozen=True)
class FeatureRecord:
    """How a frame's features were rendered: ``aux`` and ``feature_spp`` (the setting, or the
    samples the feature pass averaged as an EXR header records them; None: not recorded)."""

    aux: str
    feature_spp: int | None = None

    def samples(self, spp: float | None = None) -> int | None:
        """The samples the features average at ``spp`` samples of colour (None: unknown)."""
        if self.feature_spp is None or spp is None:
            return self.feature_spp
        return min(int(spp), self.feature_spp)

    def describe(self) -> str:
        spp = "" if self.feature_spp is None else f", feature_spp={self.feature_spp}"
        return f"aux={self.aux}{spp}"

    def to_json(self) -> dict[str, Any]:
        return {"aux": self.aux, "feature_spp": self.feature_spp}

    @classmethod
    def from_json(cls, data: Any) -> FeatureRecord | None:
        """The record of a JSON object ``{"aux": ..., "feature_spp": ...}``; None for anything
        else (no record, or one this version cannot read: the comparison is then skipped)."""
        if not isinstance(data, Mapping) or not isinstance(data.get("aux"), str):
            return None
        count = data.get("feature_spp")
        if isinstance(count, float) and count.is_integer():
            count = int(count)
        if isinstance(count, bool) or not isinstance(count, int) or count < 1:
            count = None
        return cls(data["aux"], count)


# --------------------------------------------------------------------------- the records
def manifest_features(manifest) -> FeatureRecord | None:
    """A dataset's record from its :class:`jaxden.data.layout.Manifest`: its config's ``aux``
    and ``feature_spp``, the defaults where the config predates them; None for an imported
    dataset."""
    if isinstance(manifest.extra, Mapping) and "import" in manifest.extra:
        return None
    config = manifest.config if isinstance(manifest.config, Mapping) else {}
    return FeatureRecord.from_json({
        "aux": config.get("aux", DEFAULT_AUX),
        "feature_spp": config.get("feature_spp", DEFAULT_FEATURE_SPP)})


def dataset_features(directory: str | os.PathLike) -> FeatureRecord | None:
    """The record of the dataset in ``directory`` (:func:`manifest_features`)."""
    from jaxden.data.layout import load_manifest

    return manifest_features(load_manifest(directory))


def meta_features(meta: Mapping[str, Any]) -> FeatureRecord | None:
    """A checkpoint meta record's ``trained_features`` (None: a model saved before the record
    existed, or trained on data without one)."""
    return FeatureRecord.from_json(meta.get(META_KEY)) if isinstance(meta, Mapping) else None


def header_features(header: Mapping[str, Any]) -> FeatureRecord | None:
    """An EXR header's record (:func:`jaxden.io.exr.read_header`: ``aux``, ``feature_spp``);
    None when the file records no ``aux`` (another renderer's, or written before the record)."""
    return FeatureRecord.from_json(header)


# ----------------------------------------------------------------------------- comparing
def feature_mismatch(trained: FeatureRecord | None, found: FeatureRecord | None,
                     spp: float | None = None, model: str = "the model") -> str | None:
    """How the features of a frame (``found``, of ``spp`` samples) differ from those
    ``model`` was trained on, in words, or None when they agree or either record is missing.
    ``feature_spp`` is compared as the samples averaged at ``spp``
    (:meth:`FeatureRecord.samples`), and only when both records have it."""
    if trained is None or found is None:
        return None
    problems = []
    if trained.aux != found.aux:
        problems.append("aux")
    mine, theirs = trained.samples(spp), found.samples(spp)
    if mine is not None and theirs is not None and mine != theirs:
        problems.append("feature_spp")
    if not problems:
        return None
    return (f"its features are {found.describe()}, {model} was trained on "
            f"{trained.describe()} (differing: {', '.join(problems)})")


def warn_feature_mismatch(trained: FeatureRecord | None, found: FeatureRecord | None, *,
                          where: str, model: str = "the model", spp: float | None = None,
                          fields: Iterable[str] | None = None) -> bool:
    """Print one line on stderr when :func:`feature_mismatch` finds a difference, once per
    process for each (trained, found) pair; returns whether it printed. ``where``: the frame
    (a file name); ``model``: the model's name; ``fields``: the frame fields the model reads
    (None: assume it reads the features; a model that reads none of :data:`FEATURE_FIELDS`
    is never warned about)."""
    if fields is not None and not set(fields) & set(FEATURE_FIELDS):
        return False
    problem = feature_mismatch(trained, found, spp, model)
    if problem is None:
        return False
    if (trained, found) in _warned:
        return False
    _warned.add((trained, found))
    print(f"jaxden: warning: {where}: {problem}; it sees features unlike its training data "
          f"(render the frame with --aux {trained.aux}"
          + ("" if trained.feature_spp is None else f" --feature-spp {trained.feature_spp}")
          + ", or train on a dataset of its features)", file=sys.stderr, flush=True)
    return True


def warn_frame_features(trained: FeatureRecord | None, path: str | os.PathLike, *,
                        model: str = "the model", fields: Iterable[str] | None = None) -> bool:
    """:func:`warn_feature_mismatch` for the EXR file ``path`` (its header's record and spp);
    nothing when ``trained`` is None or the header cannot be read."""
    if trained is None:
        return False
    from jaxden.errors import JaxdenError
    from jaxden.io.exr import read_header

    try:
        header = read_header(path)
    except (JaxdenError, OSError):
        return False
    spp = header.get("spp")
    spp = float(spp) if isinstance(spp, (int, float)) and not isinstance(spp, bool) else None
    return warn_feature_mismatch(trained, header_features(header), where=str(path),
                                 model=model, spp=spp, fields=fields)
