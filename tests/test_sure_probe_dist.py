"""Rademacher SURE probes (``probe_dist="rademacher"``, jaxden.sure.stein): they are the signs of
the normal draws (so every path that shares a key shares them), the divergence estimate stays
unbiased with the variance the module docstring states (no diagonal term), one probe is exact
through a diagonal Jacobian, tiles and the black-box path see the whole frame's probes, and a
mixer's ``sure.probe_dist`` reaches inference, its cache folder and the command line."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.config import load_config
from jaxden.errors import ConfigError
from jaxden.frame import Frame
from jaxden.sure.stein import PROBE_DISTS, colour_factor, colour_probes, draw_probes, sure

DN = ("NHWC", "HWIO", "NHWC")


def _frame(height=8, width=8, seed=0) -> Frame:
    rng = np.random.default_rng(seed)
    return Frame(color=rng.uniform(0.0, 2.0, (height, width, 3)).astype(np.float32),
                 variance=rng.uniform(1e-3, 5e-2, (height, width, 3)).astype(np.float32),
                 albedo=rng.uniform(0.1, 0.9, (height, width, 3)).astype(np.float32))


def _mixing_kernel(seed=1):
    """A 3 x 3 filter that mixes the channels: a Jacobian with off-diagonal terms everywhere."""
    rng = np.random.default_rng(seed)
    kernel = rng.uniform(0.0, 1.0, (3, 3, 3, 3)).astype(np.float32)
    kernel[1, 1] += 2.0 * np.eye(3, dtype=np.float32)  # a strong own-pixel term (J_ii)
    return jnp.asarray(kernel / kernel.sum(axis=(0, 1, 2), keepdims=True))


def _conv(kernel, frame):
    out = jax.lax.conv_general_dilated(frame.color[None], kernel, (1, 1), "SAME",
                                       dimension_numbers=DN,
                                       precision=jax.lax.Precision.HIGHEST)
    return out[0]


def _pixelwise(scale, frame):
    return scale * frame.albedo * frame.color + frame.albedo ** 2


def test_the_command_line_offers_the_library_s_distributions():
    import argparse

    from jaxden.cli.options import add_sure_options

    parser = argparse.ArgumentParser()
    add_sure_options(parser)
    (action,) = [a for a in parser._actions if a.dest == "probe_dist"]
    assert tuple(action.choices) == PROBE_DISTS == ("normal", "rademacher")


def test_rademacher_probes_are_the_signs_of_the_normal_draws():
    frame = _frame()
    key = jax.random.PRNGKey(3)
    scale = np.sqrt(frame.variance)
    normals = np.asarray(draw_probes(key, frame.variance, 3)) / scale
    signs = np.asarray(draw_probes(key, frame.variance, 3, dist="rademacher")) / scale
    np.testing.assert_allclose(signs, np.where(normals >= 0, 1.0, -1.0), rtol=1e-6)
    assert 0.4 < np.mean(signs > 0) < 0.6
    from jaxden.sure.stein import unit_probes

    assert np.asarray(unit_probes(jnp.zeros(2), "rademacher")).tolist() == [1.0, 1.0]
    # with a colour covariance: L r, the same signs through the Cholesky factor
    rng = np.random.default_rng(4)
    covariance = (0.5 * np.sqrt(frame.variance * np.roll(frame.variance, -1, axis=-1))
                  * rng.uniform(0.0, 1.0, frame.variance.shape)).astype(np.float32)
    with_cov = np.asarray(draw_probes(key, frame.variance, 3, covariance, dist="rademacher"))
    factor = colour_factor(jnp.asarray(frame.variance), jnp.asarray(covariance))
    np.testing.assert_allclose(with_cov, np.asarray(colour_probes(jnp.asarray(signs), factor)),
                               rtol=1e-5, atol=1e-7)


def test_one_rademacher_probe_is_exact_through_a_diagonal_jacobian():
    """J = diag(1.5 albedo): b_i (J b)_i = var_i J_ii r_i^2 = var_i J_ii for every draw; one
    normal probe is off by var_i J_ii (n_i^2 - 1)."""
    frame = _frame()
    exact = frame.variance * 1.5 * frame.albedo
    for seed in range(3):
        rad = sure(_pixelwise, frame, jax.random.PRNGKey(seed), 1, params=1.5,
                   probe_dist="rademacher")
        np.testing.assert_allclose(rad.divergence_term, exact, rtol=1e-6)
    normal = sure(_pixelwise, frame, jax.random.PRNGKey(0), 1, params=1.5)
    assert np.median(np.abs(np.asarray(normal.divergence_term) / exact - 1)) > 0.3


def test_rademacher_divergence_is_unbiased_with_the_stated_variance():
    """Through a channel-mixing blur A (J = A): over 4000 single-probe draws (seed 0), per
    pixel, the mean of b_i (A b)_i is within 5 standard errors of var_i A_ii, and its variance
    is var_i sum_{j != i} var_j A_ij^2 for Rademacher probes and that plus 2 var_i^2 A_ii^2 for
    normal ones (medians over the 192 pixels within 6 %, every pixel within 30 %: the relative
    standard error of a variance from 4000 draws is about 3 % here)."""
    frame = _frame()
    kernel = _mixing_kernel()
    var = frame.variance.reshape(-1).astype(np.float64)
    jac = np.asarray(jax.jacfwd(lambda c: _conv(kernel, frame.replace(color=c)))(
        jnp.asarray(frame.color))).reshape(var.size, var.size).astype(np.float64)
    diag = np.diag(jac)
    off = var * ((jac ** 2) @ var - diag ** 2 * var)
    keys = jax.random.split(jax.random.PRNGKey(0), 4000)
    for dist, stated in (("rademacher", off), ("normal", off + 2 * var ** 2 * diag ** 2)):
        draws = np.asarray(jax.lax.map(
            lambda k, dist=dist: sure(_conv, frame, k, 1, params=kernel,
                                      probe_dist=dist).divergence_term,
            keys)).reshape(len(keys), -1).astype(np.float64)
        error = np.abs(draws.mean(axis=0) - var * diag) / np.sqrt(stated / len(keys))
        assert error.max() < 5.0, (dist, error.max())
        ratio = draws.var(axis=0, ddof=1) / stated
        assert abs(np.median(ratio) - 1) < 0.06, (dist, np.median(ratio))
        assert 0.7 < ratio.min() and ratio.max() < 1.3, (dist, ratio.min(), ratio.max())


@pytest.fixture(scope="module")
def small_kp():
    from jaxden.denoise.nn.wskp import KPConfig
    from jaxden.denoise.registry import make_denoiser

    return make_denoiser("kp", KPConfig(num_layers=2, width=4, kernel_size=5),
                         key=jax.random.PRNGKey(0))


def test_tiles_and_the_pipeline_see_the_whole_frame_s_rademacher_probes(small_kp):
    """SURE over 24-pixel tiles equals the whole frame's with Rademacher probes, the probes
    differ from the normal ones, and a mixer trained on them hands them to inference."""
    import dataclasses

    from jaxden.progressive.mixer import closed_form_mixer
    from jaxden.progressive.pipeline import progressive_denoise
    from jaxden.render.synthetic import synthetic_render
    from jaxden.sure.denoiser import denoise_with_sure
    from jaxden.sure.tiled import sure_frame

    frame = synthetic_render("tiles", 16, seed=5, size=(60, 56)).replace(covariance=None,
                                                                         spp=16.0)
    key = jax.random.PRNGKey(2)
    whole, tile = sure_frame(small_kp, frame, key, num_probes=2, tile=0,
                             probe_dist="rademacher")
    tiled, tile = sure_frame(small_kp, frame, key, num_probes=2, tile=24,
                             probe_dist="rademacher")
    assert tile == 24
    scale = np.sqrt(np.mean(np.square(whole.divergence_term)))
    np.testing.assert_allclose(tiled.divergence_term, whole.divergence_term, atol=1e-5 * scale)
    normal, _ = sure_frame(small_kp, frame, key, num_probes=2, tile=0)
    assert not np.allclose(normal.divergence_term, whole.divergence_term, atol=1e-3 * scale)

    params, config = closed_form_mixer("closed-form:sigma=2")
    config = dataclasses.replace(config, sure=config.sure.replace(probe_dist="rademacher"))
    _, _, extras = progressive_denoise(frame, small_kp, params, config, key, num_probes=2)
    direct, _ = denoise_with_sure(small_kp, frame, key, num_probes=2, probe_dist="rademacher")
    np.testing.assert_allclose(extras["divergence"], direct.divergence_term, rtol=1e-5,
                               atol=1e-6 * scale)


def test_the_black_box_path_draws_the_same_signs():
    """Forward differences of a black box (one probe at a time, float64 sums) against the
    exact jvp with the same key: the same Rademacher probes (rtol 2e-3 at eps 1e-2, as the
    normal probes' test in test_sure.py)."""
    from jaxden.sure.settings import SureSettings
    from jaxden.sure.stein import sure_blackbox_streamed

    frame = _frame().validated(where="test")
    kernel = _mixing_kernel()
    key = jax.random.PRNGKey(6)

    def denoise_np(f):
        return np.asarray(_conv(kernel, f))

    exact = sure(_conv, frame, key, 2, params=kernel, probe_dist="rademacher")
    streamed = sure_blackbox_streamed(denoise_np, frame, key,
                                      SureSettings(probes=2, eps=1e-2, probe_dist="rademacher"))
    scale = np.abs(np.asarray(exact.divergence_term)).max()
    np.testing.assert_allclose(streamed.divergence_term, exact.divergence_term, rtol=2e-3,
                               atol=2e-3 * scale)


def test_a_wrong_distribution_is_one_line():
    from jaxden.progressive.cache import default_cache_dir
    from jaxden.progressive.mixer_config import MixerConfig, upgrade_mixer_config
    from jaxden.sure.settings import SureSettings

    frame = _frame()
    with pytest.raises(ConfigError, match="normal, rademacher, got 'uniform'"):
        sure(_pixelwise, frame, jax.random.PRNGKey(0), 1, params=1.0, probe_dist="uniform")
    with pytest.raises(ConfigError, match="probe_dist must be one of normal, rademacher"):
        MixerConfig(sure=SureSettings(probe_dist="sobol"))
    with pytest.raises(ConfigError, match="probe_dist"):  # an older config's flat key
        load_config(upgrade_mixer_config({"sure_probe_dist": "sobol"}), MixerConfig)
    rademacher = SureSettings(probe_dist="rademacher")
    assert default_cache_dir("/d", "oidn", rademacher).name == "oidn-rademacher"
    assert default_cache_dir("/d", "oidn", rademacher.replace(covariance=True)).name == (
        "oidn-cov-rademacher")
    assert default_cache_dir("/d", "oidn").name == "oidn"


def test_jaxden_sure_records_the_distribution(tmp_path, capsys):
    from jaxden.cli import main
    from jaxden.io.exr import read_header

    image = tmp_path / "f.exr"
    assert main(["render", "cornell-box", "--spp", "4", "--size", "24x24", "--seed", "1",
                 "--out", str(image)]) == 0
    out = tmp_path / "s.exr"
    # the C++ OIDN: the streamed black-box path, and no network to compile
    assert main(["sure", str(image), "--denoiser", "oidn", "--probes", "1",
                 "--probe-dist", "rademacher", "--out", str(out)]) == 0
    assert "1 rademacher probes" in capsys.readouterr().out
    assert read_header(out)["probe_dist"] == "rademacher"
    with pytest.raises(SystemExit) as raised:
        main(["sure", str(image), "--denoiser", "wskp-6", "--probe-dist", "sobol",
              "--out", str(tmp_path / "t.exr")])
    assert raised.value.code == 2
    assert "invalid choice: 'sobol'" in capsys.readouterr().err
    assert not (tmp_path / "t.exr").exists()
