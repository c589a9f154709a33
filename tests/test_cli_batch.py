"""`jaxden denoise` and `jaxden progressive` over several inputs: a batch into --out-dir gives
the images one-by-one runs give, with the denoiser loaded and compiled once; --sequence
carries a temporal denoiser's history; what cannot work is one error line before any file is
written, and --skip-existing resumes a batch."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_one_error_line, run_cli

from jaxden.denoise.registry import REGISTRY, Denoiser, load_denoiser
from jaxden.io.exr import read_channels, read_frame, read_image, write_frame
from jaxden.render.synthetic import synthetic_render

SIZE = (16, 12)  # (width, height): compiles, not runs, set the time


@pytest.fixture()
def frames(tmp_path):
    """Three small renders of one scene (seeds 0..2) in tmp_path/in."""
    folder = tmp_path / "in"
    folder.mkdir()
    paths = []
    for seed in range(3):
        path = folder / f"f{seed}.exr"
        write_frame(path, synthetic_render("batch", 4, seed=seed, size=SIZE).numpy())
        paths.append(path)
    return paths


@pytest.fixture()
def blur(monkeypatch):
    """Registers ``batch-blur`` (a 3-row box filter, differentiable JAX) for the test; with
    ``radius`` it runs over tiles. Returns the count of its traces (compilations)."""
    traces = {"count": 0}

    def register(radius: int | None = 1):
        def batch_blur(frame):
            traces["count"] += 1  # Python runs only while JAX traces
            padded = jnp.pad(frame.color, ((1, 1), (0, 0), (0, 0)), mode="edge")
            return (padded[:-2] + padded[1:-1] + padded[2:]) / 3

        denoiser = Denoiser.from_function(batch_blur, name="batch-blur", radius=radius)
        monkeypatch.setitem(REGISTRY, "batch-blur", denoiser.definition)
        return traces

    return register


def _denoise(capsys, inputs, *options):
    return run_cli(["denoise", *inputs, *options], capsys)


def test_a_batch_writes_what_one_by_one_runs_write(tmp_path, frames, blur, capsys):
    blur(radius=1)
    code, lines, out = _denoise(capsys, frames, "--model", "batch-blur", "--out-dir",
                                tmp_path / "out")
    assert code == 0, lines
    assert [line.split(" -> ")[0] for line in lines] == [
        f"jaxden: [{k}/3] {path}" for k, path in enumerate(frames, 1)]
    assert out.strip() == f"wrote 3 files into {tmp_path / 'out'} (denoised by batch-blur)"
    for path in frames:
        single = tmp_path / f"single-{path.name}"
        code, lines, out = _denoise(capsys, [path], "--model", "batch-blur", "--out", single)
        assert code == 0 and lines == [] and out.strip() == (
            f"wrote {single} (denoised by batch-blur)")
        np.testing.assert_array_equal(read_image(tmp_path / "out" / path.name),
                                      read_image(single))
        assert read_channels(tmp_path / "out" / path.name)[1]["source"] == str(path)


@pytest.mark.parametrize("radius", [None, 1])
def test_a_batch_compiles_once_per_frame_size(tmp_path, frames, blur, capsys, radius):
    """Three frames of one size and one of another: two traces of the denoiser, not four;
    over tiles (radius) as on whole frames."""
    traces = blur(radius=radius)
    other = tmp_path / "other" / "g.exr"
    other.parent.mkdir()
    write_frame(other, synthetic_render("batch", 4, seed=5, size=(20, 12)).numpy())
    code, lines, _ = _denoise(capsys, [*frames, other], "--model", "batch-blur", "--out-dir",
                              tmp_path / "out")
    assert code == 0, lines
    assert traces["count"] == 2


def test_a_sequence_carries_the_history(tmp_path, frames, capsys):
    """--sequence with svgf equals Denoiser.sequence over the frames as read; the batch form
    (each frame alone, with one note saying --sequence would carry the history) differs."""
    code, lines, out = _denoise(capsys, frames, "--model", "svgf", "--sequence", "--out-dir",
                                tmp_path / "seq")
    assert code == 0, lines
    assert "its history carried through the sequence" in out
    expected = load_denoiser("svgf").sequence([read_frame(path) for path in frames])
    got = [read_image(tmp_path / "seq" / path.name) for path in frames]
    for image, want in zip(got, expected):
        np.testing.assert_array_equal(image, np.asarray(want))
    code, lines, _ = _denoise(capsys, frames, "--model", "svgf", "--out-dir", tmp_path / "alone")
    assert code == 0, lines
    notes = [line for line in lines if "--sequence" in line]
    assert len(notes) == 1 and notes[0].startswith("jaxden: note: svgf has a temporal form")
    alone = [read_image(tmp_path / "alone" / path.name) for path in frames]
    assert np.abs(got[-1] - alone[-1]).max() > 1e-3


def test_a_sequence_of_frames_of_another_size_is_one_line(tmp_path, frames, capsys):
    odd = tmp_path / "odd" / "f9.exr"
    odd.parent.mkdir()
    write_frame(odd, synthetic_render("batch", 4, seed=9, size=(20, 12)).numpy())
    code, lines, _ = _denoise(capsys, [*frames[:2], odd, frames[2]], "--model", "svgf",
                              "--sequence", "--out-dir", tmp_path / "out")
    assert_one_error_line(code, lines, str(odd), "20x12", "16x12")
    assert not (tmp_path / "out").exists()


def test_a_sequence_that_would_need_tiles_is_one_line(tmp_path, frames, capsys):
    """A history is carried over whole frames: a step over the memory limit is refused before
    the first frame is written (and the output folder made for it is gone again)."""
    code, lines, _ = _denoise(capsys, frames, "--model", "svgf", "--sequence", "--out-dir",
                              tmp_path / "out" / "seq", "--memory-limit", "200K")
    assert_one_error_line(code, lines, str(frames[0]), "cannot run in tiles", "--memory-limit")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", ["two names", "--out", "neither", "input as output"])
def test_outputs_that_cannot_work_are_one_line_and_nothing_is_written(tmp_path, frames, case,
                                                                     capsys):
    twin = tmp_path / "twin" / frames[0].name
    twin.parent.mkdir()
    twin.write_bytes(frames[0].read_bytes())
    before = {path: path.read_bytes() for path in (*frames, twin)}
    options, words = {
        "two names": ([*frames, twin, "--out-dir", tmp_path / "out"],
                      (str(frames[0]), str(twin), "same file name")),
        "--out": ([*frames, "--out", tmp_path / "out" / "x.exr"], ("--out-dir", "3 inputs")),
        "neither": ([*frames], ("--out-dir", "--out")),
        "input as output": ([*frames, "--out-dir", frames[0].parent],
                            ("--overwrite-input", str(frames[0]))),
    }[case]
    code, lines, _ = _denoise(capsys, options, "--model", "svgf")
    assert_one_error_line(code, lines, *words)
    assert not (tmp_path / "out").exists()
    assert {path: path.read_bytes() for path in before} == before
    assert sorted(p.name for p in frames[0].parent.iterdir()) == ["f0.exr", "f1.exr", "f2.exr"]


def test_skip_existing_resumes_a_batch(tmp_path, frames, blur, capsys):
    traces = blur(radius=None)
    out = tmp_path / "out"
    assert _denoise(capsys, frames, "--model", "batch-blur", "--out-dir", out)[0] == 0
    assert traces["count"] == 1
    kept = {path.name: path.stat().st_mtime_ns for path in out.iterdir()}
    first = read_image(out / "f1.exr")
    (out / "f1.exr").unlink()  # as an interrupted batch leaves it: f0 and f2 whole, f1 absent
    code, lines, said = _denoise(capsys, frames, "--model", "batch-blur", "--out-dir", out,
                                 "--skip-existing")
    assert code == 0, lines
    assert sum("skipped (--skip-existing)" in line for line in lines) == 2
    assert said.strip().endswith("skipped 2 that exist (--skip-existing)")
    np.testing.assert_array_equal(read_image(out / "f1.exr"), first)
    for name in ("f0.exr", "f2.exr"):
        assert (out / name).stat().st_mtime_ns == kept[name]
    assert traces["count"] == 2  # a new command, a new compile; for f1 alone
    code, lines, _ = _denoise(capsys, frames, "--model", "svgf", "--sequence", "--out-dir",
                              tmp_path / "seq", "--skip-existing")
    assert_one_error_line(code, lines, "--skip-existing", "history")
    assert not (tmp_path / "seq").exists()


def test_progressive_batch_equals_one_by_one(tmp_path, frames, blur, capsys):
    blur(radius=1)
    common = ["--denoiser", "batch-blur", "--mixer", "closed-form", "--probes", "1"]
    code, lines, out = run_cli(["progressive", *frames[:2], *common, "--out-dir",
                                tmp_path / "pd", "--alpha-dir", tmp_path / "alpha"], capsys)
    assert code == 0, lines
    assert out.strip().endswith(f"; alpha in {tmp_path / 'alpha'}")
    for path in frames[:2]:
        z, alpha = tmp_path / f"z-{path.name}", tmp_path / f"a-{path.name}"
        code, lines, _ = run_cli(["progressive", path, *common, "--out", z, "--alpha", alpha],
                                 capsys)
        assert code == 0, lines
        np.testing.assert_array_equal(read_image(tmp_path / "pd" / path.name), read_image(z))
        assert read_channels(tmp_path / "alpha" / path.name)[0].keys() == \
            read_channels(alpha)[0].keys()
        for name, array in read_channels(alpha)[0].items():
            np.testing.assert_array_equal(read_channels(tmp_path / "alpha" / path.name)[0][name],
                                          array)
    code, lines, _ = run_cli(["progressive", *frames[:2], *common, "--out-dir", tmp_path / "b",
                              "--buffers", frames[2], frames[2]], capsys)
    assert_one_error_line(code, lines, "--buffers", "2 inputs")
    assert not (tmp_path / "b").exists()


def test_progressive_batch_compiles_once(tmp_path, frames, blur, capsys, monkeypatch):
    """Nothing is compiled after the first of two frames of one size (JAX's compile log)."""
    import logging
    import sys

    import jax

    from jaxden.cli import batch, denoise

    events: list[str] = []

    class Record(logging.Handler):
        def emit(self, record):
            events.append(record.getMessage())

    def say(message):
        events.append(message)
        print(message, file=sys.stderr)

    monkeypatch.setattr(denoise, "stderr", say)
    monkeypatch.setattr(batch, "stderr", say)
    handler = Record()
    logger = logging.getLogger("jax")
    logger.addHandler(handler)
    blur(radius=1)
    try:
        with jax.log_compiles(True):
            code, lines, _ = run_cli(["progressive", *frames[:2], "--denoiser", "batch-blur",
                                      "--mixer", "closed-form", "--probes", "1", "--out-dir",
                                      tmp_path / "two"], capsys)
    finally:
        logger.removeHandler(handler)
    assert code == 0, lines
    first = next(i for i, event in enumerate(events) if event.startswith("jaxden: [1/2]"))
    assert any(event.startswith("Compiling") for event in events[:first])
    assert [event for event in events[first:] if event.startswith("Compiling")] == []


def test_the_emission_note_is_said_once_for_a_batch(tmp_path, capsys):
    """Cycles frames with an Emission pass run with emission=separate: one note for the batch,
    and each image as the explicit spec gives it."""
    from pathlib import Path

    cycles = Path(__file__).parent / "data" / "cycles"
    renders = [cycles / f"passes-seed{seed}.exr" for seed in (1, 2)]
    code, lines, _ = _denoise(capsys, renders, "--from", "cycles", "--model", "oidn",
                              "--out-dir", tmp_path / "default")
    assert code == 0, lines
    notes = [line for line in lines if "kept out of the filter" in line]
    assert len(notes) == 1 and notes[0].startswith("jaxden: note: the 2 inputs: "), lines
    code, lines, out = _denoise(capsys, renders, "--from", "cycles", "--model",
                                "oidn:emission=separate", "--out-dir", tmp_path / "explicit")
    assert code == 0 and "oidn+emission-separate" in out
    for path in renders:
        np.testing.assert_array_equal(read_image(tmp_path / "default" / path.name),
                                      read_image(tmp_path / "explicit" / path.name))
