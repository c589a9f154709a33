"""``build_report``: a folder (or a `jaxden evaluate pd` result) in, one self-contained HTML page out.

Finds the files (:mod:`jaxden.report.discover`), measures and encodes every scene and draws
every training run's curves (:mod:`jaxden.report.content`), renders the page
(:mod:`jaxden.report.html`) and writes it atomically.
"""

from __future__ import annotations

from pathlib import Path

from jaxden.report.content import metric_file_content, run_content, scene_content
from jaxden.report.discover import Discovery, ReportError, discover
from jaxden.report.html import render_page


def default_output(source) -> Path:
    """``DIR/report.html`` for a folder, ``NAME.html`` beside a JSON file."""
    source = Path(source)
    return source.with_suffix(".html") if source.is_file() else source / "report.html"


def build_report(source, out=None, *, title: str | None = None, max_size: int | None = 1024,
                 progress: bool = False, found: Discovery | None = None,
                 flip_maps=None) -> Path:
    """Write the report of ``source`` (module docstring of :mod:`jaxden.report`) to ``out``
    (default :func:`default_output`); returns the path written.

    ``max_size``: the longest side of the images shown (larger ones are box-filtered for
    display; metrics always use the full images). ``found``: a :func:`discover` result to
    reuse. ``flip_maps``: FLIP already computed (by ``jaxden demo``), ``{(scene, spp, method):
    (mean, map (H, W))}``: FLIP is the slowest part of a report.

    Raises :class:`ReportError` (and :class:`jaxden.errors.ExrError` for unreadable files),
    naming the file."""
    from jaxden.fileio import atomic_write_text

    out = Path(out) if out is not None else default_output(source)
    if out.suffix.lower() not in (".html", ".htm"):
        raise ReportError(f"out={out}: the report is an .html file")
    if out.is_dir():
        raise ReportError(f"out={out}: is a folder; give a file name")
    if not out.parent.is_dir():
        raise ReportError(f"out={out}: the folder {out.parent} does not exist")
    found = found or discover(source)
    flip_maps = flip_maps or {}
    scenes = [scene_content(scene, max_size=max_size, progress=progress,
                            flip_maps={(spp, method): value
                                       for (name, spp, method), value in flip_maps.items()
                                       if name == scene.name})
              for scene in found.scenes]
    metric_sets = [metric_file_content(m) for m in found.metric_files]
    runs = [run_content(run) for run in found.runs]
    title = title or f"jaxden report: {Path(source).resolve().name}"
    atomic_write_text(out, render_page(title, str(source), scenes, metric_sets, runs))
    return out


__all__ = ["build_report", "default_output"]
