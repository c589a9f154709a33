"""Tests for jaxden.denoise.nn.layers: RepVGG blocks and their re-parameterisation."""

import flax.linen as nn
import jax
import numpy as np
import pytest

from jaxden.errors import ConfigError
from jaxden.denoise.nn.layers import (
    RepVGGBlock,
    RepVGGDeployBlock,
    reparameterize,
    reparameterize_block,
)


@pytest.fixture
def key():
    return jax.random.key(7)


def _random_params(module, x, seed, scale=0.3):
    """Params of ``module`` for input ``x`` with every leaf N(0, scale^2) (seeded NumPy).

    Shapes come from ``jax.eval_shape`` (no initialiser runs: faster, and the tests must not
    rely on the initialiser's values anyway).
    """
    shapes = jax.eval_shape(module.init, jax.random.key(0), x)
    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_map(
        lambda leaf: (scale * rng.standard_normal(leaf.shape)).astype(np.float32), shapes
    )


def _assert_close(actual, expected):
    scale = float(np.abs(expected).max())
    np.testing.assert_allclose(actual, expected, rtol=1e-5, atol=1e-5 * scale)


def _numpy_block(x, kernels, identity, slope):
    """Direct float64 sum of 'SAME' zero-padded convolutions, then identity and LeakyReLU."""
    x = np.asarray(x, np.float64)
    height, width = x.shape[-3:-1]
    out = 0.0
    for kernel in kernels:
        kernel = np.asarray(kernel, np.float64)
        r = kernel.shape[0] // 2
        padded = np.pad(x, [(0, 0)] * (x.ndim - 3) + [(r, r), (r, r), (0, 0)])
        for dy in range(kernel.shape[0]):
            for dx in range(kernel.shape[1]):
                out = out + padded[..., dy : dy + height, dx : dx + width, :] @ kernel[dy, dx]
    if identity:
        out = out + x
    return np.where(out >= 0, out, slope * out) if slope is not None else out


@pytest.mark.parametrize(
    "in_features, features, use_identity, expect_identity",
    [(6, 6, None, True), (6, 6, False, False), (4, 6, None, False)],
)
def test_training_block_matches_numpy(key, in_features, features, use_identity, expect_identity):
    x = jax.random.normal(key, (2, 9, 11, in_features))
    block = RepVGGBlock(features, use_identity=use_identity)
    params = _random_params(block, x, seed=1)
    branches = params["params"]
    kernels = [branches[name]["kernel"] for name in ("branch_5x5", "branch_3x3", "branch_1x1")]
    assert [k.shape for k in kernels] == [(s, s, in_features, features) for s in (5, 3, 1)]
    expected = _numpy_block(x, kernels, expect_identity, 0.1)
    _assert_close(block.apply(params, x), expected)


@pytest.mark.parametrize(
    "in_features, features, use_identity, activation",
    [(6, 6, None, True), (6, 6, False, True), (6, 6, True, False), (3, 8, None, True)],
)
def test_deploy_block_equals_training_block(key, in_features, features, use_identity, activation):
    x = jax.random.normal(key, (2, 13, 10, in_features))
    block = RepVGGBlock(features, use_identity=use_identity, activation=activation)
    params = _random_params(block, x, seed=2)
    deploy_params = jax.jit(reparameterize_block, static_argnums=1)(params, use_identity)
    assert jax.tree_util.tree_map(np.shape, deploy_params) == {
        "params": {"conv_5x5": {"kernel": (5, 5, in_features, features)}}
    }
    deploy = RepVGGDeployBlock(features, activation=activation)
    _assert_close(deploy.apply(deploy_params, x), block.apply(params, x))


class _Stack(nn.Module):
    """A WSKP-like stack: widen, two identity blocks, one forced off, linear last layer."""

    deploy: bool = False

    @nn.compact
    def __call__(self, x):
        specs = [(8, None, True), (8, None, True), (8, False, True), (5, None, False)]
        for i, (features, use_identity, activation) in enumerate(specs):
            name = f"block_{i}"
            if self.deploy:
                x = RepVGGDeployBlock(features, activation=activation, name=name)(x)
            else:
                block = RepVGGBlock(features, use_identity, activation=activation, name=name)
                x = block(x)
        return x


def test_reparameterized_stack_equals_training_stack(key):
    x = jax.random.normal(key, (1, 16, 16, 4))
    params = _random_params(_Stack(), x, seed=3, scale=0.2)
    deploy_params = reparameterize(params, use_identity={"block_2": False})
    expected = jax.eval_shape(_Stack(deploy=True).init, key, x)
    assert jax.tree_util.tree_map(np.shape, deploy_params) == jax.tree_util.tree_map(
        np.shape, expected
    )
    _assert_close(_Stack(deploy=True).apply(deploy_params, x), _Stack().apply(params, x))
    # Forgetting that block_2 has its identity switched off must give a different network.
    wrong = reparameterize(params)
    assert not np.allclose(_Stack(deploy=True).apply(wrong, x), _Stack().apply(params, x))


def test_reparameterize_leaves_other_params_alone(key):
    tree = {"params": {"head": {"kernel": np.ones((1, 1, 2, 2)), "bias": np.zeros(2)}}}
    assert reparameterize(tree) == tree


def test_errors(key):
    x = jax.random.normal(key, (1, 8, 8, 3))
    with pytest.raises(ConfigError, match=r"use_identity=True needs equal .* 3 -> 4"):
        jax.eval_shape(RepVGGBlock(4, use_identity=True).init, key, x)
    with pytest.raises(ConfigError, match="expected a RepVGGBlock param tree"):
        reparameterize_block({"conv_5x5": {"kernel": np.zeros((5, 5, 3, 3))}})
    params = _random_params(RepVGGBlock(3), x, seed=4)
    broken = {"params": dict(params["params"], branch_3x3={"kernel": np.zeros((5, 5, 3, 3))})}
    with pytest.raises(ConfigError, match=r"branch_3x3 kernel must be \(3, 3, in, out\)"):
        reparameterize_block(broken)
