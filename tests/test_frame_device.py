"""Frame validation without a host copy (Frame.is_valid_on_device): a frame of JAX arrays that
passes every check comes back as is, anything else takes the NumPy path, whose errors and
repairs are the reference; and SURE of a JAX denoiser gives the same result either way."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise.registry import Denoiser, DenoiserDef
from jaxden.errors import FrameError
from jaxden.frame import Frame
from jaxden.sure.denoiser import denoise_with_sure


def frame_np(seed=0, shape=(2, 9, 11)):
    rng = np.random.default_rng(seed)
    color = rng.uniform(0.0, 2.0, shape + (3,)).astype(np.float32)
    variance = rng.uniform(1e-3, 1e-2, shape + (3,)).astype(np.float32)
    covariance = (0.5 * np.sqrt(variance * np.roll(variance, -1, -1))).astype(np.float32)
    return Frame(color=color, variance=variance, covariance=covariance,
                 albedo=rng.uniform(0, 1, shape + (3,)).astype(np.float32))


def on_device(frame):
    return jax.tree_util.tree_map(jnp.asarray, frame)


@pytest.fixture(autouse=True)
def cpu_counts_as_a_device(monkeypatch):
    """The device path runs for accelerators only; the tests run it on the CPU backend."""
    monkeypatch.setattr("jaxden.frame.DEVICE_CHECK_PLATFORMS", ("cpu", "gpu", "cuda", "tpu"))


def test_a_valid_device_frame_comes_back_unchanged():
    frame = on_device(frame_np())
    assert frame.is_valid_on_device()
    assert frame.validated(where="t") is frame
    assert not frame_np().is_valid_on_device()  # NumPy fields: the NumPy path


def test_the_device_path_is_for_accelerators_only(monkeypatch):
    monkeypatch.setattr("jaxden.frame.DEVICE_CHECK_PLATFORMS", ("gpu", "cuda", "rocm", "tpu"))
    assert not on_device(frame_np()).is_valid_on_device() or jax.default_backend() != "cpu"


@pytest.mark.parametrize("spoil,nonfinite", [
    (lambda f: f.replace(color=f.color.at[1, 3, 4, 0].set(jnp.nan)), "error"),
    (lambda f: f.replace(albedo=f.albedo.at[0, 0, 0, 2].set(jnp.inf)), "error"),
    (lambda f: f.replace(variance=f.variance.at[0, 2, 2, 1].set(-1.0)), "error"),
    (lambda f: f.replace(covariance=f.covariance.at[0, 1, 1, 0].set(1.0)), "error"),
    (lambda f: f.replace(color=f.color.at[1, 3, 4, 0].set(jnp.nan)), "zero"),
    (lambda f: f.replace(variance=f.variance.at[0, 2, 2, 1].set(-1e-9)), "zero"),
], ids=["nan", "inf-feature", "negative-variance", "covariance", "nan-zeroed", "round-off"])
def test_a_failing_device_frame_gets_the_numpy_path(spoil, nonfinite):
    """The device check only says 'fine'; a failure is worded (or repaired) exactly as for
    the same frame in NumPy."""
    device = spoil(on_device(frame_np()))
    host = device.numpy()
    assert not device.is_valid_on_device()
    try:
        want = host.validated(where="t", nonfinite=nonfinite)
    except FrameError as error:
        with pytest.raises(FrameError) as got:
            device.validated(where="t", nonfinite=nonfinite)
        assert str(got.value) == str(error)
        return
    got = device.validated(where="t", nonfinite=nonfinite)
    for name in ("color", "variance", "covariance", "albedo"):
        np.testing.assert_array_equal(np.asarray(getattr(got, name)), getattr(want, name))


def _blur(params, config, frame):
    """A small JAX denoiser: a 3-tap box blur of the colour along W, mixed with albedo."""
    x = frame.color
    blurred = (jnp.roll(x, 1, -2) + x + jnp.roll(x, -1, -2)) / 3.0
    return params["w"] * blurred + (1.0 - params["w"]) * x * frame.albedo


BLUR = Denoiser(DenoiserDef("test-blur", "a box blur mixed with albedo (JAX)", object,
                            lambda config: ("albedo",), _blur), None, {"w": jnp.float32(0.7)})


def test_sure_of_a_device_frame_equals_the_numpy_one():
    host = frame_np(seed=3).replace(covariance=None)
    key = jax.random.PRNGKey(5)
    from_host, checked_host = denoise_with_sure(BLUR, host, key, num_probes=2)
    from_device, checked_device = denoise_with_sure(BLUR, on_device(host), key, num_probes=2)
    assert isinstance(checked_host.color, np.ndarray)
    assert isinstance(checked_device.color, jax.Array)  # not copied to the host
    for name in ("denoised", "sure", "divergence_term"):
        np.testing.assert_allclose(np.asarray(getattr(from_device, name)),
                                   np.asarray(getattr(from_host, name)), rtol=1e-6, atol=1e-7)
