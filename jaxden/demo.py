"""``jaxden demo``: the main job on built-in defaults (no downloads, no user data).

Renders built-in scenes progressively (increasing spp) with colour, variance of the mean and
features, plus an independent high-spp reference; denoises every level with OIDN, with the
shipped real-time denoiser WSKP-6 (``wskp-6``: trained at 1 spp, so its error stops falling as
the spp grow, where MC's and PD's keep falling) and, for each of them with a mixer shipped in
the package, with progressive denoising: PD(OIDN) with ``oidn-pd``, PD(WSKP-6) with
``wskp-6-pd`` (from 2 spp: PD needs a variance); writes every frame
as EXR and prints a table of errors against the reference (linear HDR relMSE, SMAPE, RMSE and
HDR-FLIP), also saved as ``summary.json`` and ``summary.md``.

So that the results can be looked at, it also writes (nothing here changes what is rendered or
measured):

- a PNG preview of every frame beside its EXR (``SCENE/reference.png``, ``SCENE/spp00004.png``,
  ``SCENE/spp00004.oidn.png``, ...), tone mapped at one exposure per scene
  (:func:`jaxden.report.tonemap.auto_stops` of the reference), and PD's alpha map as
  ``SCENE/spp00004.pd_oidn.alpha.exr`` / ``.alpha.png`` (white = all denoised);
- ``convergence.svg`` and ``convergence.png``: error vs spp, log-log, with MC's 1/spp rate;
- ``report.html``: the interactive report of :mod:`jaxden.report` over the whole folder.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

from jaxden.errors import JaxdenError


@dataclasses.dataclass(frozen=True)
class DemoSettings:
    scenes: tuple[str, ...] = ("cornell-box", "texture-bump", "small-lights")
    size: tuple[int, int] = (128, 128)
    spp_levels: tuple[int, ...] = (1, 4, 16, 64, 256)
    reference_spp: int = 4096
    seed: int = 7
    realtime: tuple[str, ...] = ("wskp-6",)  # denoisers run beside OIDN at every level


QUICK = DemoSettings(scenes=("cornell-box",), size=(64, 64), spp_levels=(1, 4, 16, 64),
                     reference_spp=1024)


def _metrics(image: np.ndarray, reference: np.ndarray, flip_maps: dict | None = None,
             key: tuple | None = None) -> dict[str, float]:
    """The demo's metrics; FLIP's per-pixel map (the same call returns it) is kept in
    ``flip_maps[key]`` for the report."""
    from jaxden import metrics

    flip_mean, flip_map = metrics.flip(image, reference, "HDR", return_map=True)
    if flip_maps is not None:
        flip_maps[key] = (float(flip_mean), flip_map)
    return {
        "relmse": float(metrics.relmse(image, reference)),
        "smape": float(metrics.smape(image, reference)),
        "rmse": float(metrics.rmse(image, reference)),
        "flip": float(flip_mean),
    }


def _progressive_denoisers(realtime: tuple[str, ...]) -> dict:
    """``{"pd_oidn": frame -> (image, alpha), "pd_wskp6": ...}``: PD over OIDN and over each
    real-time denoiser of the demo for which a mixer ships in the package (``oidn-pd``,
    ``wskp-6-pd``), each with its shipped mixer and SURE probes."""
    from jaxden.progressive.pipeline import shipped_progressive_denoiser

    found = {}
    for name in ("oidn", *realtime):
        run = shipped_progressive_denoiser(name)
        if run is not None:
            found[f"pd_{method_key(name)}"] = run
    return found


def method_key(spec: str) -> str:
    """The demo's method name for a denoiser spec (file names, table rows): ``wskp-6`` ->
    ``wskp6``, a checkpoint folder -> its folder name."""
    name = Path(str(spec).split(":", 1)[0]).name or str(spec)
    return "".join(c for c in name if c.isalnum() or c == "_")


def _write_preview(path: Path, image, stops: float) -> None:
    from jaxden.io.png import write_png
    from jaxden.report.tonemap import tonemap

    # a preview must not stop the demo: NaN (never seen) shows black, +inf white
    write_png(path, tonemap(np.nan_to_num(np.asarray(image), nan=0.0, posinf=1e30), stops))


def _write_plots(out: Path, rows: list[dict]) -> list[Path]:
    from jaxden.fileio import atomic_write_bytes
    from jaxden.report.figures import convergence_figure, png_bytes, svg_bytes

    figure = convergence_figure(rows, title="jaxden demo: error vs spp (linear HDR)")
    paths = [out / "convergence.svg", out / "convergence.png"]
    atomic_write_bytes(paths[0], svg_bytes(figure))
    atomic_write_bytes(paths[1], png_bytes(figure))
    return paths


def _this_run(out: Path, settings: DemoSettings):
    """The files of ``out`` that this run wrote: an earlier run into the same folder (other
    scenes, sizes or spp levels) must not mix into the report."""
    from jaxden.report import discover

    found = discover(out)
    scenes = []
    for scene in found.scenes:
        if scene.name in settings.scenes:
            images, alphas = ({key: path for key, path in table.items()
                               if key[0] in settings.spp_levels}
                              for table in (scene.images, scene.alphas))
            scenes.append(dataclasses.replace(scene, images=images, alphas=alphas))
    return dataclasses.replace(found, scenes=tuple(scenes), metric_files=())


def run_demo(out: Path, quick: bool = False, settings: DemoSettings | None = None,
             report: bool = True, progress: bool = True) -> dict:
    """Render, denoise, measure and write everything (module docstring) under ``out``;
    returns the summary (also ``summary.json``). ``report``: also write the plots and
    ``report.html``; ``progress``: a progress bar over the renders on stderr."""
    from tqdm import tqdm

    from jaxden.denoise.registry import load_denoiser, make_denoiser
    from jaxden.io.exr import write_frame, write_image
    from jaxden.io.png import write_png
    from jaxden.render.core import render_frame
    from jaxden.report.tonemap import alpha_preview, auto_stops

    settings = settings or (QUICK if quick else DemoSettings())
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise JaxdenError(f"--out {out} exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    oidn = make_denoiser("oidn")
    realtime = {method_key(name): load_denoiser(name) for name in settings.realtime}
    progressive = _progressive_denoisers(tuple(settings.realtime))
    rows, flip_maps = [], {}
    started = time.perf_counter()
    renders = tqdm(total=len(settings.scenes) * (1 + len(settings.spp_levels)), unit="render",
                   desc="demo", file=sys.stderr, disable=not progress, dynamic_ncols=True)

    def say(text: str) -> None:  # above the progress bar, on stdout as before
        renders.write(text, file=sys.stdout)
        sys.stdout.flush()

    for scene in settings.scenes:
        folder = out / scene
        folder.mkdir(exist_ok=True)
        say(f"[{scene}] reference at {settings.reference_spp} spp ...")
        renders.set_postfix_str(f"{scene} reference")
        reference = render_frame(scene, settings.reference_spp, seed=settings.seed + 1_000_003,
                                 size=settings.size)
        renders.update()
        write_frame(folder / "reference.exr", reference, attributes={"scene": scene})
        stops = auto_stops(reference.color)
        _write_preview(folder / "reference.png", reference.color, stops)
        for spp in settings.spp_levels:
            renders.set_postfix_str(f"{scene} {spp} spp")
            frame = render_frame(scene, spp, seed=settings.seed + spp, size=settings.size)
            write_frame(folder / f"spp{spp:05d}.exr", frame,
                        attributes={"scene": scene, "seed": settings.seed + spp})
            results = {"mc": frame.color}
            results["oidn"] = np.asarray(oidn(frame))
            for method, denoiser in realtime.items():
                results[method] = np.asarray(denoiser(frame))
            alphas = {}
            if frame.variance is not None:  # PD needs it: from 2 spp
                for method, run in progressive.items():
                    results[method], alphas[method] = run(frame)
            for method, image in results.items():
                stem = f"spp{spp:05d}" if method == "mc" else f"spp{spp:05d}.{method}"
                if method != "mc":
                    write_image(folder / f"{stem}.exr", np.asarray(image))
                _write_preview(folder / f"{stem}.png", image, stops)
                rows.append({"scene": scene, "spp": spp, "method": method,
                             **_metrics(np.asarray(image), reference.color, flip_maps,
                                        (scene, spp, method))})
            for method, alpha in alphas.items():
                write_image(folder / f"spp{spp:05d}.{method}.alpha.exr", np.asarray(alpha))
                write_png(folder / f"spp{spp:05d}.{method}.alpha.png", alpha_preview(alpha))
            renders.update()
            say(f"[{scene}] {spp:>5} spp: " + "  ".join(
                f"{r['method']} relMSE {r['relmse']:.4f}" for r in rows[-len(results):]))
    renders.close()
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
    print(f"\nwrote {out}/ (EXR frames and PNG previews per scene, summary.json, summary.md) "
          f"in {summary['seconds']} s")
    if report:
        from jaxden.report import build_report

        plots = _write_plots(out, rows)
        path = build_report(out, out / "report.html", title="jaxden demo", progress=progress,
                            found=_this_run(out, settings), flip_maps=flip_maps)
        print(f"wrote {', '.join(p.name for p in plots)} (error vs spp)")
        print(f"report: {path}  (open it in a web browser)")
    return summary


def _markdown_table(rows: list[dict]) -> str:
    lines = ["| scene | spp | method | relMSE | SMAPE | RMSE | FLIP |", "|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['spp']} | {r['method']} | {r['relmse']:.4f} | "
                     f"{r['smape']:.4f} | {r['rmse']:.4f} | {r['flip']:.4f} |")
    return "\n".join(lines)
