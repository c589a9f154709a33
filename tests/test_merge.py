"""jaxden.data.merge and `jaxden merge`: K independent renders -> one frame with the variance of
its mean, from the renders' spread (renderers that write no variance) or pooled exactly."""

from pathlib import Path

import numpy as np
import pytest

from jaxden.cli import main
from jaxden.data.merge import colour_digest, merge_renders, read_buffer_list
from jaxden.errors import FrameError
from jaxden.frame import Frame
from jaxden.io.exr import read_frame, read_header
from jaxden.sure.buffers import combine_buffers

CYCLES = Path(__file__).parent / "data" / "cycles"


def _renders(k, *, shape=(64, 64), sigma=(0.5, 1.0, 2.0), rho=0.6, seed=0, spp=16.0):
    """K renders of one image: truth + Gaussian noise with per-channel sd ``sigma`` and
    correlation ``rho`` between neighbouring channels (R-G, G-B, B-R through a shared term)."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(1, 2, (*shape, 3))
    frames = []
    for _ in range(k):
        shared = rng.standard_normal(shape)[..., None]
        own = rng.standard_normal((*shape, 3))
        noise = np.sqrt(rho) * shared + np.sqrt(1 - rho) * own  # unit variance, corr rho
        frames.append(Frame(color=(truth + noise * np.asarray(sigma)).astype(np.float32),
                            albedo=np.full((*shape, 3), 0.5, np.float32),
                            spp=np.float32(spp)))
    return frames


def test_spread_variance_is_unbiased_for_the_mean():
    """E[variance] = sigma^2 / K and E[covariance] = rho sigma_i sigma_j / K. Over 4096 pixels
    of K = 4 renders (3 degrees of freedom each) the mean estimate has a relative standard
    deviation of about sqrt(2 / 3 / 4096) = 1.3 %; tolerance 5 % (seed 0)."""
    sigma, rho, k = np.array([0.5, 1.0, 2.0]), 0.6, 4
    merged = merge_renders(_renders(k, sigma=sigma, rho=rho))
    np.testing.assert_allclose(merged.variance.mean(axis=(0, 1)), sigma ** 2 / k, rtol=0.05)
    pairs = sigma * np.roll(sigma, -1)  # RG, GB, BR
    np.testing.assert_allclose(merged.covariance.mean(axis=(0, 1)), rho * pairs / k, rtol=0.05)
    assert float(merged.spp) == 64.0
    np.testing.assert_allclose(merged.albedo, 0.5)


def test_spread_formula_against_numpy():
    frames = _renders(3, shape=(5, 6), seed=3)
    merged = merge_renders(frames)
    colours = np.stack([np.asarray(f.color, np.float64) for f in frames])
    np.testing.assert_allclose(merged.color, colours.mean(0), rtol=1e-6)
    np.testing.assert_allclose(merged.variance, colours.var(0, ddof=1) / 3, rtol=1e-5)


def test_renders_with_their_own_variance_are_pooled():
    frames = [f.replace(variance=np.full_like(f.color, 0.01)) for f in _renders(3, seed=4)]
    merged = merge_renders(frames)
    pooled = combine_buffers(frames)
    np.testing.assert_allclose(merged.variance, pooled.variance, rtol=1e-6)
    np.testing.assert_allclose(merged.color, pooled.color, rtol=1e-6)


@pytest.mark.parametrize("case, message", [
    ("one", "at least 2 independent renders"),
    ("size", "pixels"),
    ("spp", "equal sample counts"),
    ("fields", "have the same"),
    ("same", "same seed"),
    ("mixed", "has no variance but"),
])
def test_bad_render_sets_are_refused(case, message):
    a, b = _renders(2, shape=(8, 8), seed=5)
    if case == "one":
        frames = [a]
    elif case == "size":
        frames = [a, _renders(1, shape=(8, 9), seed=6)[0]]
    elif case == "spp":
        frames = [a, b.replace(spp=np.float32(32))]
    elif case == "fields":
        frames = [a, b.replace(albedo=None)]
    elif case == "same":
        frames = [a, b, a]
    else:
        frames = [a.replace(variance=np.ones_like(a.color)), b]
    with pytest.raises(FrameError, match=message):
        merge_renders(frames)


def test_merge_command_on_real_cycles_renders(tmp_path, capsys):
    """Two Blender 5.0 Cycles renders (seeds 1 and 2, 16 spp): merged by `jaxden merge --from
    cycles` into jaxden's layout, with the spread's variance, 32 spp and the buffers recorded."""
    renders = [CYCLES / f"spheres-16spp-seed{s}.exr" for s in (1, 2)]
    out = tmp_path / "merged.exr"
    assert main(["merge", *map(str, renders), "--from", "cycles", "--out", str(out)]) == 0
    merged = read_frame(out, require=("color", "variance", "albedo", "normal", "covariance"))
    inputs = [read_frame(r, convention="cycles") for r in renders]
    np.testing.assert_allclose(merged.color, (inputs[0].color + inputs[1].color) / 2, rtol=1e-6)
    np.testing.assert_allclose(merged.variance,
                               np.square(inputs[0].color - inputs[1].color) / 4, rtol=1e-5,
                               atol=1e-12)
    header = read_header(out)
    assert header["spp"] == 32 and header["buffers"].count(";") == 1
    assert header["variance_dof"] == 1 and float(merged.variance_dof) == 1
    listed = read_buffer_list(out)
    assert listed.convention == "cycles"
    assert listed.digests == tuple(colour_digest(f.color) for f in inputs)
    # sub-buffer SURE reads the renders by the convention they were merged with
    assert main(["sure", str(out), "--buffers", *map(str, renders), "--denoiser", "oidn",
                 "--out", str(tmp_path / "sure.exr")]) == 0
    assert main(["merge", str(renders[0]), str(renders[0]), "--from", "cycles",
                 "--out", str(tmp_path / "twice.exr")]) == 2
    assert "named twice" in capsys.readouterr().err
    assert not (tmp_path / "twice.exr").exists()


def test_one_cycles_seed_rendered_twice_is_refused_though_not_bit_for_bit_equal(tmp_path,
                                                                                 capsys):
    """Blender 5.0.1's Cycles does not repeat a render bit for bit: passes-seed1-again.exr is
    seed 1 once more, with about 40 % of its colour values changed by rounding. Their spread
    would put the variance near 0; merge refuses them as one render twice, and takes the
    renders of two seeds."""
    from jaxden.data.merge import same_render

    again = [CYCLES / "passes-seed1.exr", CYCLES / "passes-seed1-again.exr"]
    colours = [read_frame(p, convention="cycles").color for p in again]
    assert 0.3 < np.mean(colours[0] != colours[1]) < 0.8
    assert same_render(*colours, spp=4)
    other = read_frame(CYCLES / "passes-seed2.exr", convention="cycles").color
    assert not same_render(colours[0], other, spp=4)
    assert not same_render(colours[0], other)  # the stricter bound, without a sample count
    assert main(["merge", *map(str, again), "--from", "cycles",
                 "--out", str(tmp_path / "m.exr")]) == 2
    assert "are the same image (rendered with the same seed?)" in capsys.readouterr().err


def test_renders_of_noise_far_below_their_values_are_not_taken_for_one_render():
    """Independent renders differ by about 0.5 CV / sqrt(spp) (CV: a sample's coefficient of
    variation); even at CV 0.01 per sample and 4096 spp they stay clear of the bound."""
    from jaxden.data.merge import same_render

    rng = np.random.default_rng(0)
    truth = rng.uniform(0.1, 10.0, (32, 32, 3))
    spp, cv = 4096, 0.01
    a, b = (truth * (1 + cv / np.sqrt(spp) * rng.standard_normal(truth.shape))
            for _ in range(2))
    assert not same_render(a.astype(np.float32), b.astype(np.float32), spp=spp)
