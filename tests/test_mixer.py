"""Tests of the mixer network (jaxden.progressive.network.PDNet) and its pure wrappers in
jaxden.progressive: architecture against a literal NumPy forward pass, output shapes for the
paper's configuration and its ablations, alpha in [0, 1], the swap-symmetry measure, and
mixer checkpoints (round trip and every mismatch as a CheckpointError).

NumPy reference tolerance: float32 convolutions of <= 25 * 18 taps per layer and 6 layers vs
float64: rtol 1e-4 plus atol 1e-5 * max|output|.
"""

from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from jaxden import progressive as P
from jaxden.checkpoint import save_weights
from jaxden.config import load_config
from jaxden.errors import CheckpointError, ConfigError, FrameError
from jaxden.progressive.inputs import MIXER_FEATURES, MIXER_FEATURES_NO_SURE
from jaxden.progressive.network import PDNet, head_bias, mixer_module

# ------------------------------------------------------------------------ NumPy reference


def conv_same(x: np.ndarray, kernel: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """'SAME' zero-padded correlation of one image (H, W, Ci) with (k, k, Ci, Co), float64."""
    height, width = x.shape[:2]
    size = kernel.shape[0]
    r = size // 2
    padded = np.pad(x, ((r, r), (r, r), (0, 0)))
    out = np.zeros((height, width, kernel.shape[-1])) + bias
    for dy in range(size):
        for dx in range(size):
            out += padded[dy : dy + height, dx : dx + width] @ kernel[dy, dx]
    return out


def reference_pdnet(params, x: np.ndarray) -> np.ndarray:
    """PDNet forward for one image, literally from the paper's description."""
    p = jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), params)["params"]
    relu = lambda a: np.maximum(a, 0.0)
    h = relu(conv_same(x, p["conv_in"]["kernel"], p["conv_in"]["bias"]))
    for name in ("block_0", "block_1"):
        block = p[name]
        inner = relu(conv_same(h, block["conv_a"]["kernel"], block["conv_a"]["bias"]))
        h = relu(h + conv_same(inner, block["conv_b"]["kernel"], block["conv_b"]["bias"]))
    return conv_same(h, p["conv_out"]["kernel"], p["conv_out"]["bias"])


def random_images(seed: int, shape=(2, 9, 7, 3)):
    rng = np.random.default_rng(seed)
    x = rng.gamma(2.0, 0.5, shape).astype(np.float32)
    y = (x * rng.uniform(0.5, 1.5, shape)).astype(np.float32)
    var = rng.gamma(1.0, 0.05, shape).astype(np.float32)
    sure = (rng.normal(0, 0.05, shape)).astype(np.float32)
    return x, y, var, sure


def randomized(params, seed: int, scale: float = 1.0):
    """The same tree with every leaf redrawn (biases too), so no test relies on zero biases.
    NumPy draws: no JAX compilation per leaf shape."""
    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_map(
        lambda leaf: jnp.asarray(scale * 0.3 * rng.standard_normal(leaf.shape), jnp.float32),
        params,
    )


# ------------------------------------------------------------------------ architecture


def test_pdnet_parameter_layout_of_the_paper():
    config = P.MixerConfig()
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    leaves = jax.tree_util.tree_leaves_with_path(params)
    shapes = {jax.tree_util.keystr(k): v.shape for k, v in leaves}
    expected = {
        "['params']['conv_in']['kernel']": (5, 5, 18, 48),
        "['params']['conv_in']['bias']": (48,),
        "['params']['conv_out']['kernel']": (3, 3, 48, 9),
        "['params']['conv_out']['bias']": (9,),
    }
    for block in ("block_0", "block_1"):
        for conv in ("conv_a", "conv_b"):
            expected[f"['params']['{block}']['{conv}']['kernel']"] = (3, 3, 48, 48)
            expected[f"['params']['{block}']['{conv}']['bias']"] = (48,)
    assert shapes == expected  # six convolutions, no normalisation parameters


@pytest.mark.parametrize(
    "features, head, in_channels, out_channels",
    [
        (MIXER_FEATURES, "f_act", 18, 9),
        (MIXER_FEATURES_NO_SURE, "f_act", 12, 9),  # "w/o SURE"
        (MIXER_FEATURES, "sigmoid", 18, 3),  # "w/o f_act"
        (MIXER_FEATURES, "clip", 18, 3),
    ],
)
def test_shapes_for_the_paper_and_its_ablations(features, head, in_channels, out_channels):
    config = P.MixerConfig(features=features, head=head, width=4)
    assert (config.in_channels, config.out_channels) == (in_channels, out_channels)
    params = P.mixer_init(jax.random.PRNGKey(1), config)
    assert params["params"]["conv_in"]["kernel"].shape == (5, 5, in_channels, 4)
    assert params["params"]["conv_out"]["kernel"].shape == (3, 3, 4, out_channels)
    x, y, var, sure = random_images(0)
    alpha = P.mixer_alpha(params, config, x, y, var, sure if config.uses_sure else None)
    assert alpha.shape == (2, 9, 7, 3)
    z, alpha2 = P.mixer_apply(params, config, x, y, var, sure)
    np.testing.assert_array_equal(np.asarray(alpha), np.asarray(alpha2))
    assert z.shape == (2, 9, 7, 3)


def test_pdnet_matches_numpy_reference():
    module = PDNet(width=6, out_channels=9)
    x = np.random.default_rng(3).normal(size=(8, 7, 18)).astype(np.float32)
    params = randomized(jax.eval_shape(module.init, jax.random.PRNGKey(0), x[None]), seed=5)
    got = np.asarray(jax.jit(module.apply)(params, x[None])[0], np.float64)
    want = reference_pdnet(params, x.astype(np.float64))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * np.abs(want).max())


def test_mixer_alpha_is_head_of_network_of_mixer_inputs():
    for features, head in ((MIXER_FEATURES, "f_act"), (MIXER_FEATURES_NO_SURE, "sigmoid"),
                           (MIXER_FEATURES, "clip")):
        config = P.MixerConfig(features=features, head=head, width=4)
        params = randomized(P.mixer_init(jax.random.PRNGKey(2), config), seed=7)
        x, y, var, sure = random_images(1)
        inputs = P.mixer_inputs(x, y, var, sure, features=features)
        raw = jax.jit(mixer_module(config).apply)(params, inputs)
        want = P.alpha_from_head(raw, head)
        got = P.mixer_alpha(params, config, x, y, var, sure)
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6, atol=1e-7)
        z, _ = P.mixer_apply(params, config, x, y, var, sure)
        np.testing.assert_allclose(np.asarray(z), x + np.asarray(got) * (y - x), rtol=1e-6,
                                   atol=1e-6)


@pytest.mark.parametrize("head, expected", [("f_act", 0.5), ("clip", 0.5), ("sigmoid", 0.5)])
def test_centred_head_gives_alpha_one_half_without_output_weights(head, expected):
    config = P.MixerConfig(head=head, width=4)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    np.testing.assert_array_equal(np.asarray(params["params"]["conv_out"]["bias"]),
                                  head_bias(config.out_channels, head))
    params["params"]["conv_out"]["kernel"] = jnp.zeros_like(params["params"]["conv_out"]["kernel"])
    alpha = P.mixer_alpha(params, config, *random_images(2))
    np.testing.assert_array_equal(np.asarray(alpha), expected)
    # Plain zero bias: f_act = (0 - 0) / max(0, eps) = 0, sigmoid(0) = 0.5.
    plain = P.MixerConfig(head=head, width=4, centred_head=False)
    params = P.mixer_init(jax.random.PRNGKey(0), plain)
    params["params"]["conv_out"]["kernel"] = jnp.zeros_like(params["params"]["conv_out"]["kernel"])
    alpha = P.mixer_alpha(params, plain, *random_images(2))
    np.testing.assert_array_equal(np.asarray(alpha), 0.5 if head == "sigmoid" else 0.0)


@settings(max_examples=15, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**31 - 1), scale=st.sampled_from([0.1, 1.0, 30.0]),
       head=st.sampled_from(["f_act", "sigmoid", "clip"]))
def test_alpha_is_in_the_unit_interval(seed, scale, head):
    config = P.MixerConfig(head=head, width=4)
    params = randomized(P.mixer_init(jax.random.PRNGKey(0), config), seed=seed, scale=scale)
    x, y, var, sure = random_images(seed % 1000)
    alpha = np.asarray(P.mixer_alpha(params, config, 10 * x, y, var, 100 * sure))
    assert np.all(np.isfinite(alpha)) and alpha.min() >= 0.0 and alpha.max() <= 1.0


def test_mixer_is_differentiable_in_params():
    config = P.MixerConfig(width=4)
    params = randomized(P.mixer_init(jax.random.PRNGKey(0), config), seed=1, scale=0.3)
    x, y, var, sure = random_images(4)
    ref = (x + y) / 2

    def loss(p):
        z, _ = P.mixer_apply(p, config, x, y, var, sure)
        return jnp.mean((z - ref) ** 2)

    grads = jax.grad(loss)(params)
    norms = [float(jnp.linalg.norm(g)) for g in jax.tree_util.tree_leaves(grads)]
    assert all(np.isfinite(norms)) and max(norms) > 0
    # The gradient's directional derivative equals a central difference along a random
    # direction in parameter space. 92 % of these alphas sit on the [0, 1] clip, whose kinks
    # a large step crosses: float32, eps 1e-4 measured 0.8 % apart (1e-5: 0.07 %, 1e-3: 10 %);
    # bound 3 %.
    leaves, treedef = jax.tree_util.tree_flatten(params)
    keys = jax.random.split(jax.random.PRNGKey(7), len(leaves))
    direction = treedef.unflatten([jax.random.normal(k, a.shape) for k, a in zip(keys, leaves)])
    along = sum(float(jnp.vdot(g, d)) for g, d in zip(jax.tree_util.tree_leaves(grads),
                                                       jax.tree_util.tree_leaves(direction)))
    eps = 1e-4
    shifted = [jax.tree_util.tree_map(lambda p, d, s=s: p + s * eps * d, params, direction)
               for s in (1.0, -1.0)]
    central = (float(loss(shifted[0])) - float(loss(shifted[1]))) / (2 * eps)
    assert abs(along) > 1e-6
    assert abs(central - along) < 0.03 * abs(along), (central, along)


# ------------------------------------------------------------------------ swap symmetry


def test_swap_symmetry_matches_its_definition():
    config = P.MixerConfig(width=4)
    params = randomized(P.mixer_init(jax.random.PRNGKey(0), config), seed=3, scale=0.5)
    x, y, var, sure = random_images(5)
    a = np.asarray(P.mixer_alpha(params, config, x, y, var, sure))
    b = np.asarray(P.mixer_alpha(params, config, y, x, sure, var))
    gap = P.swap_symmetry(params, config, x, y, var, sure)
    assert gap == pytest.approx(float(np.mean(np.abs(a - (1 - b)))), rel=1e-5)
    assert 0.0 <= gap <= 1.0
    per_pixel = P.swap_symmetry(params, config, x, y, var, sure, per_pixel=True)
    assert per_pixel.shape == x.shape


def test_swap_symmetry_analytic_values():
    # Output weights zero: alpha is the head of the bias alone, the same for both calls.
    for head, bias, want in (("f_act", None, 0.0), ("sigmoid", 1.0, abs(2 / (1 + np.exp(-1)) - 1))):
        config = P.MixerConfig(head=head, width=4)
        params = P.mixer_init(jax.random.PRNGKey(0), config)
        out = params["params"]["conv_out"]
        out["kernel"] = jnp.zeros_like(out["kernel"])
        if bias is not None:
            out["bias"] = jnp.full_like(out["bias"], bias)
        gap = P.swap_symmetry(params, config, *random_images(6))
        assert gap == pytest.approx(want, abs=1e-6)


def test_no_sure_ablation_swaps_images_only():
    config = P.MixerConfig(features=MIXER_FEATURES_NO_SURE, width=4)
    params = randomized(P.mixer_init(jax.random.PRNGKey(0), config), seed=2)
    x, y, var, _ = random_images(7)
    a = np.asarray(P.mixer_alpha(params, config, x, y, var))
    b = np.asarray(P.mixer_alpha(params, config, y, x, var))
    assert P.swap_symmetry(params, config, x, y, var) == pytest.approx(
        float(np.mean(np.abs(a - (1 - b)))), rel=1e-5)


# ------------------------------------------------------------------------ config


def test_mixer_config_from_toml_dict_with_nested_tstat():
    config = load_config(
        {"features": list(MIXER_FEATURES_NO_SURE), "head": "sigmoid",
         "tstat": {"window": 7, "per_channel": True}},
        P.MixerConfig,
    )
    assert config.features == MIXER_FEATURES_NO_SURE and not config.uses_sure
    assert config.tstat == P.TStatConfig(window=7, per_channel=True)


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"features": ("hdr", "albedo")}, "albedo"),
        ({"head": "softmax"}, "softmax"),
        ({"swap_probability": 1.5}, "swap_probability"),
        ({"swap_average": "yes"}, "swap_average"),
        ({"width": 0}, "width"),
        ({"sure": {"probes": 2}}, "sure: expected a SureSettings"),
        ({"denoiser": ""}, "denoiser"),
    ],
)
def test_mixer_config_errors_name_the_field(changes, words):
    with pytest.raises(ConfigError, match=words):
        P.MixerConfig(**changes)


def test_mixer_input_errors():
    config = P.MixerConfig(width=4)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    x, y, var, sure = random_images(0)
    with pytest.raises(FrameError, match="sure"):
        P.mixer_alpha(params, config, x, y, var)
    with pytest.raises(FrameError, match="shape"):
        P.mixer_alpha(params, config, x, y[:, :-1], var, sure)


# ------------------------------------------------------------------------ checkpoints


def test_save_and_load_mixer_round_trip(tmp_path):
    config = P.MixerConfig(features=MIXER_FEATURES_NO_SURE, head="sigmoid", width=4,
                           input_transform="log")
    params = randomized(P.mixer_init(jax.random.PRNGKey(0), config), seed=9)
    path = tmp_path / "mixer.msgpack"
    P.save_mixer(path, params, config, steps=3)
    loaded, loaded_config = P.load_mixer(path)
    assert loaded_config == config and loaded_config.input_transform == "log"
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(loaded)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta["kind"] == "mixer" and meta["steps"] == 3
    assert meta["layout"]["in_channels"] == 12 and meta["layout"]["channels"]["var"] == [6, 9]


def _tamper(path, edit):
    meta_path = path.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    edit(meta)
    meta_path.write_text(json.dumps(meta))


def test_mixer_checkpoint_mismatches_are_checkpoint_errors(tmp_path):
    config = P.MixerConfig(width=4)
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    path = tmp_path / "m.msgpack"

    # Parameters for 18 inputs, record claiming the 12-channel "w/o SURE" features.
    P.save_mixer(path, params, config)

    def to_no_sure(meta):
        meta["model_config"]["features"] = list(MIXER_FEATURES_NO_SURE)
        meta["layout"] = P.mixer_layout(P.MixerConfig(features=MIXER_FEATURES_NO_SURE, width=4))

    _tamper(path, to_no_sure)
    with pytest.raises(CheckpointError, match=r"conv_in.*\(5, 5, 18, 4\).*\(5, 5, 12, 4\)"):
        P.load_mixer(path)

    # A recorded layout that differs from what this jaxden builds for the same config.
    P.save_mixer(path, params, config)
    _tamper(path, lambda meta: meta["layout"].update(features=meta["layout"]["features"][::-1]))
    with pytest.raises(CheckpointError, match="layout.*features"):
        P.load_mixer(path)

    # Features other than the caller needs.
    P.save_mixer(path, params, config)
    with pytest.raises(CheckpointError, match="trained on features"):
        P.load_mixer(path, expect_features=MIXER_FEATURES_NO_SURE)

    # A config this jaxden cannot read.
    _tamper(path, lambda meta: meta["model_config"].update(colour_space="aces"))
    with pytest.raises(CheckpointError, match="colour_space"):
        P.load_mixer(path)


def test_denoiser_checkpoint_is_not_a_mixer(tmp_path):
    path = tmp_path / "unet.msgpack"
    save_weights(path, {"w": np.zeros(3, np.float32)},
                 {"kind": "denoiser", "model": "unet", "model_config": {}})
    with pytest.raises(CheckpointError, match="'denoiser' checkpoint.*not a mixer"):
        P.load_mixer(path)
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        P.load_mixer(tmp_path / "missing")


def test_mixer_init_is_lecun_normal_and_matches_flax_structure():
    config = P.MixerConfig()
    params = P.mixer_init(jax.random.PRNGKey(0), config)
    flax_params = jax.eval_shape(mixer_module(config).init, jax.random.PRNGKey(0),
                                 jnp.zeros((1, 8, 8, 18)))
    assert jax.tree_util.tree_structure(params) == jax.tree_util.tree_structure(flax_params)
    # 3 x 3 x 48 x 48 = 20736 draws: the sample std is within 3 % (about 6 standard errors)
    # of 1 / sqrt(fan_in), fan_in = 432; the mean within 6 standard errors of 0.
    kernel = np.asarray(params["params"]["block_0"]["conv_a"]["kernel"])
    assert np.std(kernel) == pytest.approx(1 / np.sqrt(432), rel=0.03)
    assert abs(np.mean(kernel)) < 6 * (1 / np.sqrt(432)) / np.sqrt(kernel.size)
    assert np.all(np.asarray(params["params"]["block_1"]["conv_b"]["bias"]) == 0)
    # The output kernel is scaled by init_output_scale (0.1): 3888 draws, std within 5 %.
    out = np.asarray(params["params"]["conv_out"]["kernel"])
    assert np.std(out) == pytest.approx(0.1 / np.sqrt(432), rel=0.05)
    again = P.mixer_init(jax.random.PRNGKey(0), config)
    other = P.mixer_init(jax.random.PRNGKey(1), config)
    np.testing.assert_array_equal(kernel,
                                  np.asarray(again["params"]["block_0"]["conv_a"]["kernel"]))
    assert not np.array_equal(kernel, np.asarray(other["params"]["block_0"]["conv_a"]["kernel"]))
    # Different kernels are different parts of the sequence, not copies.
    assert not np.allclose(kernel, np.asarray(params["params"]["block_0"]["conv_b"]["kernel"]))


SAVE_ON_TWO_DEVICES = """
import os, sys
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
import jax, jax.numpy as jnp, optax
from jaxden import progressive as P
from jaxden.checkpoint import Checkpointer
from jaxden.progressive.mixer import mixer_meta
from jaxden.train.loop import TrainState
from jaxden.train.sharding import data_mesh, replicate
assert len(jax.devices()) == 2
config = P.MixerConfig(width=4)
params = P.mixer_init(jax.random.PRNGKey(3), config)
optimizer = optax.adam(1e-3)
state = replicate(TrainState(params, optimizer.init(params), jnp.asarray(5)), data_mesh())
checkpointer = Checkpointer(sys.argv[1])
checkpointer.save(5, state, mixer_meta(config))
checkpointer.wait()
checkpointer.close()
"""


LOAD_ON_ONE_DEVICE = """
import os, sys
os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=1"
import jax, numpy as np
from jaxden import progressive as P
assert len(jax.devices()) == 1, jax.devices()
params, config = P.load_mixer(sys.argv[1])
assert config == P.MixerConfig(width=4), config
want = P.mixer_init(jax.random.PRNGKey(3), config)
leaves = jax.tree_util.tree_leaves(params)
assert len(leaves) == len(jax.tree_util.tree_leaves(want))
for a, b in zip(jax.tree_util.tree_leaves(want), leaves):
    assert len(b.devices()) == 1, b.sharding  # a plain one-device array, not a sharded view
    np.testing.assert_array_equal(np.asarray(b), np.asarray(a))
print("LOADED", len(leaves))
"""


@pytest.mark.slow  # ~15 s idle: trains a mixer on 2 devices, loads it on 1
def test_load_mixer_from_a_run_on_another_device_count(tmp_path):
    """`jaxden train` with two virtual CPU devices (as mixer-oidn.toml recommends) saves arrays
    sharded over both; a one-device process must still load the mixer. conftest gives this
    process two devices, so the one-device load runs in a subprocess started with one."""
    import subprocess
    import sys

    workdir = tmp_path / "run"
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    subprocess.run([sys.executable, "-c", SAVE_ON_TWO_DEVICES, str(workdir)], check=True,
                   env=env, timeout=300)
    # Both processes draw the init on the CPU: the loaded arrays equal it exactly.
    loaded = subprocess.run([sys.executable, "-c", LOAD_ON_ONE_DEVICE, str(workdir)],
                            env=env, timeout=300, capture_output=True, text=True,
                            check=False)
    assert loaded.returncode == 0, loaded.stderr[-3000:]
    assert loaded.stdout.split() == ["LOADED", str(len(jax.tree_util.tree_leaves(
        P.mixer_init(jax.random.PRNGKey(3), P.MixerConfig(width=4)))))]
    # ... and this (two-device) process loads it too.
    params, config = P.load_mixer(workdir)
    assert config == P.MixerConfig(width=4)
    want = P.mixer_init(jax.random.PRNGKey(3), config)
    # Equal to float32 rounding: the saving process draws its init on the CPU, this one on
    # whatever backend it runs (an H100's normal draws differ from the CPU's in the last bit).
    for a, b in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(params)):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-6, atol=1e-7)
