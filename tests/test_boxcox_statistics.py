"""Frame.boxcox: the per-pixel sample statistics StatMC tests with, from the renderer, in
files, in datasets and merged from K renders.

References: explicit samples (a render split into 1-spp passes, whose films are the samples
themselves) through the slow obvious form ``boxcox_of_samples``; exact pooling checked
against the statistics of all samples at once; the renderer without statistics (the colour
must not change).
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxden.errors import FrameError
from jaxden.frame import CHANNELS, Frame
from jaxden.render.integrators import boxcox_of_samples, boxcox_statistics

SIZE = (24, 16)  # width, height: a tiny Cornell box


def raw_moments(samples):
    """mean(s^k), k = 1..3, of s = 2 sqrt(L) over axis 0, in float64."""
    s = 2.0 * np.sqrt(np.maximum(samples, 0.0))
    return [np.mean(s ** k, axis=0) for k in (1, 2, 3)]


def test_statistics_from_raw_moments_match_the_samples_own():
    rng = np.random.default_rng(0)
    samples = rng.gamma(0.7, 2.0, size=(64, 5, 6, 3))  # skewed, as path-traced radiance
    expected = boxcox_of_samples(samples)
    got = boxcox_statistics(*raw_moments(samples), 64)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    b = 2.0 * np.sqrt(samples) - 2.0
    np.testing.assert_allclose(expected[..., 0:3], b.mean(0), rtol=1e-6)
    np.testing.assert_allclose(expected[..., 3:6], b.var(0), rtol=1e-5)
    from scipy.stats import moment
    np.testing.assert_allclose(expected[..., 6:9], moment(b, 3, axis=0), rtol=1e-4, atol=1e-7)


def test_round_off_never_gives_a_constant_pixel_a_skewness():
    # a constant pixel: the raw moments' cancellation leaves only round-off, which is zeroed
    s1 = np.full((1, 1, 3), 2.0 * np.sqrt(37.0))
    s1_32 = s1.astype(np.float32).astype(np.float64)  # what a float32 film holds
    stats = boxcox_statistics(s1_32, (s1 ** 2).astype(np.float32), (s1 ** 3).astype(np.float32),
                              1024)
    assert np.all(stats[..., 6:9] == 0) and np.all(stats[..., 3:6] >= 0)


def test_the_skewness_is_clipped_to_what_n_samples_can_have():
    n = 4
    # raw moments inconsistent with any 4 samples (a third moment far too large)
    stats = boxcox_statistics(np.full((1, 3), 1.0), np.full((1, 3), 2.0), np.full((1, 3), 50.0),
                              n)
    second, third = stats[..., 3:6], stats[..., 6:9]
    bound = (n - 2) / np.sqrt(n - 1) * second ** 1.5
    np.testing.assert_allclose(third, bound, rtol=1e-5)
    # and n samples reach it: one outlier among n
    x = np.array([0.0, 0.0, 0.0, 1.0])
    d = x - x.mean()
    assert np.isclose(np.mean(d ** 3) / np.mean(d ** 2) ** 1.5, (n - 2) / np.sqrt(n - 1))


def test_pooling_k_renders_equals_the_statistics_of_all_their_samples():
    from jaxden.data.merge import pool_boxcox

    rng = np.random.default_rng(1)
    counts = [3, 8, 5]
    parts = [rng.lognormal(0.0, 1.0, size=(n, 4, 3, 3)) for n in counts]
    pooled = pool_boxcox([boxcox_of_samples(p) for p in parts], counts)
    np.testing.assert_allclose(pooled, boxcox_of_samples(np.concatenate(parts)), rtol=1e-5,
                               atol=1e-6)


@pytest.fixture(scope="module")
def rendered():
    from jaxden.render.core import render_frame

    budget = SIZE[0] * SIZE[1]  # one sample per pixel and pass: each pass is one sample
    with_stats = render_frame("cornell-box", 12, seed=3, size=SIZE, statistics=True,
                              max_samples_per_pass=budget)
    plain = render_frame("cornell-box", 12, seed=3, size=SIZE, max_samples_per_pass=budget)
    return with_stats, plain


def test_the_renderer_gives_the_statistics_of_its_own_samples(rendered):
    from jaxden.render import core, integrators

    frame, _ = rendered
    scene, sensor, _ = core._scene_and_sensor("cornell-box", SIZE, None, None)
    _, moment = core._integrators(scene, None, True)
    channels = integrators.MOMENT_CHANNELS + len(integrators.STATISTICS_AOVS)
    samples = np.stack([core._render(scene, sensor, moment, core.derive_seed(3, "color", i), 1,
                                     channels)[..., :3] for i in range(12)])
    np.testing.assert_allclose(samples.mean(0), frame.color, rtol=1e-5, atol=1e-6)
    expected = boxcox_of_samples(samples)
    scale = np.abs(expected).max(axis=(0, 1))
    assert np.all(np.abs(frame.boxcox - expected).max(axis=(0, 1)) <= 1e-4 * (1 + scale))
    assert np.all(frame.boxcox[..., 3:6] >= 0)


def test_statistics_do_not_change_the_colour_or_its_variance(rendered):
    frame, plain = rendered
    assert plain.boxcox is None and frame.boxcox.shape == (SIZE[1], SIZE[0], 9)
    np.testing.assert_allclose(frame.color, plain.color, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(frame.variance, plain.variance, rtol=1e-5, atol=1e-9)


def test_files_keep_the_statistics_in_float32(tmp_path, rendered):
    from jaxden.io.exr import read_frame, read_header, write_frame

    frame, _ = rendered
    write_frame(tmp_path / "f.exr", frame, half=True)
    header = read_header(tmp_path / "f.exr")
    assert set(CHANNELS["boxcox"]) <= set(header["channels"])
    back = read_frame(tmp_path / "f.exr")
    np.testing.assert_array_equal(back.boxcox, frame.boxcox)
    assert back.statistics_count() == 12


def test_validation_refuses_a_negative_second_moment_and_clips_round_off():
    boxcox = np.zeros((2, 2, 9), np.float32)
    boxcox[0, 1, 4] = -0.5
    frame = Frame(color=np.ones((2, 2, 3), np.float32), boxcox=boxcox)
    with pytest.raises(FrameError, match=r"boxcox.*m2.*\(0, 1, 1\)"):
        frame.validated("f.exr")
    boxcox[0, 1, 4] = -1e-9
    repaired = frame.replace(boxcox=boxcox).validated("f.exr", nonfinite="zero")
    assert repaired.boxcox[0, 1, 4] == 0
    with pytest.raises(FrameError, match="shape"):
        Frame(color=np.ones((2, 2, 3), np.float32), boxcox=np.zeros((2, 2, 3))).validated()


def test_merging_renders_pools_their_statistics_or_takes_those_of_their_means(rendered):
    from jaxden.data.merge import merge_renders
    from jaxden.render.core import render_frame

    first, _ = rendered
    second = render_frame("cornell-box", 12, seed=4, size=SIZE, statistics=True)
    pooled = merge_renders([first, second])
    assert pooled.statistics_count() == 24
    np.testing.assert_allclose(pooled.boxcox[..., 0:3],
                               (first.boxcox[..., 0:3] + second.boxcox[..., 0:3]) / 2, rtol=1e-5,
                               atol=1e-6)
    colours_only = [f.replace(variance=None, covariance=None, boxcox=None)
                    for f in (first, second, render_frame("cornell-box", 12, seed=5, size=SIZE))]
    spread = merge_renders(colours_only)
    assert spread.statistics_count() == 3
    np.testing.assert_allclose(spread.boxcox,
                               boxcox_of_samples(np.stack([f.color for f in colours_only])),
                               rtol=1e-6, atol=1e-7)


def test_a_dataset_with_statistics_writes_them_in_every_item(tmp_path):
    from jaxden.data import build_dataset
    from jaxden.data.config import DatasetConfig
    from jaxden.io.exr import read_frame

    config = DatasetConfig(name="s", scenes=("cornell-box",), size=(32, 32), crop_size=8,
                           crops_per_scene=1, spp=(4,), reference_spp=8, seed=2,
                           statistics=True)
    manifest = build_dataset(config, tmp_path / "d", executor="serial", progress=False)
    for item in manifest.items:
        frame = read_frame(tmp_path / "d" / item.path)
        assert frame.boxcox is not None and frame.statistics_count() == item.spp


def test_a_file_without_statistics_says_how_to_render_them(tmp_path, rendered, capsys):
    from helpers import run_cli

    from jaxden.io.exr import write_frame

    _, plain = rendered
    write_frame(tmp_path / "f.exr", plain)
    code, err, _ = run_cli(["denoise", tmp_path / "f.exr", "--model", "statmc", "--out",
                            tmp_path / "o.exr"], capsys)
    message = " ".join(err)
    assert code != 0 and "boxcox.m3.B" in message and "--statistics" in message
    assert not (tmp_path / "o.exr").exists()
