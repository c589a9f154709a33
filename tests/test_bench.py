"""Smoke runs of every benchmark in jaxden/bench at a tiny size: each runs through
``jaxden.bench.run(name, as_json=True, quick=True)``, prints one JSON object (alone on stdout)
with the keys its docstring promises, and its ratios are finite and positive. No timing is
asserted (a shared 2-core machine makes any bound meaningless here; the real numbers come from
``jaxden bench``).

The ``quick`` sizes are shrunk further through each module's QUICK_* constants, and the frame
the denoiser / SURE / progressive benchmarks read is a Mitsuba-free synthetic one
(``$JAXDEN_BENCH_FRAME``), so only the render benchmark renders.
"""

from __future__ import annotations

import json
import math

import pytest

from jaxden import bench
from jaxden.bench import BENCH_FRAME_ENV

FRAME_SIZE = (32, 24)  # (width, height)
ALL = ("decoder", "denoisers", "progressive", "render", "sharding", "sure")


@pytest.fixture(scope="module")
def frame_file(tmp_path_factory):
    from jaxden.io.exr import write_frame
    from jaxden.render.synthetic import synthetic_render

    path = tmp_path_factory.mktemp("bench") / "frame.exr"
    write_frame(path, synthetic_render("bench", 4, seed=1, size=FRAME_SIZE))
    return path


@pytest.fixture
def tiny(monkeypatch, frame_file):
    """Every benchmark's quick size made tiny, and the synthetic bench frame."""
    from jaxden.bench import decoder, denoisers, progressive, render, sharding, sure

    monkeypatch.setenv(BENCH_FRAME_ENV, str(frame_file))
    monkeypatch.setattr(decoder, "QUICK_SIZE", (24, 32))
    monkeypatch.setattr(decoder, "QUICK_REPEATS", 1)
    monkeypatch.setattr(decoder, "KERNEL_SIZES", (3, 5))
    for module in (denoisers, progressive, sure):
        monkeypatch.setattr(module, "QUICK_SIZE", FRAME_SIZE)
        monkeypatch.setattr(module, "QUICK_REPEATS", 1)
    monkeypatch.setattr(sure, "MODEL", "wskp3")
    monkeypatch.setattr(render, "QUICK", ((16, 16), 2, 1))
    monkeypatch.setattr(sharding, "QUICK", (2, 16, 1))


def run_json(name, capsys) -> dict:
    capsys.readouterr()
    result = bench.run(name, as_json=True, quick=True)
    printed = json.loads(capsys.readouterr().out)  # the JSON alone; the table on stderr
    assert printed == json.loads(json.dumps(result, sort_keys=True, default=str))
    assert printed["bench"] == name
    return printed


def assert_ratios(result: dict, keys) -> None:
    for key in keys:
        assert key in result, (key, sorted(result))
    ratios = [k for k in result if "ratio" in k or "_over_" in k]
    assert set(keys) <= set(ratios)
    for key in ratios:
        value = result[key]
        assert isinstance(value, float) and math.isfinite(value) and value > 0, (key, value)


def test_every_benchmark_is_registered_and_tested():
    assert tuple(bench.names()) == ALL


def test_unknown_benchmark_names_the_valid_ones():
    from jaxden.errors import JaxdenError

    with pytest.raises(JaxdenError, match="valid: decoder, denoisers"):
        bench.run("nope")


@pytest.mark.slow  # a smoke test (5-10 s); test_kernels.py checks both decoder forms
def test_decoder_bench(tiny, capsys):
    result = run_json("decoder", capsys)
    assert_ratios(result, ["memory_ratio", "time_ratio", "cpu_time_ratio",
                           "backward_memory_ratio", "backward_time_ratio"])
    assert result["size"] == "32x24x3" and result["kernel_sizes"] == "3,5"
    # The two forms compute the same thing (float32 round-off), as the bench reports.
    assert 0 <= result["max_rel_difference"] < 1e-4
    for key in ("box_mb", "unfold_mb", "box_s", "unfold_s", "backward_box_s"):
        assert result[key] > 0


def test_denoisers_bench_one_model(tiny, capsys, monkeypatch):
    """The benchmark's loop with one model, KP (the fastest to initialise and compile; each
    model costs ~5-15 s here); all four in test_denoisers_bench (slow)."""
    from jaxden.bench import denoisers

    monkeypatch.setattr(denoisers, "MODELS", {"kp": "kp"})
    monkeypatch.setattr(denoisers, "OIDN_JAX", False)
    monkeypatch.setattr(denoisers, "BASELINES", {})
    monkeypatch.setattr(denoisers, "DC_BASE", None)
    monkeypatch.setattr(denoisers, "NFOR", False)
    monkeypatch.setattr(denoisers, "NJS_BASE", None)
    result = run_json("denoisers", capsys)
    assert_ratios(result, ["kp_over_oidn"])
    assert (result["width"], result["height"]) == FRAME_SIZE
    assert result["kp_s"] > 0 and result["oidn_s"] > 0


@pytest.mark.slow  # SVGF, BMFR (each also as a sequence step), DC, NFOR compiled: ~30-60 s
def test_denoisers_bench_times_the_comparisons_against_wskp6(tiny, capsys, monkeypatch):
    """The papers' baselines are timed in the same run as WSKP-6, as ratios to it."""
    from jaxden.bench import denoisers

    monkeypatch.setattr(denoisers, "MODELS", {"wskp6": "wskp"})
    monkeypatch.setattr(denoisers, "OIDN_JAX", False)
    monkeypatch.setattr(denoisers, "DC_BASE", "wskp-6")
    monkeypatch.setattr(denoisers, "NJS_BASE", "wskp-6")
    result = run_json("denoisers", capsys)
    keys = ("svgf", "svgf_step", "bmfr", "bmfr_step", "dc", "nfor", "njs", "statmc",
            "statmc_moon", "oidn")
    assert_ratios(result, [f"{key}_over_wskp6" for key in keys])
    for key in keys:
        assert result[f"{key}_over_wskp6"] == pytest.approx(result[f"{key}_s"]
                                                            / result["wskp6_s"])


@pytest.mark.slow  # every model initialised and compiled: ~1-3 min here
def test_denoisers_bench(tiny, capsys):
    from jaxden.bench import denoisers

    result = run_json("denoisers", capsys)
    assert_ratios(result, [f"{key}_over_oidn" for key in (*denoisers.MODELS, "oidnjax")]
                  + [f"{key}_over_kp" for key in denoisers.MODELS if key != "kp"])
    assert (result["width"], result["height"]) == FRAME_SIZE
    for key in (*denoisers.MODELS, "oidn"):
        assert result[f"{key}_s"] > 0
    assert result["wskp6_over_kp"] == pytest.approx(result["wskp6_s"] / result["kp_s"])
    assert 0 < result["wskp6_network_over_kp"] < result["wskp6_over_kp"]


@pytest.mark.slow  # a smoke test (10-20 s); experiments/run_benchmarks.sh runs the bench
def test_sure_bench(tiny, capsys):
    result = run_json("sure", capsys)
    assert_ratios(result, ["jvp_k1_over_forward", "jvp_over_fd_k4"])
    assert (result["width"], result["height"]) == FRAME_SIZE
    assert {"forward_s", "jvp_k1_s", "jvp_k4_s", "fd_k4_s"} <= set(result)
    assert result["denoiser"] == "wskp3 (3 layers, deploy form)"


@pytest.mark.slow  # a smoke test (10-20 s); experiments/run_benchmarks.sh runs the bench
def test_progressive_bench(tiny, capsys):
    result = run_json("progressive", capsys)
    assert_ratios(result, ["pd_over_oidn", "pd_single_over_oidn", "mixer_over_oidn",
                           "tstat_over_oidn", "guard_over_oidn", "closed_form_over_oidn",
                           "closed_form_stops_over_closed_form", "guard_strata_over_guard",
                           "pd_wskp6_over_wskp6",
                           "pd_wskp6_closed_form_k1_over_wskp6", "pd_oidnjax_over_oidn",
                           "oidnjax_over_oidn", "oidnjax_sure_over_oidn",
                           "oidnjax_mixer_over_oidn", "oidnjax_tstat_over_oidn"])
    assert (result["width"], result["height"]) == FRAME_SIZE and result["mixer"] == "oidn-pd"
    # PD around a JAX base does at least the base's own forward
    assert result["pd_wskp6_s"] > result["wskp6_s"]
    assert result["pd_oidnjax_s"] > result["oidnjax_s"]
    assert result["pd_oidnjax_sure"] == "jvp, 1 rademacher probe"


def test_render_bench(tiny, capsys):
    result = run_json("render", capsys)
    assert_ratios(result, ["ratio", "cpu_ratio", "ratio_legacy_features",
                           "cpu_ratio_legacy_features"])
    assert result["size"] == "16x16" and result["spp"] == 2 and result["scene"] == "cornell-box"


@pytest.mark.slow  # two subprocesses each compile a U-Net / WSKP-6 train step: ~50-90 s here
def test_sharding_bench(tiny, capsys):
    result = run_json("sharding", capsys)
    assert_ratios(result, ["ratio", "unet_ratio", "wskp_ratio"])
    assert result["ratio"] == result["unet_ratio"]
    assert (result["batch"], result["size"], result["devices"]) == (2, 16, 2)
