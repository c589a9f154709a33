"""The frame-size benchmarks (``jaxden bench progressive|denoisers --size WxH,...``,
jaxden/bench/frames.py): each command in its own process, wall time and peak RSS per
megapixel, ratios against ``jaxden denoise --model oidn`` at the same size.

One test runs the real ``jaxden denoise --model oidn`` once at 96 x 64 (one JAX child, ~5-10 s
here); the rest of the bookkeeping (ratios, size scaling, a failing command, the table) runs
with cheap stand-in commands (``python -c``). No timing is asserted.
"""

from __future__ import annotations

import json
import sys

import pytest
from helpers import assert_one_error_line, run_cli

from jaxden import bench
from jaxden.bench import BENCH_FRAME_ENV, frames

PER_COMMAND = ("s", "gb", "cpu_s", "status", "s_per_mp", "gb_per_mp")


@pytest.fixture(scope="module")
def frame_file(tmp_path_factory):
    from jaxden.io.exr import write_frame
    from jaxden.render.synthetic import synthetic_render

    path = tmp_path_factory.mktemp("frames") / "frame.exr"
    write_frame(path, synthetic_render("bench", 4, seed=1, size=(32, 24)))
    return path


@pytest.fixture
def synthetic(monkeypatch, frame_file):
    """The bench frame tiled from a 32 x 24 synthetic one (no Mitsuba render)."""
    monkeypatch.setenv(BENCH_FRAME_ENV, str(frame_file))
    return frame_file


def python(code: str):
    """A stand-in command: ``python -c CODE`` (it is given the input and output paths)."""
    return lambda source, out: [sys.executable, "-c", code, source, out]


def run_json(capsys, name, sizes, quick=True) -> dict:
    capsys.readouterr()
    result = bench.run(name, as_json=True, quick=quick, sizes=sizes)
    out = capsys.readouterr().out
    printed = json.loads(out)  # the JSON alone; the table on stderr
    assert printed == json.loads(json.dumps(result, sort_keys=True, default=str))
    assert printed["bench"] == name
    return printed


def test_denoise_oidn_at_one_small_size(synthetic, capsys, monkeypatch):
    oidn = frames.COMMANDS["denoisers"]["oidn"]
    monkeypatch.setitem(frames.COMMANDS, "denoisers", {"oidn": oidn})
    result = run_json(capsys, "denoisers", [(96, 64)])
    prefix = "oidn_96x64"
    for metric in PER_COMMAND:
        assert f"{prefix}_{metric}" in result, (metric, sorted(result))
    assert result[f"{prefix}_status"] == 0, result.get(f"{prefix}_error")
    assert result[f"{prefix}_gb"] > 0 and result[f"{prefix}_s"] > 0
    mp = 96 * 64 / 1e6
    assert result[f"{prefix}_s_per_mp"] == pytest.approx(result[f"{prefix}_s"] / mp)
    assert result[f"{prefix}_gb_per_mp"] == pytest.approx(result[f"{prefix}_gb"] / mp)
    assert (result["sizes"], result["commands"], result["runs"]) == ("96x64", "oidn", 1)
    assert "32x24" in result["frame_source"] and result["cpus"] >= 1 and result["ram_gb"] > 0
    assert "device_count" not in result["xla_flags"]  # the children get JAX's default devices


def test_ratios_scaling_and_a_failing_command(synthetic, capsys, monkeypatch):
    """Stand-ins: the peer holds ~50 MB, 'big' ~150 MB more, 'fail' exits 3 with a message;
    1920x1080 is played by 32x24."""
    monkeypatch.setitem(frames.COMMANDS, "progressive", {
        "oidn": python("x = bytearray(50_000_000)"),
        "big": python("x = bytearray(200_000_000)"),
        "fail": python("import sys; sys.exit('boom: the frame is too big')"),
    })
    monkeypatch.setattr(frames, "REFERENCE_SIZE", (32, 24))
    monkeypatch.setenv("JAXDEN_MEMORY_LIMIT", "4G")
    result = run_json(capsys, "progressive", [(32, 24), (64, 48), (32, 24)])
    assert (result["sizes"], result["commands"]) == ("32x24,64x48", "oidn,big,fail")
    for size in ("32x24", "64x48"):
        assert result[f"big_{size}_gb"] > result[f"oidn_{size}_gb"] + 0.1
        assert result[f"big_over_oidn_time_{size}"] == pytest.approx(
            result[f"big_{size}_s"] / result[f"oidn_{size}_s"])
        assert result[f"big_over_oidn_memory_{size}"] > 1
        assert result[f"fail_{size}_status"] == 1
        assert result[f"fail_{size}_error"] == "boom: the frame is too big"
        assert f"fail_{size}_s_per_mp" not in result and f"fail_over_oidn_time_{size}" not in result
    ratio = result["big_time_per_mp_64x48_over_32x24"]
    assert ratio == pytest.approx(result["big_64x48_s_per_mp"] / result["big_32x24_s_per_mp"])
    assert "big_memory_per_mp_64x48_over_32x24" in result
    assert "big_marginal_gb_per_mp_32x24_to_64x48" in result
    assert not any(key.startswith("fail_") and "_per_mp" in key for key in result)
    assert result["JAXDEN_MEMORY_LIMIT"] == "4G"
    capsys.readouterr()
    bench.run("progressive", quick=True, sizes=[(32, 24)])
    table = capsys.readouterr().out.splitlines()
    assert table[0] == "benchmark progressive (sizes 32x24) (quick)"
    assert "peak GB" in table[1] and "GB/MP" in table[1]
    rows = {line.split()[1]: line for line in table[2:5]}
    assert set(rows) == {"oidn", "big", "fail"}
    assert rows["fail"].rstrip().endswith("1: boom: the frame is too big")


def test_runs_report_the_last_and_the_first(synthetic, capsys, monkeypatch):
    monkeypatch.setitem(frames.COMMANDS, "denoisers", {"oidn": python("pass")})
    monkeypatch.setattr(frames, "RUNS", 2)
    result = run_json(capsys, "denoisers", [(16, 16)], quick=False)
    assert result["runs"] == 2
    assert {"oidn_16x16_first_s", "oidn_16x16_first_gb", "oidn_16x16_s"} <= set(result)


def test_a_command_past_the_timeout_is_stopped_and_recorded(synthetic, capsys, monkeypatch):
    monkeypatch.setitem(frames.COMMANDS, "denoisers", {"oidn": python("import time; "
                                                                      "time.sleep(60)")})
    monkeypatch.setattr(frames, "TIMEOUT_S", 1.0)
    result = run_json(capsys, "denoisers", [(16, 16)])
    assert result["oidn_16x16_status"] == -9 and result["oidn_16x16_s"] < 30
    assert result["oidn_16x16_error"] == "stopped after 1 s (TIMEOUT_S)"


@pytest.mark.slow  # two JAX children, PD compiles: ~30-60 s here
def test_progressive_commands_at_one_small_size(synthetic, capsys):
    result = run_json(capsys, "progressive", [(64, 48)])
    assert result["commands"] == "oidn,pd_oidn,pd_wskp6"
    for key in ("oidn", "pd_oidn"):
        assert result[f"{key}_64x48_status"] == 0, result.get(f"{key}_64x48_error")
        assert result[f"{key}_64x48_gb"] > 0
    assert result["pd_oidn_over_oidn_time_64x48"] > 0


@pytest.mark.parametrize("text, words", [
    ("12x", ["--size", "'12x'"]),
    ("0x10", ["--size", "positive", "'0x10'"]),
    ("96x64,abc", ["--size", "'abc'"]),
    ("1x2x3", ["--size", "'1x2x3'"]),
])
def test_bad_sizes_are_one_line_errors(text, words, capsys):
    assert_one_error_line(*run_cli(["bench", "progressive", "--size", text], capsys)[:2], *words)


def test_size_is_refused_by_benchmarks_without_it(capsys):
    code, lines, _ = run_cli(["bench", "render", "--size", "64x64"], capsys)
    assert_one_error_line(code, lines, "'render' takes no sizes", "denoisers, progressive")


def test_parse_sizes():
    assert frames.parse_sizes("1280x720, 1920X1080,1280x720") == [(1280, 720), (1920, 1080)]
    for bad in ("", "12x", "x12", "0x10", "-4x4", "1280x720,"):
        with pytest.raises(ValueError):
            frames.parse_sizes(bad)


def test_tiled_frame_repeats_the_source(frame_file):
    import numpy as np

    from jaxden.io.exr import read_frame

    source = read_frame(frame_file)
    big = frames.tiled(source, (70, 30))
    assert big.color.shape == (30, 70, 3) and big.depth.shape == (30, 70, 1)
    np.testing.assert_array_equal(big.color[24:, 32:64], source.color[:6])
    np.testing.assert_array_equal(big.variance[:24, 64:], source.variance[:, :6])
    assert float(big.spp) == float(source.spp)
