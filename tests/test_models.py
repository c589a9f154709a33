"""WSKP, KP and multi-resolution WSKP: shapes, exact structure properties, references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoisers import make_denoiser
from jaxden.errors import FrameError
from jaxden.frame import Frame
from jaxden.nn import wskp


def random_frame(h=12, w=10, seed=0, batch=()):
    rng = np.random.default_rng(seed)
    shape = batch + (h, w)
    normal = rng.normal(size=shape + (3,))
    return Frame(
        color=rng.uniform(0, 2, shape + (3,)).astype(np.float32),
        albedo=rng.uniform(0, 1, shape + (3,)).astype(np.float32),
        normal=(normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32),
        depth=rng.uniform(1, 5, shape + (1,)).astype(np.float32),
    )


@pytest.mark.parametrize("name", ["wskp3", "kp2"])
def test_models_denoise_any_size_and_batch(name):
    den = make_denoiser(name, key=jax.random.PRNGKey(0))
    for frame in (random_frame(13, 9), random_frame(8, 8, batch=(2,))):
        out = den(frame)
        assert out.shape == frame.color.shape and bool(jnp.all(jnp.isfinite(out)))


def test_per_pixel_kernels_match_unfold_reference():
    rng = np.random.default_rng(1)
    color = rng.normal(size=(6, 7, 3)).astype(np.float32)
    k = 5
    weights = rng.uniform(size=(6, 7, k * k)).astype(np.float32)
    out = np.asarray(wskp.apply_per_pixel_kernels(jnp.asarray(color), jnp.asarray(weights), k))
    padded = np.pad(color, ((2, 2), (2, 2), (0, 0)))
    expected = np.zeros_like(color)
    for y in range(6):
        for x in range(7):
            window = padded[y : y + k, x : x + k].reshape(k * k, 3)
            expected[y, x] = weights[y, x] @ window
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)


def test_wskp_with_zero_network_is_fused_box_filter_on_irradiance():
    """With all network weights 0 the importance maps and logits are 0: every kernel is a
    plain (zero-padded, renormalised) box filter and the fusion an equal average."""
    config = wskp.WSKPConfig(kernel_sizes=(3, 5))
    params = jax.tree_util.tree_map(jnp.zeros_like, wskp.wskp_init(jax.random.PRNGKey(0), config))
    frame = random_frame(9, 8)
    out = np.asarray(wskp.wskp_denoise(params, config, frame))
    f = config.albedo_floor
    albedo = np.where(frame.albedo >= f, frame.albedo, 1.0 - (1.0 - f) * frame.albedo / f)
    assert (frame.albedo < f).any()  # the draw exercises the ramp
    irr = frame.color / albedo

    def box(image, k):
        r = k // 2
        num = np.pad(image, ((r, r), (r, r), (0, 0)))
        den = np.pad(np.ones(image.shape[:2] + (1,)), ((r, r), (r, r), (0, 0)))
        s = lambda a: sum(a[dy : dy + image.shape[0], dx : dx + image.shape[1]] for dy in range(k) for dx in range(k))  # noqa: E731
        return s(num) / s(den)

    expected = 0.5 * (box(irr, 3) + box(irr, 5)) * albedo
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("floor", [1e-3, 0.05, 0.5])
def test_safe_albedo_is_continuous_and_bounds_the_amplification(floor):
    """The demodulation divisor equals the albedo from the floor up, is 1 at albedo 0, never
    drops below the floor (so no pixel is amplified more than 1 / floor), and is continuous:
    no jump at the floor, where the first form (1 below, albedo above) jumped by 1 / floor."""
    a = np.concatenate([np.linspace(0.0, 1.0, 20001), [floor, np.nextafter(floor, 0)]]).astype(np.float32)
    safe = np.asarray(wskp.safe_albedo(jnp.asarray(a), floor))
    np.testing.assert_array_equal(safe[a >= floor], a[a >= floor])
    assert safe[0] == 1.0 and safe.min() >= floor * (1 - 1e-6)
    order = np.argsort(a)
    assert np.abs(np.diff(safe[order])).max() < 2e-4 / floor + 1e-6


def test_multiresolution_combination_eq7_with_constant_alpha():
    """Eq. 7 keeps the fine level's detail and takes the coarse level's low frequencies: with
    a constant image every level agrees and the output is that constant."""
    config = wskp.WSKPMRConfig()
    params = wskp.wskp_mr_init(jax.random.PRNGKey(3), config)
    frame = random_frame(16, 12)
    frame = frame.replace(color=np.full_like(frame.color, 0.7), albedo=np.ones_like(frame.albedo))
    out = np.asarray(wskp.wskp_mr_denoise(params, config, frame))
    np.testing.assert_allclose(out, 0.7, rtol=1e-5)


def test_missing_features_are_named():
    den = make_denoiser("wskp", key=jax.random.PRNGKey(0))
    with pytest.raises(FrameError, match="albedo, normal, depth"):
        den(Frame(color=np.zeros((8, 8, 3), np.float32)))


@pytest.mark.parametrize("name", ["wskp3", "kp2", "wskp_mr"])
def test_deployed_form_gives_the_same_output(name):
    den = make_denoiser(name, key=jax.random.PRNGKey(5))
    frame = random_frame(13, 9, seed=4)  # odd sizes: the multi-resolution model pads
    deployed = den.deployed()
    assert deployed.config.deploy and deployed.deployed() is deployed
    assert deployed(frame).shape == frame.color.shape
    np.testing.assert_allclose(np.asarray(deployed(frame)), np.asarray(den(frame)), rtol=1e-4, atol=1e-5)
