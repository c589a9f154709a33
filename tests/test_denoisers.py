"""The denoiser registry, the U-Net and the OIDN black box."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise.models import UNetConfig
from jaxden.denoise.oidn import OIDNConfig
from jaxden.denoise.registry import make_denoiser
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame, stack


def smooth_scene(h=64, w=64, seed=0):
    """A smooth clean image (low-frequency gradients) and a noisy version with known variance."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    clean = np.stack([0.5 + 0.4 * np.sin(3 * xx), 0.4 + 0.3 * yy, 0.3 + 0.2 * np.cos(2 * xx * yy)], -1)
    variance = np.full_like(clean, 0.01)
    noisy = clean + rng.normal(size=clean.shape) * np.sqrt(variance)
    albedo = np.full_like(clean, 0.8)
    normal = np.zeros_like(clean)
    normal[..., 2] = 1
    frame = Frame(
        color=np.maximum(noisy, 0).astype(np.float32),
        variance=variance.astype(np.float32),
        albedo=albedo.astype(np.float32),
        normal=normal.astype(np.float32),
        spp=np.float32(4),
    )
    return frame, clean.astype(np.float32)


def test_unknown_denoiser_lists_registered_ones():
    with pytest.raises(ConfigError, match="registered denoisers: .*oidn.*unet"):
        make_denoiser("bm3d")


def test_wrong_config_type_is_an_error():
    with pytest.raises(ConfigError, match="takes a UNetConfig"):
        make_denoiser("unet", OIDNConfig())


def test_oidn_lowers_error_on_noisy_smooth_image():
    frame, clean = smooth_scene()
    denoised = make_denoiser("oidn")(frame)
    mse_noisy = np.mean((frame.color - clean) ** 2)
    mse_oidn = np.mean((denoised - clean) ** 2)
    assert denoised.shape == clean.shape and np.isfinite(denoised).all()
    assert mse_oidn < 0.2 * mse_noisy, (mse_oidn, mse_noisy)


def test_oidn_batch_equals_per_frame():
    frames = [smooth_scene(32, 32, seed=s)[0] for s in range(2)]
    batch = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *frames)
    den = make_denoiser("oidn", OIDNConfig(quality="fast"))
    out = den(batch)
    for i, frame in enumerate(frames):
        np.testing.assert_array_equal(out[i], den(frame))


def test_oidn_clean_aux_auto_follows_the_frame_spp():
    """auto = cleanAux for frames of >= clean_aux_min_spp samples (or unknown spp), not below;
    in a batch, per frame. The outputs must equal those of the fixed settings, which differ
    (noisy features: OIDN filters the albedo's noise too)."""
    rng = np.random.default_rng(3)
    frame, _ = smooth_scene(32, 32)
    frame = frame.replace(albedo=np.clip(frame.albedo + 0.2 * rng.normal(size=frame.albedo.shape),
                                         0, 1).astype(np.float32))
    yes, no = (make_denoiser("oidn", OIDNConfig(quality="fast", clean_aux=c)) for c in ("yes", "no"))
    auto = make_denoiser("oidn", OIDNConfig(quality="fast", clean_aux="auto"))
    low, high = frame.replace(spp=np.float32(4)), frame.replace(spp=np.float32(8))
    np.testing.assert_array_equal(make_denoiser("oidn", OIDNConfig(quality="fast"))(low),
                                  yes(low))  # the default is "yes"
    assert np.abs(yes(low) - no(low)).max() > 1e-3
    np.testing.assert_array_equal(auto(low), no(low))
    np.testing.assert_array_equal(auto(high), yes(high))
    np.testing.assert_array_equal(auto(frame.replace(spp=None)), yes(frame))
    batch = jax.tree_util.tree_map(lambda *xs: np.stack(xs), low, high)
    out = auto(batch)
    np.testing.assert_array_equal(out[0], no(low))
    np.testing.assert_array_equal(out[1], yes(high))
    assert OIDNConfig(clean_aux="auto", clean_aux_min_spp=64).features_are_clean(32) is False
    with pytest.raises(ConfigError, match="clean_aux must be auto, yes or no"):
        OIDNConfig(clean_aux=True)


@pytest.mark.slow  # ~10 s; the U-Net's numerics: tests/test_unet_reference.py
@pytest.mark.parametrize("size", [(37, 21)])
def test_unet_any_size_nonnegative_and_differentiable(size):
    frame, _ = smooth_scene(*size)
    den = make_denoiser("unet", key=jax.random.PRNGKey(1))
    out = den(frame)
    assert out.shape == frame.color.shape and bool(jnp.all(out >= 0))
    # The jvp along a random tangent equals a central difference of the same function: in
    # float32 with eps 1e-4 their relative L2 difference measured 0.8 % (2 % at eps 1e-3:
    # ReLU kinks and round-off); 3 % is the bound. A zero or wrong-tangent jvp gives ~1.
    fn = den.function()
    color = jnp.asarray(frame.color)
    tangent = jax.random.normal(jax.random.PRNGKey(2), color.shape) * (0.1 + color)
    _, jvp_out = jax.jvp(lambda c: fn(frame.replace(color=c)), (color,), (tangent,))
    eps = 1e-4
    central = (fn(frame.replace(color=color + eps * tangent))
               - fn(frame.replace(color=color - eps * tangent))) / (2 * eps)
    norm = float(jnp.linalg.norm(jvp_out))
    assert norm > 1e-3
    assert float(jnp.linalg.norm(jvp_out - central)) < 0.03 * norm
    # A batch is denoised image by image.
    flipped = frame.replace(color=frame.color[:, ::-1], variance=frame.variance[:, ::-1],
                            albedo=frame.albedo[:, ::-1], normal=frame.normal[:, ::-1])
    both = np.asarray(fn(stack([frame, flipped])))
    np.testing.assert_allclose(both[0], np.asarray(out), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(both[1], np.asarray(fn(flipped)), rtol=1e-5, atol=1e-6)


def test_unet_feature_set_without_hdr_is_refused():
    with pytest.raises(FrameError, match="must include 'hdr'"):
        make_denoiser("unet", UNetConfig(features=("var", "sure")), key=jax.random.PRNGKey(0))


@pytest.mark.slow  # two U-Net inits, 8-21 s; missing features are refused by every denoiser's
def test_unet_feature_sets_and_missing_feature():  # check_frame (tested for kp, oidn, ...)
    frame, _ = smooth_scene(16, 16)
    den = make_denoiser("unet", UNetConfig(features=("hdr", "var")), key=jax.random.PRNGKey(0))
    assert jax.eval_shape(den, frame).shape == (16, 16, 3)  # traced, not compiled: fast
    den = make_denoiser("unet", UNetConfig(features=("hdr", "alb", "nrm")), key=jax.random.PRNGKey(0))
    with pytest.raises(FrameError, match="needs the frame feature.*albedo.*normal"):
        den(Frame(color=frame.color, variance=frame.variance))
