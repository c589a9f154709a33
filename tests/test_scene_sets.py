"""The committed Mitsuba scene sets of experiments/scenes/ (the out-of-distribution set of
dataset-ood.toml and the stress set of dataset-stress.toml): their textures are what each set's
make_textures.py writes, and every scene of the dataset config loads (and, with --runslow,
renders)."""

import importlib.util
import tomllib
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
#: scene set -> (folder, dataset config, number of scenes)
SETS = {
    "ood": (ROOT / "experiments" / "scenes" / "ood", "dataset-ood.toml", 7),
    "stress": (ROOT / "experiments" / "scenes" / "stress", "dataset-stress.toml", 8),
}

mi = pytest.importorskip("mitsuba")


def _make_textures(folder: Path):
    """The set's make_textures.py as a module (the script is part of the repository)."""
    spec = importlib.util.spec_from_file_location(f"make_textures_{folder.name}",
                                                  folder / "make_textures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _scenes(config_name: str) -> list[str]:
    config = tomllib.loads((ROOT / "experiments" / "configs" / config_name).read_text())
    return config["scenes"]


@pytest.mark.parametrize("name", sorted(SETS))
def test_the_committed_textures_are_what_the_script_writes(name):
    from jaxden.io.exr import read_image

    folder = SETS[name][0]
    expected = _make_textures(folder).textures()
    assert sorted(expected) == sorted(p.name for p in (folder / "textures").iterdir())
    for texture, image in expected.items():
        path = folder / "textures" / texture
        if texture.endswith(".png"):
            stored = np.asarray(mi.Bitmap(str(path)))
            np.testing.assert_array_equal(stored.reshape(image.shape), image, err_msg=texture)
        else:  # written as half floats
            np.testing.assert_allclose(read_image(path), image, rtol=1e-3, atol=1e-4,
                                       err_msg=texture)


@pytest.mark.parametrize("name", sorted(SETS))
def test_every_scene_of_the_dataset_config_exists_and_loads(name):
    from jaxden.render.load import load_scene

    folder, config_name, count = SETS[name]
    scenes = _scenes(config_name)
    assert len(scenes) == count
    for scene in scenes:
        path = ROOT / scene
        assert path.parent == folder and path.is_file(), scene
        loaded = load_scene(path, size=(8, 8))
        assert tuple(int(v) for v in loaded.sensors()[0].film().size()) == (8, 8), scene


@pytest.mark.slow  # fifteen Mitsuba compilations
@pytest.mark.parametrize("name", sorted(SETS))
def test_every_scene_renders_finite_and_lit(name):
    from jaxden.render.core import render_frame

    for scene in _scenes(SETS[name][1]):
        frame = render_frame(ROOT / scene, spp=4, size=(16, 16), seed=0)
        color = np.asarray(frame.color)
        assert np.all(np.isfinite(color)) and color.mean() > 0.05, scene
