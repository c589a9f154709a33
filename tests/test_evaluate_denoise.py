"""jaxden.evaluate.denoise (the ``denoise`` and ``sequences`` evaluators): every row equals
the metrics computed directly on the same images; temporal accumulation on a static-camera
sequence of a fixed image beats single frames; the sweep's [evaluate] denoise table reaches
result.json and summary.md."""

from __future__ import annotations

import numpy as np
import pytest

from jaxden import metrics
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig, SplitConfig
from jaxden.data.crops import iter_crops
from jaxden.denoise.registry import Denoiser, DenoiserDef
from jaxden.evaluate import denoise as report
from jaxden.render.synthetic import synthetic_render


def box3(params, config, frame):
    """A 3 x 3 box filter (edge-padded): a denoiser with a known output."""
    x = np.asarray(frame.color, np.float32)
    padded = np.pad(x, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = x.shape[:2]
    return sum(padded[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


BOX = Denoiser(DenoiserDef("box3", "3x3 box", object, lambda c: ("color",), box3,
                           differentiable=False), None)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("rt")
    config = DatasetConfig(name="rt-tiny", scenes=("a", "b"), size=(32, 32), crop_size=16,
                           crops_per_scene=1, spp=(1, 4), reference_spp=64, seed=2,
                           splits=SplitConfig(train=0.0, val=0.0, test=1.0))
    build_dataset(config, out, render_fn=synthetic_render, progress=False)
    return out


def test_rows_equal_direct_metrics(dataset):
    rows = report.evaluate_denoiser(dataset, BOX, spp=(1,))
    assert len(rows) == 2 and all(r["spp"] == 1 for r in rows)
    crop, reference, [(spp, frame)] = next(iter_crops(dataset, "test", (1,), min_spp=1))
    assert spp == 1 and frame.variance is None
    row = rows[0]
    assert row["crop"] == crop.id
    denoised = box3(None, None, frame)
    assert row["den_psnr"] == pytest.approx(float(metrics.psnr(denoised, reference.color)))
    assert row["den_ssim"] == pytest.approx(float(metrics.ssim(denoised, reference.color)))
    assert row["den_relmse"] == pytest.approx(float(metrics.relmse(denoised, reference.color)))
    assert row["mc_flip"] == pytest.approx(float(metrics.flip(frame.color, reference.color)))
    nc = float(metrics.noise_corrected_mse(denoised, reference.color, reference.variance))
    assert row["den_mse_nc"] == pytest.approx(nc)
    # the box filter removes most of the per-pixel noise of this smooth image
    assert row["den_psnr"] > row["mc_psnr"] + 3
    summary = report.summarize(rows)
    assert summary["count"] == 2
    assert summary["den_psnr"] == pytest.approx(np.mean([r["den_psnr"] for r in rows]))
    assert summary["den_rmse_nc"] == pytest.approx(np.sqrt(max(summary["den_mse_nc"], 0)))
    table = report.markdown({"box": summary})
    assert f"{summary['den_psnr']:.2f}" in table


@pytest.mark.slow  # ~20 s; test_temporal.py tests accumulation, rt-main measures it on rt-seq
def test_temporal_accumulation_beats_single_frames(tmp_path):
    """A static camera (orbit of 0 degrees): accumulation averages the frames, so its input
    error falls about as 1 / frames, and the denoised accumulated frames beat the single ones.
    (At 24 x 24 a pixel spans ~3 % of the depth and 1-spp positions jitter within it: the
    position test gets a tolerance above that.)"""
    from jaxden.data.sequences import SequenceConfig, build_sequences
    from jaxden.denoise.temporal import TemporalConfig

    config = SequenceConfig(scenes=("cornell-box",), size=(24, 24), frames=6, spp=1,
                            reference_spp=64, seed=1, path="orbit", rotation_deg=0.0)
    build_sequences(config, tmp_path, progress=False)
    rows = report.evaluate_sequences(tmp_path, BOX,
                                      temporal=TemporalConfig(position_tolerance=0.1))
    assert [r["frame"] for r in rows] == [1, 2, 3, 4, 5]
    last = rows[-1]
    assert last["acc_mse_nc"] < 0.5 * last["mc_mse_nc"]
    summary = report.summarize(rows)
    assert summary["tdn_mse_nc"] < summary["den_mse_nc"]
