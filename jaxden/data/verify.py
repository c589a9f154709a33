"""Check a built dataset against its manifest.

``verify_dataset(DIR)`` checks every planned item: the file exists, its size and SHA-256 match
the manifest, it reads back as a complete, finite frame with the dataset features (variance
when spp > 1), of the crop's size, and its header names the same item, seed and spp; and the
emission (``emission.R/G/B``) is in all files or in none (datasets of a jaxden older than
``Frame.emission`` have none, and load and work without it). The report
lists every problem with its path; the CLI prints them and exits non-zero if there are any.
``build_dataset`` on the same folder re-renders exactly the items that fail.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from jaxden.data.layout import (
    CONFIG_NAME,
    LOCK_NAME,
    MANIFEST_NAME,
    TEMP_PATTERN,
    Item,
    load_manifest,
    required_features,
    sha256_file,
)
from jaxden.errors import DatasetError, ExrError


@dataclasses.dataclass(frozen=True)
class Problem:
    """One failed check: the file, the item id (None for files outside the plan), what failed."""

    path: str
    item: str | None
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.message}"


@dataclasses.dataclass
class VerifyReport:
    """Result of :func:`verify_dataset`. ``ok`` is True when there are no problems; warnings
    (stray files) do not count as problems."""

    directory: str
    items_total: int
    items_checked: int
    problems: list[Problem]
    warnings: list[str]

    @property
    def ok(self) -> bool:
        return not self.problems

    def summary(self) -> str:
        state = "OK" if self.ok else f"{len(self.problems)} problem(s)"
        return (
            f"{self.directory}: {self.items_checked}/{self.items_total} items checked, {state}"
            + (f", {len(self.warnings)} warning(s)" if self.warnings else "")
        )

    def __str__(self) -> str:
        lines = [self.summary()]
        lines += [f"  problem: {p}" for p in self.problems]
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _same_number(found, expected) -> bool:
    """Whether a header value is the number ``expected`` (False for text such as 'abc')."""
    if isinstance(found, bool):
        return False
    try:
        return float(found) == float(expected)
    except (TypeError, ValueError):
        return False


def check_item_file(
    path: str | os.PathLike, item: Item, window: tuple[int, int, int, int], *, read: bool = True
) -> list[str]:
    """Problems of one item's EXR (not its checksum): header, size, channels, values.

    Returns an empty list when the file is a complete frame for ``item``.
    """
    from jaxden.io.exr import read_frame, read_header

    problems = []
    try:
        header = read_header(path)
    except ExrError as error:
        return [f"unreadable: {error}"]
    height, width = window[2], window[3]
    if tuple(header.get("size", ())) != (width, height):
        problems.append(f"size {header.get('size')} (W, H), expected ({width}, {height})")
    for key, expected in (("item", item.id), ("seed", item.seed), ("spp", item.spp)):
        found = header.get(key)
        if found is None:
            problems.append(f"header has no jaxden.{key} (expected {expected!r})")
        elif key == "spp" and not _same_number(found, expected):
            problems.append(f"header jaxden.spp is {found!r}, expected {expected!r}")
        elif key != "spp" and found != expected:
            problems.append(f"header jaxden.{key} is {found!r}, expected {expected!r}")
    if read and not problems:
        try:
            read_frame(path, require=required_features(item.spp))
        except ExrError as error:
            message = str(error)
            prefix = f"{path}: "
            problems.append(message[len(prefix) :] if message.startswith(prefix) else message)
    return problems


def verify_dataset(
    directory: str | os.PathLike,
    *,
    checksums: bool = True,
    read: bool = True,
    progress: bool = False,
) -> VerifyReport:
    """Check every item of the dataset in ``directory`` against ``manifest.json``.

    ``checksums``: compare sizes and SHA-256 (the slow part for big datasets); ``read``: decode
    every EXR and check its features and values. Raises DatasetError only when the folder or
    its manifest is missing or unreadable; every other finding is a Problem in the report.
    """
    directory = Path(directory)
    manifest = load_manifest(directory)
    windows = {crop.id: crop.window for crop in manifest.crops}
    problems: list[Problem] = []
    items = manifest.items
    iterator = items
    if progress:
        from tqdm.auto import tqdm

        iterator = tqdm(items, desc=f"verify {directory}", unit=" files")
    checked = 0
    for item in iterator:
        path = directory / item.path
        shown = str(path)
        if Path(item.path).is_absolute() or ".." in Path(item.path).parts:
            problems.append(Problem(shown, item.id, f"the manifest's path {item.path!r} leaves "
                                    f"the dataset folder"))
            continue
        if not item.done:
            problems.append(
                Problem(shown, item.id, "not built yet (no checksum in the manifest): run the "
                        "build again to finish the dataset")
            )
            continue
        if not path.is_file():
            problems.append(Problem(shown, item.id, "missing"))
            continue
        checked += 1
        if checksums:
            size = path.stat().st_size
            if size != item.bytes:
                problems.append(
                    Problem(shown, item.id, f"size {size} bytes, manifest says {item.bytes}")
                )
                continue
            digest = sha256_file(path)
            if digest != item.sha256:
                problems.append(
                    Problem(shown, item.id, f"SHA-256 {digest[:12]}... does not match the "
                            f"manifest's {item.sha256[:12]}... (file changed or corrupt)")
                )
                continue
        for message in check_item_file(path, item, windows[item.crop], read=read):
            problems.append(Problem(shown, item.id, message))
    problems += _mixed_emission(directory, items)
    planned = {str(Path(item.path)) for item in items}
    warnings = []
    for root, folders, files in os.walk(directory):
        if Path(root) == Path(directory) and "derived" in folders:
            folders.remove("derived")  # caches computed from the dataset (e.g. SURE maps)
        for name in files:
            relative = os.path.relpath(os.path.join(root, name), directory)
            if relative in planned or relative in (MANIFEST_NAME, CONFIG_NAME, LOCK_NAME):
                continue
            temporary = TEMP_PATTERN.match(name)
            kind = "leftover temporary file" if temporary else "file not in the manifest"
            warnings.append(f"{os.path.join(root, name)}: {kind}")
    return VerifyReport(str(directory), len(items), checked, problems, sorted(warnings))


def _mixed_emission(directory: Path, items: list[Item]) -> list[Problem]:
    """A Problem for each file without the emission when other files of the dataset have it
    (files of two jaxden versions); none when all or none have it (an older dataset)."""
    from jaxden.frame import CHANNELS
    from jaxden.io.exr import read_header

    has: dict[str, bool] = {}
    for item in items:
        try:
            has[item.id] = set(CHANNELS["emission"]) <= set(
                read_header(directory / item.path)["channels"])
        except (ExrError, OSError):
            continue  # reported above
    if all(has.values()) or not any(has.values()):
        return []
    return [Problem(str(directory / item.path), item.id,
                    f"no emission ({'/'.join(CHANNELS['emission'])}) while {sum(has.values())} "
                    f"other files of the dataset have it: files of two jaxden versions; delete "
                    f"the files without it and run the build again")
            for item in items if has.get(item.id) is False]


def check_covariance_recorded(directory: Path, items: list, skip: list = (), *,
                              channels: dict | None = None) -> None:
    """Refuse to finish a build whose files lack the colour covariance beside their variance:
    they were rendered by a jaxden older than ``Frame.covariance``, whose renderer writes it,
    and finishing the build would mix files with and without it (SURE from the covariance
    would then silently fall back to the per-channel form on some items). ``channels``:
    ``{item path: its channel names}`` already read (else the headers are read here)."""
    from jaxden.frame import CHANNELS

    finished, channels = _finished_channels(directory, items, skip, channels)
    lacking = [item.path for item in finished
               if set(CHANNELS["variance"]) <= channels[item.path]
               and not set(CHANNELS["covariance"]) <= channels[item.path]]
    _refuse_mixing(directory, lacking, len(finished),
                   f"have the variance but no colour covariance (channels "
                   f"{'/'.join(CHANNELS['covariance'])})")


def check_emission_recorded(directory: Path, items: list, skip: list = (), *,
                            channels: dict | None = None) -> None:
    """Refuse to finish a build whose files lack the emission (``Frame.emission``, written
    in every file by this jaxden's renderer): they come from an older jaxden, and finishing
    the build would mix files with and without it (a denoiser with ``emission=separate`` would
    then fail on some items). Such a dataset, finished by the jaxden that started it, loads and
    works as before, without emission."""
    from jaxden.frame import CHANNELS

    finished, channels = _finished_channels(directory, items, skip, channels)
    lacking = [item.path for item in finished
               if not set(CHANNELS["emission"]) <= channels[item.path]]
    _refuse_mixing(directory, lacking, len(finished),
                   f"have no emission (channels {'/'.join(CHANNELS['emission'])})")


def check_renderer_fields_recorded(directory: Path, items: list, skip: list = ()) -> None:
    """Before a resumed build of jaxden's renderer renders the rest (``skip``): every finished
    file has what the renderer records beside the colour, the covariance and the emission
    (:func:`check_covariance_recorded`, :func:`check_emission_recorded`); one header read
    per file."""
    _, channels = _finished_channels(directory, items, skip, None)
    check_covariance_recorded(directory, items, skip, channels=channels)
    check_emission_recorded(directory, items, skip, channels=channels)


def _finished_channels(directory: Path, items: list, skip, channels: dict | None):
    """(items not in ``skip``, {their path: set of channel names}) from the EXR headers."""
    from jaxden.io.exr import read_header

    waiting = {item.id for item in skip}  # not rendered yet
    finished = [item for item in items if item.id not in waiting]
    channels = dict(channels or {})
    for item in finished:
        if item.path not in channels:
            channels[item.path] = set(read_header(directory / item.path)["channels"])
    return finished, channels


def _refuse_mixing(directory: Path, lacking: list[str], finished: int, what: str) -> None:
    if lacking:
        raise DatasetError(
            f"{directory}: {len(lacking)} of its {finished} finished files ({lacking[0]}, "
            f"...) {what}, which this jaxden's renderer records: they come from an older "
            f"jaxden, and finishing the build would mix files with and without it. Build into "
            f"another folder, or delete {directory} to rebuild it.")
