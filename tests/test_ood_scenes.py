"""The out-of-distribution scenes (experiments/scenes/ood/, dataset-ood.toml): their textures
are what make_textures.py writes, and every scene loads (and, with --runslow, renders)."""

import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
OOD = ROOT / "experiments" / "scenes" / "ood"
sys.path.insert(0, str(OOD))
import make_textures  # noqa: E402  (the script is part of the repository: no skip)

mi = pytest.importorskip("mitsuba")


def _scenes() -> list[str]:
    config = tomllib.loads((ROOT / "experiments" / "configs" / "dataset-ood.toml").read_text())
    return config["scenes"]


def test_the_committed_textures_are_what_the_script_writes():
    from jaxden.io.exr import read_image

    expected = make_textures.textures()
    assert sorted(expected) == sorted(p.name for p in (OOD / "textures").iterdir())
    for name, image in expected.items():
        path = OOD / "textures" / name
        if name.endswith(".png"):
            stored = np.asarray(mi.Bitmap(str(path)))
            np.testing.assert_array_equal(stored.reshape(image.shape), image, err_msg=name)
        else:  # written as half floats
            np.testing.assert_allclose(read_image(path), image, rtol=1e-3, atol=1e-4,
                                       err_msg=name)


def test_every_scene_of_the_dataset_config_exists_and_loads():
    from jaxden.render.load import load_scene

    scenes = _scenes()
    assert len(scenes) == 7
    for scene in scenes:
        path = ROOT / scene
        assert path.parent == OOD and path.is_file(), scene
        loaded = load_scene(path, size=(8, 8))
        assert tuple(int(v) for v in loaded.sensors()[0].film().size()) == (8, 8), scene


@pytest.mark.slow  # seven Mitsuba compilations
def test_every_scene_renders_finite_and_lit():
    from jaxden.render.core import render_frame

    for scene in _scenes():
        frame = render_frame(ROOT / scene, spp=4, size=(16, 16), seed=0)
        color = np.asarray(frame.color)
        assert np.all(np.isfinite(color)) and color.mean() > 0.05, scene
