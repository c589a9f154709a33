"""Checkpoints: round trips, and clear errors for checkpoints of another model or config."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.checkpoint import Checkpointer, load_weights, save_weights
from jaxden.errors import CheckpointError


def params_of(width):
    k1, k2 = jax.random.split(jax.random.PRNGKey(width))
    return {"conv": {"kernel": jax.random.normal(k1, (3, 3, 4, width)), "bias": jnp.zeros(width)},
            "out": {"kernel": jax.random.normal(k2, (1, 1, width, 3))}}


META = {"kind": "denoiser", "model": "wskp", "model_config": {"width": 8}}


def test_round_trip_latest_step_and_retention(tmp_path):
    ckpt = Checkpointer(tmp_path / "work", max_to_keep=2)
    for step in (1, 2, 3):
        ckpt.save(step, {"params": params_of(8), "step": jnp.asarray(step)}, META)
    ckpt.wait()
    assert ckpt.latest_step() == 3
    state, meta = Checkpointer(tmp_path / "work").restore({"params": params_of(8), "step": jnp.asarray(0)})
    assert int(state["step"]) == 3 and meta["model"] == "wskp" and meta["step"] == 3
    np.testing.assert_array_equal(state["params"]["conv"]["kernel"], params_of(8)["conv"]["kernel"])
    with pytest.raises(CheckpointError, match="no checkpoint at step 1"):
        Checkpointer(tmp_path / "work").restore(step=1)


def test_other_model_or_config_is_named(tmp_path):
    ckpt = Checkpointer(tmp_path / "w")
    ckpt.save(1, {"params": params_of(8)}, META)
    ckpt.wait()
    with pytest.raises(CheckpointError, match="model: checkpoint has 'wskp', expected 'unet'"):
        ckpt.restore(expect={"model": "unet"})
    with pytest.raises(CheckpointError, match="model_config"):
        ckpt.restore(expect={"model_config": {"width": 16}})
    with pytest.raises(CheckpointError, match="shape"):
        ckpt.restore({"params": params_of(16)})


def test_empty_or_missing_folder(tmp_path):
    with pytest.raises(CheckpointError, match="no checkpoint folder"):
        Checkpointer(tmp_path / "absent", create=False)
    with pytest.raises(CheckpointError, match="no finished checkpoint"):
        Checkpointer(tmp_path / "empty").restore()


def test_released_weights_round_trip_and_errors(tmp_path):
    path = tmp_path / "model.msgpack"
    save_weights(path, params_of(8), META)
    params, meta = load_weights(path, params_of(8), expect={"model": "wskp"})
    np.testing.assert_array_equal(params["out"]["kernel"], params_of(8)["out"]["kernel"])
    with pytest.raises(CheckpointError, match="expected 'kp'"):
        load_weights(path, params_of(8), expect={"model": "kp"})
    with pytest.raises(CheckpointError, match=r"\['conv'\]\['bias'\] has shape \(8,\)"):
        load_weights(path, params_of(16))
    path.write_bytes(path.read_bytes()[:20])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_weights(path, params_of(8))
