"""The WSKP paper's comparisons (its Tables 1-3) on jaxden's data: SVGF, BMFR, NBGD and MR-KP
beside WSKP-6, WSKP-3, KP and OIDN.

    python experiments/rt_comparisons.py [--home $JAXDEN_HOME] [--out experiments/results/rt]

Scores here, on the held-out sets the real-time tables use (``data/rt-test``: 24 crops at
1 spp; ``data/rt-seq``: 6 camera-path sequences of 16 frames with motion vectors), every method
that needs no training run of this machine: the noisy input, the temporally accumulated input,
OIDN, SVGF (the paper's and Falcor's settings), BMFR and the shipped WSKP-6 and WSKP-3 (the
``train-rt.toml`` recipe, seed 0: runs ``wskp6-s0`` of rt-main and ``wskp3`` of rt-variants);
reads the trained runs that have finished (``runs/sweeps/{rt-main,rt-wskp3,rt-variants,
rt-baselines}/*/result.json``: WSKP-6, KP, WSKP-3, NBGD and MR-KP with two seeds each; a method
whose runs are missing says so) and the time ratios of ``experiments/results/bench/bench-denoisers.json``
(1280 x 720, every method in one run, as ratios to WSKP-6). Writes ``rt-comparisons.md`` and
``.json``.

The setting of both papers' comparisons (BASELINES.md section 0): every method sees the same
albedo demodulation and the same temporal accumulation of its input. On the sequences each
method is therefore scored three ways: on each 1-spp frame alone (``per frame``), on the
temporally accumulated input (``accumulated``: :func:`jaxden.denoise.temporal.accumulate`,
the pre-accumulation the WSKP and NBGD pipelines feed every network), and for the temporal
methods (SVGF, BMFR) with their own history (``own history``: the method's temporal form over
the raw 1-spp frames). The first frame of each sequence (no history) is left out.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from jaxden.evaluate.seeds import METRICS, group, single, stats, table

REPO = Path(__file__).resolve().parent.parent
SWEEPS = ("rt-main", "rt-wskp3", "rt-variants", "rt-baselines")
#: Methods scored here: (key, label, denoiser spec).
SCORED = (("oidn", "OIDN 2 (pretrained, 'high')", "oidn"),
          ("svgf", "SVGF (paper settings)", "svgf"),
          ("svgf_falcor", "SVGF (Falcor settings)", "svgf:preset=falcor"),
          ("bmfr", "BMFR", "bmfr"),
          ("wskp6_shipped", "WSKP-6 (shipped weights: run wskp6-s0)", "wskp-6"),
          ("wskp3_shipped", "WSKP-3 (shipped weights)", "wskp-3"))
#: Trained rows: (model key of the sweeps' runs, label).
TRAINED = (("wskp", "WSKP-6"), ("wskp3", "WSKP-3"), ("kp", "KP (13x13)"),
           ("nbgd", "NBGD"), ("mrkp", "MR-KP"))
#: bench-denoisers.json keys of each method's time.
BENCH_KEYS = {"WSKP-6": "wskp6", "WSKP-3": "wskp3", "KP (13x13)": "kp", "NBGD": "nbgd",
              "MR-KP": "mrkp", "OIDN 2 (pretrained, 'high')": "oidn", "SVGF, one frame": "svgf",
              "SVGF, a frame of a sequence": "svgf_step", "BMFR, one frame": "bmfr",
              "BMFR, a frame of a sequence": "bmfr_step", "NFOR (two half buffers)": "nfor",
              "Deep Combiner over OIDN in JAX": "dc"}


#: What a training-free method's scores depend on besides its spec and the data: the code that
#: scores and runs any denoiser, and each method's own modules (their bytes are hashed; an
#: edit there rescores that method; ``--rescore`` redoes all), and OIDN's library.
SCORING_CODE = ("jaxden/evaluate/denoise.py", "jaxden/metrics.py", "jaxden/frame.py",
                "jaxden/io/exr.py", "jaxden/tiling.py", "jaxden/denoise/registry.py",
                "jaxden/denoise/temporal.py", "jaxden/denoise/tiled.py",
                "jaxden/denoise/emission.py")
METHOD_CODE = {"oidn": ("jaxden/denoise/oidn.py",), "svgf": ("jaxden/denoise/svgf.py",),
               "bmfr": ("jaxden/denoise/bmfr.py",),
               "wskp": ("jaxden/denoise/models.py", "jaxden/denoise/kernels.py",
                        "jaxden/denoise/nn/wskp.py", "jaxden/denoise/nn/layers.py",
                        "jaxden/weights")}


def scoring_key(spec: str, data: list[Path]) -> str:
    """A digest of everything a score of ``spec`` on ``data`` depends on: the spec, each data
    folder's manifest, the files of :data:`SCORING_CODE` and the installed OIDN's version."""
    import hashlib
    from importlib import metadata

    digest = hashlib.sha256(spec.encode())
    for folder in data:
        manifest = folder / "manifest.json"
        digest.update(manifest.read_bytes() if manifest.is_file() else b"-")
    method = spec.split(":")[0].split("-")[0]
    for entry in SCORING_CODE + METHOD_CODE.get(method, ("jaxden/denoise",)):
        path = REPO / entry
        for file in sorted(path.rglob("*") if path.is_dir() else [path]):
            if file.is_file() and "__pycache__" not in file.parts:
                digest.update(str(file.relative_to(REPO)).encode())
                digest.update(file.read_bytes())
    for package in ("pyoidn", "oidn"):
        try:
            digest.update(f"{package}={metadata.version(package)}".encode())
        except metadata.PackageNotFoundError:
            pass
    return digest.hexdigest()


def score(home: Path, rescore: bool = False) -> dict[str, dict]:
    """``{key: {"den": summary on rt-test, "seq": summary on rt-seq}}`` of :data:`SCORED`.

    Scores are kept in ``$JAXDEN_HOME/runs/rt-comparisons/scores.json`` under
    :func:`scoring_key`: a rerun after a training run finishes reuses them (the scoring takes
    ~25 minutes on two cores, mostly SVGF's sequences); any change of the data or of the
    scoring code rescores, and so does ``rescore``."""
    from jaxden.evaluate import denoise as report
    from jaxden.fileio import atomic_write_text

    cache_path = home / "runs" / "rt-comparisons" / "scores.json"
    cache = json.loads(cache_path.read_text()) if cache_path.is_file() and not rescore else {}
    out: dict[str, dict] = {}
    test, seq = home / "data" / "rt-test", home / "data" / "rt-seq"
    for key, _, spec in SCORED:
        fingerprint = scoring_key(spec, [test, seq])
        if fingerprint in cache:
            out[key] = cache[fingerprint]
            continue
        out[key] = {}
        if test.is_dir():
            out[key]["den"] = report.summarize(report.evaluate_denoiser(test, spec, spp=(1,)))
        if seq.is_dir():
            out[key]["seq"] = report.summarize(report.evaluate_sequences(seq, spec))
        cache[fingerprint] = out[key]
        cache_path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(cache_path, json.dumps(cache, default=float))
        print(f"scored {spec}", file=sys.stderr, flush=True)
    return out


def trained_runs(home: Path) -> dict[str, list[dict]]:
    """``{model: [result.json, ...]}`` of the finished runs of :data:`SWEEPS` (WSKP runs with
    a 1 x 1 kernel among their sizes are another model and left out; a run whose whole config
    another sweep's run already has, seed included, is counted once)."""
    results, configs = [], set()
    for sweep in SWEEPS:
        folder = home / "runs" / "sweeps" / sweep
        for path in sorted(folder.glob("*/result.json")):
            result = json.loads(path.read_text())
            key = json.dumps(result["config"], sort_keys=True)
            if key not in configs:
                configs.add(key)
                results.append(result)
    plain = [r for r in results
             if 1 not in (r["config"].get("model_config", {}).get("kernel_sizes") or [])]
    return group(plain, lambda r: r["config"]["model"])


def rows(scored: dict, runs: dict[str, list[dict]]) -> tuple[list, list]:
    """The per-frame and the sequence rows: ``[(label, {metric: (mean, std, n)}), ...]``."""
    label = {key: text for key, text, _ in SCORED}
    per_frame = [("1-spp input", single(scored["oidn"].get("den"), "mc"))]
    per_frame += [(label[k], single(scored[k].get("den"), "den")) for k, _, _ in SCORED]
    per_frame += [(f"{text}, trained here (runs: {len(runs.get(m, []))})",
                   stats(runs.get(m, []), "den", "den")) for m, text in TRAINED]
    sequences = [("1-spp input", single(scored["oidn"].get("seq"), "mc")),
                 ("accumulated input", single(scored["oidn"].get("seq"), "acc"))]
    for key, _, _ in SCORED:
        summary = scored[key].get("seq")
        sequences += [(f"{label[key]}, per frame", single(summary, "den")),
                      (f"{label[key]}, accumulated", single(summary, "tdn"))]
        if summary and any(k.startswith("seq_") for k in summary):
            sequences.append((f"{label[key]}, own history", single(summary, "seq")))
    for model, text in TRAINED:
        members = runs.get(model, [])
        sequences += [(f"{text}, trained here, per frame", stats(members, "seq", "den")),
                      (f"{text}, trained here, accumulated", stats(members, "seq", "tdn"))]
    return per_frame, sequences


def claims(per_frame: list, bench: dict) -> list[str]:
    """The papers' claims, each with the numbers that decide it (or what is missing)."""
    psnr = {label: row.get("psnr") for label, row in per_frame}

    def trained(text):
        return next((v for k, v in psnr.items() if k.startswith(f"{text}, trained here")), None)

    def ratio(a, b):
        ka, kb = f"{a}_s", f"{b}_s"
        return bench[ka] / bench[kb] if ka in bench and kb in bench else None

    lines = ["## The papers' claims on this data", ""]
    wskp = trained("WSKP-6") or psnr.get("WSKP-6 (shipped weights: run wskp6-s0)")
    for other, key, words in (("KP (13x13)", "kp", "comparable to KP at about half its time"),
                              ("NBGD", "nbgd", "better than NBGD at equal time")):
        theirs, time = trained(other), ratio("wskp6", key)
        if wskp is None or theirs is None:
            lines.append(f"- WSKP-6 {words}: not measured yet ({other} runs missing)")
            continue
        margin = wskp[0] - theirs[0]
        spreads = [s for s in (wskp[1], theirs[1]) if s == s]  # NaN: one seed
        spread = f"{max(spreads):.2f} dB" if spreads else "not measured: one seed each"
        timing = "no time measured" if time is None else f"WSKP-6 takes {time:.2f}x its time"
        lines.append(f"- WSKP-6 {words}: PSNR {wskp[0]:.2f} against {theirs[0]:.2f} dB "
                     f"(margin {margin:+.2f} dB, seed-to-seed standard deviation "
                     f"{spread}); {timing}")
    return lines


def time_table(bench: dict) -> list[str]:
    lines = ["| method | time / WSKP-6 | seconds |", "|---|---:|---:|"]
    for label, key in BENCH_KEYS.items():
        if f"{key}_s" in bench and "wskp6_s" in bench:
            lines.append(f"| {label} | {bench[f'{key}_s'] / bench['wskp6_s']:.3f} | "
                         f"{bench[f'{key}_s']:.4g} |")
        else:
            lines.append(f"| {label} | not measured | |")
    return lines


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--home", default=os.environ.get("JAXDEN_HOME", "~/jaxden-work"))
    parser.add_argument("--out", default=str(REPO / "experiments" / "results" / "rt"))
    parser.add_argument("--rescore", action="store_true",
                        help="score the training-free methods afresh (not from the cache)")
    args = parser.parse_args(argv)
    home, out = Path(args.home).expanduser(), Path(args.out)
    scored = score(home, args.rescore)
    runs = trained_runs(home)
    per_frame, sequences = rows(scored, runs)
    bench_path = REPO / "experiments" / "results" / "bench" / "bench-denoisers.json"
    bench = json.loads(bench_path.read_text()) if bench_path.is_file() else {}
    text = ["<!-- generated by: python experiments/rt_comparisons.py -->",
            "# WSKP paper Tables 1-3 on jaxden's data: the comparisons", "",
            "Held-out set `data/rt-test` (dataset-rt-test.toml: 24 crops of 12 procedural "
            "scenes of seeds no training set uses, 1-spp inputs, 2048-spp references) and "
            "sequences `data/rt-seq` (sequences-rt-test.toml: 6 camera paths of 16 frames at "
            "128 x 128, 1 spp, 512-spp references; first frame of each left out). Trained "
            "methods: recipe `train-rt.toml` (4000 steps, batch 8 of 64 x 64 crops, SMAPE) on "
            "`data/rt`, sweeps rt-main (WSKP-6, KP), rt-wskp3 and rt-variants (WSKP-3) and rt-baselines "
            "(NBGD, MR-KP), mean ± standard deviation over seeds. PSNR and SSIM tone-mapped "
            "(clip, gamma 2.2), relMSE and FLIP linear HDR. Training-free methods run here; "
            "`accumulated` = the method on the temporally accumulated input (the papers' "
            "common setting), `own history` = the temporal method's own reprojection and "
            "accumulation over the raw frames.", "",
            "## Table 1: per frame, 1 spp", "", table(per_frame), "",
            "## Table 2: sequences", "", table(sequences), "",
            "## Table 3: time at 1280 x 720 (one run of `jaxden bench denoisers`, CPU)", "",
            *time_table(bench), "", *claims(per_frame, bench), ""]
    (out / "rt-comparisons.md").write_text("\n".join(text))
    (out / "rt-comparisons.json").write_text(json.dumps(
        {"per_frame": dict(per_frame), "sequences": dict(sequences),
         "runs": {m: [r["run"] for r in members] for m, members in runs.items()},
         "metrics": [m for m, _, _ in METRICS]}, indent=1, sort_keys=True, default=str))
    print(f"wrote {out / 'rt-comparisons.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
