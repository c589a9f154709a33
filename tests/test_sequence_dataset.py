"""Sequence sets (jaxden.data.sequences): frames with motion and a reference each, a rebuild
renders nothing, a damaged frame makes its sequence render again (same bytes: seeded), another
config in the same folder is refused, and the CLI gives one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxden import cli
from jaxden.data.sequences import (
    MANIFEST_NAME,
    SequenceConfig,
    build_sequences,
    load_sequence,
)
from jaxden.errors import ConfigError, DatasetError

CONFIG = SequenceConfig(name="t", scenes=("cornell-box",), size=(20, 16), frames=3, spp=2,
                        reference_spp=4, seed=5, rotation_deg=20.0)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("seq")
    build_sequences(CONFIG, out, progress=False)
    return out


def test_frames_motion_and_references(built):
    manifest = json.loads((built / MANIFEST_NAME).read_text())
    (key,) = manifest["sequences"]
    frames, references = load_sequence(built, key)
    assert len(frames) == len(references) == 3
    for frame, reference in zip(frames, references):
        assert frame.color.shape == (16, 20, 3) and frame.motion.shape == (16, 20, 2)
        assert float(frame.spp) == 2 and float(reference.spp) == 4
        assert not np.array_equal(frame.color, reference.color)  # independent renders
    assert np.all(frames[0].motion == 0)
    assert np.abs(frames[1].motion).max() > 0.1  # the camera moved (20 degrees of orbit)


def test_rebuild_renders_nothing_and_repairs(built):
    files = sorted(built.rglob("*.exr"))
    stamps = {f: f.stat().st_mtime_ns for f in files}
    build_sequences(CONFIG, built, progress=False)
    assert {f: f.stat().st_mtime_ns for f in files} == stamps
    victim = files[2]
    good = victim.read_bytes()
    victim.write_bytes(good[: len(good) // 2])
    build_sequences(CONFIG, built, progress=False)
    assert victim.read_bytes() == good  # the same seeds give the same file


def test_other_config_is_refused(built):
    with pytest.raises(DatasetError, match="another sequence set"):
        build_sequences(SequenceConfig(**{**CONFIG.__dict__, "frames": 4}), built, progress=False)


def test_config_errors():
    with pytest.raises(ConfigError, match="reference_spp"):
        SequenceConfig(scenes=("cornell-box",), spp=8, reference_spp=4)
    with pytest.raises(ConfigError, match="no scenes"):
        SequenceConfig()


def test_cli_bad_key_is_one_line(tmp_path, capsys):
    config = tmp_path / "s.toml"
    config.write_text('scenes = ["cornell-box"]\nframez = 3\n')
    code = cli.main(["dataset", "sequences", str(config), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "framez" in err[0]
    assert not (tmp_path / "o").exists()
