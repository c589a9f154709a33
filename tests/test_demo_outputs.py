"""`jaxden demo` shows its results: PNG previews of every frame, the convergence plot (PNG and
SVG), report.html (whose table holds the demo's own numbers), the report's path printed last,
a progress bar on stderr; and the printed error table is what summary.json holds.

The fast test runs the demo's entry point on a 32x32 Cornell box (2 spp levels, a 64-spp
reference), in a folder holding files of an earlier run that the report must leave out;
`jaxden demo --quick` itself (about 30 s on 2 cores) is marked slow.
"""

from __future__ import annotations

import json
import re
import struct

import numpy as np
import pytest

from jaxden.report.encode import decode_array

SPP = (4, 16)


def png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", path
    return struct.unpack(">II", data[16:24])


def page_data(path) -> dict:
    text = path.read_text()
    return json.loads(re.search(r'id="jaxden-data">(.*?)</script>', text, re.DOTALL).group(1))


def check_outputs(out, scene: str, spp_levels, size: int) -> dict:
    """Everything the demo should have written; returns the summary."""
    folder = out / scene
    pd_levels = [spp for spp in spp_levels if spp > 1]  # PD needs a variance: 2 spp or more
    stems = ["reference"] + [f"spp{spp:05d}{suffix}" for spp in spp_levels
                             for suffix in ("", ".oidn", ".wskp6")] + [
        f"spp{spp:05d}{suffix}" for spp in pd_levels
        for suffix in (".pd_oidn", ".pd_oidn.alpha", ".pd_wskp6", ".pd_wskp6.alpha")]
    for stem in stems:
        assert (folder / f"{stem}.exr").is_file(), stem
        assert png_size(folder / f"{stem}.png") == (size, size), stem
        assert (folder / f"{stem}.png").stat().st_size > 200, stem
    from jaxden.io.exr import read_image

    assert not (folder / "spp00001.pd_oidn.exr").exists()
    assert not (folder / "spp00001.pd_wskp6.exr").exists()
    alpha = read_image(folder / f"spp{pd_levels[0]:05d}.pd_oidn.alpha.exr")
    assert alpha.shape == (size, size, 3) and 0 <= alpha.min() and alpha.max() <= 1
    svg = (out / "convergence.svg").read_text()
    assert svg.lstrip().startswith("<?xml") and "<svg" in svg and "samples per pixel" in svg
    assert png_size(out / "convergence.png")[0] > 400
    assert (out / "convergence.png").stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    report = out / "report.html"
    assert report.stat().st_size > 20_000
    data = page_data(report)
    (page_scene,) = data["scenes"]
    assert page_scene["name"] == scene and page_scene["spp"] == list(spp_levels)
    assert page_scene["methods"] == ["mc", "oidn", "pd_oidn", "pd_wskp6", "wskp6"]
    assert {"reference", f"{spp_levels[-1]}/pd_oidn", f"flip/{spp_levels[0]}/mc",
            f"relse/{spp_levels[0]}/oidn", f"alpha/{spp_levels[-1]}/pd_oidn"} <= set(
        page_scene["arrays"])
    assert decode_array(page_scene["arrays"]["reference"]).std() > 0
    # the page's numbers are the demo's numbers, to the last bit
    page_rows = {(r["spp"], r["method"]): r for r in page_scene["rows"]}
    for row in summary["rows"]:
        shown = page_rows[row["spp"], row["method"]]
        for metric in ("relmse", "smape", "rmse", "flip"):
            assert shown[metric] == row[metric], (row, metric)
    return summary


def test_demo_writes_previews_plots_and_report(tmp_path, capsys):
    from jaxden.demo import DemoSettings, run_demo
    from jaxden.io.exr import write_image

    # left by an earlier run into the same folder: not part of this run's report
    stale = np.ones((8, 8, 3), np.float32)
    for name in ("cornell-box/spp00256.exr", "old-scene/reference.exr", "old-scene/spp4.exr"):
        (tmp_path / name).parent.mkdir(exist_ok=True)
        write_image(tmp_path / name, stale)
    settings = DemoSettings(scenes=("cornell-box",), size=(32, 32), spp_levels=SPP,
                            reference_spp=64, seed=7)
    summary = run_demo(tmp_path, settings=settings)
    captured = capsys.readouterr()
    check_outputs(tmp_path, "cornell-box", SPP, 32)
    lines = captured.out.strip().splitlines()
    assert lines[-1] == f"report: {tmp_path / 'report.html'}  (open it in a web browser)"
    table = "\n".join(line for line in lines if line.startswith("|"))
    assert table == (tmp_path / "summary.md").read_text().strip()
    assert len(summary["rows"]) == 10  # mc, oidn, wskp6, pd_oidn, pd_wskp6 at 4 and 16 spp
    assert "demo" in captured.err and "render" in captured.err  # the tqdm bar
    assert "| cornell-box |" not in captured.err  # the table stays on stdout


@pytest.mark.slow
def test_quick_demo_command(tmp_path, capsys):
    from jaxden import cli
    from jaxden.demo import QUICK

    out = tmp_path / "demo-out"
    assert cli.main(["demo", "--quick", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    summary = check_outputs(out, QUICK.scenes[0], QUICK.spp_levels, QUICK.size[0])
    assert summary["settings"]["spp_levels"] == list(QUICK.spp_levels)
    assert captured.out.strip().splitlines()[-1].startswith(f"report: {out / 'report.html'}")
    assert np.isfinite([r["relmse"] for r in summary["rows"]]).all()


def test_demo_denoiser_flag_sets_the_denoisers_beside_oidn(tmp_path, monkeypatch):
    """`jaxden demo --denoiser A --denoiser B` runs A and B beside OIDN (repeats once), on the
    quick or the full settings otherwise unchanged; no flag keeps the default (WSKP-6)."""
    import jaxden.demo
    from jaxden import cli

    seen = []
    monkeypatch.setattr(jaxden.demo, "run_demo",
                        lambda out, settings=None, report=True: seen.append(settings) or {})
    assert cli.main(["demo", "--quick", "--out", str(tmp_path), "--denoiser", "oidn-jax",
                     "--denoiser", "wskp-3", "--denoiser", "oidn-jax"]) == 0
    assert cli.main(["demo", "--out", str(tmp_path)]) == 0
    assert seen[0] == jaxden.demo.dataclasses.replace(jaxden.demo.QUICK,
                                                      realtime=("oidn-jax", "wskp-3"))
    assert seen[1] == jaxden.demo.DemoSettings()
    assert jaxden.demo.method_key("oidn-jax") == "oidnjax"
    assert jaxden.demo.method_key("/runs/finetune-oidn:emission=separate") == "finetuneoidn"


@pytest.mark.slow
def test_demo_with_oidn_in_jax(tmp_path):
    """OIDN in JAX in the demo: its rows, and PD over it with the mixer that ships for it."""
    from jaxden.demo import DemoSettings, run_demo

    settings = DemoSettings(scenes=("cornell-box",), size=(32, 32), spp_levels=(4,),
                            reference_spp=64, seed=7, realtime=("oidn-jax",))
    summary = run_demo(tmp_path, settings=settings, report=False, progress=False)
    rows = {row["method"]: row for row in summary["rows"]}
    assert set(rows) == {"mc", "oidn", "oidnjax", "pd_oidn", "pd_oidnjax"}
    assert abs(rows["oidnjax"]["rmse"] - rows["oidn"]["rmse"]) < 1e-4 * rows["oidn"]["rmse"]
    assert (tmp_path / "cornell-box" / "spp00004.pd_oidnjax.alpha.exr").is_file()
