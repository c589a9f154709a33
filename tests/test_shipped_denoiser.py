"""The real-time denoiser shipped in the package (jaxden/weights/wskp-6.*).

Its weights must be small, load by name on a fresh install in their deployed form, carry a
model card with the command that retrains them, record the recipe of the committed sweep run
they come from, and denoise a real 1-spp render through `jaxden denoise --model wskp-6`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxden import cli, metrics
from jaxden.denoise.registry import WEIGHTS_DIR, load_denoiser
from jaxden.io.exr import read_image, write_frame

ROOT = Path(__file__).resolve().parent.parent


def test_wskp6_files_card_and_recipe():
    path = WEIGHTS_DIR / "wskp-6.msgpack"
    assert path.stat().st_size < 2**20  # a few hundred KB: the deployed 5x5 convolutions
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["kind"] == "denoiser" and meta["model"] == "wskp"
    assert meta["model_config"]["deploy"] is True
    assert meta["model_config"]["kernel_sizes"] == [3, 5, 7, 9, 11, 13]
    # The recorded recipe is the committed sweep run's: same seed, steps, data and optimiser.
    from jaxden.config import config_to_dict, load_config
    from jaxden.sweep import load_sweep, plan_runs
    from jaxden.train.config import TrainConfig

    trained = meta["trained"]
    sweep, axes, base = load_sweep(ROOT / trained["sweep"])
    (run,) = [r for r in plan_runs(sweep, axes) if r.name == trained["run"]]
    config = load_config(base, TrainConfig, overrides=list(run.overrides))
    assert (config.model, config.seed, config.optim.steps) == ("wskp", trained["seed"],
                                                               trained["steps"])
    assert config_to_dict(config.optim) == trained["optim"]
    assert trained["data"]["dataset"] == "$JAXDEN_HOME/data/rt"  # no user's path in the package
    card = path.with_suffix(".md").read_text()
    for needle in (f"jaxden sweep {trained['sweep']}", "ship_denoiser.py", "Measured quality",
                   "dataset-rt.toml", f"seed {trained['seed']}"):
        assert needle in card, needle
    denoiser = load_denoiser("wskp-6")
    assert denoiser.name == "wskp" and denoiser.config.deploy


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
