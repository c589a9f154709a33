"""The real-time denoisers shipped in the package (jaxden/weights/NAME.* of kind "denoiser").

Each one's weights must be small, load by name on a fresh install, carry a model card with the
command that retrains them, and record the recipe of the committed sweep run they come from;
WSKP-6 ships in its deployed form and denoises a real 1-spp render through
`jaxden denoise --model wskp-6`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxden import cli, metrics
from jaxden.denoise.registry import WEIGHTS_DIR, load_denoiser
from jaxden.io.exr import read_image, write_frame

ROOT = Path(__file__).resolve().parent.parent


SHIPPED = sorted(p.stem for p in WEIGHTS_DIR.glob("*.json")
                 if json.loads(p.read_text()).get("kind") == "denoiser")


def test_wskp6_is_shipped_deployed_with_its_six_kernel_sizes():
    assert "wskp-6" in SHIPPED
    meta = json.loads((WEIGHTS_DIR / "wskp-6.json").read_text())
    assert meta["model"] == "wskp" and meta["model_config"]["deploy"] is True
    assert meta["model_config"]["kernel_sizes"] == [3, 5, 7, 9, 11, 13]
    denoiser = load_denoiser("wskp-6")
    assert denoiser.name == "wskp" and denoiser.config.deploy


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_denoiser_files_card_and_recipe(name):
    path = WEIGHTS_DIR / f"{name}.msgpack"
    assert path.stat().st_size < 8 * 2**20  # a few MB at most (the U-Net); WSKP a few 100 KB
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["kind"] == "denoiser"
    # The recorded recipe is the committed sweep run's: same model, seed, steps, data, optimiser.
    from jaxden.config import config_to_dict, load_config
    from jaxden.sweep import load_sweep, plan_runs
    from jaxden.train.config import TrainConfig

    trained = meta["trained"]
    sweep, axes, base = load_sweep(ROOT / trained["sweep"])
    (run,) = [r for r in plan_runs(sweep, axes) if r.name == trained["run"]]
    config = load_config(base, TrainConfig, overrides=list(run.overrides))
    assert (config.model, config.seed, config.optim.steps) == (meta["model"], trained["seed"],
                                                               trained["steps"])
    assert config_to_dict(config.optim) == trained["optim"]
    assert trained["data"]["dataset"] == "$JAXDEN_HOME/data/rt"  # no user's path in the package
    card = path.with_suffix(".md").read_text()
    for needle in (f"jaxden sweep {trained['sweep']}", "ship_denoiser.py", "Measured quality",
                   "dataset-rt.toml", f"seed {trained['seed']}", f"--model {name}"):
        assert needle in card, needle
    # It loads by name and denoises a frame with the features its card names.
    denoiser = load_denoiser(name)
    assert denoiser.name == meta["model"]
    rng = np.random.default_rng(0)
    frame = {"color": rng.uniform(0, 1, (16, 16, 3)).astype(np.float32),
             "albedo": np.full((16, 16, 3), 0.5, np.float32),
             "normal": np.dstack([np.zeros((16, 16, 2)), np.ones((16, 16, 1))]).astype(np.float32),
             "depth": np.ones((16, 16, 1), np.float32)}
    from jaxden.frame import Frame

    out = np.asarray(denoiser(Frame(**frame)))
    assert out.shape == (16, 16, 3) and np.isfinite(out).all()


def test_denoise_command_with_the_shipped_model_beats_the_noisy_input(tmp_path):
    """A 1-spp render of the built-in texture-bump scene (no emitter in view), scored like the
    model card (tone-mapped PSNR) against a 256-spp render: WSKP-6 gains at least 6 dB (on the
    held-out set it gains 11)."""
    from jaxden.render.core import render_frame

    size = (48, 48)
    noisy = render_frame("texture-bump", 1, seed=3, size=size)
    reference = render_frame("texture-bump", 256, seed=4, size=size).color
    write_frame(tmp_path / "in.exr", noisy)
    assert cli.main(["denoise", str(tmp_path / "in.exr"), "--model", "wskp-6",
                     "--out", str(tmp_path / "out.exr")]) == 0
    out = read_image(tmp_path / "out.exr")
    assert out.shape == (48, 48, 3) and np.isfinite(out).all()
    gain = float(metrics.psnr(out, reference)) - float(metrics.psnr(noisy.color, reference))
    assert gain > 6.0, gain
