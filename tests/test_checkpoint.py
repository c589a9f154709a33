"""Checkpoints: round trips, clear errors for checkpoints of another model or config, and no
stray tracebacks from reads that finish after a failed restore."""

import contextlib
import sys

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


def test_reads_finishing_after_a_failed_restore_print_nothing(capfd, monkeypatch):
    """What a restore meets on a damaged file: orbax awaits every TensorStore read in a fresh
    event loop, one read fails, the loop is closed, and another read completes afterwards.
    Its callback reaches the closed loop: TensorStore prints "Event loop is closed" with a
    traceback, unless the loop came from ``late_callbacks_dropped`` (as every restore's does)."""
    import asyncio
    import threading

    ts = pytest.importorskip("tensorstore")
    from jaxden.checkpoint import late_callbacks_dropped

    unraisable = []  # where TensorStore reports the callback's error, beside printing it
    monkeypatch.setattr(sys, "unraisablehook", lambda u: unraisable.append(str(u.exc_value)))

    def race(tolerant: bool) -> str:
        promise, pending = ts.Promise.new()

        async def failing():
            await asyncio.sleep(0.01)
            raise ValueError("a damaged file")

        async def restore():
            await asyncio.gather(pending, failing())

        with late_callbacks_dropped() if tolerant else contextlib.nullcontext():
            loop = asyncio.new_event_loop()
        try:
            with pytest.raises(ValueError, match="damaged"):
                loop.run_until_complete(restore())
        finally:
            loop.close()
        finishing = threading.Thread(target=lambda: promise.set_result(1))
        finishing.start()
        finishing.join()
        reported = capfd.readouterr().err + "".join(unraisable)
        unraisable.clear()
        return reported

    policy = asyncio.get_event_loop_policy()
    assert "Event loop is closed" in race(tolerant=False)  # the race itself
    assert race(tolerant=True) == ""
    assert asyncio.get_event_loop_policy() is policy  # put back after the block
