"""Statistical calibration of render_frame's variance of the mean.

Setup: a built-in scene at 48 x 48, R = 16 independent renders at n = 16 spp (seeds
BASE_SEED + 0..15), and 4 renders at 4n = 64 spp. Checks, pooled over pixels and channels:

1. estimated / empirical variance of the mean = 1 within 10%: the estimate is the average over
   renders of Frame.variance, the empirical value the unbiased variance of Frame.color over
   the R renders;
2. estimated var(4n spp) / var(n spp) = 0.25 +- 0.03.

Pooling (sums over pixels before the ratio) is necessary: the per-pixel ratio of two noisy
variance estimates is biased upward.

Excluded pixels: those whose mean colour over the R renders exceeds 1 in any channel, and
their 8 neighbours (a 3 x 3 dilation). These are the directly visible emitter and the pixels
around it whose box-filter footprint catches part of it: a few of their samples see radiance
~18 and the rest ~0.5, so their sample distribution is extremely heavy-tailed and the
empirical variance over only 16 renders is itself uncertain by tens of percent. They carry
most of the pooled sum, so with them the pooled ratio swings 0.81-1.14 between seed sets
(PLATFORM-NOTES); without them it is 0.98-1.02 (measured over 10 seed sets here: estimated /
empirical 0.981-1.017, var ratio 0.247-0.253). The exclusion is a property of the test's
estimator, not of the variance: the estimate is unbiased on those pixels too.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from jaxden.render import load_scene, render_frame

SIZE = (48, 48)
RENDERS = 16
SPP = 16
BASE_SEED = 1000


def _renders(name: str, spp: int, count: int, base_seed: int):
    scene = load_scene(name, size=SIZE)
    frames = [render_frame(scene, spp=spp, seed=base_seed + r) for r in range(count)]
    colours = np.stack([f.color for f in frames]).astype(np.float64)
    variances = np.stack([f.variance for f in frames]).astype(np.float64)
    return colours, variances


def _calibration(name: str, base_seed: int = BASE_SEED):
    colours, variances = _renders(name, SPP, RENDERS, base_seed)
    bright = (colours.mean(0) > 1.0).any(-1)
    keep = ~binary_dilation(bright, structure=np.ones((3, 3), bool))
    empirical = colours.var(0, ddof=1)
    estimated = variances.mean(0)
    _, variances_4n = _renders(name, 4 * SPP, 4, base_seed + 500)
    return keep, estimated, empirical, variances_4n.mean(0)


def _check(name: str, keep, estimated, empirical, estimated_4n, min_kept: float):
    assert keep.mean() > min_kept, f"{name}: too many pixels excluded ({(~keep).sum()})"
    ratio = estimated[keep].sum() / empirical[keep].sum()
    assert abs(ratio - 1) < 0.10, f"{name}: estimated / empirical variance {ratio:.3f}"
    for channel in range(3):
        per_channel = estimated[keep][:, channel].sum() / empirical[keep][:, channel].sum()
        assert abs(per_channel - 1) < 0.10, f"{name}: channel {channel}: {per_channel:.3f}"
    spp_ratio = estimated_4n[keep].sum() / estimated[keep].sum()
    assert abs(spp_ratio - 0.25) < 0.03, f"{name}: var(4n) / var(n) = {spp_ratio:.4f}"


@pytest.fixture(scope="module")
def cornell_calibration():
    return _calibration("cornell-box")


def test_variance_calibration_cornell_box(cornell_calibration):
    keep, estimated, empirical, estimated_4n = cornell_calibration
    # Only the ceiling light and its border go: ~2% of the 48 x 48 pixels.
    assert 0 < (~keep).sum() < 0.05 * keep.size
    _check("cornell-box", keep, estimated, empirical, estimated_4n, min_kept=0.95)


@pytest.mark.parametrize("factor", [SPP, 1.15, 1 / 1.15])
def test_variance_check_rejects_a_miscalibrated_estimate(cornell_calibration, factor):
    """The same check fails for a wrong estimator: the sample variance instead of the variance
    of the mean (a forgotten '/ spp', factor 16), and estimates 15 % too high or too low (the
    10 % tolerance has the power to see them; the measured ratio is 0.98-1.02)."""
    keep, estimated, empirical, estimated_4n = cornell_calibration
    with pytest.raises(AssertionError, match="estimated / empirical"):
        _check("cornell-box", keep, estimated * factor, empirical, estimated_4n * factor,
               min_kept=0.95)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["glossy-glass", "env-sun", "texture-bump"])
def test_variance_calibration_other_scenes(name):
    keep, estimated, empirical, estimated_4n = _calibration(name)
    # env-sun's sky is > 1 almost everywhere above the horizon and is excluded with the rule.
    _check(name, keep, estimated, empirical, estimated_4n, min_kept=0.4)
