"""Visual reports: one self-contained HTML page over rendered results (``jaxden report``).

Per scene the page shows an A/B comparison (a split slider between any two methods or the
reference, chosen in two dropdowns), a strip of every method at the chosen spp, false-colour
error maps (relative squared error, FLIP) and mixer alpha maps with colour bars, all with one
shared zoom and pan and an exposure control in stops applied in the page; then a convergence
plot (log-log error vs spp with MC's 1/spp rate as a guide) and the metrics table. Results of
``jaxden evaluate`` (JSON, no images) get their plot and table; training runs (folders with a
``metrics.jsonl``) get their loss curves.

The input convention (:mod:`jaxden.report.discover`)::

    DIR/SCENE/reference.exr            the reference of SCENE (required)
    DIR/SCENE/sppN.exr                 the Monte Carlo input at N spp (method "mc")
    DIR/SCENE/sppN.METHOD.exr          METHOD's result at N spp
    DIR/SCENE/sppN.METHOD.alpha.exr    optional: the mixer's alpha behind METHOD at N spp
    DIR/*.json                         optional: jaxden evaluate results
    DIR/RUN/metrics.jsonl              optional: a training run (its loss curves)

which is what ``jaxden demo`` writes. Modules: ``discover`` (the convention), ``errormaps``
(maps and metrics), ``tonemap`` (exposure, sRGB, colour maps), ``encode`` (pixels in the
page), ``figures`` (matplotlib plots), ``content`` (a scene's data), ``html`` (the page),
``build`` (all of it: :func:`build_report`).
"""

from jaxden.report.build import build_report, default_output
from jaxden.report.discover import CONVENTION, ReportError, discover

__all__ = ["CONVENTION", "ReportError", "build_report", "default_output", "discover"]
