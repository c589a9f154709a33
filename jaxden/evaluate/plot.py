"""Log-log plots of results as SVG documents (no plotting dependency): error against spp, one
panel per metric or base, one curve per method; the figures of PD and SURE results are made
with it."""

from __future__ import annotations

import numpy as np


def convergence_methods(denoiser: str = "OIDN") -> tuple[tuple[str, str, str], ...]:
    """The convergence curves (key, legend, colour) for a base denoiser's label."""
    return (("mc", "MC", "#7f7f7f"), ("denoiser", denoiser, "#1f77b4"),
            ("pd", f"PD({denoiser})", "#d62728"), ("oracle", "oracle mix (8x8 tiles)", "#2ca02c"))


METHODS = convergence_methods()
PANELS = (("rmse", "RMSE"), ("relmse", "relMSE"))


def _log_ticks(lo: float, hi: float) -> list[float]:
    return [10.0**k for k in range(int(np.floor(np.log10(lo))), int(np.ceil(np.log10(hi))) + 1)]


def svg_plot(curves: dict, title: str, panels=PANELS, methods=METHODS,
             dashed=("oracle",)) -> str:
    """Log-log panels side by side (``panels``: (key, label) pairs, one per panel; ``methods``:
    (key, legend, colour) per curve; ``dashed``: the keys drawn dashed), as an SVG document
    (no plotting dependency)."""
    pw, ph, ml, mr, mt, mb = 360, 280, 62, 14, 36, 46
    width = len(panels) * (pw + ml + mr)
    height = ph + mt + mb + 22 * len(methods)
    out = [(f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'font-family="sans-serif" font-size="12">'),
           f'<rect width="{width}" height="{height}" fill="white"/>',
           f'<text x="{width / 2}" y="18" text-anchor="middle" font-size="14">{title}</text>']
    for p, (metric, label) in enumerate(panels):
        ox = p * (pw + ml + mr) + ml
        data = curves[metric]
        spps = [s for s, _ in next(iter(data.values()))]
        values = [v for series in data.values() for _, v in series if v > 0]
        x0, x1 = np.log2(min(spps)), np.log2(max(spps))
        ticks = _log_ticks(min(values), max(values))
        y0, y1 = np.log10(ticks[0]), np.log10(ticks[-1])

        def px(spp, x0=x0, x1=x1, ox=ox):
            return ox + (np.log2(spp) - x0) / max(x1 - x0, 1e-9) * pw

        def py(v, y0=y0, y1=y1):
            return mt + ph - (np.log10(v) - y0) / max(y1 - y0, 1e-9) * ph

        out.append(f'<rect x="{ox}" y="{mt}" width="{pw}" height="{ph}" fill="none" '
                   f'stroke="black"/>')
        for t in ticks:
            y = py(t)
            out.append(f'<line x1="{ox}" y1="{y:.1f}" x2="{ox + pw}" y2="{y:.1f}" '
                       f'stroke="#ddd"/>')
            out.append(f'<text x="{ox - 4}" y="{y + 4:.1f}" text-anchor="end">{t:.0e}</text>')
        for s in spps:
            x = px(s)
            out.append(f'<line x1="{x:.1f}" y1="{mt}" x2="{x:.1f}" y2="{mt + ph}" '
                       f'stroke="#eee"/>')
            out.append(f'<text x="{x:.1f}" y="{mt + ph + 16}" text-anchor="middle">{s}</text>')
        out.append(f'<text x="{ox + pw / 2}" y="{mt + ph + 34}" text-anchor="middle">'
                   f'samples per pixel</text>')
        out.append(f'<text x="{ox + 8}" y="{mt + 16}">{label} (mean over crops)</text>')
        for method, _, colour in methods:
            points = " ".join(f"{px(s):.1f},{py(v):.1f}" for s, v in data[method] if v > 0)
            dash = ' stroke-dasharray="5,3"' if method in dashed else ""
            out.append(f'<polyline points="{points}" fill="none" stroke="{colour}" '
                       f'stroke-width="2"{dash}/>')
            for s, v in data[method]:
                if v > 0:
                    out.append(f'<circle cx="{px(s):.1f}" cy="{py(v):.1f}" r="2.5" '
                               f'fill="{colour}"/>')
    for i, (method, name, colour) in enumerate(methods):
        y = mt + ph + mb + 14 + 22 * i
        dash = ' stroke-dasharray="5,3"' if method in dashed else ""
        out.append(f'<line x1="{ml}" y1="{y - 4}" x2="{ml + 30}" y2="{y - 4}" '
                   f'stroke="{colour}" stroke-width="2"{dash}/>')
        out.append(f'<text x="{ml + 38}" y="{y}">{name}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"
