"""Merged buffers all the way into progressive denoising: `jaxden progressive X.exr --buffers ...`
(sub-buffer SURE fed to the mixer and the t-statistic), the record of its buffers that a merged
file carries and the checks of --buffers against it, and the variance's degrees of freedom
(``Frame.variance_dof``) in the error guard's bound."""

from __future__ import annotations

import shutil

import jax
import numpy as np
import pytest
from helpers import assert_one_error_line, run_cli
from scipy.stats import chi2

from jaxden import progressive as P
from jaxden.cli import main
from jaxden.data.merge import (
    BufferList,
    colour_digest,
    combine_buffers,
    merge_renders,
    read_buffer_list,
)
from jaxden.errors import ExrError, FrameError
from jaxden.frame import Frame, stack
from jaxden.io.exr import read_frame, read_header, read_image, write_frame
from jaxden.progressive.closed_form import gaussian_taps
from jaxden.progressive.guard import guard_sample_count, variance_inflation
from jaxden.progressive.pipeline import mix_given_sure
from jaxden.progressive.tiled import progressive_frame
from jaxden.render.synthetic import synthetic_render

K = 4
SPP = 4  # per buffer


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """K synthetic renders of one frame without a variance (as Cycles writes them: colour and
    features), b0..b3.exr, one more (b4.exr, another seed), and `jaxden merge` of b0..b3."""
    folder = tmp_path_factory.mktemp("merge-buffers")
    paths = []
    for seed in range(K + 1):
        paths.append(folder / f"b{seed}.exr")
        frame = synthetic_render("pipeline", SPP, seed=10 + seed, size=(24, 20))
        write_frame(paths[-1], frame.replace(variance=None))
    merged = folder / "merged.exr"
    assert main(["merge", *map(str, paths[:K]), "--out", str(merged)]) == 0
    return folder, paths, merged


def _sure_channels(path):
    return read_image(path, ("sure.R", "sure.G", "sure.B"))


def test_merged_header_lists_its_buffers_and_the_variance_dof(renders):
    folder, paths, merged = renders
    listed = read_buffer_list(merged)
    assert listed.files == tuple(map(str, paths[:K]))
    assert listed.digests == tuple(colour_digest(read_frame(p).color) for p in paths[:K])
    assert listed.convention is None and read_header(merged)["variance_dof"] == K - 1
    frame = read_frame(merged)
    assert float(frame.variance_dof) == K - 1 and float(frame.spp) == K * SPP
    # round trip of both keys through any file, a convention and a fractional dof included
    other = BufferList(("a;b.exr", "c d.exr"), (colour_digest(frame.color),
                                                 colour_digest(2 * frame.color)), "cycles", "L")
    path = folder / "round.exr"
    write_frame(path, frame.replace(variance_dof=np.float32(7.5)), attributes=other.attributes())
    assert read_buffer_list(path) == other and float(read_frame(path).variance_dof) == 7.5
    assert read_buffer_list(paths[0]) is None and read_frame(paths[0]).variance_dof is None


def test_bad_header_records_are_one_line_errors(renders, tmp_path):
    _, _, merged = renders
    frame = read_frame(merged)
    path = tmp_path / "bad.exr"
    write_frame(path, frame, attributes={"variance_dof": 0})
    with pytest.raises(ExrError, match="variance_dof.*must be > 0"):
        read_frame(path)
    write_frame(path, frame.replace(variance_dof=None), attributes={"buffer_sha256": "abc"})
    with pytest.raises(ExrError, match="bad.exr.*malformed"):
        read_buffer_list(path)


def test_progressive_with_buffers_runs_and_its_sure_is_sure_buffers(renders, capsys):
    """`jaxden progressive merged.exr --buffers b0..b3`: z' is the mixer stage run on the SURE
    that `jaxden sure --buffers` writes for the same input (to float32 rounding), and the
    header says how SURE was computed."""
    folder, paths, merged = renders
    buffers = [str(p) for p in paths[:K]]
    sure_out, z_out, alpha_out = folder / "sure.exr", folder / "z.exr", folder / "alpha.exr"
    code, lines, stdout = run_cli(["sure", merged, "--buffers", *buffers, "--denoiser", "oidn",
                                   "--out", sure_out], capsys)
    assert code == 0, lines
    code, lines, stdout = run_cli(["progressive", merged, "--buffers", *buffers, "--denoiser",
                                   "oidn", "--mixer", "closed-form", "--out", z_out,
                                   "--alpha", alpha_out], capsys)
    assert code == 0, lines
    assert f"SURE from {K} sub-buffers" in stdout
    header = read_header(z_out)
    assert header["method"] == "buffers" and header["buffers"] == K
    assert "probes" not in header

    frame = read_frame(merged)
    params, config = P.load_mixer("closed-form")
    colours = np.stack([read_frame(p).color for p in paths[:K]])
    outputs, _ = progressive_frame(frame, "oidn", params, config, jax.random.PRNGKey(0),
                                   keep=("z", "sure", "denoised"), buffers=colours)
    np.testing.assert_allclose(outputs["sure"], _sure_channels(sure_out), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(outputs["denoised"], read_image(sure_out), rtol=1e-6)
    np.testing.assert_allclose(read_image(z_out), outputs["z"], rtol=1e-6, atol=1e-7)
    z_direct, alpha_direct, _, _ = mix_given_sure(
        frame.color, read_image(sure_out), frame.variance, _sure_channels(sure_out), params,
        config, spp=frame.spp, variance_dof=frame.variance_dof)
    np.testing.assert_allclose(read_image(z_out), np.asarray(z_direct), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(read_image(alpha_out), np.asarray(alpha_direct), atol=1e-6)


@pytest.mark.parametrize("command", ["sure", "progressive"])
@pytest.mark.parametrize("case, words", [
    ("other", ("b4.exr", "is not one of the 4 buffers", "merged.exr")),
    ("count", ("names 3 files", "merged.exr", "4 buffers")),
    ("twice", ("b1.exr", "b1-copy.exr", "the same image")),
])
def test_wrong_buffers_are_refused_in_one_line(renders, capsys, command, case, words):
    folder, paths, merged = renders
    names = [str(p) for p in paths[:K]]
    if case == "other":
        names[3] = str(paths[K])
    elif case == "count":
        names = names[:3]
    else:
        copy = folder / "b1-copy.exr"
        shutil.copyfile(paths[1], copy)
        names[2] = str(copy)
    out = folder / f"refused-{command}-{case}.exr"
    extra = ["--mixer", "closed-form"] if command == "progressive" else []
    code, lines, _ = run_cli([command, merged, "--buffers", *names, "--denoiser", "oidn",
                              *extra, "--out", out], capsys)
    assert_one_error_line(code, lines, *words)
    assert not out.exists()


def test_merged_input_without_buffers_gets_a_one_line_hint(renders, capsys):
    folder, _, merged = renders
    out = folder / "probes.exr"
    code, lines, _ = run_cli(["sure", merged, "--denoiser", "oidn", "--probes", 1,
                              "--out", out], capsys)
    assert code == 0 and out.exists()
    notes = [line for line in lines if "--buffers" in line]
    assert len(notes) == 1 and notes[0].startswith("jaxden: note: ") and "b0.exr" in notes[0]
    assert "sub-buffer SURE" in notes[0]


def test_merge_records_the_degrees_of_freedom():
    """Spread of K renders: K - 1 whatever the spp; pooled from the renders' own variances:
    K m - 1 (= spp - 1), more where a render records its own dof (sum d_k + K - 1)."""
    frames = [synthetic_render("pipeline", 16, seed=s, size=(6, 5)) for s in range(3)]
    spread = merge_renders([f.replace(variance=None) for f in frames])
    assert float(spread.variance_dof) == 2 and float(spread.spp) == 48
    pooled = merge_renders(frames)
    assert float(pooled.variance_dof) == 47 == float(pooled.spp) - 1
    assert combine_buffers(frames).variance_dof is None  # spp - 1
    own = combine_buffers([frames[0].replace(variance_dof=np.float32(3)), *frames[1:]])
    assert float(own.variance_dof) == 3 + 15 + 15 + 2


def test_frame_variance_dof_is_validated_stacked_and_cropped():
    frame = synthetic_render("pipeline", 4, size=(6, 5)).replace(variance_dof=np.float32(3))
    assert float(frame.crop(1, 1, 2, 2).variance_dof) == 3
    assert stack([frame, frame]).variance_dof.shape == (2,)
    with pytest.raises(FrameError, match="only some have variance_dof"):
        stack([frame, frame.replace(variance_dof=None)])
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(FrameError, match="variance_dof must be > 0"):
            frame.replace(variance_dof=np.float32(bad)).validated()


def _effective_pixels(sigma: float) -> float:
    radius = max(1, int(np.ceil(3 * sigma)))
    offsets = np.arange(-radius, radius + 1)
    window = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma ** 2))
    return window.sum() ** 2 / np.square(window).sum()


@pytest.mark.parametrize("sigma, confidence", [(1.0, 2.0), (2.5, 3.0)])
def test_inflation_with_variance_dof_matches_numpy(sigma, confidence):
    """1 + c sqrt(2 / (d N_eff)) with d = K - 1 for K merged renders; N_eff of the literal 2-D
    window; the spp path is the same formula at d = spp - 1."""
    cfg = P.TStatConfig(guard_sigma=sigma, guard_confidence=confidence)
    n_eff = _effective_pixels(sigma)
    for k in (2, 4, 16):
        want = 1 + confidence * np.sqrt(2 / ((k - 1) * n_eff))
        got = float(variance_inflation(None, cfg, variance_dof=k - 1))
        np.testing.assert_allclose(got, want, rtol=1e-6)
        np.testing.assert_allclose(got, float(variance_inflation(64.0, cfg, variance_dof=k - 1)),
                                   rtol=0)  # the dof wins over spp
        np.testing.assert_allclose(float(variance_inflation(k, cfg)),
                                   float(variance_inflation(None, cfg, variance_dof=k - 1)),
                                   rtol=0)
    assert guard_sample_count(64.0, None) == 64.0 and guard_sample_count(None, None) is None
    assert float(guard_sample_count(64.0, 3.0)) == 4.0


def test_bound_from_the_dof_covers_the_variance_of_a_merged_mean():
    """K = 4 renders of 16 spp (unit per-sample variance) merged by their spread: the variance
    of the merged mean is 1/64, estimated with 3 degrees of freedom. The guard's bound, the
    Gaussian local mean of the estimate (interior pixels, sigma 1) times its inflation, should
    cover 1/64 with probability P(chi^2_k >= k / I), k = 3 N_eff = 37.7, I = 1.46: 0.929. The
    spp-based bound (I = 1.10 at 64 spp) covers it with 0.630. Measured over 8 images of
    64 x 64 x 3 (seed 0): within 0.02 of 0.929, and at least 0.2 above the spp-based."""
    cfg = P.TStatConfig()
    rng = np.random.default_rng(0)
    taps = gaussian_taps(cfg.guard_sigma).astype(np.float64)
    taps /= taps.sum()
    true_variance = 1.0 / (K * 16)
    local_means, dof = [], None
    for _ in range(8):
        frames = [Frame(color=(1.0 + rng.standard_normal((64, 64, 3)) / 4).astype(np.float32),
                        spp=np.float32(16)) for _ in range(K)]
        merged = merge_renders(frames)
        dof, spp = float(merged.variance_dof), float(merged.spp)
        var = np.asarray(merged.variance, np.float64)
        rows = np.apply_along_axis(np.convolve, 0, var, taps, mode="valid")
        local_means.append(np.apply_along_axis(np.convolve, 1, rows, taps, mode="valid"))
    local = np.stack(local_means)
    assert dof == K - 1 and spp == K * 16
    by_dof = float(variance_inflation(None, cfg, variance_dof=dof))
    by_spp = float(variance_inflation(spp, cfg))
    covered_dof = np.mean(local * by_dof >= true_variance)
    covered_spp = np.mean(local * by_spp >= true_variance)
    k = dof * _effective_pixels(cfg.guard_sigma)
    predicted = chi2.sf(k / by_dof, k)
    assert abs(predicted - 0.929) < 0.002
    assert abs(covered_dof - predicted) < 0.02, (covered_dof, predicted)
    assert covered_dof > covered_spp + 0.2, (covered_dof, covered_spp)
