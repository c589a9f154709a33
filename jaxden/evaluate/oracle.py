"""Oracles that read the reference: the 8 x 8-tile least-squares mix and the true error (the
bounds the PD results carry beside PD), and the ``oracle`` evaluator: how much of the tile
oracle's gain a mixer could reach at all, its alphas cross-fitted on an independent render.

The tile oracle (:func:`oracle_alpha`) fits one alpha per channel and 8 x 8 tile to the
reference *and to this render's own noise*: it sees where this render's fireflies and noise
happen to fall, which no estimator can. The cross-fitted oracle keeps everything else (the
reference, the tile, the least-squares fit) but fits on an independent render x' of the same
crop with the same per-pixel variance, and applies the alphas to the render x being measured
(and the other way round; both directions are averaged). It is what a mixer could reach if it
knew, per tile, the best alpha in expectation up to the noise of one render: a fair bound
where the oracle is not.

The dataset's spp levels are independent renders (their own sampler seeds), but none has a
twin at the same spp. For level N with levels N/2 and 2N both present, x' = w x_2N + (1 - w)
x_N/2 with w in [0, 1] the root of w^2 / 2N + (1 - w)^2 / (N / 2) = 1 / N: unbiased,
independent of x_N, with exactly x_N's per-pixel variance (its noise is a blend of two sample
counts rather than one, so its tails differ a little). Features, variance and covariance are
blended the same way (variance and covariance with w^2 and (1 - w)^2). The denoiser runs on x'
as on x.

The result: per spp, the mean over crops of RMSE over the denoiser's for the oracle, the
cross-fitted oracle and PD (from ``report``, a PD result on the same crops and spp), and the
share of the oracle's gain (1 - ratio) / (1 - oracle ratio) each reaches, over spp.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from jaxden.errors import DatasetError
from jaxden.evaluate.evaluator import Evaluator

ORACLE_BLOCK = 8


def oracle_alpha(x, y, reference, block: int = ORACLE_BLOCK) -> np.ndarray:
    """The alpha of :func:`oracle_mix`: one value in [0, 1] per channel and per ``block`` x
    ``block`` tile, the least-squares fit of ``x + alpha (y - x)`` to the reference, spread over
    the tile's pixels; (H, W, C) float64."""
    x, y, r = (np.asarray(a, np.float64) for a in (x, y, reference))
    h, w = x.shape[:2]
    out = np.empty_like(x)
    for top in range(0, h, block):
        for left in range(0, w, block):
            tile = np.s_[top : top + block, left : left + block]
            d = (y - x)[tile]
            num = np.sum((r - x)[tile] * d, axis=(0, 1))
            den = np.sum(d * d, axis=(0, 1))
            out[tile] = np.clip(np.divide(num, den, out=np.zeros_like(num), where=den > 0), 0, 1)
    return out


def true_error(y, reference) -> np.ndarray:
    """What SURE estimates, read off the reference: the per-pixel squared error of ``y``
    against the reference frame's colour less the variance of the reference's pixel mean
    (unbiased for the squared error against the true image, as SURE is); (H, W, C) float32.
    Fed to a mixer in place of SURE it measures what a perfect SURE would give."""
    y = np.asarray(y, np.float64)
    err = (y - np.asarray(reference.color, np.float64)) ** 2
    return (err - np.asarray(reference.variance, np.float64)).astype(np.float32)


def oracle_mix(x, y, reference, block: int = ORACLE_BLOCK) -> np.ndarray:
    """The best mix ``x + alpha (y - x)`` with one alpha in [0, 1] per channel and per
    ``block`` x ``block`` tile, fitted by least squares to the reference: an upper bound on
    what a mixer whose alpha varies on that scale can reach (it sees the reference, so it is
    not a method). Tiles at the right/bottom edge may be smaller."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return (x + oracle_alpha(x, y, reference, block) * (y - x)).astype(np.float32)


def blend_weight(n: int, low: int, high: int) -> float:
    """w in [0, 1] with w^2 / high + (1 - w)^2 / low = 1 / n (variance of the blend equals that
    of an n-spp render, for low < n < high)."""
    a, b, c = 1.0 / high + 1.0 / low, -2.0 / low, 1.0 / low - 1.0 / n
    disc = b * b - 4 * a * c
    roots = [(-b - math.sqrt(disc)) / (2 * a), (-b + math.sqrt(disc)) / (2 * a)]
    inside = [r for r in roots if 0.0 <= r <= 1.0]
    if not inside:
        raise ValueError(f"no blend of {low} and {high} spp has the variance of {n} spp")
    return inside[0]


def blend_frames(high_frame, low_frame, w: float):
    """w * high + (1 - w) * low, field by field (variance with the squared weights)."""
    changes = {}
    for name in ("color", "albedo", "normal", "depth"):
        a, b = getattr(high_frame, name), getattr(low_frame, name)
        if a is not None and b is not None:
            changes[name] = (w * np.asarray(a, np.float64)
                             + (1 - w) * np.asarray(b, np.float64)).astype(np.float32)
    for name in ("variance", "covariance"):  # of the mean: squared weights (independent)
        a, b = getattr(high_frame, name), getattr(low_frame, name)
        if a is not None and b is not None:
            changes[name] = (w * w * np.asarray(a, np.float64)
                             + (1 - w) ** 2 * np.asarray(b, np.float64)).astype(np.float32)
        elif name == "covariance":
            changes[name] = None
    return low_frame.replace(**changes)


@dataclasses.dataclass(frozen=True)
class OracleOptions:
    """``report``: a PD result's .json on the same data, whose PD rows are compared."""

    denoiser: str = "oidn"
    split: str = "test"
    report: str | None = None


def crossfit_rows(data, options: OracleOptions, *, progress: bool = False) -> list[dict]:
    """One row per (crop, spp N with N/2 and 2N present): RMSE of MC, the denoiser, the tile
    oracle and the cross-fitted oracle on the dataset's render (``_0``) and on its blended
    twin (``_1``), and the blend weight. ``progress``: a line per row."""
    from jaxden import metrics
    from jaxden.data.crops import iter_crops
    from jaxden.denoise.registry import load_denoiser

    model = load_denoiser(options.denoiser)
    denoise = model.function()
    rows = []
    for crop, reference, inputs in iter_crops(data, options.split):
        frames = dict(inputs)
        for n in sorted(frames):
            if n // 2 not in frames or 2 * n not in frames:
                continue
            w = blend_weight(n, n // 2, 2 * n)
            x = frames[n]
            twin = blend_frames(frames[2 * n], frames[n // 2], w)
            pair = [(np.asarray(f.color, np.float64), np.asarray(denoise(f), np.float64))
                    for f in (x, twin)]
            r = np.asarray(reference.color, np.float64)
            alphas = [oracle_alpha(px, py, r) for px, py in pair]
            row = {"crop": crop.id, "spp": n, "blend_weight": w}

            def rmse(image, target=reference.color):
                return float(metrics.rmse(image.astype(np.float32), target))

            for side, (px, py) in enumerate(pair):  # side 0: the dataset's render, 1: its twin
                other = alphas[1 - side]
                row[f"denoiser_rmse_{side}"] = rmse(py)
                row[f"mc_rmse_{side}"] = rmse(px)
                row[f"oracle_rmse_{side}"] = rmse(px + alphas[side] * (py - px))
                row[f"crossfit_rmse_{side}"] = rmse(px + other * (py - px))
            rows.append(row)
            if progress:
                print(f"{crop.id} {n} spp: oracle "
                      f"{row['oracle_rmse_0'] / row['denoiser_rmse_0']:.3f} cross-fit "
                      f"{row['crossfit_rmse_0'] / row['denoiser_rmse_0']:.3f} of the denoiser",
                      flush=True)
    if not rows:
        raise DatasetError(f"{data}: no spp level N with N/2 and 2N both present")
    return rows


def summarize_crossfit(rows: list[dict], report: dict | None) -> dict:
    """Per spp the mean ratios to the denoiser's RMSE (oracle, cross-fit, PD of ``report``),
    their means over spp and each one's share of the oracle's gain."""
    pd_rows = {}
    if report is not None:
        pd_rows = {(r["crop"], r["spp"]): r["pd_rmse"] / r["denoiser_rmse"]
                   for r in report["rows"]}
    per_spp = {}
    for n in sorted({r["spp"] for r in rows}):
        cell = [r for r in rows if r["spp"] == n]
        entry = {}
        for method in ("oracle", "crossfit"):
            ratios = [r[f"{method}_rmse_{s}"] / r[f"denoiser_rmse_{s}"] for r in cell
                      for s in (0, 1)]
            entry[method] = float(np.mean(ratios))
        pd = [pd_rows[(r["crop"], n)] for r in cell if (r["crop"], n) in pd_rows]
        entry["pd"] = float(np.mean(pd)) if len(pd) == len(cell) else None
        per_spp[n] = entry
    means = {m: float(np.mean([e[m] for e in per_spp.values()])) for m in ("oracle", "crossfit")}
    if all(e["pd"] is not None for e in per_spp.values()):
        means["pd"] = float(np.mean([e["pd"] for e in per_spp.values()]))
    gain = 1.0 - means["oracle"]
    shares = {m: (1.0 - v) / gain for m, v in means.items() if m != "oracle"}
    return {"per_spp": {str(k): v for k, v in per_spp.items()}, "mean_over_spp": means,
            "share_of_oracle_gain": shares}


def report_label(report: dict | None) -> str:
    """The PD column's name: the report's mixer spec and its overrides."""
    if report is None:
        return "PD"
    source = report.get("provenance", {})
    spec = source.get("mixer", {}).get("spec", "?")
    overrides = source.get("mixer_overrides") or []
    return f"PD (mixer {spec}{''.join(f', {o}' for o in overrides)})"


def markdown_crossfit(summary: dict, denoiser: str, label: str = "PD") -> str:
    lines = [(f"RMSE over {denoiser}'s (mean over crops; the oracle and the cross-fitted oracle "
              f"also over both renders of each pair):"), "",
             f"| spp | 8 x 8 oracle | cross-fitted oracle | {label} |",
             "|---:|---:|---:|---:|"]
    for n, e in summary["per_spp"].items():
        pd = "" if e["pd"] is None else f"{e['pd']:.3f}"
        lines.append(f"| {n} | {e['oracle']:.3f} | {e['crossfit']:.3f} | {pd} |")
    m, s = summary["mean_over_spp"], summary["share_of_oracle_gain"]
    pd = f"{m['pd']:.3f}" if "pd" in m else ""
    lines.append(f"| mean | {m['oracle']:.3f} | {m['crossfit']:.3f} | {pd} |")
    lines += ["", ("Share of the 8 x 8 oracle's RMSE gain, (1 - ratio) / (1 - oracle ratio), "
                   "mean ratios over spp:"), ""]
    lines += [f"- {name}: {value:.0%}" for name, value in
              (("cross-fitted oracle", s["crossfit"]), ("PD", s.get("pd")))
              if value is not None]
    return "\n".join(lines) + "\n"


def _report(provenance: dict) -> dict | None:
    path = provenance.get("report")
    return json.loads(Path(path).read_text()) if path else None


EVALUATOR = Evaluator(
    name="oracle",
    description="the 8x8-tile oracle's alphas cross-fitted on an independent render: how much "
                "of the oracle's gain a mixer could reach",
    options=OracleOptions,
    run=crossfit_rows,
    summarize=lambda rows, provenance: {"summary": summarize_crossfit(rows, _report(provenance))},
    table=lambda fields, rows, provenance: markdown_crossfit(
        fields["summary"], provenance["denoiser"], report_label(_report(provenance))),
    provenance=lambda options: {"denoiser": options.denoiser, "report": options.report},
)
