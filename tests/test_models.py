"""WSKP, KP and multi-resolution WSKP: shapes, exact structure properties, references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise.nn import wskp
from jaxden.denoise.registry import make_denoiser
from jaxden.errors import FrameError
from jaxden.frame import Frame


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


@pytest.mark.parametrize("name", [pytest.param("wskp3", marks=pytest.mark.slow), "kp2"])
def test_models_denoise_any_size_and_batch(name):
    den = make_denoiser(name, key=jax.random.PRNGKey(0))
    for frame in (random_frame(13, 9), random_frame(8, 8, batch=(2,))):
        out = den(frame)
        assert out.shape == frame.color.shape and bool(jnp.all(jnp.isfinite(out)))
    # a batch is denoised image by image: each output equals the single-frame call
    batch = random_frame(8, 8, seed=3, batch=(2,))
    out = np.asarray(den(batch))
    for i in range(2):
        single = jax.tree_util.tree_map(lambda a, i=i: a[i], batch)
        np.testing.assert_allclose(out[i], np.asarray(den(single)), rtol=1e-5, atol=1e-6)
    assert np.abs(out[0] - out[1]).max() > 1e-3  # two different frames, two different outputs


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


def _box(image, k):
    """Zero-padded, renormalised k x k box filter of an (H, W, C) image (NumPy reference)."""
    r = k // 2
    num = np.pad(image, ((r, r), (r, r), (0, 0)))
    den = np.pad(np.ones(image.shape[:2] + (1,)), ((r, r), (r, r), (0, 0)))
    h, w = image.shape[:2]
    total = lambda a: sum(a[dy : dy + h, dx : dx + w] for dy in range(k) for dx in range(k))
    return total(num) / total(den)


def zero_params(init, config):
    """A model's parameter tree with every entry 0 (shapes by eval_shape: no init compile)."""
    shapes = jax.eval_shape(lambda: init(jax.random.PRNGKey(0), config))
    return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def _safe_albedo(albedo, floor):
    return np.where(albedo >= floor, albedo, 1.0 - (1.0 - floor) * albedo / floor)


def test_wskp_with_zero_network_is_fused_box_filter_on_irradiance():
    """With all network weights 0 the importance maps and logits are 0: every kernel is a
    plain (zero-padded, renormalised) box filter and the fusion an equal average."""
    config = wskp.WSKPConfig(kernel_sizes=(3, 5))
    params = zero_params(wskp.wskp_init, config)
    frame = random_frame(9, 8)
    out = np.asarray(wskp.wskp_denoise(params, config, frame))
    albedo = _safe_albedo(frame.albedo, config.albedo_floor)
    assert (frame.albedo < config.albedo_floor).any()  # the draw exercises the ramp
    irr = frame.color / albedo
    expected = 0.5 * (_box(irr, 3) + _box(irr, 5)) * albedo
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


@pytest.mark.slow  # ~9 s idle
def test_multiresolution_combination_eq7_with_zero_network():
    """Eq. 7 with all network weights 0: every level is the equal fusion of box filters of its
    (2x2-averaged) irradiance, alpha = sigmoid(0) = 1/2, and levels combine from the coarsest up
    as o = f - alpha U(D(f)) + alpha U(c); checked against that NumPy form on a noisy image
    (a constant image would pass any combination rule)."""
    config = wskp.WSKPMRConfig(levels=3, kernel_sizes=(3, 5))
    params = zero_params(wskp.wskp_mr_init, config)
    frame = random_frame(16, 12, seed=5)  # a multiple of 2^(levels-1): no padding
    out = np.asarray(wskp.wskp_mr_denoise(params, config, frame))
    albedo = _safe_albedo(frame.albedo.astype(np.float64), config.albedo_floor)

    def down(x):
        return x.reshape(x.shape[0] // 2, 2, x.shape[1] // 2, 2, -1).mean(axis=(1, 3))

    def up(x):
        return x.repeat(2, axis=0).repeat(2, axis=1)

    irradiance = [frame.color / albedo]
    for _ in range(config.levels - 1):
        irradiance.append(down(irradiance[-1]))
    filtered = [0.5 * (_box(irr, 3) + _box(irr, 5)) for irr in irradiance]
    result = filtered[-1]
    for fine in filtered[-2::-1]:
        result = fine - 0.5 * up(down(fine)) + 0.5 * up(result)
    np.testing.assert_allclose(out, result * albedo, rtol=1e-4, atol=1e-5)
    # ... and not what the finest level alone gives (the coarse levels matter)
    assert np.abs(out - filtered[0] * albedo).max() > 1e-2


def test_missing_features_are_named():
    den = make_denoiser("wskp", key=jax.random.PRNGKey(0))
    with pytest.raises(FrameError, match="albedo, normal, depth"):
        den(Frame(color=np.zeros((8, 8, 3), np.float32)))


@pytest.mark.parametrize("name", ["wskp3", "kp2", pytest.param("wskp_mr", marks=pytest.mark.slow)])
def test_deployed_form_gives_the_same_output(name):
    den = make_denoiser(name, key=jax.random.PRNGKey(5))
    frame = random_frame(13, 9, seed=4)  # odd sizes: the multi-resolution model pads
    deployed = den.deployed()
    assert deployed.config.deploy and deployed.deployed() is deployed
    assert deployed(frame).shape == frame.color.shape
    np.testing.assert_allclose(np.asarray(deployed(frame)), np.asarray(den(frame)), rtol=1e-4, atol=1e-5)
