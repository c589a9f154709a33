"""EXR round trips and every way a file or frame can be wrong."""

import os

import numpy as np
import pytest

from jaxden.errors import ExrError, FrameError
from jaxden.frame import CHANNELS, Frame, stack
from jaxden.io import exr


def make_frame(h=6, w=7, seed=0, full=True):
    rng = np.random.default_rng(seed)
    fields = dict(
        color=rng.uniform(0, 4, (h, w, 3)).astype(np.float32),
        variance=rng.uniform(0, 0.1, (h, w, 3)).astype(np.float32),
    )
    if full:
        normal = rng.normal(size=(h, w, 3)).astype(np.float32)
        fields.update(
            albedo=rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
            normal=normal / np.linalg.norm(normal, axis=-1, keepdims=True),
            depth=rng.uniform(0.5, 9, (h, w, 1)).astype(np.float32),
            position=rng.normal(size=(h, w, 3)).astype(np.float32),
            motion=rng.normal(size=(h, w, 2)).astype(np.float32),
            emission=rng.uniform(0, 2, (h, w, 3)).astype(np.float32),
            boxcox=np.concatenate([rng.uniform(-2, 3, (h, w, 3)), rng.uniform(0, 1, (h, w, 3)),
                                   rng.uniform(-1, 1, (h, w, 3))], axis=-1).astype(np.float32),
        )
        var = fields["variance"]
        fields["covariance"] = (rng.uniform(-0.9, 0.9, (h, w, 3))
                                * np.sqrt(var * np.roll(var, -1, axis=-1))).astype(np.float32)
    return Frame(**fields, spp=np.float32(16))


def test_frame_round_trip_is_bit_exact_with_channel_names_and_header(tmp_path):
    frame = make_frame()
    path = tmp_path / "f.exr"
    exr.write_frame(path, frame, attributes={"seed": 42, "scene": "cornell-box"})
    header = exr.read_header(path)
    expected = sorted(c for names in CHANNELS.values() for c in names)
    assert header["channels"] == expected
    assert header["spp"] == 16 and header["seed"] == 42 and header["scene"] == "cornell-box"
    assert header["size"] == (7, 6)
    back = exr.read_frame(path)
    for field in CHANNELS:
        np.testing.assert_array_equal(getattr(back, field), getattr(frame, field))
    assert float(back.spp) == 16.0


def test_half_storage_rounds_to_float16(tmp_path):
    frame = make_frame(full=False)
    path = tmp_path / "h.exr"
    exr.write_frame(path, frame, half=["variance"])
    back = exr.read_frame(path)
    np.testing.assert_array_equal(back.color, frame.color)
    np.testing.assert_array_equal(back.variance, frame.variance.astype(np.float16).astype(np.float32))
    assert not np.array_equal(back.variance, frame.variance)


def test_missing_required_feature_names_field_and_channels(tmp_path):
    path = tmp_path / "c.exr"
    exr.write_image(path, np.ones((4, 4, 3)))
    with pytest.raises(ExrError, match=r"variance.*variance\.R.*file has channels B, G, R"):
        exr.read_frame(path, require=("color", "variance"))


def test_incomplete_feature_is_an_error(tmp_path):
    path = tmp_path / "p.exr"
    ones = np.ones((3, 3), np.float32)
    exr.write_channels(path, {"R": ones, "G": ones, "B": ones, "albedo.R": ones})
    with pytest.raises(ExrError, match="albedo.*incomplete"):
        exr.read_frame(path)


def test_truncated_file_is_a_clear_error(tmp_path, capfd):
    """One ExrError naming the file (with libOpenEXR's reason), and none of the library's own
    prints on stdout / stderr around it."""
    path = tmp_path / "t.exr"
    exr.write_frame(path, make_frame(32, 32))
    data = path.read_bytes()
    capfd.readouterr()
    for cut in (len(data) // 3, len(data) - 20):
        bad = tmp_path / f"cut{cut}.exr"
        bad.write_bytes(data[:cut])
        with pytest.raises(ExrError, match=str(bad.name)) as info:
            exr.read_frame(bad)
        assert "truncated or corrupt" in str(info.value) and "\n" not in str(info.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    exr.read_frame(path)  # the intact file still reads, with nothing printed
    assert capfd.readouterr() == ("", "")


def test_non_exr_missing_and_folder(tmp_path):
    junk = tmp_path / "junk.exr"
    junk.write_text("not an image at all")
    with pytest.raises(ExrError, match="not an OpenEXR file"):
        exr.read_frame(junk)
    with pytest.raises(ExrError, match="no such file"):
        exr.read_frame(tmp_path / "absent.exr")
    with pytest.raises(ExrError, match="folder"):
        exr.read_frame(tmp_path)


def test_nan_is_error_by_default_and_zero_policy_repairs(tmp_path):
    frame = make_frame(full=False)
    color = frame.color.copy()
    color[2, 3, 1] = np.nan
    path = tmp_path / "n.exr"
    with pytest.raises(ExrError, match="refusing to write channel 'G' with 1 non-finite"):
        exr.write_channels(path, {c: color[..., i] for i, c in enumerate("RGB")})
    assert not path.exists() and not list(tmp_path.iterdir())
    exr.write_channels(path, {c: color[..., i] for i, c in enumerate("RGB")},
                       allow_nonfinite=True)  # as another renderer might
    with pytest.raises(ExrError, match=r"colou?r.*non-finite.*\(2, 3, 1\)"):
        exr.read_frame(path)
    repaired = exr.read_frame(path, nonfinite="zero")
    assert repaired.color[2, 3, 1] == 0 and np.isfinite(repaired.color).all()


def test_negative_variance_rejected_and_round_off_clipped_on_request(tmp_path):
    frame = make_frame(full=False)
    variance = frame.variance.copy()
    variance[1, 1, 0] = -1e-9  # round-off size
    with pytest.raises(FrameError, match="variance must be >= 0"):
        frame.replace(variance=variance).validated()
    fixed = frame.replace(variance=variance).validated(nonfinite="zero")
    assert fixed.variance[1, 1, 0] == 0
    variance[1, 1, 0] = -0.5  # not round-off: a wrong file
    with pytest.raises(FrameError, match="negative"):
        frame.replace(variance=variance).validated(nonfinite="zero")


def test_shape_mismatch_and_wrong_channel_count():
    frame = make_frame(full=False)
    with pytest.raises(FrameError, match="'variance' has size"):
        frame.replace(variance=np.zeros((5, 7, 3), np.float32)).validated()
    with pytest.raises(FrameError, match=r"'depth' must have shape \(\.\.\., H, W, 1\)"):
        frame.replace(depth=np.zeros((6, 7, 3), np.float32)).validated()


def test_write_is_atomic_no_partial_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "a.exr"
    exr.write_frame(path, make_frame(seed=1))
    before = path.read_bytes()
    import OpenEXR

    class Exploding:
        def __init__(self, *args, **kwargs):
            pass

        def write(self, name):
            with open(name, "wb") as handle:
                handle.write(b"partial")
            raise KeyboardInterrupt

    monkeypatch.setattr(OpenEXR, "File", Exploding)
    with pytest.raises(KeyboardInterrupt):
        exr.write_frame(path, make_frame(seed=2))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["a.exr"]


def test_foreign_exr_with_channel_map_and_sample_variance(tmp_path):
    rng = np.random.default_rng(3)
    color = rng.uniform(0, 1, (4, 5, 3)).astype(np.float32)
    sample_var = rng.uniform(0, 2, (4, 5, 3)).astype(np.float32)
    path = tmp_path / "other.exr"
    channels = {c: color[..., i] for i, c in enumerate("RGB")}
    channels.update({f"var.{c}": sample_var[..., i] for i, c in enumerate("RGB")})
    exr.write_channels(path, channels)
    with pytest.raises(ExrError, match="needs the sample count"):
        exr.read_frame(
            path,
            channel_map={"variance": ("var.R", "var.G", "var.B")},
            variance_is_sample_variance=True,
        )
    frame = exr.read_frame(
        path,
        require=("color", "variance"),
        channel_map={"variance": ("var.R", "var.G", "var.B")},
        variance_is_sample_variance=True,
        spp=8,
    )
    np.testing.assert_allclose(frame.variance, sample_var / 8, rtol=1e-7)


def test_image_round_trip_and_default_names(tmp_path):
    image = np.random.default_rng(0).uniform(size=(3, 4, 3)).astype(np.float32)
    exr.write_image(tmp_path / "i.exr", image)
    np.testing.assert_array_equal(exr.read_image(tmp_path / "i.exr"), image)
    exr.write_image(tmp_path / "y.exr", image[..., 0])
    np.testing.assert_array_equal(exr.read_image(tmp_path / "y.exr"), image[..., :1])


def test_stack_and_crop():
    frames = [make_frame(seed=i) for i in range(3)]
    batch = stack(frames)
    assert batch.color.shape == (3, 6, 7, 3) and batch.spp.shape == (3,)
    for i, frame in enumerate(frames):  # in order, every field
        for name in frame.features():
            np.testing.assert_array_equal(getattr(batch, name)[i], getattr(frame, name))
        assert batch.spp[i] == frame.spp
    crop = frames[0].crop(1, 2, 3, 4)
    np.testing.assert_array_equal(crop.motion, frames[0].motion[1:4, 2:6])
    with pytest.raises(FrameError, match="does not fit"):
        frames[0].crop(4, 0, 3, 3)
    with pytest.raises(FrameError, match="different features"):
        stack([make_frame(full=False), make_frame()])
    with pytest.raises(FrameError, match="needs the frame feature"):
        make_frame(full=False).require("albedo", "normal", who="WSKP")


def test_reading_from_a_worker_thread_works(tmp_path):
    """Reads outside the main thread do not touch the process's stdout / stderr descriptors
    (the noise hold is main-thread only) and give the same data and errors."""
    import concurrent.futures

    path = tmp_path / "t.exr"
    exr.write_frame(path, make_frame(16, 16))
    bad = tmp_path / "bad.exr"
    bad.write_bytes(path.read_bytes()[:200])
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        colours = list(pool.map(lambda _: exr.read_frame(path).color, range(4)))
        with pytest.raises(ExrError, match="bad.exr"):
            pool.submit(exr.read_frame, bad).result()
    for colour in colours:
        np.testing.assert_array_equal(colour, exr.read_frame(path).color)


def test_covariance_must_be_a_covariance_of_the_variance(tmp_path):
    """Frame.covariance (R G, G B, B R of the mean) needs the variance and must meet
    |cov_ab| <= sqrt(var_a var_b): a covariance from another render or per sample while the
    variance is of the mean is refused, naming the pair; round-off within the slack passes."""
    frame = make_frame()
    var = np.asarray(frame.variance, np.float64)
    bound = np.sqrt(var * np.roll(var, -1, axis=-1))
    at_bound = frame.replace(covariance=(bound * (1 + 1e-4)).astype(np.float32))
    at_bound.validated()  # within the relative slack (float32 files, clipped round-off)
    clipped = at_bound.validated(nonfinite="zero").covariance
    assert (np.abs(clipped) <= bound.astype(np.float32) * (1 + 1e-6)).all()
    cov = np.array(frame.covariance)
    cov[2, 3, 1] = 2.0 * bound[2, 3, 1]
    with pytest.raises(FrameError, match=r"cov\(G, B\)\| > sqrt\(var var\) at 1 value\(s\) "
                                         r"\(first at index \(2, 3, 1\)"):
        frame.replace(covariance=cov).validated(where="f.exr")
    with pytest.raises(FrameError, match="'covariance' needs the variance"):
        frame.replace(variance=None).validated()
    # a file storing the per-sample (co)variance: both are divided by spp on reading
    path = tmp_path / "per-sample.exr"
    per_sample = frame.replace(variance=frame.variance * 16, covariance=frame.covariance * 16)
    exr.write_frame(path, per_sample)
    with pytest.raises(ExrError, match="jaxden wrote this file"):  # it holds that of the mean
        exr.read_frame(path, variance_is_sample_variance=True)
    channels = {name: np.asarray(getattr(per_sample, field))[..., i]  # as another renderer
                for field in per_sample.features() for i, name in enumerate(CHANNELS[field])}
    exr.write_channels(path, channels, attributes={"spp": float(per_sample.spp)})
    back = exr.read_frame(path, variance_is_sample_variance=True)
    np.testing.assert_allclose(back.covariance, frame.covariance, rtol=1e-6)
    np.testing.assert_allclose(back.variance, frame.variance, rtol=1e-6)


def test_links_that_loop_or_dangle_are_named(tmp_path):
    loop = tmp_path / "loop.exr"
    loop.symlink_to(loop)
    with pytest.raises(ExrError, match="loops back on itself"):
        exr.read_frame(loop)
    dangling = tmp_path / "dangling.exr"
    dangling.symlink_to(tmp_path / "nothing.exr")
    with pytest.raises(ExrError, match="a symbolic link to nothing"):
        exr.read_frame(dangling)


def test_strata_narrower_than_a_sixteenth_stop_are_refused():
    from jaxden.errors import ConfigError
    from jaxden.progressive.mixer import MixerConfig
    from jaxden.progressive.tstat import TStatConfig

    with pytest.raises(ConfigError, match=r"closed_form_stops: 1e-300 is outside"):
        MixerConfig(denoiser="oidn", closed_form_stops=1e-300)
    with pytest.raises(ConfigError, match=r"guard_strata: 0.01 is outside"):
        TStatConfig(guard_strata=0.01)
