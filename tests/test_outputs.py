"""Output files and failed starts: checked before any work, all or nothing, clear errors.

Commands that write several files (render --buffers, progressive --alpha) leave all or none;
output paths the OS refuses give one-line errors naming the path; a training run whose config
fails leaves no workdir behind; values that do not fit the chosen precision are refused.
"""

import os
from pathlib import Path

import numpy as np
import pytest

from jaxden.cli import main
from jaxden.errors import ExrError, FrameError, OutputError
from jaxden.fileio import all_or_nothing, atomic_write_text, check_outputs
from jaxden.frame import Frame
from jaxden.io.exr import read_frame, write_channels, write_frame
from jaxden.sure.buffers import sure_buffers


def _files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ------------------------------------------------------------------------------ fileio


def test_check_outputs_refuses_folders_duplicates_and_missing_parents(tmp_path):
    (tmp_path / "d.exr").mkdir()
    ok = tmp_path / "a.exr"
    assert check_outputs(("--out", ok)) == [ok]
    with pytest.raises(OutputError, match=r"--out .*d\.exr: is a folder"):
        check_outputs(("--out", tmp_path / "d.exr"))
    with pytest.raises(OutputError, match=r"--alpha .*a\.exr: the same file as --out"):
        check_outputs(("--out", ok), ("--alpha", tmp_path / "." / "a.exr"))
    with pytest.raises(OutputError, match="folder .*nope does not exist"):
        check_outputs(("--out", tmp_path / "nope" / "a.exr"))
    (tmp_path / "plain").write_text("x")
    with pytest.raises(OutputError, match="does not exist"):
        check_outputs(("--out", tmp_path / "plain" / "a.exr"))


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_check_outputs_refuses_a_read_only_folder(tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="no permission"):
            check_outputs(("--out", locked / "a.exr"))
    finally:
        locked.chmod(0o755)


def test_atomic_write_onto_a_folder_is_an_output_error(tmp_path):
    (tmp_path / "x.txt").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        atomic_write_text(tmp_path / "x.txt", "data")
    with pytest.raises(OutputError, match="cannot write"):
        atomic_write_text(tmp_path / "missing" / "x.txt", "data")
    assert _files(tmp_path) == ["x.txt"]  # no temporary file left


def test_all_or_nothing_removes_what_the_block_wrote(tmp_path):
    with pytest.raises(RuntimeError), all_or_nothing():
        atomic_write_text(tmp_path / "a.txt", "a")
        atomic_write_text(tmp_path / "b.txt", "b")
        raise RuntimeError("the third write failed")
    assert _files(tmp_path) == []
    with all_or_nothing():
        atomic_write_text(tmp_path / "a.txt", "a")
    assert _files(tmp_path) == ["a.txt"]  # kept when the block succeeds


# ------------------------------------------------------------------------------ EXR


def test_half_precision_overflow_is_refused_and_writes_nothing(tmp_path):
    color = np.full((4, 5, 3), 2.0, np.float32)
    color[1, 2, 0] = 1e5  # beyond float16's 65504
    frame = Frame(color=color, variance=np.zeros_like(color))
    with pytest.raises(ExrError, match=r"'R' has 1 value\(s\) beyond the float16 range.*1e\+05"):
        write_frame(tmp_path / "f.exr", frame, half=True)
    assert _files(tmp_path) == []
    write_frame(tmp_path / "f.exr", frame)  # float32 holds it
    assert read_frame(tmp_path / "f.exr").color.max() == pytest.approx(1e5)


@pytest.mark.parametrize("spp", [0, -4])
def test_sample_variance_with_a_non_positive_spp_is_named(tmp_path, spp):
    plane = np.ones((3, 4), np.float32)
    path = tmp_path / "s.exr"
    write_channels(path, {"R": plane, "G": plane, "B": plane, "variance.R": plane,
                          "variance.G": plane, "variance.B": plane}, attributes={"spp": spp})
    with pytest.raises(ExrError, match=f"jaxden.spp must be a positive sample count, got {spp}"):
        read_frame(path, variance_is_sample_variance=True)
    with pytest.raises(ExrError, match="spp= must be a positive sample count"):
        read_frame(path, variance_is_sample_variance=True, spp=0.0)


# ------------------------------------------------------------------------------ sub-buffers


def test_sub_buffers_must_be_distinct_and_of_equal_spp():
    rng = np.random.default_rng(0)
    parts = [rng.uniform(0, 1, (6, 5, 3)).astype(np.float32) for _ in range(3)]
    twice = [parts[0], parts[0], parts[1]]
    frame = Frame(color=np.mean(twice, axis=0), variance=np.full((6, 5, 3), 0.01, np.float32))
    with pytest.raises(FrameError, match="sub-buffers 0 and 1 are identical"):
        sure_buffers(lambda f: np.asarray(f.color), frame, np.stack(twice))
    frames = [Frame(color=p, spp=np.float32(s)) for p, s in zip(parts, (4, 4, 8))]
    full = Frame(color=np.mean(parts, axis=0), variance=np.full((6, 5, 3), 0.01, np.float32))
    with pytest.raises(FrameError, match=r"equal spp, got \[4.0, 8.0\]"):
        sure_buffers(lambda f: np.asarray(f.color), full, frames)


def test_cli_sure_refuses_buffers_of_unequal_spp(tmp_path, capsys):
    rng = np.random.default_rng(1)
    parts = [rng.uniform(0, 1, (6, 5, 3)).astype(np.float32) for _ in range(2)]
    paths = []
    for i, (part, spp) in enumerate(zip(parts, (4, 8))):
        paths.append(tmp_path / f"b{i}.exr")
        write_frame(paths[-1], Frame(color=part, spp=np.float32(spp)))
    full = Frame(color=np.mean(parts, axis=0), variance=np.full((6, 5, 3), 0.01, np.float32),
                 albedo=np.ones((6, 5, 3), np.float32), normal=np.ones((6, 5, 3), np.float32))
    write_frame(tmp_path / "in.exr", full)
    code = main(["sure", str(tmp_path / "in.exr"), "--buffers", *map(str, paths),
                 "--denoiser", "oidn", "--out", str(tmp_path / "s.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "equal spp" in err and "b1.exr" in err
    assert not (tmp_path / "s.exr").exists()


# ------------------------------------------------------------------------------ CLI


def test_cli_output_problems_are_one_line_errors_before_any_work(tmp_path, capsys):
    (tmp_path / "d.exr").mkdir()
    code = main(["render", "cornell-box", "--spp", "4", "--size", "8x8",
                 "--out", str(tmp_path / "d.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "d.exr: is a folder" in err and "Traceback" not in err
    # render --buffers: a folder in the way of sub-buffer 1 stops it before anything is written
    (tmp_path / "f.b1.exr").mkdir()
    code = main(["render", "cornell-box", "--spp", "4", "--size", "8x8", "--buffers", "2",
                 "--out", str(tmp_path / "f.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "sub-buffer 1" in err and "f.b1.exr: is a folder" in err
    assert _files(tmp_path) == ["d.exr", "f.b1.exr"]
    # progressive: --alpha on the same path as --out
    code = main(["progressive", str(tmp_path / "in.exr"), "--denoiser", "oidn",
                 "--out", str(tmp_path / "o.exr"), "--alpha", str(tmp_path / "o.exr")])
    err = capsys.readouterr().err
    assert code == 2 and "--alpha" in err and "the same file as --out" in err
    # denoise now checks its output name like the other commands
    code = main(["denoise", str(tmp_path / "in.exr"), "--model", "oidn",
                 "--out", str(tmp_path / "o.png")])
    assert code == 2 and "must name an .exr" in capsys.readouterr().err


def test_cli_folder_that_cannot_be_made_is_named(tmp_path, capsys):
    (tmp_path / "plain").write_text("x")
    config = Path(__file__).parent.parent / "experiments" / "configs" / "dataset-tiny.toml"
    code = main(["dataset", "build", str(config), "--out", str(tmp_path / "plain" / "ds")])
    err = capsys.readouterr().err
    assert code == 2 and "plain" in err and "Traceback" not in err


def test_dataset_build_with_an_unknown_scene_leaves_no_folder(tmp_path, capsys):
    config = Path(__file__).parent.parent / "experiments" / "configs" / "dataset-tiny.toml"
    out = tmp_path / "ds"
    code = main(["dataset", "build", str(config), "--out", str(out), "scenes=['cornell-boks']"])
    err = capsys.readouterr().err
    assert code == 2 and "'scenes'" in err and "did you mean 'cornell-box'" in err
    assert not out.exists()
    code = main(["dataset", "verify", str(config)])
    assert code == 2 and "is a file, not a dataset folder" in capsys.readouterr().err


def test_failed_training_start_leaves_no_workdir(tmp_path, capsys):
    """A config that fails at start (here: no such dataset) must not leave a workdir whose
    recorded config then refuses the corrected command."""
    config = Path(__file__).parent.parent / "experiments" / "configs" / "mixer-tiny.toml"
    workdir = tmp_path / "run"
    code = main(["train", str(config), f"data.dataset={tmp_path / 'absent'}",
                 "--workdir", str(workdir)])
    assert code == 2 and "absent" in capsys.readouterr().err
    assert not workdir.exists()


def test_even_kernel_sizes_are_a_config_error():
    from jaxden.errors import ConfigError
    from jaxden.denoise.nn.wskp import KPConfig, WSKPConfig, WSKPMRConfig

    for make in (lambda: WSKPConfig(kernel_sizes=(3, 4)), lambda: WSKPMRConfig(kernel_sizes=()),
                 lambda: KPConfig(kernel_size=6)):
        with pytest.raises(ConfigError, match="kernel sizes must be odd"):
            make()


def test_model_config_errors_name_the_file(tmp_path, capsys):
    source = Path(__file__).parent.parent / "experiments" / "configs" / "train-wskp.toml"
    bad = tmp_path / "bad.toml"
    bad.write_text(source.read_text() + "\n")
    code = main(["train", str(bad), "model_config.widht=8", "--workdir", str(tmp_path / "w")])
    err = capsys.readouterr().err
    assert code == 2 and "bad.toml" in err and "widht" in err and "model_config" in err
    code = main(["train", str(bad), "model=wskpp", "--workdir", str(tmp_path / "w")])
    err = capsys.readouterr().err
    assert code == 2 and "bad.toml" in err and "model = 'wskpp'" in err
    assert not (tmp_path / "w").exists()


def test_multi_part_exr_with_variance_in_a_later_part_is_read(tmp_path, capsys):
    """Every part of a multi-part file is read (the variance here lives in the second)."""
    import OpenEXR

    plane = np.ones((4, 5), np.float32)
    def header():
        return {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION}

    parts = [OpenEXR.Part(header(), {c: plane.copy() for c in "RGB"}, "color"),
             OpenEXR.Part(header(), {f"variance.{c}": plane.copy() for c in "RGB"}, "variance")]
    path = tmp_path / "multi.exr"
    OpenEXR.File(parts).write(str(path))
    code = main(["sure", str(path), "--denoiser", "oidn", "--out", str(tmp_path / "s.exr")])
    assert code == 0, capsys.readouterr().err
    assert (tmp_path / "s.exr").exists()
