"""An output path that is one of the command's inputs is refused with one line (the input is
left byte for byte unchanged), also through a symbolic link, a hard link or another spelling
of the path, unless --overwrite-input is given."""

from __future__ import annotations

import os

import numpy as np
import pytest

from jaxden import cli
from jaxden.io.exr import read_frame, write_frame
from jaxden.render.synthetic import synthetic_render


@pytest.fixture()
def render(tmp_path):
    path = tmp_path / "f.exr"
    write_frame(path, synthetic_render("overwrite", 16, seed=1, size=(12, 10)).numpy())
    return path


def _spellings(path, kind):
    if kind == "same":
        return path
    if kind == "dotted":
        return path.parent / "." / path.name
    if kind == "symlink":
        link = path.parent / "link.exr"
        link.symlink_to(path)
        return link
    link = path.parent / "hard.exr"
    os.link(path, link)
    return link


def _run(capsys, argv):
    capsys.readouterr()
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("kind", ["same", "dotted", "symlink", "hardlink"])
@pytest.mark.parametrize("command", [
    ["denoise", "{in}", "--model", "oidn", "--out", "{out}"],
    ["sure", "{in}", "--denoiser", "oidn", "--probes", "1", "--out", "{out}"],
    ["progressive", "{in}", "--denoiser", "oidn", "--mixer", "closed-form", "--out", "{out}"],
    ["progressive", "{in}", "--denoiser", "oidn", "--mixer", "closed-form", "--out",
     "{other}", "--alpha", "{out}"],
])
def test_output_equal_to_input_is_refused(render, capsys, kind, command):
    before = render.read_bytes()
    out = _spellings(render, kind)
    argv = [w.format(**{"in": render, "out": out, "other": render.parent / "z.exr"})
            for w in command]
    code, err = _run(capsys, argv)
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("jaxden: error: ") and "--overwrite-input" in err[0]
    assert render.read_bytes() == before
    assert not (render.parent / "z.exr").exists()


def test_overwrite_input_flag_allows_it(render, capsys):
    code, err = _run(capsys, ["denoise", render, "--model", "oidn", "--out", render,
                              "--overwrite-input"])
    assert code == 0, err
    frame = read_frame(render)
    assert frame.variance is None and np.isfinite(frame.color).all()  # replaced, as asked


def test_sure_buffer_as_output_is_refused(render, tmp_path, capsys):
    buffer = tmp_path / "b0.exr"
    buffer.write_bytes(render.read_bytes())
    code, err = _run(capsys, ["sure", render, "--denoiser", "oidn", "--buffers", buffer,
                              buffer, "--out", buffer])
    assert code == 2 and "is the input file" in err[0]
