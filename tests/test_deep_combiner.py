"""Deep Combiner (``dc``): the kernel combination against a NumPy loop, the weight
normalisation, the network's shapes and size, the base inside apply (jvp through base and
combiner against finite differences), training through jaxden's own train step, and the
refusal of a checkpoint over another base."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise import Denoiser, load_denoiser, make_denoiser
from jaxden.denoise import deep_combiner as dc
from jaxden.denoise.nn.combiner import (
    combine,
    combiner_inputs,
    combiner_output,
    normalize_weights,
    normalized_depth,
    receptive_radius,
    window_offset,
)
from jaxden.errors import CheckpointError, ConfigError, FrameError
from jaxden.frame import Frame

#: The authors' network: 13 -> 100 (x5) -> 225, 5 x 5 kernels with biases.
PAPER_PARAMETERS = (5 * 5 * 13 * 100 + 100) + 4 * (5 * 5 * 100 * 100 + 100) \
    + (5 * 5 * 100 * 225 + 225)
#: One frame size for the tests that run the model (their compiled programs are shared).
SIDE = 16


def random_frame(key, shape=(16, 16), batch=(), *, variance=True) -> Frame:
    keys = jax.random.split(key, 5)
    h, w = shape
    color = jax.random.uniform(keys[0], (*batch, h, w, 3), minval=0.05, maxval=1.5)
    normal = jax.random.normal(keys[1], (*batch, h, w, 3))
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)
    return Frame(
        color=color,
        variance=jnp.full(color.shape, 0.01) if variance else None,
        albedo=jax.random.uniform(keys[2], (*batch, h, w, 3)),
        normal=normal,
        depth=jax.random.uniform(keys[3], (*batch, h, w, 1), minval=1.0, maxval=5.0),
        spp=jnp.full(batch, 4.0),
    )


def numpy_combine(corr, rand, weights, kernel_size):
    """The combination as the paper writes it, one pixel and one offset at a time."""
    corr, rand, weights = (np.asarray(a, np.float64) for a in (corr, rand, weights))
    height, width, _ = corr.shape
    radius = kernel_size // 2
    out = corr.copy()
    for y in range(height):
        for x in range(width):
            for index in range(kernel_size * kernel_size):
                dy, dx = index // kernel_size - radius, index % kernel_size - radius
                qy, qx = y + dy, x + dx
                if 0 <= qy < height and 0 <= qx < width:
                    out[y, x] += weights[y, x, index] * (rand[qy, qx] - corr[qy, qx])
    return out


# ------------------------------------------------------------------------- combination
@pytest.mark.parametrize("kernel_size, shape", [(15, (6, 9)), (15, (17, 19)), (5, (7, 6))])
def test_combine_matches_numpy_loop(kernel_size, shape):
    """Windows larger than the image, and a 5 x 5 one, on batches of two images."""
    rng = np.random.default_rng(0)
    corr = rng.uniform(0, 2, (2, *shape, 3)).astype(np.float32)
    rand = rng.uniform(0, 2, (2, *shape, 3)).astype(np.float32)
    raw = rng.normal(size=(2, *shape, kernel_size * kernel_size)).astype(np.float32)
    weights = np.asarray(normalize_weights(raw))
    out = np.asarray(jax.jit(combine, static_argnums=3)(corr, rand, weights, kernel_size))
    for b in range(2):
        np.testing.assert_allclose(out[b], numpy_combine(corr[b], rand[b], weights[b],
                                                         kernel_size), rtol=1e-5, atol=1e-6)


def test_window_order_is_row_major():
    """Weight channel i picks the neighbour at (i // 15 - 7, i % 15 - 7)."""
    assert window_offset(0) == (-7, -7)
    assert window_offset(7) == (-7, 0)
    assert window_offset(14) == (-7, 7)
    assert window_offset(15) == (-6, -7)
    assert window_offset(112) == (0, 0)
    assert window_offset(224) == (7, 7)
    h, w = 20, 20
    rand = np.arange(h * w * 3, dtype=np.float32).reshape(h, w, 3)
    corr = np.zeros_like(rand)
    for index in (0, 16, 112, 200):
        weights = np.zeros((h, w, 225), np.float32)
        weights[..., index] = 1.0
        dy, dx = window_offset(index)
        out = np.asarray(combine(corr, rand, weights))
        np.testing.assert_array_equal(out[10, 10], rand[10 + dy, 10 + dx])


def test_normalize_weights_sum_to_one_or_zero():
    raw = np.random.default_rng(1).normal(size=(4, 5, 225)).astype(np.float32)
    raw[0, 0] = -np.abs(raw[0, 0])  # every weight <= 0 at one pixel
    raw[1, 1] = 0.0
    weights = np.asarray(normalize_weights(raw))
    sums = weights.sum(-1)
    assert (weights >= 0).all()
    assert sums[0, 0] == 0 and sums[1, 1] == 0
    mask = np.ones(sums.shape, bool)
    mask[0, 0] = mask[1, 1] = False
    np.testing.assert_allclose(sums[mask], 1.0, rtol=1e-5)
    # all weights 0: the output is corr itself, bit for bit
    rng = np.random.default_rng(2)
    corr = rng.uniform(size=(4, 5, 3)).astype(np.float32)
    rand = rng.uniform(size=(4, 5, 3)).astype(np.float32)
    out = np.asarray(combine(corr, rand, np.zeros((4, 5, 225), np.float32)))
    np.testing.assert_array_equal(out, corr)


def test_combine_checks_shapes():
    good = np.zeros((4, 5, 3), np.float32)
    with pytest.raises(FrameError, match="weights must have shape"):
        combine(good, good, np.zeros((4, 5, 224), np.float32))
    with pytest.raises(FrameError, match="one shape"):
        combine(good, np.zeros((4, 6, 3), np.float32), np.zeros((4, 5, 225), np.float32))
    with pytest.raises(ConfigError, match="odd"):
        combine(good, good, np.zeros((4, 5, 16), np.float32), kernel_size=4)


def test_inputs_and_depth():
    frame = random_frame(jax.random.PRNGKey(3), (8, 8))
    x = jax.jit(combiner_inputs)(frame.color, frame.color * 0.5, frame.normal, frame.albedo,
                                 frame.depth)
    assert x.shape == (8, 8, 13)
    depth = np.asarray(x[..., 12])
    assert depth.min() == 0.0 and depth.max() == pytest.approx(1.0)
    assert np.all(np.asarray(normalized_depth(frame.depth, "zero")) == 0)
    assert np.all(np.asarray(normalized_depth(jnp.ones((4, 4, 1)))) == 0)  # a flat image
    assert receptive_radius() == 12


# ----------------------------------------------------------------------------- the model
@pytest.fixture
def passthrough_base(monkeypatch):
    """``dc`` over a base whose output is its input colour (resolve_base patched)."""
    base = Denoiser.from_function(lambda frame: frame.color, name="passthrough")
    digest = dc.base_sha256(base)
    monkeypatch.setattr(dc, "resolve_base", lambda spec: (base, digest))
    return base


def test_dc_over_identity_base_returns_colour(passthrough_base):
    config = dc.DeepCombinerConfig(base="passthrough")
    model = make_denoiser("dc", config, key=jax.random.PRNGKey(6))
    frame = random_frame(jax.random.PRNGKey(7), (SIDE, SIDE))
    np.testing.assert_array_equal(np.asarray(model(frame)), np.asarray(frame.color))


@pytest.fixture(scope="module")
def model():
    """``dc`` over the shipped WSKP-6 with freshly drawn combiner weights."""
    return make_denoiser("dc", key=jax.random.PRNGKey(0))


def test_init_apply_shapes_and_parameter_count(model):
    assert model.config.base == "wskp-6" and len(model.config.base_sha256) == 64
    leaves = jax.tree_util.tree_leaves(model.params)
    assert sum(leaf.size for leaf in leaves) == PAPER_PARAMETERS == 1_595_725
    assert len(leaves) == 12  # six kernels and six biases: no base weight among them
    shapes = jax.tree_util.tree_map(jnp.shape, model.params)["params"]
    assert shapes["conv0"]["kernel"] == (5, 5, 13, 100)
    assert shapes["conv5"]["kernel"] == (5, 5, 100, 225)
    assert model.fields_read() == ("color", "albedo", "normal", "depth")
    batch = random_frame(jax.random.PRNGKey(1), (SIDE, SIDE), (2,))
    out = model(batch)
    assert out.shape == (2, SIDE, SIDE, 3) and bool(jnp.all(jnp.isfinite(out)))
    single = model(jax.tree_util.tree_map(lambda a: a[1], batch))
    np.testing.assert_allclose(np.asarray(single), np.asarray(out[1]), rtol=1e-5, atol=1e-6)


def test_jvp_through_base_and_combiner_matches_finite_differences(model):
    """d out / d colour along a tangent, by jax.jvp through WSKP-6 and the combiner, against
    central differences with step h = 1e-2 in float32, at every pixel and channel: equal to
    within 1 % of the largest |jvp| (measured: 0.4 %; the ReLU kinks and float32 rounding
    bound how close a difference quotient gets). The base's part counts: the jvp with the
    base's output held fixed differs from it by more than 10 % of that scale."""
    frame = random_frame(jax.random.PRNGKey(3), (SIDE, SIDE))
    tangent = jax.random.normal(jax.random.PRNGKey(4), frame.color.shape) * 0.1
    fn = model.function()

    def of_colour(color):
        return fn(frame.replace(color=color))

    jvp = jax.jit(lambda c, t: jax.jvp(of_colour, (c,), (t,))[1])(frame.color, tangent)
    h = 1e-2
    fd = (of_colour(frame.color + h * tangent) - of_colour(frame.color - h * tangent)) / (2 * h)
    scale = float(jnp.max(jnp.abs(jvp)))
    np.testing.assert_allclose(np.asarray(fd), np.asarray(jvp), atol=0.01 * scale, rtol=0)

    base = dc.checked_base(model.config)
    corr = base.function()(frame)

    def combiner_only(color):
        return combiner_output(dc.combiner_net(model.config), model.params, corr, color,
                               frame.normal, frame.albedo, frame.depth)

    fixed = jax.jit(lambda c, t: jax.jvp(combiner_only, (c,), (t,))[1])(frame.color, tangent)
    assert float(jnp.max(jnp.abs(fixed - jvp))) > 0.1 * scale, float(
        jnp.max(jnp.abs(fixed - jvp))) / scale


def test_relmse_dc_loss():
    from jaxden.train.losses import get_loss

    rng = np.random.default_rng(5)
    x = rng.uniform(size=(2, 4, 5, 3)).astype(np.float32)
    y = rng.uniform(size=(2, 4, 5, 3)).astype(np.float32)
    expected = np.mean((x - y) ** 2 / (y.mean(-1, keepdims=True) ** 2 + 0.01))
    assert float(get_loss("relmse_dc")(x, y)) == pytest.approx(expected, rel=1e-5)
    with pytest.raises(FrameError):
        dc.relmse_channel_mean(x, y[:, :3])


def test_training_steps_lower_relmse():
    """Five steps of jaxden's own train step (model 'dc' through its Task) on one synthetic
    batch lower the relMSE; the optimiser holds the combiner's parameters only."""
    from jaxden.train.config import OptimConfig, TrainConfig
    from jaxden.train.loop import TrainState, make_train_step
    from jaxden.train.optim import loss_function, make_optimizer
    from jaxden.train.tasks import make_task

    config = TrainConfig(model="dc", optim=OptimConfig(
        steps=5, learning_rate=1e-4, schedule="constant", loss="relmse_dc"))
    task = make_task(config)
    assert task.features == ("color", "albedo", "normal", "depth")
    frame = random_frame(jax.random.PRNGKey(8), (SIDE, SIDE), (2,), variance=False)
    reference = jnp.asarray(frame.color)
    noisy = frame.replace(color=reference * jax.random.gamma(
        jax.random.PRNGKey(9), 2.0, reference.shape) / 2.0)  # mean-preserving noise
    batch = {"input": noisy, "reference": reference}
    params = task.init(jax.random.PRNGKey(10), batch)
    optimizer = make_optimizer(config.optim)
    state = TrainState(params, optimizer.init(params), jnp.asarray(0, jnp.int32))
    with_mu = lambda node: hasattr(node, "mu")  # Adam's state
    adam_mu = next(s for s in jax.tree_util.tree_leaves(state.opt_state, is_leaf=with_mu)
                   if with_mu(s)).mu
    assert jax.tree_util.tree_structure(adam_mu) == jax.tree_util.tree_structure(params)
    step = jax.jit(make_train_step(task, optimizer, loss_function("relmse_dc")))
    losses = []
    for _ in range(6):
        state, metrics = step(state, batch)
        losses.append(float(metrics["loss"]))
    assert all(np.isfinite(losses))
    assert losses[-1] < 0.9 * losses[0], losses


# ----------------------------------------------------------------------- checkpoints
def _save_base(path, seed):
    from jaxden.checkpoint import save_weights

    base = make_denoiser("kp1", key=jax.random.PRNGKey(seed))
    save_weights(path, base.params, {"kind": "denoiser", "model": "kp1", "model_config": {}})


def test_checkpoint_over_another_base_is_refused(tmp_path):
    from jaxden.checkpoint import save_weights
    from jaxden.config import config_to_dict

    base_file = tmp_path / "base.msgpack"
    _save_base(base_file, seed=0)
    config = dc.DeepCombinerConfig(base=str(base_file))
    model = make_denoiser("dc", config, key=jax.random.PRNGKey(1))
    meta = {"kind": "denoiser", "model": "dc", "model_config": config_to_dict(config)}
    save_weights(tmp_path / "dc.msgpack", model.params, meta)
    loaded = load_denoiser(str(tmp_path / "dc.msgpack"))
    assert loaded.config == config

    # the base's file retrained: other weights under the same name
    _save_base(base_file, seed=1)
    with pytest.raises(CheckpointError, match="trained over base .*base.msgpack"):
        load_denoiser(str(tmp_path / "dc.msgpack"))
    with pytest.raises(dc.BaseMismatchError):
        model.function()(random_frame(jax.random.PRNGKey(2), (8, 8)))  # apply refuses too

    # the config edited to name another base, with the old digest
    meta["model_config"]["base"] = "wskp-6"
    (tmp_path / "dc.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="trained over base 'wskp-6'"):
        load_denoiser(str(tmp_path / "dc.msgpack"))


def test_black_box_base_is_refused():
    with pytest.raises(ConfigError, match="black box"):
        dc.DeepCombinerConfig(base="oidn")


@pytest.mark.slow
def test_oidn_jax_base_jvp_matches_finite_differences():
    """As the WSKP-6 test, over OIDN in JAX (a U-Net with max pooling) on a 32 x 32 frame,
    h = 1e-2: the difference quotients cross more kinks (pooling switches), so the criterion
    is on quantiles of |fd - jvp| / max |jvp|: median below 0.5 %, 99th percentile below
    3 % (measured: 0.09 %, 1.1 %; the largest, 7 %, at a few pooling switches)."""
    model = make_denoiser("dc", dc.DeepCombinerConfig(base="oidn-jax"),
                          key=jax.random.PRNGKey(2))
    assert model.fields_read()[:3] == ("color", "albedo", "normal")
    frame = random_frame(jax.random.PRNGKey(3), (32, 32))
    tangent = jax.random.normal(jax.random.PRNGKey(4), frame.color.shape) * 0.1
    fn = model.function()

    def of_colour(color):
        return fn(frame.replace(color=color))

    jvp = jax.jit(lambda c, t: jax.jvp(of_colour, (c,), (t,))[1])(frame.color, tangent)
    h = 1e-2
    fd = (of_colour(frame.color + h * tangent) - of_colour(frame.color - h * tangent)) / (2 * h)
    error = np.abs(np.asarray(fd - jvp)) / float(jnp.max(jnp.abs(jvp)))
    assert np.median(error) < 0.005 and np.quantile(error, 0.99) < 0.03, (
        np.median(error), np.quantile(error, 0.99))


@pytest.mark.slow
def test_train_load_sure_progressive_and_resume_over_another_base(tmp_path):
    """jaxden's loop trains a (narrow) dc over a base file on the tiny dataset; its workdir
    loads as a denoiser; SURE by jvp and progressive denoising run through it. Once the base
    file holds other weights, neither loading the workdir nor resuming the run is allowed."""
    from helpers import build_tiny_dataset

    from jaxden.progressive import closed_form_mixer, progressive_denoise
    from jaxden.sure import sure
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import train_and_evaluate

    dataset = build_tiny_dataset(tmp_path / "tiny")
    base_file = tmp_path / "base.msgpack"
    _save_base(base_file, seed=0)
    toml = tmp_path / "train.toml"
    toml.write_text(f"""
model = "dc"
log_every = 1
eval_every = 2
eval_batches = 1
checkpoint_every = 2
[model_config]
base = "{base_file}"
hidden_widths = [8, 8, 8, 8, 8]
[data]
dataset = "{dataset}"
crop_size = 16
batch_size = 2
[optim]
steps = 4
learning_rate = 1e-4
schedule = "constant"
loss = "relmse_dc"
""")
    workdir = tmp_path / "run"
    result = train_and_evaluate(load_train_config(toml), workdir, progress=False,
                                stop_after=2, tensorboard=False)
    assert np.isfinite(result["val_loss"])
    model = load_denoiser(str(workdir))
    assert model.name == "dc" and model.config.hidden_widths == (8,) * 5
    frame = random_frame(jax.random.PRNGKey(0), (32, 32))
    estimate = sure(model.function(), frame, jax.random.PRNGKey(1), 2, "jvp")
    assert bool(jnp.all(jnp.isfinite(estimate.sure)))
    mixer_params, mixer_config = closed_form_mixer()
    image = progressive_denoise(frame, model, mixer_params, mixer_config,
                                jax.random.PRNGKey(2))[0]
    assert image.shape == (32, 32, 3) and bool(jnp.all(jnp.isfinite(image)))

    _save_base(base_file, seed=1)  # the base retrained
    with pytest.raises(CheckpointError, match="trained over base"):
        load_denoiser(str(workdir))
    with pytest.raises(CheckpointError, match="base_sha256"):
        train_and_evaluate(load_train_config(toml), workdir, progress=False, tensorboard=False)
