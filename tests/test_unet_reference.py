"""The U-Net (jaxden/denoise/nn/unet.py) against an obvious NumPy forward pass of the same
architecture with the same parameters: 3x3 'SAME' convolutions (zero padding, cross-correlation
as flax.linen.Conv, kernel (3, 3, C_in, C_out) + bias) written as a loop over the nine taps,
ReLU, 2x2 max-pooling, nearest x2 upsampling and skip concatenation, in the module's order;
then the denoiser's input transforms, edge padding to a multiple of 16, crop and expm1 clamp.

The reference runs in float64; the module in float32. Tolerance: float32 round-off through 16
convolutions (measured: 2e-6 of the output scale), asserted at rtol 1e-4 with an absolute floor
of 1e-5 of the output's scale.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxden.denoise.nn.unet import UNet, unet_denoise
from jaxden.frame import Frame


def conv3x3(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """'SAME' 3x3 cross-correlation of (H, W, C_in) with (3, 3, C_in, C_out), plus bias."""
    height, width, _ = x.shape
    padded = np.pad(x, ((1, 1), (1, 1), (0, 0)))
    out = np.zeros((height, width, kernel.shape[-1]))
    for dy in range(3):
        for dx in range(3):
            out += padded[dy:dy + height, dx:dx + width, :] @ kernel[dy, dx]
    return out + bias


def relu(x):
    return np.maximum(x, 0.0)


def max_pool(x: np.ndarray) -> np.ndarray:
    height, width, channels = x.shape
    out = np.empty((height // 2, width // 2, channels))
    for i in range(height // 2):
        for j in range(width // 2):
            out[i, j] = x[2 * i:2 * i + 2, 2 * j:2 * j + 2].max(axis=(0, 1))
    return out


def upsample(x: np.ndarray) -> np.ndarray:
    height, width, channels = x.shape
    out = np.empty((2 * height, 2 * width, channels))
    for i in range(2 * height):
        for j in range(2 * width):
            out[i, j] = x[i // 2, j // 2]
    return out


def reference_unet(params, x: np.ndarray) -> np.ndarray:
    """(H, W, C_in) -> (H, W, 3), float64, H and W multiples of 16."""
    p = {name: (np.asarray(v["kernel"], np.float64), np.asarray(v["bias"], np.float64))
         for name, v in params["params"].items()}

    def c(name, y):
        return conv3x3(y, *p[name])

    skip0 = x
    y = relu(c("enc_conv0", x))
    y = max_pool(relu(c("enc_conv1", y)))
    skip1 = y
    y = max_pool(relu(c("enc_conv2", y)))
    skip2 = y
    y = max_pool(relu(c("enc_conv3", y)))
    skip3 = y
    y = max_pool(relu(c("enc_conv4", y)))
    y = relu(c("enc_conv5a", y))
    y = relu(c("enc_conv5b", y))
    for a, b, skip in (("dec_conv4a", "dec_conv4b", skip3), ("dec_conv3a", "dec_conv3b", skip2),
                       ("dec_conv2a", "dec_conv2b", skip1), ("dec_conv1a", "dec_conv1b", skip0)):
        y = np.concatenate([upsample(y), skip], axis=-1)
        y = relu(c(a, y))
        y = relu(c(b, y))
    return c("dec_conv0", y)


def random_params(module, shape, seed: int):
    """Parameters of ``module`` for inputs of ``shape`` (the structure from flax, by
    ``eval_shape``: no eager init), every kernel and bias drawn here (biases nonzero, so a
    dropped bias shows), kernels scaled by fan-in so activations stay O(1) through the depth."""
    params = jax.eval_shape(module.init, jax.random.PRNGKey(0), np.zeros(shape, np.float32))
    rng = np.random.default_rng(seed)

    def draw(path, leaf):
        shape = leaf.shape
        if path[-1].key == "kernel":
            fan_in = shape[0] * shape[1] * shape[2]
            return (rng.standard_normal(shape) * np.sqrt(2.0 / fan_in)).astype(np.float32)
        return (0.1 * rng.standard_normal(shape)).astype(np.float32)

    return jax.tree_util.tree_map_with_path(draw, params)


def assert_close(actual, reference):
    scale = float(np.abs(reference).max())
    assert scale > 1e-3  # a non-trivial output
    np.testing.assert_allclose(np.asarray(actual, np.float64), reference, rtol=1e-4,
                               atol=1e-5 * scale)


def test_unet_module_matches_numpy_reference():
    """Default widths (32/48/64/80/96, 112/96/64/64/32) on a 16 x 32 input of 9 channels."""
    module = UNet()
    rng = np.random.default_rng(0)
    x = rng.standard_normal((16, 32, 9)).astype(np.float32)
    params = random_params(module, x[None].shape, seed=1)
    actual = np.asarray(module.apply(params, x[None]))[0]
    assert actual.shape == (16, 32, 3)
    assert_close(actual, reference_unet(params, x.astype(np.float64)))


@pytest.mark.parametrize("features", [("hdr",), ("hdr", "alb", "nrm", "var")])
def test_unet_denoise_matches_numpy_reference(features):
    """The denoiser around the module: log1p of radiance and albedo, arctan of the variance,
    normals as given, edge padding of an 18 x 13 frame to 32 x 16, crop, expm1 clamped at 0."""
    module = UNet(encoder_widths=(8, 8, 12, 12, 16), decoder_widths=(16, 12, 12, 8, 8))
    rng = np.random.default_rng(2)
    height, width = 18, 13
    normal = rng.standard_normal((height, width, 3))
    frame = Frame(color=rng.gamma(1.0, 1.0, (height, width, 3)).astype(np.float32),
                  variance=rng.uniform(0, 2, (height, width, 3)).astype(np.float32),
                  albedo=rng.uniform(0, 1, (height, width, 3)).astype(np.float32),
                  normal=(normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(
                      np.float32),
                  depth=rng.uniform(1, 3, (height, width, 1)).astype(np.float32))
    channels = 3 * len(features)
    params = random_params(module, (1, 32, 16, channels), seed=3)
    parts = {"hdr": np.log1p(frame.color.astype(np.float64)),
             "alb": np.log1p(frame.albedo.astype(np.float64)),
             "var": np.arctan(frame.variance.astype(np.float64)),
             "nrm": frame.normal.astype(np.float64)}
    x = np.concatenate([parts[f] for f in features], axis=-1)
    padded = np.pad(x, ((0, 32 - height), (0, 16 - width), (0, 0)), mode="edge")
    want = np.maximum(np.expm1(reference_unet(params, padded)[:height, :width]), 0.0)
    actual = np.asarray(unet_denoise(module, params, frame, features))
    assert actual.shape == (height, width, 3)
    assert 0 < np.mean(want > 0) < 1  # the clamp is exercised both ways
    assert_close(actual, want)
