"""The report's plots with matplotlib: convergence (error vs samples per pixel, log-log) and
training curves (loss vs step).

:func:`convergence_figure` draws one panel per metric (rows: scenes), a line per method and,
in the panels of metrics whose Monte Carlo error falls at a known rate, the guide line of that
rate through MC's first point: relMSE and MSE fall as 1/spp, RMSE as 1/sqrt(spp) (the same
rate of the MSE). FLIP has no such rate and gets no guide. :func:`training_figure` draws a
run's curves (train loss, validation metrics) over its steps. :func:`svg_bytes` and
:func:`png_bytes` render a figure reproducibly (no date, fixed SVG ids).
"""

from __future__ import annotations

import io
from collections import defaultdict

from jaxden.report.discover import MC, order_methods
from jaxden.report.errormaps import METRIC_NAMES

#: Slope of MC's error vs spp on a log-log plot, per metric (1/spp for the MSE family).
MC_RATES = {"relmse": 1.0, "mse": 1.0, "mse_nc": 1.0, "rmse": 0.5, "rmse_nc": 0.5}
#: Fixed colours, so that a method looks the same in every plot of a report.
METHOD_COLOURS = {MC: "#7f7f7f", "oidn": "#1f77b4", "denoiser": "#1f77b4",
                  "pd_oidn": "#d62728", "pd": "#d62728", "oracle": "#2ca02c"}
_CYCLE = ("#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22", "#1f77b4",
          "#d62728", "#2ca02c")
DEFAULT_METRICS = ("relmse", "rmse", "flip")


def method_colours(methods) -> dict[str, str]:
    """A colour per method: the fixed ones above, the rest from a cycle in order."""
    colours, spare = {}, iter(_CYCLE * 4)
    for method in methods:
        colours[method] = METHOD_COLOURS.get(method) or next(spare)
    return colours


def guide_label(rate: float) -> str:
    return "∝ 1/spp (MC)" if rate == 1.0 else "∝ 1/√spp (MC)"


def _plain(base):
    """``base`` (a LogFormatter) choosing which ticks get a label, written as ``0.06``."""

    class PlainLogFormatter(base):
        def __call__(self, x, pos=None):
            return f"{x:.3g}" if super().__call__(x, pos) else ""

    return PlainLogFormatter


def convergence_figure(rows: list[dict], metrics=DEFAULT_METRICS, title: str | None = None):
    """A matplotlib Figure: rows = scenes (in order of appearance), columns = ``metrics``
    present in ``rows``; x = spp, y = the metric, both log scale.

    ``rows``: ``{scene, spp, method, <metric>: value}`` (one per scene, spp and method)."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FixedLocator, LogFormatter, NullLocator

    metrics = [m for m in metrics if any(m in row for row in rows)]
    scenes = list(dict.fromkeys(row["scene"] for row in rows))
    methods = order_methods({row["method"] for row in rows})
    colours = method_colours(methods)
    figure = Figure(figsize=(3.6 * max(len(metrics), 1), 2.8 * max(len(scenes), 1) + 0.7),
                    layout="constrained")
    axes = figure.subplots(max(len(scenes), 1), max(len(metrics), 1), squeeze=False)
    for r, scene in enumerate(scenes):
        curves: dict[str, dict[str, list[tuple[int, float]]]] = defaultdict(dict)
        for row in rows:
            if row["scene"] != scene:
                continue
            for metric in metrics:
                value = row.get(metric)
                if value is not None and value > 0:
                    curves[metric].setdefault(row["method"], []).append((row["spp"], value))
        for c, metric in enumerate(metrics):
            ax = axes[r][c]
            levels = sorted({spp for points in curves[metric].values() for spp, _ in points})
            for method in methods:
                points = sorted(curves[metric].get(method, []))
                if points:
                    ax.plot(*zip(*points), marker="o", markersize=3.5, linewidth=1.6,
                            color=colours[method], label=method)
            rate = MC_RATES.get(metric)
            anchor_method = MC if MC in curves[metric] else next(iter(curves[metric]), None)
            if rate is not None and anchor_method is not None and len(levels) > 1:
                spp0, value0 = min(curves[metric][anchor_method])
                ax.plot(levels, [value0 * (spp / spp0) ** -rate for spp in levels],
                        linestyle="--", color="black", linewidth=1.0, label=guide_label(rate))
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            # plain-text tick labels: matplotlib's default mathtext ones take seconds to lay out
            ax.yaxis.set_major_formatter(_plain(LogFormatter)())
            ax.yaxis.set_minor_formatter(_plain(LogFormatter)(labelOnlyBase=False,
                                                              minor_thresholds=(2, 0.5)))
            if levels:
                ax.xaxis.set_major_locator(FixedLocator(levels))
                ax.xaxis.set_minor_locator(NullLocator())
                every = 1 if len(levels) <= 6 else 2  # room for the labels
                ax.set_xticklabels([str(spp) if i % every == 0 else ""
                                    for i, spp in enumerate(levels)])
            ax.set_xlabel("samples per pixel")
            ax.set_ylabel(METRIC_NAMES.get(metric, metric))
            ax.grid(True, which="both", color="#e4e4e4", linewidth=0.6)
            ax.set_title(f"{scene}: {METRIC_NAMES.get(metric, metric)}" if len(scenes) > 1
                         else METRIC_NAMES.get(metric, metric), fontsize=10)
            ax.legend(fontsize=7, frameon=False)
    if title:
        figure.suptitle(title, fontsize=11)
    return figure


#: Training curves: metrics.jsonl key -> (legend, colour); the noisy input's loss is dashed.
TRAINING_CURVES = {"loss": ("train loss", "#1f77b4"), "val_loss": ("validation loss", "#d62728"),
                   "val_baseline_loss": ("validation: noisy input", "#7f7f7f")}
#: The y axis of a training plot is logarithmic when its values span more than this ratio.
LOG_SCALE_RATIO = 5.0


def training_figure(curves: dict[str, list[tuple[int, float]]], title: str | None = None):
    """A matplotlib Figure of a training run: a line per curve (``{key: [(step, value)]}``,
    keys as metrics.jsonl names them), x = step; y log scale when every value is positive and
    they span more than :data:`LOG_SCALE_RATIO`. Each line's SVG group id is ``curve-KEY``;
    sparse curves (validation) carry a marker per point."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import LogFormatter

    figure = Figure(figsize=(6.4, 3.4), layout="constrained")
    ax = figure.add_subplot()
    spare = iter(_CYCLE * 4)
    values = [v for points in curves.values() for _, v in points]
    for key, points in curves.items():
        if not points:
            continue
        label, colour = TRAINING_CURVES.get(key, (key, None))
        steps, ys = zip(*sorted(points))
        ax.plot(steps, ys, color=colour or next(spare), label=label, gid=f"curve-{key}",
                linewidth=1.4, linestyle="--" if key.endswith("baseline_loss") else "-",
                marker="o" if key != "loss" and len(points) <= 60 else None, markersize=3)
    if values and min(values) > 0 and max(values) > LOG_SCALE_RATIO * min(values):
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(_plain(LogFormatter)())
        ax.yaxis.set_minor_formatter(_plain(LogFormatter)(labelOnlyBase=False,
                                                          minor_thresholds=(2, 0.5)))
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, which="both", color="#e4e4e4", linewidth=0.6)
    if values:
        ax.legend(fontsize=7, frameon=False)
    if title:
        ax.set_title(title, fontsize=10)
    return figure


def _save(figure, fmt: str, **options) -> bytes:
    import matplotlib

    buffer = io.BytesIO()
    with matplotlib.rc_context({"svg.hashsalt": "jaxden", "svg.fonttype": "none"}):
        figure.savefig(buffer, format=fmt, **options)
    return buffer.getvalue()


def svg_bytes(figure) -> bytes:
    """The figure as SVG (text kept as text, no date: the same figure gives the same bytes)."""
    return _save(figure, "svg", metadata={"Date": None})


def png_bytes(figure, dpi: int = 120) -> bytes:
    return _save(figure, "png", dpi=dpi, metadata={"Software": None})


__all__ = ["DEFAULT_METRICS", "MC_RATES", "TRAINING_CURVES", "convergence_figure",
           "method_colours", "png_bytes", "svg_bytes", "training_figure"]
