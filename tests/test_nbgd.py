"""NBGD (jaxden.denoise.nn.nbgd, registered by jaxden.denoise.rt_baselines): the bilateral grid's
splat and slice against NumPy loops over every cell, splat-then-slice of a constant, the
gradients in the guide and the values against finite differences, and the model: shapes,
parameter count, receptive field and tiles, a training smoke and the `jaxden train` path."""

from __future__ import annotations

import tomllib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jaxden.denoise.rt_baselines as rt
from jaxden.denoise.nn import nbgd
from jaxden.denoise.registry import make_denoiser
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame
from jaxden.render.synthetic import synthetic_render
from jaxden.train.losses import get_loss

ROOT = Path(__file__).resolve().parent.parent


def _tent(t):
    return max(0.0, 1.0 - np.sqrt(t * t + 1e-8))


def _cell_weight(y, x, g, i, j, d, spatial, range_size):
    """The trilinear tent weight of pixel (y, x) with guide g for cell (i, j, d)."""
    return (_tent((y + 0.5) / spatial - (i + 0.5)) * _tent((x + 0.5) / spatial - (j + 0.5))
            * _tent((g + 0.5) / range_size - (d + 0.5)))


def splat_reference(values, guide, spatial, range_size):
    """(H, W, C), (H, W) -> grid: every pixel added into every cell with its tent weight."""
    height, width, channels = values.shape
    rows, cols, bins = -(-height // spatial), -(-width // spatial), 256 // range_size
    num = np.zeros((rows, cols, bins, channels))
    den = np.zeros((rows, cols, bins, 1))
    for y in range(height):
        for x in range(width):
            for i in range(rows):
                for j in range(cols):
                    for d in range(bins):
                        w = _cell_weight(y, x, guide[y, x], i, j, d, spatial, range_size)
                        num[i, j, d] += w * values[y, x]
                        den[i, j, d] += w
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def slice_reference(grid, guide, spatial, range_size):
    """grid, (H, W) -> (H, W, C): per pixel and channel, the tent-weighted mean over every
    cell whose value is > 0."""
    height, width = guide.shape
    rows, cols, bins, channels = grid.shape
    out = np.zeros((height, width, channels))
    for y in range(height):
        for x in range(width):
            for c in range(channels):
                num = den = 0.0
                for i in range(rows):
                    for j in range(cols):
                        for d in range(bins):
                            w = _cell_weight(y, x, guide[y, x], i, j, d, spatial, range_size)
                            if w > 0 and grid[i, j, d, c] > 0:
                                num += w * grid[i, j, d, c]
                                den += w
                out[y, x, c] = num / den if den > 0 else 0.0
    return out


def test_splat_matches_a_loop_over_pixels_and_cells():
    rng = np.random.default_rng(0)
    values = rng.uniform(0, 3, (2, 7, 9, 2))
    # guides inside and outside [0, 255]; one on a cell centre ((g + 0.5) / r - 0.5 integer)
    guide = rng.uniform(-20, 275, (2, 7, 9))
    guide[0, 0, 0] = 2 * 32 + 15.5
    for spatial, range_size in ((2, 32), (4, 64), (3, 16)):
        grid = np.asarray(nbgd.splat(jnp.asarray(values, jnp.float32),
                                     jnp.asarray(guide, jnp.float32), spatial, range_size))
        for n in range(2):
            expected = splat_reference(values[n], guide[n], spatial, range_size)
            assert grid[n].shape == expected.shape
            np.testing.assert_allclose(grid[n], expected, rtol=2e-5, atol=1e-6)


def test_slice_matches_a_loop_with_empty_and_negative_cells_skipped():
    rng = np.random.default_rng(1)
    height, width, spatial, range_size = 6, 7, 2, 32
    rows, cols, bins = nbgd.grid_shape(height, width, spatial, range_size)
    grid = rng.normal(size=(rows, cols, bins, 3))  # about half the cells skipped per channel
    grid[rng.uniform(size=grid.shape) < 0.2] = 0.0
    guide = rng.uniform(-10, 265, (height, width))
    out = np.asarray(nbgd.slice_grid(jnp.asarray(grid, jnp.float32),
                                     jnp.asarray(guide, jnp.float32), spatial, range_size))
    np.testing.assert_allclose(out, slice_reference(grid, guide, spatial, range_size),
                               rtol=2e-5, atol=1e-6)


def test_splat_then_slice_of_a_constant_is_the_constant():
    rng = np.random.default_rng(2)
    constant = np.array([0.3, 2.0, 7.0], np.float32)
    for height, width, spatial, range_size in ((16, 16, 4, 4), (13, 21, 8, 8), (9, 5, 16, 16)):
        guide = jnp.asarray(rng.uniform(0, 255, (2, height, width)), jnp.float32)
        values = jnp.broadcast_to(constant, (2, height, width, 3))
        out = nbgd.bilateral_filter(values, guide, spatial, range_size)
        np.testing.assert_allclose(np.asarray(out), np.broadcast_to(constant, out.shape),
                                   rtol=1e-5)


def _away_from_kinks(guide, range_size, margin=0.05):
    """Guides whose cell coordinate is not within ``margin`` of an integer (where the tents
    have their kinks and the set of cells changes)."""
    coord = (guide + 0.5) / range_size - 0.5
    frac = coord - np.floor(coord)
    return (frac > margin) & (frac < 1 - margin)


def test_gradients_in_guide_and_values_match_finite_differences():
    """Central differences in float64 with step 1e-4 (guide units) / 1e-5 (values), at pixels
    whose guide is away from the tents' kinks: agreement to 1e-5 relative."""
    spatial, range_size, eps = 2, 16, 1e-4
    rng = np.random.default_rng(3)
    values = rng.uniform(0.1, 2.0, (6, 6, 3))
    guide = rng.uniform(5, 250, (6, 6))
    weights = rng.normal(size=(6, 6, 3))
    with jax.enable_x64(True):
        def loss(v, g):
            return jnp.sum(jnp.asarray(weights) * nbgd.bilateral_filter(v, g, spatial, range_size))

        v64, g64 = jnp.asarray(values), jnp.asarray(guide)
        grad_v, grad_g = jax.grad(loss, argnums=(0, 1))(v64, g64)
        assert np.isfinite(np.asarray(grad_g)).all() and np.abs(np.asarray(grad_g)).max() > 0
        points = np.argwhere(_away_from_kinks(guide, range_size))[:4]
        assert len(points) == 4
        for y, x in points:
            step = np.zeros_like(guide)
            step[y, x] = eps
            fd = (loss(v64, g64 + step) - loss(v64, g64 - step)) / (2 * eps)
            np.testing.assert_allclose(float(grad_g[y, x]), float(fd), rtol=1e-5, atol=1e-9)
            step = np.zeros_like(values)
            step[y, x, 1] = 1e-5
            fd = (loss(v64 + step, g64) - loss(v64 - step, g64)) / 2e-5
            np.testing.assert_allclose(float(grad_v[y, x, 1]), float(fd), rtol=1e-5, atol=1e-9)
        # forward mode (SURE's jvp) agrees with reverse mode
        tangent = rng.normal(size=guide.shape)
        _, jvp = jax.jvp(lambda g: loss(v64, g), (g64,), (jnp.asarray(tangent),))
        np.testing.assert_allclose(float(jvp), float(jnp.sum(grad_g * tangent)), rtol=1e-10)


def test_float32_gradients_are_finite_at_cell_centres_and_outside_the_range():
    guide = jnp.asarray(np.array([[3.5, 0.0, 255.0, -40.0], [300.0, 7.5, 11.5, 128.0]]),
                        jnp.float32)  # (g + 0.5) / 4 - 0.5 = 0.5, ...; 3.5 and 7.5: centres
    values = jnp.ones((2, 4, 3)) * jnp.arange(1, 4.0)

    def loss(v, g):
        return jnp.sum(nbgd.bilateral_filter(v, g, 4, 4) ** 2)

    for grad in jax.grad(loss, argnums=(0, 1))(values, guide):
        assert bool(jnp.all(jnp.isfinite(grad)))


def test_grid_ops_refuse_wrong_shapes():
    with pytest.raises(FrameError, match="guide"):
        nbgd.splat(jnp.zeros((4, 4, 3)), jnp.zeros((4, 5)), 2, 32)
    grid = nbgd.splat(jnp.zeros((4, 4, 3)), jnp.zeros((4, 4)), 2, 32)
    with pytest.raises(FrameError, match="slice_grid"):
        nbgd.slice_grid(grid, jnp.zeros((8, 8)), 2, 32)
    with pytest.raises(ConfigError, match="cell sizes"):
        nbgd.grid_shape(4, 4, 2, 512)
    with pytest.raises(ConfigError, match="one value per grid"):
        rt.NBGDConfig(grid_spatial=(4, 8), grid_range=(4, 8, 16))


# ------------------------------------------------------------------------------- the model
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


def test_nbgd_shapes_finiteness_and_parameter_count():
    den = make_denoiser("nbgd", key=jax.random.PRNGKey(0))
    # GuideNet as released: 5x5x10x20 + 20 and 5x5x20x5 + 5 = 7525 parameters
    count = sum(leaf.size for leaf in jax.tree_util.tree_leaves(den.params))
    assert count == (5 * 5 * 10 * 20 + 20) + (5 * 5 * 20 * 5 + 5) == 7525
    frame = random_frame(37, 21, batch=(2,))  # not a multiple of any cell size
    out = den(frame)
    assert out.shape == frame.color.shape and bool(jnp.all(jnp.isfinite(out)))
    assert den.definition.required(den.config) == ("color", "albedo", "normal", "depth")


def test_nbgd_with_equal_guides_and_weights_is_the_mean_of_the_three_grids():
    """Zero parameters: sigmoid(0) = 0.5, every guide 127.5 and every weight 1/2, so the
    fusion is 0.5 s1 + 0.5 s2 + 0 s3, on the irradiance, remodulated."""
    config = rt.NBGDConfig()
    shapes = jax.eval_shape(lambda: rt.nbgd_init(jax.random.PRNGKey(0), config))
    params = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
    frame = random_frame(32, 32, seed=4)
    out = jax.jit(rt.nbgd_denoise, static_argnums=1)(params, config, frame)
    albedo = np.where(frame.albedo >= 0.05, frame.albedo,
                      1.0 - 0.95 * frame.albedo / 0.05)
    irradiance = jnp.asarray(frame.color / albedo)
    guide = jnp.full((32, 32), 127.5)
    expected = nbgd.fuse_grids(jnp.full((32, 32, 5), 0.5), irradiance, ((4, 4), (8, 8), (16, 16)))
    assert np.allclose(expected, 0.5 * nbgd.bilateral_filter(irradiance, guide, 4, 4) + 0.5 * (
        nbgd.bilateral_filter(irradiance, guide, 8, 8)), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(out), np.asarray(expected) * albedo, rtol=1e-5,
                               atol=1e-6)


def test_stated_receptive_field_is_the_measured_one():
    """Pixels less than 2 s = 32 apart share a cell of the coarsest grid (31), plus the two
    5 x 5 convolutions of the guide (4): the support of one output pixel reaches 35."""
    den = make_denoiser("nbgd", key=jax.random.PRNGKey(3))
    spec = den.tile_spec()
    assert spec.radius == 35 and spec.multiple == 16
    frame = synthetic_render("field", 4, size=(112, 96))
    apply = jax.jit(lambda color, f: den.function()(f.replace(color=color))[71, 66].sum())
    grad = np.asarray(jax.grad(apply)(jnp.asarray(frame.color), frame))
    rows, cols = np.nonzero(np.abs(grad).sum(-1))
    assert max(np.abs(rows - 71).max(), np.abs(cols - 66).max()) == spec.radius


@pytest.mark.slow  # ~5 s: two more compiles of the model
def test_tiles_equal_the_whole_frame():
    from jaxden.denoise.tiled import denoise_frame

    den = make_denoiser("nbgd", key=jax.random.PRNGKey(3))
    frame = synthetic_render("field", 4, size=(112, 96))
    whole, _ = denoise_frame(den, frame, tile=0)
    tiled, plan = denoise_frame(den, frame, tile=32)
    assert plan is not None and plan.tile == 32
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-6)


def _smoke_batch():
    noisy = [synthetic_render(name, 2, seed=i, size=(32, 32)) for i, name in enumerate("ab")]
    clean = [synthetic_render(name, 4096, seed=9, size=(32, 32)) for name in "ab"]
    stack = lambda frames: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *frames)
    frame = stack([f.replace(variance=None, covariance=None, position=None) for f in noisy])
    return frame, jnp.stack([f.color for f in clean])


def train_smoke(name, steps=8, learning_rate=1e-3):
    """SMAPE before and after ``steps`` Adam steps on two 32 x 32 synthetic crops."""
    den = make_denoiser(name, key=jax.random.PRNGKey(0))
    frame, target = _smoke_batch()
    smape = get_loss("smape")
    optimizer = optax.adam(learning_rate)

    @jax.jit
    def step(params, state):
        loss, grads = jax.value_and_grad(
            lambda p: smape(den.definition.apply(p, den.config, frame), target))(params)
        updates, state = optimizer.update(grads, state, params)
        return optax.apply_updates(params, updates), state, loss

    params, state = den.params, optimizer.init(den.params)
    losses = []
    for _ in range(steps + 1):  # the last call's loss is that of the parameters after `steps`
        params, state, loss = step(params, state)
        losses.append(float(loss))
    return losses[0], losses[-1]


def test_a_few_adam_steps_lower_the_loss():
    first, last = train_smoke("nbgd", steps=8, learning_rate=1e-2)
    assert np.isfinite(last) and last < 0.97 * first, (first, last)


def test_names_are_new_and_a_second_owner_is_refused():
    import dataclasses

    from jaxden.denoise.registry import REGISTRY, register
    from jaxden.registry import PluginClashError

    assert REGISTRY.owner("nbgd") == REGISTRY.owner("mrkp") == "jaxden.denoise.rt_baselines"
    with pytest.raises(PluginClashError, match="'nbgd'"):
        register(dataclasses.replace(REGISTRY["nbgd"]), owner="someone.elses.plugin")


# ------------------------------------------------------------------------------ training
@pytest.mark.parametrize("model,config_cls", [("nbgd", "NBGDConfig"), ("mrkp", "MRKPConfig")])
def test_train_config_is_train_rt_with_the_model_changed(model, config_cls):
    """train-nbgd.toml and train-mrkp.toml are the real-time recipe with the model changed."""
    from jaxden.train.config import load_train_config
    from jaxden.train.tasks import model_config

    rt_config = tomllib.loads((ROOT / "experiments/configs/train-rt.toml").read_text())
    ours = tomllib.loads((ROOT / f"experiments/configs/train-{model}.toml").read_text())
    assert ours.pop("model") == model and rt_config.pop("model") == "wskp"
    assert ours.pop("model_config") == {}
    assert ours == rt_config
    config = load_train_config(ROOT / f"experiments/configs/train-{model}.toml")
    assert model_config(config) == getattr(rt, config_cls)()


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    from helpers import build_tiny_dataset

    return build_tiny_dataset(tmp_path_factory.mktemp("nbgd-tiny") / "tiny")


def test_jaxden_train_trains_nbgd(tiny_dataset, tmp_path, capsys):
    """`jaxden train` with the real config, pointed at the tiny dataset: 3 steps, a checkpoint
    that loads back as the denoiser."""
    from helpers import metrics_records, run_cli

    from jaxden.denoise.registry import load_denoiser

    code, errors, _ = run_cli(
        ["train", ROOT / "experiments/configs/train-nbgd.toml", "--workdir", tmp_path / "run",
         f"data.dataset={tiny_dataset}", "data.crop_size=32", "data.batch_size=1", "data.spp=[2]",
         "optim.steps=3", "eval_every=3", "eval_batches=1", "checkpoint_every=3",
         "log_every=1"], capsys)
    assert code == 0, errors
    records = metrics_records(tmp_path / "run")
    assert any(r.get("step") == 3 and np.isfinite(r.get("loss", np.nan)) for r in records)
    den = load_denoiser(tmp_path / "run")
    assert den.name == "nbgd" and den.config == rt.NBGDConfig()
