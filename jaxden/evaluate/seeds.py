"""Tables of trained runs over seeds: the evaluations a sweep's runs recorded, as mean ± standard
deviation cells of markdown tables (the experiments' real-time tables and comparisons).

A run's ``result.json`` holds ``evaluations``: ``{"KIND:DATA": {"<prefix>_<metric>": value}}``
(:mod:`jaxden.sweep`); :func:`stats` gathers one ``<prefix>_<metric>`` over runs, :func:`single`
makes the same cells of one summary, :func:`table` writes them.
"""

from __future__ import annotations

import math

#: (metric, column title, format) of the real-time tables.
METRICS = (("psnr", "PSNR (dB)", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"),
           ("relmse", "relMSE", "{:.4f}"), ("flip", "FLIP", "{:.4f}"))


def _evaluation(result: dict, kind: str) -> dict | None:
    for name, value in result.get("evaluations", {}).items():
        if name.startswith(kind + ":"):
            return value
    return None


def mean_std(values: list[float]) -> tuple[float, float, int]:
    n = len(values)
    mean = sum(values) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (n - 1)) if n > 1 else float("nan")
    return mean, std, n


def group(results: list[dict], key) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for result in results:
        groups.setdefault(key(result), []).append(result)
    return groups


def stats(members: list[dict], kind: str, prefix: str) -> dict[str, tuple[float, float, int]]:
    out = {}
    for metric, _, _ in METRICS:
        values = [e[f"{prefix}_{metric}"] for m in members
                  if (e := _evaluation(m, kind)) and f"{prefix}_{metric}" in e]
        if values:
            out[metric] = mean_std(values)
    return out


def cell(stat, fmt: str) -> str:
    if stat is None:
        return "not run"
    mean, std, n = stat
    spread = "" if n < 2 else f" ± {fmt.format(std)}"
    return fmt.format(mean) + spread + ("" if n < 2 else f" ({n} seeds)")


def table(rows: list[tuple[str, dict]]) -> str:
    lines = ["| method | " + " | ".join(m[1] for m in METRICS) + " |",
             "|---|" + "---:|" * len(METRICS)]
    for label, row in rows:
        lines.append(f"| {label} | " + " | ".join(cell(row.get(m), f) for m, _, f in METRICS)
                     + " |")
    return "\n".join(lines)


def single(summary: dict | None, prefix: str) -> dict:
    if not summary:
        return {}
    return {m: (summary[f"{prefix}_{m}"], float("nan"), 1) for m, _, _ in METRICS
            if f"{prefix}_{m}" in summary}


