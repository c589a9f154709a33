"""``jaxden demo``: the main job on built-in defaults (no downloads, no user data).

Renders built-in scenes progressively (increasing spp) with colour, variance of the mean and
features, plus an independent high-spp reference; denoises every level with OIDN and, when a
mixer for OIDN ships with the package, with progressive denoising PD(OIDN); writes every frame
as EXR and prints a table of errors against the reference (linear HDR relMSE, SMAPE, RMSE and
HDR-FLIP), also saved as ``summary.json`` and ``summary.md``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from jaxden.errors import JaxdenError


@dataclasses.dataclass(frozen=True)
class DemoSettings:
    scenes: tuple[str, ...] = ("cornell-box", "texture-bump")
    size: tuple[int, int] = (128, 128)
    spp_levels: tuple[int, ...] = (4, 16, 64, 256)
    reference_spp: int = 4096
    seed: int = 7


QUICK = DemoSettings(scenes=("cornell-box",), size=(64, 64), spp_levels=(4, 16, 64), reference_spp=1024)


def _metrics(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    from jaxden import metrics

    return {
        "relmse": float(metrics.relmse(image, reference)),
        "smape": float(metrics.smape(image, reference)),
        "rmse": float(metrics.rmse(image, reference)),
        "flip": float(metrics.flip(image, reference, "HDR")),
    }


def _progressive_denoiser():
    """``frame -> (image, alpha)`` for PD(OIDN) if a shipped mixer exists, else None."""
    try:
        from jaxden.progressive import shipped_progressive_denoiser
    except ImportError:
        return None
    return shipped_progressive_denoiser("oidn")


def run_demo(out: Path, quick: bool = False, settings: DemoSettings | None = None) -> dict:
    from jaxden.denoisers import make_denoiser
    from jaxden.io.exr import write_frame, write_image
    from jaxden.render.core import render_frame

    settings = settings or (QUICK if quick else DemoSettings())
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise JaxdenError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    oidn = make_denoiser("oidn")
    progressive = _progressive_denoiser()
    rows = []
    started = time.perf_counter()
    for scene in settings.scenes:
        folder = out / scene
        folder.mkdir(exist_ok=True)
        print(f"[{scene}] reference at {settings.reference_spp} spp ...", flush=True)
        reference = render_frame(scene, settings.reference_spp, seed=settings.seed + 1_000_003,
                                 size=settings.size)
        write_frame(folder / "reference.exr", reference, attributes={"scene": scene})
        for spp in settings.spp_levels:
            frame = render_frame(scene, spp, seed=settings.seed + spp, size=settings.size)
            write_frame(folder / f"spp{spp:05d}.exr", frame,
                        attributes={"scene": scene, "seed": settings.seed + spp})
            results = {"mc": frame.color}
            results["oidn"] = np.asarray(oidn(frame))
            if progressive is not None:
                results["pd_oidn"], _ = progressive(frame)
            for method, image in results.items():
                if method != "mc":
                    write_image(folder / f"spp{spp:05d}.{method}.exr", np.asarray(image))
                rows.append({"scene": scene, "spp": spp, "method": method,
                             **_metrics(np.asarray(image), reference.color)})
            print(f"[{scene}] {spp:>5} spp: " + "  ".join(
                f"{r['method']} relMSE {r['relmse']:.4f}" for r in rows[-len(results):]), flush=True)
    summary = {
        "settings": dataclasses.asdict(settings),
        "metrics": "linear HDR against an independent reference render; relMSE = mean((x-r)^2/"
                   "(r^2+0.01)), SMAPE = mean(|x-r|/(|x|+|r|+0.01)), FLIP in HDR mode",
        "seconds": round(time.perf_counter() - started, 1),
        "rows": rows,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    table = _markdown_table(rows)
    (out / "summary.md").write_text(table + "\n")
    print()
    print(table)
    print(f"\nwrote {out}/ (EXR frames per scene, summary.json, summary.md) in {summary['seconds']} s")
    return summary


def _markdown_table(rows: list[dict]) -> str:
    lines = ["| scene | spp | method | relMSE | SMAPE | RMSE | FLIP |", "|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['spp']} | {r['method']} | {r['relmse']:.4f} | "
                     f"{r['smape']:.4f} | {r['rmse']:.4f} | {r['flip']:.4f} |")
    return "\n".join(lines)
