"""The report page: one self-contained HTML file (no network access, nothing beside it).

The markup (controls, views, colour bars, plots and tables) is written here; the pixels go in
as a JSON block (``<script type="application/json" id="jaxden-data">``, arrays encoded as
:mod:`jaxden.report.encode` says) that the inline script ``assets/report.js`` decodes, tone
maps and draws into the canvases; ``assets/report.css`` is inlined too. Plots are matplotlib
SVGs in ``data:`` URIs.
"""

from __future__ import annotations

import datetime
import html
import json
import math
from importlib import resources

from jaxden.report.content import MetricContent, RunContent, SceneContent
from jaxden.report.discover import REFERENCE, order_methods
from jaxden.report.encode import data_uri
from jaxden.report.errormaps import HIGHER_IS_BETTER, METRIC_NAMES, best_methods
from jaxden.report.tonemap import COLORMAPS, STOPS_RANGE, colormap_table

COMPARE_SIZE = 640  # CSS pixels of the longer side of the A/B view
PANEL_SIZE = 208  # ... and of each view in the strips
HELP = ("Wheel: zoom (all views of a scene together) · drag: pan · double-click: reset · "
        "hover: linear values · the slider under the A/B view moves the split.")


def _esc(text) -> str:
    return html.escape(str(text), quote=True)


def _asset(name: str) -> str:
    return resources.files("jaxden.report").joinpath("assets", name).read_text("utf-8")


def _fit(width: int, height: int, longest: int) -> tuple[int, int]:
    if width >= height:
        return longest, max(1, round(longest * height / width))
    return max(1, round(longest * width / height)), longest


def _format(value: float | None) -> str:
    if value is None:
        return "–"
    if not math.isfinite(value):
        return "∞" if value > 0 else "–"
    if value == 0 or 1e-3 <= abs(value) < 1e4:
        return f"{value:.4g}" if abs(value) < 100 else f"{value:.2f}"
    return f"{value:.3e}"


def metrics_table(rows: list[dict], metrics=None) -> str:
    """An HTML table of ``rows`` (spp, method, metrics); the best value per spp in bold."""
    if metrics is None:
        metrics = [m for m in METRIC_NAMES if any(m in row for row in rows)]
    best = {metric: best_methods(rows, metric) for metric in metrics}
    head = "".join(f"<th>{_esc(METRIC_NAMES.get(m, m))}{' ↑' if m in HIGHER_IS_BETTER else ''}"
                   f"</th>" for m in metrics)
    body = []
    order = {method: i for i, method in enumerate(order_methods({r["method"] for r in rows}))}
    for row in sorted(rows, key=lambda r: (r["spp"], order[r["method"]])):
        cells = []
        for metric in metrics:
            value = row.get(metric)
            strong = best[metric].get(row["spp"]) == row["method"]
            text = _format(value)
            cells.append(f"<td>{f'<b>{text}</b>' if strong else text}</td>")
        body.append(f"<tr><td>{row['spp']}</td><td>{_esc(row['method'])}</td>"
                    f"{''.join(cells)}</tr>")
    return (f'<table class="metrics"><thead><tr><th>spp</th><th>method</th>{head}</tr></thead>'
            f"<tbody>{''.join(body)}</tbody></table>")


def _select(control: str, options, selected) -> str:
    items = "".join(f'<option value="{_esc(value)}"{" selected" if value == selected else ""}>'
                    f"{_esc(label)}</option>" for value, label in options)
    return f'<select data-control="{control}">{items}</select>'


def _canvas(size: tuple[int, int], role: str, layer: str = "", method: str = "") -> str:
    attributes = f'data-role="{role}"'
    if layer:
        attributes += f' data-layer="{_esc(layer)}" data-method="{_esc(method)}"'
    return (f'<canvas class="view" {attributes} width="{size[0]}" height="{size[1]}" '
            f'style="width:{size[0]}px;height:{size[1]}px"></canvas>')


def _colour_bar(layer: dict, name: str) -> str:
    low, high = layer["low"], layer["high"]
    if layer["scale"] == "log":
        decades = range(round(math.log10(low)), round(math.log10(high)) + 1)
        ticks = [f"{10.0 ** k:g}" for k in decades]
    else:
        ticks = [f"{low + (high - low) * i / 4:g}" for i in range(5)]
    labels = "".join(f"<span>{t}</span>" for t in ticks)
    return (f'<div class="colorbar"><canvas data-colorbar="{name}" width="256" height="12">'
            f'</canvas><div class="ticks">{labels}</div>'
            f'<div class="bar-title">{_esc(layer["detail"])}'
            f'{" (log scale)" if layer["scale"] == "log" else ""}</div></div>')


def _strip(scene: SceneContent, layer: str, methods: list[str]) -> str:
    size = _fit(scene.width, scene.height, PANEL_SIZE)
    figures = "".join(
        f'<figure>{_canvas(size, "panel", layer, method)}'
        f'<figcaption data-caption="{_esc(method)}">{_esc(method)}</figcaption></figure>'
        for method in methods)
    return f'<div class="strip">{figures}</div>'


def scene_section(index: int, scene: SceneContent) -> str:
    methods = scene.methods
    choices = [(m, m) for m in methods] + [(REFERENCE, REFERENCE)]
    layer_choices = [("image", "image")] + [(name, layer["title"])
                                             for name, layer in scene.layers.items()]
    size = _fit(scene.width, scene.height, COMPARE_SIZE)
    low, high = STOPS_RANGE
    shown = ("full resolution" if scene.factor == 1
             else f"shown at 1/{scene.factor} resolution, measured at full")
    parts = [
        f'<section class="scene" id="scene-{index}" data-scene="{index}">',
        f"<h2>{_esc(scene.name)}</h2>",
        (f'<p class="where">{_esc(scene.folder)} · {scene.width * scene.factor}x'
        f"{scene.height * scene.factor} pixels, {shown}</p>"),
        '<div class="controls">',
        (f'<label>spp {_select("spp", [(s, s) for s in scene.spp_levels], scene.spp_levels[0])}'
        "</label>"),
        f'<label>A {_select("a", choices, methods[0])}</label>',
        (f'<label>B {_select("b", choices, methods[-1] if len(methods) > 1 else REFERENCE)}'
        "</label>"),
        f'<label>show {_select("layer", layer_choices, "image")}</label>',
        (f'<label>exposure <input type="range" data-control="stops" min="{low}" max="{high}" '
        f'step="0.1" value="{scene.stops}"> <output data-out="stops"></output></label>'),
        '<button type="button" data-action="auto">auto exposure</button>',
        '<button type="button" data-action="reset">reset zoom</button>',
        "</div>",
        '<div class="compare"><div class="viewport">',
        _canvas(size, "compare"),
        ('<span class="tag tag-a" data-out="a"></span><span class="tag tag-b" data-out="b">'
        "</span></div>"),
        (f'<input type="range" class="split" data-control="split" min="0" max="1000" '
        f'value="500" aria-label="A/B split" style="width:{size[0]}px">'),
        '<div class="readout" data-out="readout">hover over an image for its values</div>',
        "</div>",
        '<h3>Images at <span data-out="spp"></span> spp</h3>',
        _strip(scene, "image", [*methods, REFERENCE]),
    ]
    for name, layer in scene.layers.items():
        targets = scene.alpha_methods if name == "alpha" else methods
        parts += [(f"<h3>{_esc(layer['title'])} at "
                  f'<span data-out="spp"></span> spp</h3>'),
                  _strip(scene, name, targets), _colour_bar(layer, name)]
    parts += ["<h3>Convergence</h3>",
              (f'<img class="plot" alt="error vs spp of {_esc(scene.name)}" '
              f'src="{data_uri(scene.plot_svg, "image/svg+xml")}">'),
              "<h3>Metrics</h3>", metrics_table(scene.rows),
              ('<p class="note">relMSE, SMAPE, RMSE, FLIP: linear HDR against the reference '
              "(FLIP in HDR mode); PSNR and SSIM: on clip(v, 0, 1)^(1/2.2). Bold: the best "
              "per spp.</p>"), "</section>"]
    return "\n".join(parts)


def metric_section(index: int, content: MetricContent) -> str:
    return "\n".join([
        f'<section class="metricset" id="metrics-{index}">',
        f"<h2>{_esc(content.name)}</h2>", f'<p class="where">{_esc(content.path)}</p>',
        f'<p class="note">{_esc(content.note)}</p>',
        (f'<img class="plot" alt="error vs spp of {_esc(content.name)}" '
        f'src="{data_uri(content.plot_svg, "image/svg+xml")}">'),
        metrics_table(content.rows, list(content.metrics)), "</section>"])


def run_section(index: int, run: RunContent) -> str:
    """A training run: its curves (train loss and validation metrics against the step) and
    the last value of each."""
    parts = [f'<section class="run" id="run-{index}">', f"<h2>{_esc(run.name)} (training)</h2>",
             f'<p class="where">{_esc(run.folder)} · metrics.jsonl up to step {run.steps}</p>']
    if run.plot_svg is None:
        parts.append('<p class="note">nothing logged yet</p>')
    else:
        parts.append(f'<img class="plot" alt="training curves of {_esc(run.name)}" '
                     f'src="{data_uri(run.plot_svg, "image/svg+xml")}">')
        last = " · ".join(f"{_esc(key)} {_format(value)} (step {run.curves[key][-1][0]})"
                          for key, value in run.last.items())
        parts.append(f'<p class="note">last values: {last}</p>')
    parts.append("</section>")
    return "\n".join(parts)


def page_data(scenes: list[SceneContent]) -> dict:
    """The JSON the script reads: per scene its sizes, choices, layers, rows and arrays."""
    import base64

    return {
        "stopsRange": list(STOPS_RANGE),
        "colormaps": {name: base64.b64encode(colormap_table(name).tobytes()).decode("ascii")
                      for name in COLORMAPS},
        "scenes": [{"name": s.name, "width": s.width, "height": s.height, "factor": s.factor,
                    "stops": s.stops, "spp": s.spp_levels, "methods": s.methods,
                    "layers": s.layers, "rows": [_finite(row) for row in s.rows],
                    "arrays": s.arrays} for s in scenes],
    }


def _finite(row: dict) -> dict:
    """JSON has no infinities (PSNR of an exact match): None instead."""
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in row.items()}


def render_page(title: str, source: str, scenes: list[SceneContent],
                metric_sets: list[MetricContent], runs: list[RunContent] = ()) -> str:
    """The whole page as a string: scenes, metric files, then training runs."""
    from jaxden import __version__

    data = json.dumps(page_data(scenes), separators=(",", ":"), allow_nan=False)
    data = data.replace("</", "<\\/")  # never close the script element early
    nav = "".join(f'<li><a href="#scene-{i}">{_esc(s.name)}</a></li>'
                  for i, s in enumerate(scenes))
    nav += "".join(f'<li><a href="#metrics-{i}">{_esc(m.name)}</a> (metrics)</li>'
                   for i, m in enumerate(metric_sets))
    nav += "".join(f'<li><a href="#run-{i}">{_esc(r.name)}</a> (training)</li>'
                   for i, r in enumerate(runs))
    today = datetime.date.today().isoformat()
    return "\n".join([
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        '<link rel="icon" href="data:,">', f"<title>{_esc(title)}</title>",
        f"<style>\n{_asset('report.css')}\n</style></head><body>",
        (f"<header><h1>{_esc(title)}</h1><p class=\"where\">{_esc(source)} · jaxden "
        f"{_esc(__version__)} · {today}</p><p class=\"help\">{_esc(HELP)}</p>"
        f'<div class="status" data-out="status">loading images…</div>'
        f"<nav><ul>{nav}</ul></nav></header><main>"),
        *(scene_section(i, s) for i, s in enumerate(scenes)),
        *(metric_section(i, m) for i, m in enumerate(metric_sets)),
        *(run_section(i, r) for i, r in enumerate(runs)),
        "</main>",
        f'<script type="application/json" id="jaxden-data">{data}</script>',
        f"<script>\n{_asset('report.js')}\n</script>", "</body></html>", ""])


__all__ = ["metric_section", "metrics_table", "page_data", "render_page", "run_section",
           "scene_section"]
