"""MR-KP (jaxden.denoise.nn.mrkp, registered by jaxden.denoise.rt_baselines): the kernel filter
against an explicit window loop, the authors' upsampling and the 2 x 2 pool against NumPy
loops, the coarse-to-fine combination against NumPy, and the model: shapes, parameter count,
receptive field, a training smoke and the `jaxden train` path."""

from __future__ import annotations

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_nbgd import random_frame, train_smoke

import jaxden.denoise.rt_baselines as rt
from jaxden.denoise.nn import mrkp
from jaxden.denoise.nn.wskp import downsample
from jaxden.denoise.registry import make_denoiser
from jaxden.errors import ConfigError, FrameError

ROOT = Path(__file__).resolve().parent.parent


def kernel_reference(color, weights, k):
    """(H, W, C), (H, W, k*k) -> (H, W, C): for each pixel and channel, the window's taps that
    are inside the image and > 0, weighted by the kernel, over the kernel's sum + 1e-8."""
    height, width, channels = color.shape
    r = k // 2
    out = np.zeros_like(color)
    for y in range(height):
        for x in range(width):
            for c in range(channels):
                num = den = 0.0
                for dy in range(-r, r + 1):
                    for dx in range(-r, r + 1):
                        qy, qx = y + dy, x + dx
                        if 0 <= qy < height and 0 <= qx < width and color[qy, qx, c] > 0:
                            w = weights[y, x, (dy + r) * k + dx + r]
                            num += w * color[qy, qx, c]
                            den += w
                out[y, x, c] = num / (den + 1e-8)
    return out


def upsample_reference(x):
    """The authors' rule, pixel by pixel: output (i, j) averages the low-resolution (a, b) with
    a in {floor(i/2 + 0.05), ceil(i/2 - 0.05)}, b likewise, inside the image."""
    h, w, c = x.shape
    out = np.zeros((2 * h, 2 * w, c))
    for i in range(2 * h):
        for j in range(2 * w):
            rows = {math.floor(i / 2 + 0.05), math.ceil(i / 2 - 0.05)}
            cols = {math.floor(j / 2 + 0.05), math.ceil(j / 2 - 0.05)}
            taps = [x[a, b] for a in rows for b in cols if a < h and b < w]
            out[i, j] = np.mean(taps, axis=0)
    return out


def pool_reference(x):
    h, w, c = x.shape
    out = np.zeros((h // 2, w // 2, c))
    for i in range(h // 2):
        for j in range(w // 2):
            out[i, j] = x[2 * i : 2 * i + 2, 2 * j : 2 * j + 2].reshape(4, c).mean(0)
    return out


def test_kernel_filter_matches_an_explicit_window_loop():
    rng = np.random.default_rng(0)
    color = rng.normal(0.5, 1.0, (6, 7, 3))  # about a third of the taps <= 0: skipped
    weights = np.maximum(rng.normal(size=(6, 7, 25)), 0.0)  # ReLU outputs, many exact zeros
    weights[0, 0] = 0.0  # a dead kernel: output 0
    out = np.asarray(mrkp.apply_kernels(jnp.asarray(color, jnp.float32),
                                        jnp.asarray(weights, jnp.float32), 5))
    expected = kernel_reference(color, weights, 5)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    assert np.all(out[0, 0] == 0)
    with pytest.raises(FrameError, match="weights"):
        mrkp.apply_kernels(jnp.zeros((6, 7, 3)), jnp.zeros((6, 7, 9)), 5)


def test_upsampling_and_pooling_match_numpy_loops():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(5, 4, 2))
    np.testing.assert_allclose(np.asarray(mrkp.upsample(jnp.asarray(x, jnp.float32))),
                               upsample_reference(x), rtol=1e-6, atol=1e-6)
    batch = rng.normal(size=(2, 6, 8, 3))
    np.testing.assert_allclose(np.asarray(mrkp.upsample(jnp.asarray(batch, jnp.float32)))[1],
                               upsample_reference(batch[1]), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(np.asarray(downsample(jnp.asarray(batch, jnp.float32)))[0],
                               pool_reference(batch[0]), rtol=1e-6, atol=1e-6)


def test_coarse_to_fine_combination_matches_numpy():
    """b3 = d3 - a3 U(P(d3)) + a3 U(x4), b2 = d2 - a2 U(P(d2)) + a2 U(b3), b1 likewise."""
    rng = np.random.default_rng(2)
    sizes = (16, 8, 4)
    filtered = [rng.uniform(0, 2, (s, s, 3)) for s in sizes]
    alphas = [rng.uniform(0, 3, (s, s, 1)) for s in sizes]
    coarsest = rng.uniform(0, 2, (2, 2, 3))
    b = coarsest
    for d, a in zip(reversed(filtered), reversed(alphas)):
        b = d - a * upsample_reference(pool_reference(d)) + a * upsample_reference(b)
    out = mrkp.combine_levels([jnp.asarray(f, jnp.float32) for f in filtered],
                              [jnp.asarray(a, jnp.float32) for a in alphas],
                              jnp.asarray(coarsest, jnp.float32))
    np.testing.assert_allclose(np.asarray(out), b, rtol=1e-5, atol=1e-5)


def test_upconv_is_flax_conv_transpose():
    """The decoder's stride-2 transposed convolution, computed per output phase, equals
    flax's ConvTranspose with the same parameters (odd sizes, a batch, and no batch)."""
    import flax.linen as nn

    x = jax.random.normal(jax.random.PRNGKey(0), (2, 5, 7, 6))
    reference = nn.ConvTranspose(4, (3, 3), strides=(2, 2), padding="SAME")
    params = reference.init(jax.random.PRNGKey(1), x)
    params = jax.tree_util.tree_map(lambda a: a + 0.1, params)  # a non-zero bias too
    ours = mrkp.UpConv(4)
    assert jax.tree_util.tree_map(jnp.shape, ours.init(jax.random.PRNGKey(1), x)) == \
        jax.tree_util.tree_map(jnp.shape, params)
    np.testing.assert_allclose(np.asarray(ours.apply(params, x)),
                               np.asarray(reference.apply(params, x)), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(np.asarray(ours.apply(params, x[1])),
                               np.asarray(reference.apply(params, x))[1], rtol=1e-5, atol=1e-5)


def test_mrkp_filter_with_uniform_kernels_and_no_blend_is_a_box_filter():
    """alpha 0 at every level: the output is the finest level's filter alone; all-ones
    kernels make it the renormalised 5 x 5 box filter of the positive taps."""
    rng = np.random.default_rng(3)
    irradiance = rng.uniform(0.1, 2, (16, 16, 3))
    heads = [jnp.concatenate([jnp.ones((s, s, 25)), jnp.zeros((s, s, 1))], axis=-1)
             for s in (16, 8, 4)]
    out = mrkp.mrkp_filter(heads, jnp.asarray(irradiance, jnp.float32), 5)
    np.testing.assert_allclose(np.asarray(out),
                               kernel_reference(irradiance, np.ones((16, 16, 25)), 5),
                               rtol=1e-5)


def test_mrkp_shapes_finiteness_and_parameter_count():
    den = make_denoiser("mrkp", key=jax.random.PRNGKey(0))
    conv = lambda k, cin, cout: k * k * cin * cout + cout
    # encoder 10->48, 4 x 48->48; decoder 48->48 (from the bottleneck), 4 x 96->48;
    # 3 heads 96->26 (25 kernel weights + alpha)
    expected = (conv(3, 10, 48) + 4 * conv(3, 48, 48) + conv(3, 48, 48) + 4 * conv(3, 96, 48)
                + 3 * conv(3, 96, 26))
    count = sum(leaf.size for leaf in jax.tree_util.tree_leaves(den.params))
    assert count == expected == 341838
    frame = random_frame(37, 21, batch=(2,))  # padded to 64 x 32 and cropped back
    out = den(frame)
    assert out.shape == frame.color.shape and bool(jnp.all(jnp.isfinite(out)))
    with pytest.raises(ConfigError, match="filter_levels"):
        rt.MRKPConfig(levels=2, filter_levels=3)


@pytest.mark.slow  # ~8 s: the default network's gradient on a 256 x 256 frame
def test_stated_receptive_field_bounds_the_measured_one():
    """With positive weights (no unit is dead and no path cancels) the support of one output
    pixel reaches 94 pixels left and up, 77 right and down (measured over all 32 residues
    of the pooling grid); the interval bound states 98 and 77."""
    from jaxden.render.synthetic import synthetic_render

    den = make_denoiser("mrkp", key=jax.random.PRNGKey(3))
    params = jax.tree_util.tree_map(lambda a: jnp.abs(a) + 0.01, den.params)
    frame = synthetic_render("field", 4, size=(256, 256))
    radius = den.tile_spec().radius
    assert radius == 98 and den.tile_spec().multiple == 32

    @jax.jit
    def grad(color, frame, centre):
        return jax.grad(lambda c: den.definition.apply(params, den.config, frame.replace(
            color=c))[centre[0], centre[1]].sum())(color)

    measured = 0
    for centre in ((159, 159), (145, 145)):  # the worst residues mod 32, left and right
        rows, cols = np.nonzero(np.abs(np.asarray(grad(frame.color, frame,
                                                       jnp.array(centre)))).sum(-1))
        measured = max(measured, np.abs(rows - centre[0]).max(), np.abs(cols - centre[1]).max())
    assert 90 <= measured <= radius, measured


@pytest.mark.slow  # ~15 s: the model on 228-pixel windows and on the whole frame
def test_tiles_equal_the_whole_frame():
    from jaxden.denoise.tiled import denoise_frame
    from jaxden.render.synthetic import synthetic_render

    den = make_denoiser("mrkp", key=jax.random.PRNGKey(3))
    frame = synthetic_render("field", 4, size=(288, 256))
    whole, _ = denoise_frame(den, frame, tile=0)
    tiled, plan = denoise_frame(den, frame, tile=32)
    assert plan is not None and plan.tile == 32
    np.testing.assert_allclose(tiled, whole, rtol=1e-4, atol=1e-5)


def test_a_few_adam_steps_lower_the_loss():
    first, last = train_smoke("mrkp", steps=8, learning_rate=1e-3)
    assert np.isfinite(last) and last < 0.97 * first, (first, last)


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from helpers import build_tiny_dataset

    return build_tiny_dataset(tmp_path_factory.mktemp("mrkp-tiny") / "tiny")


@pytest.mark.slow  # ~12 s: compiling MR-KP's train and eval steps
def test_jaxden_train_trains_mrkp(tiny_dataset, tmp_path, capsys):
    from helpers import metrics_records, run_cli

    from jaxden.denoise.registry import load_denoiser

    code, errors, _ = run_cli(
        ["train", ROOT / "experiments/configs/train-mrkp.toml", "--workdir", tmp_path / "run",
         f"data.dataset={tiny_dataset}", "data.crop_size=32", "data.batch_size=1", "data.spp=[2]",
         "optim.steps=3", "eval_every=3", "eval_batches=1", "checkpoint_every=3",
         "log_every=1"], capsys)
    assert code == 0, errors
    records = metrics_records(tmp_path / "run")
    assert any(r.get("step") == 3 and np.isfinite(r.get("loss", np.nan)) for r in records)
    den = load_denoiser(tmp_path / "run")
    assert den.name == "mrkp" and den(random_frame(16, 16)).shape == (16, 16, 3)
