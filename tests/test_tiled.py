"""Progressive denoising over tiles (jaxden.tiling, jaxden.progressive.tiled): the tiles' probes
are the whole frame's, tiles equal the whole frame to float rounding when the overlap covers
the receptive fields (and differ at the seams when it does not), the stated receptive fields
bound the measured ones, and the memory plan refuses what cannot fit in one line."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise.registry import make_denoiser
from jaxden.frame import Frame
from jaxden.progressive.mixer_config import MixerConfig, closed_form_mixer
from jaxden.progressive.network import mixer_alpha, mixer_init
from jaxden.progressive.tiled import (
    MemoryPlanError,
    closed_form_radius,
    mixer_radius,
    progressive_denoise_tiled,
    progressive_frame,
    tile_halo,
    tstat_radius,
)
from jaxden.progressive.tstat import TStatConfig, consistent_alpha
from jaxden.render.synthetic import synthetic_render
from jaxden.sure.settings import SureSettings
from jaxden.sure.stein import window_normal
from jaxden.tiling import tile_grid


def _frame(width=120, height=100, seed=3) -> Frame:
    """The synthetic frame with a lamp (a 6 x 6 square of radiance 40) and a vertical step
    edge, both crossing tile seams of 40-pixel tiles."""
    frame = synthetic_render("tiles", 16, seed=seed, size=(width, height))
    color = np.array(frame.color)
    variance = np.array(frame.variance)
    rng = np.random.default_rng(seed)
    color[:, 77:] *= 0.2                       # an edge at column 77 (seam at 80)
    variance[:, 77:] *= 0.04
    lamp = (slice(37, 43), slice(37, 43))      # across the seams at row 40 and column 40
    noise = rng.normal(size=color[lamp].shape).astype(np.float32)
    color[lamp] = 40.0 + 4.0 * noise
    variance[lamp] = 16.0
    return frame.replace(color=color, variance=variance, covariance=None, spp=16.0)


def _rel(a, b) -> float:
    return float(np.sqrt(np.mean(np.square(a - b))) / np.sqrt(np.mean(np.square(b))))


def test_window_normal_is_the_slice_of_the_whole_draw():
    key = jax.random.PRNGKey(7)
    shape = (37, 53, 3)
    whole = jax.random.normal(key, (math.prod(shape),), jnp.float32).reshape(shape)
    window = window_normal(key, shape, jnp.asarray([5, 11]), (20, 30))
    np.testing.assert_array_equal(np.asarray(window), np.asarray(whole)[5:25, 11:41])


def test_tile_grid_covers_once_with_the_halo_and_one_window_size():
    for height, width, tile, halo, multiple in ((100, 130, 32, 7, 1), (1080, 1920, 512, 59, 1),
                                                (300, 257, 64, 109, 16), (50, 50, 64, 5, 1)):
        tiles = tile_grid(height, width, tile, halo, multiple)
        covered = np.zeros((height, width), np.int32)
        for t in tiles:
            covered[t.out_slices] += 1
            (r0, r1), (c0, c1) = t.out
            (s0, s1), (u0, u1) = t.src
            assert s0 % multiple == 0 and u0 % multiple == 0
            assert r0 - s0 >= halo or s0 == 0
            assert s1 - r1 >= halo or s1 == height
            assert c0 - u0 >= halo or u0 == 0
            assert u1 - c1 >= halo or u1 == width
        assert (covered == 1).all()
        sizes = {t.src_shape for t in tiles}
        assert len(sizes) <= (1 if multiple == 1 else 4), sizes


@pytest.fixture(scope="module")
def small_kp():
    from jaxden.denoise.nn.wskp import KPConfig

    return make_denoiser("kp", KPConfig(num_layers=2, width=4, kernel_size=5),
                         key=jax.random.PRNGKey(0))


def test_tiles_equal_the_whole_frame_and_a_short_overlap_shows(small_kp):
    """kp (2 RepVGG layers, 5 x 5 kernels at p: radius 4) with SURE by jvp, the closed-form mixer
    at sigma 2 (radius 6) and the t-statistic with its guard (5): 17 pixels. 40-pixel tiles
    equal the whole frame. An overlap that leaves out a stage's field shows at the seams:
    5 pixels (the t-statistic's alone) in alpha', 3 (less than the denoiser's) in y and SURE. (An
    overlap short by a few pixels changes little: the last taps of a Gaussian weigh ~1e-7 of
    its centre, and this random denoiser's effective field is smaller than its stated one.)"""
    frame = _frame()
    _, config = closed_form_mixer("closed-form:sigma=2")
    key = jax.random.PRNGKey(1)
    halo = tile_halo(small_kp, config, config.tstat)
    assert halo == 4 + 6 + 5
    options = dict(sure=SureSettings(probes=2), tstat=config.tstat,
                   keep=("z", "alpha_prime", "denoised", "sure"))
    whole, plan = progressive_denoise_tiled(frame, small_kp, {}, config, key, tile=0, **options)
    assert plan.tile == 0
    tiled, plan = progressive_denoise_tiled(frame, small_kp, {}, config, key, tile=40, **options)
    assert plan.tile == 40 and plan.stage == "all"
    for name in options["keep"]:
        assert _rel(tiled[name], whole[name]) < 1e-5, name
    short, _ = progressive_denoise_tiled(frame, small_kp, {}, config, key, tile=40, halo=5,
                                         **options)
    assert _rel(short["alpha_prime"], whole["alpha_prime"]) > 1e-3
    assert _rel(short["denoised"], whole["denoised"]) < 1e-6  # y needs 4: still exact
    short, _ = progressive_denoise_tiled(frame, small_kp, {}, config, key, tile=40, halo=3,
                                         **options)
    assert _rel(short["denoised"], whole["denoised"]) > 1e-3
    assert _rel(short["sure"], whole["sure"]) > 1e-3


def test_tile_halo_covers_the_widened_guard_cap_window(small_kp):
    """With ``tstat.guard_cap_spp`` = 16 the guard's cap at 2 spp also reads a window of sigma
    sqrt(15) (12 pixels each side): where y is off x by ~10 standard errors on a 9 x 9 block (the
    cap binds on the wide window too), the guard's alpha at the block's centre reads the
    variance 12 pixels away, and the halo grows from 15 to 4 + 6 + 12; at 32 spp and without a
    sample count (the option does nothing) the guard reads its own 3. (y differs from x
    everywhere: where the residual is exactly 0 the ratio's gradient is NaN.)"""
    from jaxden.progressive.tstat import error_guard

    _, config = closed_form_mixer("closed-form:sigma=2")
    tstat = dataclasses.replace(config.tstat, guard_cap_spp=16.0)
    assert tile_halo(small_kp, config, config.tstat) == 4 + 6 + 5
    assert tile_halo(small_kp, config, tstat) == 4 + 6 + 12 and tstat_radius(tstat) == 12
    rng = np.random.default_rng(0)
    x = rng.uniform(0.5, 1.5, (40, 40, 3)).astype(np.float32)
    var = np.full_like(x, 0.01)
    y = x + 0.01 * rng.standard_normal(x.shape).astype(np.float32)
    y[16:25, 16:25] += 0.316
    alpha = np.ones_like(x)
    for spp, radius in ((2.0, 12), (32.0, 3), (None, 3)):
        measured = _support(lambda v: error_guard(alpha, x, y, v, tstat, spp=spp), var,
                            (20, 20))
        assert measured == radius, (spp, measured)


@pytest.mark.slow
def test_tiled_matches_the_untiled_pipeline_with_a_network_mixer(small_kp):
    """The same against progressive_denoise itself (separately compiled stages), with the
    paper's network mixer (radius 7) and the per-channel SURE it learned."""
    from jaxden.progressive.pipeline import progressive_denoise

    frame = _frame(seed=4)
    config = MixerConfig(width=4, denoiser="kp", sure=SureSettings(probes=1))
    params = mixer_init(jax.random.PRNGKey(2), config)
    key = jax.random.PRNGKey(5)
    z, alpha_prime, _ = progressive_denoise(frame, small_kp, params, config, key)
    outputs, plan = progressive_frame(frame, small_kp, params, config, key, tile=40)
    assert plan is not None and plan.tile == 40
    assert _rel(outputs["z"], np.asarray(z)) < 1e-5
    assert _rel(outputs["alpha_prime"], np.asarray(alpha_prime)) < 1e-5


def test_black_box_runs_whole_and_the_mixer_over_tiles():
    pytest.importorskip("pyoidn")
    from jaxden.denoise.registry import load_denoiser

    frame = _frame(96, 88, seed=5)
    _, config = closed_form_mixer("closed-form:sigma=2")
    oidn = load_denoiser("oidn")
    key = jax.random.PRNGKey(0)
    options = dict(sure=SureSettings(probes=1), tstat=config.tstat, keep=("z", "alpha"))
    whole, _ = progressive_denoise_tiled(frame, oidn, {}, config, key, tile=0, **options)
    tiled, plan = progressive_denoise_tiled(frame, oidn, {}, config, key, tile=32, **options)
    assert plan.stage == "mixer" and plan.halo == 6 + 5
    assert _rel(tiled["z"], whole["z"]) < 1e-6
    short, _ = progressive_denoise_tiled(frame, oidn, {}, config, key, tile=32, halo=4,
                                         **options)
    assert _rel(short["alpha"], whole["alpha"]) > 1e-4


# ----------------------------------------------------------------------- receptive fields
def _support(fn, image, centre) -> int:
    """Chebyshev radius of the pixels of ``image`` (H, W, C) whose gradient of channel 0 of
    ``fn(image)`` at ``centre`` is non-zero."""
    grad = jax.grad(lambda x: fn(x)[centre[0], centre[1], 0])(jnp.asarray(image))
    rows, cols = np.nonzero(np.abs(np.asarray(grad)).sum(-1))
    return int(max(np.abs(rows - centre[0]).max(), np.abs(cols - centre[1]).max()))


@pytest.mark.parametrize("name,config", [
    ("wskp", dict(num_layers=3, width=4, kernel_sizes=(3, 7))),
    ("kp", dict(num_layers=2, width=4, kernel_size=5)),
])
def test_stated_denoiser_fields_bound_the_measured_ones(name, config):
    from jaxden.denoise.registry import get_definition

    definition = get_definition(name)
    den = make_denoiser(name, definition.config_cls(**config), key=jax.random.PRNGKey(3))
    frame = synthetic_render("field", 4, size=(48, 48))
    spec = den.tile_spec()
    measured = _support(lambda c: den.function()(frame.replace(color=c)), frame.color, (24, 24))
    assert measured <= spec.radius and measured >= spec.radius - 1, (measured, spec.radius)


@pytest.mark.slow
def test_unet_field_and_pooling_grid():
    """The network itself (before the clamp at 0 that zeroes a random U-Net's gradient)."""
    from jaxden.denoise.models import UNET_RADIUS, UNetConfig
    from jaxden.denoise.nn.unet import UNet

    den = make_denoiser("unet", UNetConfig(features=("hdr",)), key=jax.random.PRNGKey(0))
    spec = den.tile_spec()
    assert spec.radius == UNET_RADIUS and spec.multiple == 16
    module = UNet((8,) * 5, (8,) * 5)
    image = jax.random.normal(jax.random.PRNGKey(1), (256, 256, 3))
    params = module.init(jax.random.PRNGKey(2), image[None])
    measured = _support(lambda x: module.apply(params, x[None])[0], image, (128, 128))
    assert 79 <= measured <= UNET_RADIUS, measured


@pytest.mark.slow
def test_stated_mixer_and_tstat_fields_bound_the_measured_ones():
    x = synthetic_render("mixer", 16, size=(64, 64))
    y = np.asarray(x.color) * 0.9
    var, sure_map = np.asarray(x.variance), np.asarray(x.variance) * 0.5
    for config in (MixerConfig(width=4), MixerConfig(kind="closed_form", closed_form_sigma=3.0),
                   MixerConfig(width=4, head="closed_form_logit", closed_form_sigma=3.0,
                               features=(*MixerConfig().features, "closed_form"))):
        params = mixer_init(jax.random.PRNGKey(0), config) if config.kind == "network" else {}
        measured = _support(lambda s: mixer_alpha(params, config, x.color, y, var, s),
                            sure_map, (32, 32))
        assert measured <= mixer_radius(config) and measured >= mixer_radius(config) - 1, (
            config.kind, config.head, measured)
    assert closed_form_radius(MixerConfig(closed_form_sigma=12.0)) == 36
    tstat = TStatConfig()
    alpha = np.full_like(y, 0.5)

    def scaled(a):
        mixed = x.color + a * (y - x.color)
        return consistent_alpha(a, x.color, y, var, mixed, tstat, 16.0)

    measured = _support(scaled, alpha, (32, 32))
    assert measured == tstat_radius(tstat) == 5


# --------------------------------------------------------------------------------- memory
def test_plan_refuses_what_cannot_fit_in_one_line(small_kp):
    frame = _frame()
    _, config = closed_form_mixer("closed-form:sigma=2")
    options = dict(sure=SureSettings(probes=1), tstat=config.tstat)
    with pytest.raises(MemoryPlanError, match="own arrays need about"):
        progressive_denoise_tiled(frame, small_kp, {}, config, jax.random.PRNGKey(0),
                                  limit=100_000, **options)
    with pytest.raises(MemoryPlanError, match=r"smallest tile \(64 px \+ 15 px overlap\)"):
        progressive_denoise_tiled(frame, small_kp, {}, config, jax.random.PRNGKey(0),
                                  limit=3_000_000, **options)
    _, plan = progressive_denoise_tiled(frame, small_kp, {}, config, jax.random.PRNGKey(0),
                                        plan_only=True, **options)
    assert plan.tile == 0 and 0 < plan.tile_bytes < plan.limit


def test_cli_refuses_a_frame_that_cannot_fit_and_writes_nothing(tmp_path, capsys):
    """`jaxden progressive` and `jaxden denoise` with a memory limit below what the frame
    needs: one line naming the stage and the memory, exit 2, no output file; an allocation
    failure from XLA is one line too."""
    from helpers import assert_one_error_line, run_cli

    from jaxden.io.exr import write_frame

    source = tmp_path / "in.exr"
    write_frame(source, _frame(64, 48))
    out = tmp_path / "out.exr"
    code, lines, _ = run_cli(["progressive", source, "--denoiser", "wskp-6", "--mixer",
                              "closed-form", "--memory-limit", "20K", "--out", out], capsys)
    assert_one_error_line(code, lines, "own arrays need about", "memory limit 20.0 KiB")
    code, lines, _ = run_cli(["progressive", source, "--denoiser", "wskp-6", "--mixer",
                              "closed-form", "--memory-limit", "200K", "--out", out], capsys)
    assert_one_error_line(code, lines, "the denoiser, SURE, mixer and t-statistic",
                          "smallest tile (64 px + 59 px overlap)")
    code, lines, _ = run_cli(["denoise", source, "--model", "wskp-6", "--memory-limit", "1M",
                              "--out", out], capsys)
    assert_one_error_line(code, lines, "denoising a 64x48 frame with wskp",
                          "smallest tile (64 px + 18 px overlap)")
    assert not out.exists()
    code, lines, _ = run_cli(["denoise", source, "--model", "wskp-6", "--memory-limit", "8X",
                              "--out", out], capsys)
    assert_one_error_line(code, lines, "--memory-limit='8X'", "such as 8G")


def test_allocation_failures_are_one_line():
    from jaxden.cli import _is_allocation_failure

    class JaxRuntimeError(Exception):
        pass

    text = "RESOURCE_EXHAUSTED: Out of memory allocating 25878533024 bytes."
    assert _is_allocation_failure(JaxRuntimeError(text))
    assert not _is_allocation_failure(JaxRuntimeError("INVALID_ARGUMENT: shapes"))
    assert not _is_allocation_failure(ValueError(text))
