"""The `jaxden` command end to end (in-process), including its one-line user errors."""

import json
import subprocess
import sys

import numpy as np
import pytest

from jaxden.cli import main
from jaxden.io.exr import read_frame, read_header, read_image


def test_render_writes_every_feature_channel(tmp_path, capsys):
    out = tmp_path / "f.exr"
    assert main(["render", "cornell-box", "--spp", "16", "--size", "64x64", "--out", str(out)]) == 0
    channels = set(read_header(out)["channels"])
    for name in ("R", "G", "B", "variance.R", "variance.G", "variance.B", "albedo.R", "albedo.G",
                 "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth.Z"):
        assert name in channels
    frame = read_frame(out, require=("color", "variance", "albedo", "normal", "depth"))
    assert frame.color.shape == (64, 64, 3) and float(frame.spp) == 16
    assert "wrote" in capsys.readouterr().out


def test_render_aux_specular_chain_is_recorded_and_changes_the_albedo(tmp_path):
    first, chain = tmp_path / "first.exr", tmp_path / "chain.exr"
    common = ["render", "glossy-glass", "--spp", "4", "--size", "32x32", "--seed", "3"]
    assert main(common + ["--aux", "first-hit", "--out", str(first)]) == 0
    assert main(common + ["--feature-spp", "2", "--out", str(chain)]) == 0
    assert (read_header(first)["aux"], read_header(first)["feature_spp"]) == ("first-hit", 4)
    assert (read_header(chain)["aux"], read_header(chain)["feature_spp"]) == ("specular-chain", 2)
    a, b = read_frame(first), read_frame(chain)
    np.testing.assert_array_equal(a.color, b.color)
    assert np.abs(a.albedo - b.albedo).max() > 0.1


def test_render_buffers_then_sure_from_buffers(tmp_path, capsys):
    """`jaxden render --buffers 4` writes 4 sub-buffers and their combination, which
    `jaxden sure --buffers` accepts."""
    out = tmp_path / "f.exr"
    assert main(["render", "cornell-box", "--spp", "8", "--size", "16x16", "--buffers", "4",
                 "--seed", "3", "--out", str(out)]) == 0
    buffers = [tmp_path / f"f.b{k}.exr" for k in range(4)]
    parts = [read_frame(b) for b in buffers]
    full = read_frame(out)
    assert float(full.spp) == 8 and all(float(p.spp) == 2 for p in parts)
    assert [read_header(b)["seed"] for b in buffers] == [12, 13, 14, 15]
    np.testing.assert_allclose(full.color, np.mean([p.color for p in parts], axis=0),
                               rtol=1e-5, atol=1e-7)
    capsys.readouterr()
    sure_out = tmp_path / "s.exr"
    assert main(["sure", str(out), "--buffers", *map(str, buffers), "--denoiser", "oidn",
                 "--out", str(sure_out)]) == 0
    assert "4 buffers" in capsys.readouterr().out
    assert main(["render", "cornell-box", "--spp", "6", "--buffers", "4",
                 "--out", str(tmp_path / "g.exr")]) == 2
    assert "--buffers 4" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["render", "no-such-scene", "--spp", "4", "--out", "x.exr"], "unknown scene 'no-such-scene'"),
        (["render", "missing.xml", "--spp", "4", "--out", "x.exr"], "missing.xml"),
        (["render", "procedural:abc", "--spp", "4", "--out", "x.exr"], "procedural"),
        (["render", "cornell-box", "--spp", "4", "--out", "x.png"], "must name an .exr"),
        (["denoise", "absent.exr", "--model", "oidn", "--out", "y.exr"], "absent.exr: no such file"),
        (["denoise", "absent.exr", "--model", "wskp", "--out", "y.exr"], "needs trained weights"),
        (["dataset", "verify", "no-such-dir"], "no-such-dir"),
        (["bench", "nonsense"], "unknown benchmark 'nonsense'"),
    ],
)
def test_user_errors_are_one_line_and_exit_2(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxden: error:") and message in err and "\n" not in err, err


@pytest.mark.parametrize("argv", [["render", "cornell-box", "--spp", "0", "--out", "x.exr"],
                                  ["render", "cornell-box", "--spp", "4", "--size", "64", "--out", "x.exr"]])
def test_argument_errors_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2


def test_config_key_error_names_key_and_file(tmp_path, capsys):
    config = tmp_path / "bad.toml"
    config.write_text('scenes = ["cornell-box"]\ncrop_sise = 32\n')
    assert main(["dataset", "build", str(config), "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "crop_sise" in err and "bad.toml" in err and "crop_size" in err


def test_overrides_are_taken_after_options_too(tmp_path, capsys):
    """`jaxden dataset build CONFIG --out DIR key=value` (the order the dataset configs document)
    applies the override just as `CONFIG key=value --out DIR` does: a bad key is reported by
    the config loader, naming it, in both orders; a stray word is an argparse error."""
    config = "experiments/configs/dataset-tiny.toml"
    out = str(tmp_path / "d")
    for argv in (["dataset", "build", config, "--out", out, "crop_sise=32"],
                 ["dataset", "build", config, "crop_sise=32", "--out", out]):
        assert main(argv) == 2
        assert "crop_sise" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["dataset", "build", config, "--out", out, "stray"])
    assert "unrecognized arguments: stray" in capsys.readouterr().err


def test_dataset_build_verify_and_denoise_with_oidn(tmp_path, capsys):
    out = tmp_path / "tiny"
    assert main(["dataset", "build", "experiments/configs/dataset-tiny.toml", "--out", str(out),
                 "--workers", "1"]) == 0
    assert main(["dataset", "verify", str(out)]) == 0
    manifest = json.loads((out / "manifest.json").read_text())
    item = next(i for i in manifest["items"] if i["spp"] == 8)
    noisy = out / item["path"]
    denoised = tmp_path / "den.exr"
    assert main(["denoise", str(noisy), "--model", "oidn", "--out", str(denoised)]) == 0
    image = read_image(denoised)
    assert image.shape == read_frame(noisy).color.shape and np.isfinite(image).all()
    # Corrupt one file: verify reports it and exits 1.
    noisy.write_bytes(noisy.read_bytes()[:100])
    assert main(["dataset", "verify", str(out)]) == 1
    assert "PROBLEM" in capsys.readouterr().out


def test_console_script_is_installed():
    result = subprocess.run([sys.executable, "-m", "jaxden.cli", "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "render" in result.stdout and "dataset" in result.stdout


def test_version(capsys):
    from jaxden import __version__

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0 and capsys.readouterr().out.strip() == f"jaxden {__version__}"



def test_sure_cache_takes_the_sure_settings_flags():
    """`jaxden dataset sure-cache` reads its SURE options as one SureSettings, through the
    same flags as `jaxden sure` (unset: the mixer's defaults)."""
    from jaxden.cli import build_parser
    from jaxden.cli.options import sure_settings
    from jaxden.sure import SureSettings

    args = build_parser().parse_args(["dataset", "sure-cache", "D", "--denoiser", "oidn",
                                      "--probes", "2", "--covariance", "--seed", "3"])
    assert sure_settings(args) == SureSettings(probes=2, covariance=True, seed=3)
    args = build_parser().parse_args(["dataset", "sure-cache", "D", "--denoiser", "oidn"])
    assert sure_settings(args) == SureSettings()
