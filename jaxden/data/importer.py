"""Import another renderer's EXRs as a jaxden dataset (``jaxden dataset import``).

The source folder holds one folder per camera view::

    SRC/<view>/reference.exr            the view's high-spp reference, carrying its variance
    SRC/<view>/reference/b0.exr ..      or K >= 2 independent renders (different seeds) of it
    SRC/<view>/spp<N>.exr               an N-spp input: one render, carrying its variance when
                                        N > 1 (a 1-spp input has none)
    SRC/<view>/spp<N>/b0.exr .. bK-1    or K >= 2 independent renders whose sample counts sum
                                        to N (e.g. spp4/b0..b3.exr of 1 spp each)

View names are folder names of letters, digits and ``- _ .``; every view has the same input
levels N and every file the same size. Files and folders whose names start with ``.``, and
files that are not ``.exr``, are ignored; any other ``.exr`` file or folder is an error. The
files are read by a renderer's channel conventions (``convention``:
:mod:`jaxden.io.conventions`; ``channel_map`` names channels by hand and wins) and must hold
the colour, albedo, normal and depth. Only raw Monte Carlo means are imported: a denoised
Cycles render gives its Noisy Image pass, a denoised image is refused, and so is a render
made with adaptive sampling (seen in Cycles' Debug Sample Count pass), whose pixels took
other counts than its level's N. Buffers are
merged by :func:`jaxden.data.merge.merge_renders` (the variance of the mean from their spread,
or pooled from their own variances), exactly as ``jaxden merge`` does. A sample count in a
file's header must agree with the name (``spp<N>``: N in all; the reference's must agree with
``reference_spp`` when both are given); buffers without one share N equally.

The result is what ``jaxden dataset build`` writes (:mod:`jaxden.data.layout`): a
:class:`DatasetConfig` with one scene per view (``scenes`` = the view names, ``size`` = the
views' size), ``crops_per_scene`` random crops per view of side ``crop_size``, placed and
seeded by ``seed`` as the builder places them, every input level and the reference per crop;
views in ``val`` and ``held_out`` go to the val and test splits, every other view to train.
The files are written by :func:`jaxden.data.builder.build_dataset` with a renderer that reads
the source instead of rendering, so the import is atomic and resumable as a build is: an
interrupted import resumes when run again, a finished one returns at once, and ``jaxden
dataset verify``, ``jaxden train``, ``jaxden sweep`` and the evaluators read it unchanged. The
manifest's ``renderer`` names the source files' digest (a rerun with other files is refused)
and its ``extra.import`` records the source folder, the convention and every item's files.

Everything is checked before anything is written: a bad source is one DatasetError (or
ExrError / FrameError) naming the file, and leaves no dataset folder behind; a bad argument is
an :class:`ImportArgumentError` naming the parameter. The dataset's
``aux`` and ``feature_spp`` are the defaults and mean nothing here: the features are the
source renderer's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jaxden.data.config import DatasetConfig, SplitConfig
from jaxden.data.layout import ITEM_FEATURES, LOCK_NAME, MANIFEST_NAME, TEMP_PATTERN, Manifest
from jaxden.errors import ConfigError, DatasetError, ExrError

REFERENCE_STEM = "reference"
LEVEL_PATTERN = re.compile(r"^spp(\d+)$")
BUFFER_PATTERN = re.compile(r"^b(\d+)\.exr$", re.IGNORECASE)
VIEW_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
#: Fields kept beside the required ones when every source that can have them has them.
OPTIONAL_FIELDS: tuple[str, ...] = ("position", "emission")
LAYOUT = ("SRC/<view>/reference.exr (or reference/b<k>.exr) and SRC/<view>/spp<N>.exr (or "
          "spp<N>/b<k>.exr)")


def _parameter(parameter: str, *value) -> str:
    return f"{parameter}={value[0]}" if value else parameter


class ImportArgumentError(DatasetError):
    """A DatasetError about :func:`import_dataset`'s arguments. Its message names them as the
    function's parameters (``held_out``, ``crop_size=21``); :meth:`naming` gives the same
    message naming them otherwise (the CLI's flags: ``--held-out``, ``--crop 21``).

    ``describe(name)`` makes the message, ``name(parameter[, value])`` naming a parameter."""

    def __init__(self, describe: Callable[[Callable[..., str]], str] | str) -> None:
        self.describe = describe if callable(describe) else (lambda name: describe)
        super().__init__(self.describe(_parameter))

    def naming(self, names: dict[str, str]) -> str:
        """The message with each parameter in ``names`` called by its entry there, followed
        by its value after a space (``{"crop_size": "--crop"}``: ``--crop 21``)."""
        def name(parameter: str, *value) -> str:
            if parameter not in names:
                return _parameter(parameter, *value)
            return " ".join([names[parameter], *map(str, value)])

        return self.describe(name)

    def __reduce__(self):  # the message travels; the function that made it need not pickle
        return type(self), (str(self),)


@dataclasses.dataclass(frozen=True)
class Source:
    """One render of a view as the source folder holds it: the reference or one input level.

    ``files``: paths relative to the source folder ('/'-separated), one file or the K buffers
    in buffer order; ``buffers``: whether they are buffers to merge; ``level``: N of
    ``spp<N>`` (None for the reference)."""

    view: str
    kind: str  # "input" or "reference"
    level: int | None
    files: tuple[str, ...]
    buffers: bool

    @property
    def name(self) -> str:
        """The source's path relative to the source folder, without ``.exr`` for one file."""
        stem = REFERENCE_STEM if self.kind == "reference" else f"spp{self.level}"
        return f"{self.view}/{stem}" + ("" if self.buffers else ".exr")


@dataclasses.dataclass(frozen=True)
class ResolvedSource:
    """A :class:`Source` with what its headers say: its sample count ``spp``, each file's
    (``file_spp``, given to the reader), its size (width, height) and the fields its merged
    frame has (``fields``, before the dataset chooses which to keep)."""

    source: Source
    spp: int
    file_spp: tuple[float, ...]
    size: tuple[int, int]
    fields: frozenset[str]


# ----------------------------------------------------------------------------- layout scan
def scan_source(root: str | os.PathLike) -> list[list[Source]]:
    """The views of a source folder, each as ``[reference, input levels in spp order]``
    (names only; no file is decoded). Raises DatasetError naming the entry that does not
    fit the layout (module docstring), a view without a reference or inputs, a view whose
    levels differ from the first view's, and a folder without views."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: is a file, not a folder of views" if root.exists()
                           else f"source folder {root} does not exist")
    views = []
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            views.append(_scan_view(root, entry))
        elif entry.name.lower().endswith(".exr"):
            raise DatasetError(f"{entry}: an EXR directly in the source folder; the layout is "
                               f"{LAYOUT}: put each view's renders in a folder of its own")
    if not views:
        raise DatasetError(f"{root}: holds no view folders (the layout is {LAYOUT})")
    first = views[0]
    levels = [s.level for s in first[1:]]
    for view in views[1:]:
        if [s.level for s in view[1:]] != levels:
            raise DatasetError(
                f"{root / view[0].view}: has the inputs "
                f"{', '.join(f'spp{s.level}' for s in view[1:])} but {root / first[0].view} "
                f"has {', '.join(f'spp{n}' for n in levels)}: every view needs the same levels")
    return views


def _scan_view(root: Path, folder: Path) -> list[Source]:
    view = folder.name
    if not VIEW_PATTERN.match(view) or view.lower().endswith(".xml"):
        raise DatasetError(f"{folder}: a view folder's name must be letters, digits and - _ . "
                           f"(not ending in .xml)")
    found: dict[str, tuple[Source, Path]] = {}
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            key = entry.name
        elif entry.name.lower().endswith(".exr"):
            key = entry.name[:-4]
        else:
            continue  # notes, scene files: not renders
        match = LEVEL_PATTERN.match(key)
        if key != REFERENCE_STEM and (match is None or int(match.group(1)) == 0):
            raise DatasetError(f"{entry}: not part of the import layout (a view folder holds "
                               f"reference.exr or reference/, and spp<N>.exr or spp<N>/ with "
                               f"N >= 1)")
        kind, level = ("reference", None) if key == REFERENCE_STEM else ("input",
                                                                           int(match.group(1)))
        files = (_buffer_files(root, entry) if entry.is_dir()
                 else (entry.relative_to(root).as_posix(),))
        source = Source(view, kind, level, files, entry.is_dir())
        slot = kind if level is None else f"spp{level}"
        if slot in found:
            raise DatasetError(f"{entry}: the view has {found[slot][1].name} too: give each "
                               f"level once, as one file or as a folder of buffers")
        found[slot] = (source, entry)
    if "reference" not in found:
        raise DatasetError(f"{folder}: the view has no reference (reference.exr, or "
                           f"reference/b0.exr .. as K independent renders)")
    inputs = sorted((s for s, _ in found.values() if s.kind == "input"), key=lambda s: s.level)
    if not inputs:
        raise DatasetError(f"{folder}: the view has no inputs (spp<N>.exr or spp<N>/b<k>.exr)")
    return [found["reference"][0], *inputs]


def _buffer_files(root: Path, folder: Path) -> tuple[str, ...]:
    numbered: dict[int, Path] = {}
    for entry in sorted(folder.iterdir()):
        if entry.name.startswith("."):
            continue
        match = BUFFER_PATTERN.match(entry.name)
        if entry.is_dir() or (match is None and entry.name.lower().endswith(".exr")):
            raise DatasetError(f"{entry}: not part of the import layout (a folder of buffers "
                               f"holds b0.exr, b1.exr, ...)")
        if match is None:
            continue
        index = int(match.group(1))
        if index in numbered:
            raise DatasetError(f"{entry}: the same buffer number as {numbered[index].name}")
        numbered[index] = entry
    if len(numbered) < 2:
        raise DatasetError(f"{folder}: holds {len(numbered)} buffer(s); a folder of buffers "
                           f"needs K >= 2 independent renders (b0.exr, b1.exr, ...) with "
                           f"different seeds")
    return tuple(numbered[i].relative_to(root).as_posix() for i in sorted(numbered))


# ----------------------------------------------------------------------------- headers
def _file_header(path: Path, convention: str | None, layer: str | None,
                 channel_map: dict | None = None):
    """(sample count or None, size (W, H), fields present) from one file's header."""
    from jaxden.frame import CHANNELS
    from jaxden.io.conventions import resolve
    from jaxden.io.exr import read_header

    header = read_header(path)
    present = set(header["channels"])
    if convention is None:
        mapping, spp = dict(CHANNELS), header.get("spp")
    else:
        reading = resolve(convention, present, header, layer=layer, where=str(path))
        mapping, spp = dict(reading.mapping), reading.spp
    mapping.update({field: tuple(names) for field, names in (channel_map or {}).items()})
    if spp is not None:
        try:
            spp = float(spp)
        except (TypeError, ValueError):
            raise ExrError(f"{path}: header attribute spp is not a number: {spp!r}") from None
        if not (math.isfinite(spp) and spp > 0):
            raise ExrError(f"{path}: its header's sample count must be > 0, got {spp:g}")
    fields = frozenset(f for f, names in mapping.items() if set(names) <= present)
    return spp, tuple(header["size"]), fields


def resolve_source(root: Path, source: Source, *, convention: str | None = None,
                   layer: str | None = None, reference_spp: int | None = None,
                   channel_map: dict | None = None) -> ResolvedSource:
    """Read a source's headers: its sample count (see the module docstring), size and
    fields. Raises DatasetError naming the file for a count that contradicts the name or
    ``reference_spp``, a reference whose count is nowhere, buffers of different sizes or
    fields, and a single file of N > 1 samples without a variance."""
    paths = [root / f for f in source.files]
    headers = [_file_header(p, convention, layer, channel_map) for p in paths]
    where = root / source.name
    for path, (_, size, fields) in zip(paths[1:], headers[1:]):
        if size != headers[0][1] or fields != headers[0][2]:
            what = (f"{size[0]}x{size[1]} pixels" if size != headers[0][1]
                    else f"the fields {', '.join(sorted(fields))}")
            first = (f"{headers[0][1][0]}x{headers[0][1][1]}" if size != headers[0][1]
                     else ", ".join(sorted(headers[0][2])))
            raise DatasetError(f"{path}: has {what}, but {paths[0].name} has {first}: the "
                               f"buffers of one level are renders of one view and setup")
    counts = [spp for spp, _, _ in headers]
    stated = source.level if source.kind == "input" else reference_spp
    if all(c is None for c in counts):
        if stated is None:
            raise ImportArgumentError(
                lambda name: f"{where}: the reference's sample count is in no header (read as "
                             f"{convention or 'jaxden'}): give it with "
                             f"{name('reference_spp', 'N')}")
        if source.buffers and stated % len(paths):
            raise DatasetError(f"{where}: {len(paths)} buffers without a sample count in their "
                               f"headers cannot share {stated} spp equally")
        total, file_spp = stated, (stated / len(paths),) * len(paths)
    elif any(c is None for c in counts):
        index = counts.index(None)
        raise DatasetError(f"{paths[index]}: its header has no sample count while "
                           f"{paths[counts.index(next(c for c in counts if c))].name}'s has: "
                           f"buffers of one level come from one renderer setup")
    else:
        total, file_spp = sum(counts), tuple(counts)
        if stated is not None and not math.isclose(total, stated, rel_tol=1e-6):
            said = "the name" if source.kind == "input" else None
            raise ImportArgumentError(
                lambda name: f"{where}: the header{'s say' if source.buffers else ' says'} "
                             f"{total:g} spp{' in all' if source.buffers else ''}, "
                             f"{said or name('reference_spp')} says {stated}")
        if abs(total - round(total)) > 1e-6 * total:
            raise DatasetError(f"{where}: the headers say {total:g} spp, not a whole number")
    spp = round(total)
    fields = set(headers[0][2])
    if source.buffers and "variance" not in fields:  # merged from their spread
        fields |= {"variance", "covariance"}
    if spp == 1:
        fields -= {"variance", "covariance"}
    elif "variance" not in fields:
        what = "input" if source.kind == "input" else "reference"
        raise DatasetError(
            f"{where}: a {spp}-spp {what} needs the variance of its mean, and this file (read "
            f"as {convention or 'jaxden'}) has none: render it as K >= 2 independent buffers "
            f"{root / source.view / where.stem}/b0.exr, b1.exr, ... with different seeds")
    return ResolvedSource(source, spp, file_spp, headers[0][1], frozenset(fields))


def read_source(root: Path, resolved: ResolvedSource, *, convention: str | None = None,
                layer: str | None = None, nonfinite: str = "error",
                channel_map: dict | None = None):
    """The source as one Frame: the file, or its buffers merged (:func:`merge_renders`);
    ExrError / FrameError naming the file for a missing colour, feature or channel of
    ``channel_map``, a non-finite value (unless ``nonfinite='zero'``), a denoised colour, a
    render made with adaptive sampling (its pixels took other counts than the level's) and
    buffers that are one render twice."""
    from jaxden.data.merge import merge_renders
    from jaxden.io.exr import read_frame

    paths = [root / f for f in resolved.source.files]
    require = tuple(dict.fromkeys((*ITEM_FEATURES, *(channel_map or {}))))
    frames = [read_frame(path, require=require, nonfinite=nonfinite, convention=convention,
                         layer=layer, spp=spp, channel_map=channel_map, refuse_denoised=True)
              for path, spp in zip(paths, resolved.file_spp)]
    if not resolved.source.buffers:
        return frames[0]
    return merge_renders(frames, names=[str(p) for p in paths])


def kept_fields(resolved: list[ResolvedSource]) -> tuple[str, ...]:
    """The fields every dataset file gets: the required ones, the variance where spp > 1,
    and the covariance, position and emission where every source that can have them does."""
    keep = list(ITEM_FEATURES) + ["variance"]
    multi = [r for r in resolved if r.spp > 1]
    if multi and all("covariance" in r.fields for r in multi):
        keep.append("covariance")
    keep += [f for f in OPTIONAL_FIELDS if all(f in r.fields for r in resolved)]
    return tuple(keep)


# ----------------------------------------------------------------------------- renderer
class ImportedRenders:
    """The dataset builder's renderer for an import: the item whose seed is asked for is
    read from its source (merged when buffers), cut to the crop and given the kept fields.
    Keeps the current view's decoded sources (the builder works crop by crop, view by view).
    ``renderer_name`` of the builder reads ``__qualname__``, which names the sources'
    digest, so a resumed import is refused when the source files have changed."""

    def __init__(self, root: Path, by_seed: dict[int, ResolvedSource], digest: str, *,
                 convention: str | None, layer: str | None, nonfinite: str,
                 keep: tuple[str, ...], channel_map: dict | None = None) -> None:
        self.root = root
        self.by_seed = by_seed
        self.options = {"convention": convention, "layer": layer, "nonfinite": nonfinite,
                        "channel_map": channel_map}
        self.keep = keep
        self.__qualname__ = f"ImportedRenders[{convention or 'jaxden'},{digest[:16]}]"
        self._view: str | None = None
        self._frames: dict[str, Any] = {}

    def __call__(self, scene, spp, seed=0, size=None, *, crop=None, **_):
        import numpy as np

        resolved = self.by_seed[seed]
        view = resolved.source.view
        if view != self._view:
            self._view, self._frames = view, {}
        name = resolved.source.name
        if name not in self._frames:
            self._frames[name] = read_source(self.root, resolved, **self.options).numpy()
        frame = self._frames[name]
        top, left, height, width = crop
        fields = {f: getattr(frame, f)[top:top + height, left:left + width].astype(np.float32)
                  for f in self.keep if getattr(frame, f) is not None
                  and (spp > 1 or f not in ("variance", "covariance"))}
        dof = frame.variance_dof if spp > 1 else None
        from jaxden.frame import Frame

        return Frame(**fields, spp=np.float32(spp),
                     variance_dof=None if dof is None else np.float32(np.asarray(dof)))


# ----------------------------------------------------------------------------- import
def _check_views(parameter: str, names, views: list[str]) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(n for n in names if n))
    unknown = [n for n in names if n not in views]
    if unknown:
        raise ImportArgumentError(
            lambda name: f"{name(parameter)}: {', '.join(unknown)} is not a view of the source "
                         f"(views: {', '.join(views)})")
    return names


def sources_digest(root: Path, resolved: list[ResolvedSource], settings: dict) -> str:
    """sha256 over every source file's path and bytes and the reading ``settings``."""
    from jaxden.provenance import file_sha256

    entries = [(f, file_sha256(root / f)) for r in resolved for f in r.source.files]
    return hashlib.sha256(json.dumps([entries, settings], sort_keys=True).encode()).hexdigest()


def import_dataset(
    source: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    convention: str | None = None,
    layer: str | None = None,
    crop_size: int = 128,
    crops_per_view: int = 4,
    seed: int = 0,
    held_out=(),
    val=(),
    reference_spp: int | None = None,
    name: str | None = None,
    half: bool = False,
    nonfinite: str = "error",
    progress: bool = True,
    channel_map: dict | None = None,
) -> Manifest:
    """Import the source folder (module docstring) as a dataset in ``out_dir``; return its
    complete manifest.

    ``convention``: the renderer whose channel names the files follow (None: jaxden's);
    ``layer``: the render layer of a layered (Cycles) file with several; ``channel_map``:
    field -> channel names, named by hand (wins over the convention). ``crop_size``,
    ``crops_per_view`` (the config's ``crops_per_scene``), ``seed``, ``half``: as in a
    :class:`DatasetConfig`. ``held_out`` / ``val``: view names for the test / val splits.
    ``reference_spp``: the references' sample count where no header records it. ``name``:
    the dataset's label (default: the source folder's name). ``nonfinite``: 'error' or 'zero'
    (:meth:`jaxden.frame.Frame.validated`). Safe to interrupt and rerun.
    """
    from jaxden.data.builder import build_dataset, renderer_name
    from jaxden.data.layout import load_manifest, plan_dataset

    root = Path(source).absolute()
    directory = Path(out_dir)
    _check_convention(convention)
    if directory.absolute() == root or root in directory.absolute().parents:
        raise ImportArgumentError(
            lambda name: f"{name('out_dir', directory)}: inside the source folder {root}; "
                         f"write the dataset elsewhere")
    views = scan_source(root)
    channel_map = _check_channel_map(channel_map)
    options = {"convention": convention, "layer": layer, "channel_map": channel_map}
    resolved = [[resolve_source(root, s, reference_spp=reference_spp, **options) for s in view]
                for view in views]
    flat = [r for view in resolved for r in view]
    first = flat[0]
    for r in flat:
        if r.size != first.size:
            raise DatasetError(
                f"{root / r.source.files[0]}: {r.size[0]}x{r.size[1]} pixels, but "
                f"{root / first.source.files[0]} is {first.size[0]}x{first.size[1]}: every "
                f"render of the source folder must have one size")
    references = [view[0] for view in resolved]
    if len({r.spp for r in references}) > 1:
        other = next(r for r in references if r.spp != references[0].spp)
        raise DatasetError(f"{root / other.source.name}: {other.spp} spp, but "
                           f"{root / references[0].source.name} has {references[0].spp}: "
                           f"every view's reference needs the same sample count")
    levels = tuple(s.level for s in views[0][1:])
    if references[0].spp < max(levels):
        raise DatasetError(f"{root / references[0].source.name}: the reference has "
                           f"{references[0].spp} spp, fewer than the largest input's "
                           f"{max(levels)}")
    names = [view[0].view for view in views]
    held_out = _check_views("held_out", held_out, names)
    val = _check_views("val", val, names)
    both = sorted(set(held_out) & set(val))
    if both:
        raise ImportArgumentError(
            lambda name: f"{name('held_out')} and {name('val')} both name {', '.join(both)}")
    width, height = first.size
    if not 1 <= crop_size <= min(width, height):
        raise ImportArgumentError(
            lambda name: f"{name('crop_size', crop_size)}: must be in 1..{min(width, height)} "
                         f"(the views are {width}x{height})")
    try:
        config = DatasetConfig(
            name=name or root.name, scenes=tuple(names), size=(width, height),
            crop_size=crop_size, crops_per_scene=crops_per_view, spp=levels,
            reference_spp=references[0].spp, seed=seed, half=half,
            splits=SplitConfig(train=1.0, val=0.0, test=0.0, val_scenes=val,
                               test_scenes=held_out))
    except ConfigError as error:
        raise DatasetError(f"import of {root}: {error}") from None
    settings = {**options, "nonfinite": nonfinite, "reference_spp": references[0].spp}
    if channel_map is None:  # as before channel_map existed: earlier imports resume
        del settings["channel_map"]
    digest = sources_digest(root, flat, settings)
    plan = plan_dataset(config)
    by_view = {view[0].source.view: view for view in resolved}
    scene_of = {crop.id: crop.scene for crop in plan.crops}
    by_seed: dict[int, ResolvedSource] = {}
    for item in plan.items:
        view = by_view[scene_of[item.crop]]
        match = view[0] if item.kind == "reference" else next(
            r for r in view[1:] if r.source.level == item.spp)
        if by_seed.setdefault(item.seed, match) is not match:
            raise ImportArgumentError(
                lambda name, seed=item.seed: f"two items of the plan share the seed {seed}; "
                                             f"import with another {name('seed')}")
    renders = ImportedRenders(root, by_seed, digest, nonfinite=nonfinite,
                              keep=kept_fields(flat), **options)
    if not _resuming(directory, renderer_name(renders)):
        _validate(root, flat, options, nonfinite, progress)
    manifest = build_dataset(config, directory, executor="serial", render_fn=renders,
                             progress=progress)
    manifest.extra = {**manifest.extra, "import": {
        "source": str(root), "convention": convention or "jaxden", "layer": layer,
        **({} if channel_map is None else {"channels": channel_map}),
        "sources_sha256": digest, "nonfinite": nonfinite,
        "items": {item.id: list(by_seed[item.seed].source.files) for item in manifest.items}}}
    from jaxden.fileio import folder_lock

    with folder_lock(directory, LOCK_NAME, "import"):
        if load_manifest(directory).extra != manifest.extra:
            manifest.save(directory)
    return manifest


def _check_channel_map(channel_map) -> dict[str, list[str]] | None:
    """``channel_map`` as field -> list of names (JSON-ready); ImportArgumentError for an
    unknown field or a wrong count of names."""
    from jaxden.frame import CHANNELS

    if not channel_map:
        return None
    checked = {}
    for field, names in channel_map.items():
        names = [str(n) for n in ((names,) if isinstance(names, str) else names)]
        if field not in CHANNELS or len(names) != len(CHANNELS[field]):
            want = ("one of " + ", ".join(CHANNELS) if field not in CHANNELS
                    else f"{len(CHANNELS[field])} channel name(s) for {field}")
            given = f"{field}={','.join(names)}: expected {want}"
            raise ImportArgumentError(lambda name, given=given: f"{name('channel_map')}: {given}")
        checked[field] = names
    return checked


def _check_convention(convention: str | None) -> None:
    """DatasetError for a renderer that writes one file per output (Falcor): a source file of
    the layout holds a whole render."""
    from jaxden.io.conventions import CONVENTIONS

    known = CONVENTIONS.get(convention) if convention is not None else None
    if known is not None and getattr(known, "file_pattern", None):
        raise ImportArgumentError(
            lambda name: f"{name('convention', convention)}: {convention} writes one file per "
                         f"output, and the import reads one file per render: merge each "
                         f"render's captures into one file SRC/<view>/spp<N>.exr first (as "
                         f"`jaxden merge --from {convention}` does) and import those with "
                         f"{name('convention')} left out")


def _resuming(directory: Path, renderer: str) -> bool:
    """Whether ``directory`` holds an import of the same source files (already checked by the
    import that started it); DatasetError when it holds anything else."""
    from jaxden.data.layout import load_manifest

    if not directory.exists():
        return False
    if not directory.is_dir():
        raise ImportArgumentError(
            lambda name: f"{name('out_dir', directory)}: exists and is not a folder")
    if not (directory / MANIFEST_NAME).exists():
        foreign = sorted(p.name for p in directory.iterdir()
                         if p.name != LOCK_NAME and not TEMP_PATTERN.match(p.name))
        if foreign:
            raise ImportArgumentError(
                lambda name: f"{name('out_dir', directory)}: is not empty "
                             f"({', '.join(foreign[:5])}) and has no {MANIFEST_NAME}: refusing "
                             f"to import into it")
        return False
    stored = load_manifest(directory).renderer
    if stored != renderer:
        raise ImportArgumentError(
            lambda name: f"{name('out_dir', directory)}: holds a dataset made by {stored}, not "
                         f"by this import ({renderer}: other source files or settings); import "
                         f"into another folder, or delete {directory} first")
    return True


def _validate(root: Path, resolved: list[ResolvedSource], options: dict, nonfinite: str,
              progress: bool) -> None:
    """Decode every source once (merging buffers): the errors :func:`read_source` raises come
    here, before anything is written."""
    iterator = resolved
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(resolved, desc=f"check {root.name}", unit=" renders", leave=False)
    for r in iterator:
        read_source(root, r, nonfinite=nonfinite, **options)
