"""Tests of jaxden.render: variant choice, integrators, scene library, XML, render_frame.

Renders are tiny (a few hundred pixels, a few spp) and reuse loaded scenes: Mitsuba's LLVM
JIT compiles each new kernel once (a few hundred ms), then renders are quick.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap

import mitsuba as mi  # a hard dependency: a broken install must fail loudly, not skip
import numpy as np
import pytest

from jaxden.errors import JaxdenError, SceneError
from jaxden.frame import Frame
from jaxden.render import (
    choose_variant,
    core,
    integrators,
    list_scenes,
    load,
    load_scene,
    prepare_scene,
    render_frame,
    variant,
)

BUILTIN = ("cornell-box", "texture-bump", "glossy-glass", "env-sun", "small-lights")
# Reflectances of mi.cornell_box()'s three diffuse materials.
CORNELL_ALBEDOS = np.array([
    [0.885809, 0.698859, 0.666422],  # white
    [0.570068, 0.0430135, 0.0443706],  # red
    [0.105421, 0.37798, 0.076425],  # green
])


@pytest.fixture(scope="module")
def cornell():
    """The Cornell box at 32 x 24 (width x height)."""
    return load_scene("cornell-box", size=(32, 24))


@pytest.fixture(scope="module")
def cornell_frame(cornell):
    return render_frame(cornell, spp=8, seed=5)


# ---------------------------------------------------------------------------- variant
def test_variant_is_an_rgb_variant_and_set():
    chosen = choose_variant()
    assert chosen in ("llvm_ad_rgb", "scalar_rgb")
    assert variant.ensure_variant() == chosen
    assert mi.variant() == chosen


def test_variant_override_must_be_installed_rgb_variant(monkeypatch):
    monkeypatch.setenv(variant.ENV_VARIANT, "llvm_ad_spectral_not_a_variant")
    with pytest.raises(JaxdenError, match="not an installed RGB Mitsuba variant.*scalar_rgb"):
        choose_variant()


def test_variant_falls_back_with_one_notice(monkeypatch, tmp_path, capsys):
    """A failed probe selects scalar_rgb and prints exactly one line to stderr."""
    calls = []
    monkeypatch.delenv(variant.ENV_VARIANT, raising=False)
    monkeypatch.setenv("JAXDEN_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(variant, "_chosen", None)
    monkeypatch.setattr(variant, "_notice_printed", False)
    monkeypatch.setattr(variant, "probe_variant",
                        lambda name, timeout=0: calls.append(name) or (False, "simulated abort"))
    assert choose_variant() == "scalar_rgb"
    assert choose_variant() == "scalar_rgb"  # cached in-process: no second probe
    assert calls == ["llvm_ad_rgb"]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simulated abort" in err[0] and "scalar_rgb" in err[0]
    assert "libllvm19" in err[0]


def test_variant_cache_file_stale_or_corrupt_is_ignored(monkeypatch, tmp_path):
    calls = []
    monkeypatch.delenv(variant.ENV_VARIANT, raising=False)
    monkeypatch.setenv("JAXDEN_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(variant, "probe_variant",
                        lambda name, timeout=0: calls.append(name) or (True, ""))
    cache = tmp_path / variant.CACHE_FILE_NAME
    for content in ("{not json", json.dumps({"key": "stale", "variant": "llvm_ad_rgb"}),
                    json.dumps({"key": variant.cache_key(), "variant": "bogus_variant"})):
        cache.write_text(content)
        monkeypatch.setattr(variant, "_chosen", None)
        assert choose_variant() == "llvm_ad_rgb"
    assert len(calls) == 3  # every bad cache forced a probe
    entry = json.loads(cache.read_text())
    assert entry["key"] == variant.cache_key() and entry["variant"] == "llvm_ad_rgb"
    monkeypatch.setattr(variant, "_chosen", None)
    assert choose_variant() == "llvm_ad_rgb"
    assert len(calls) == 3  # a valid entry is used without probing


def test_probe_of_a_broken_variant_fails_cleanly():
    ok, reason = variant.probe_variant("no_such_variant", timeout=120)
    assert not ok
    assert "probe render failed" in reason and "no_such_variant" in reason


def test_scalar_variant_override_renders_in_subprocess(tmp_path):
    script = textwrap.dedent("""
        import numpy as np, mitsuba as mi
        from jaxden.render import render_frame
        frame = render_frame("cornell-box", spp=4, seed=1, size=(8, 6))
        assert mi.variant() == "scalar_rgb", mi.variant()
        assert frame.color.shape == (6, 8, 3) and np.isfinite(frame.color).all()
        assert frame.variance.shape == (6, 8, 3) and (frame.variance >= 0).all()
        assert frame.color.mean() > 0.01
        print("OK", mi.variant())
    """)
    env = dict(os.environ, JAXDEN_MITSUBA_VARIANT="scalar_rgb")
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                            text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "OK scalar_rgb" in result.stdout


# ---------------------------------------------------------------------------- integrators
def test_moment_colour_equals_plain_path_render(cornell):
    """Same seed and spp: the wrapper's colour equals plain `path` to float32 round-off.

    Not bit for bit: a film with extra channels accumulates in a different order (measured:
    at most ~3 ulp). A different seed differs by orders of magnitude more, so the wrapper
    draws the same random numbers.
    """
    sensor = cornell.sensors()[0]
    path = integrators.path_integrator(8)
    moment = integrators.moment_integrator(max_depth=8)
    plain = np.array(mi.render(cornell, sensor=sensor, integrator=path, seed=7, spp=8))
    both = np.array(mi.render(cornell, sensor=sensor, integrator=moment, seed=7, spp=8))
    other = np.array(mi.render(cornell, sensor=sensor, integrator=path, seed=8, spp=8))
    assert both.shape == plain.shape[:2] + (integrators.MOMENT_CHANNELS,)
    np.testing.assert_allclose(both[..., :3], plain, rtol=1e-6, atol=1e-7)
    assert np.abs(other - plain).max() > 1e-2
    # Second moments: m2 >= m1^2 (Cauchy-Schwarz) up to round-off, and the cross moments
    # mean(L_a L_b) <= sqrt(m2_a m2_b).
    assert (both[..., 3:6] >= both[..., :3] ** 2 * (1 - 1e-5) - 1e-7).all()
    m2 = both[..., 3:6].astype(np.float64)
    assert (np.abs(both[..., 6:9]) <= np.sqrt(m2 * np.roll(m2, -1, axis=-1)) * (1 + 1e-5)
            + 1e-7).all()


def test_moment_at_one_spp_is_the_square_of_the_sample(cornell):
    """With one sample per pixel m2 = L^2 and m11 = L_a L_b exactly: the AOVs are the squares
    and the cross products (R G, G B, B R) of that sample."""
    moment = integrators.moment_integrator(max_depth=8)
    image = np.array(mi.render(cornell, integrator=moment, seed=3, spp=1))
    np.testing.assert_allclose(image[..., 3:6], image[..., :3] ** 2, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(image[..., 6:9], image[..., :3] * np.roll(image[..., :3], -1, -1),
                               rtol=1e-6, atol=1e-8)


def test_variance_of_mean_formula_against_numpy():
    rng = np.random.default_rng(0)
    samples = rng.gamma(2.0, 1.0, size=(16, 5, 3))  # 16 samples per "pixel"
    m1, m2 = samples.mean(0), (samples**2).mean(0)
    expected = samples.var(0, ddof=1) / 16
    np.testing.assert_allclose(integrators.variance_of_mean(m1, m2, 16), expected, rtol=1e-12)
    assert (integrators.variance_of_mean(m1, m1**2 - 1e-9, 16) == 0).all()  # clipped at 0


def test_covariance_of_mean_formula_against_numpy():
    """The covariance of the mean between channel pairs (R, G), (G, B), (B, R) equals NumPy's
    sample covariance / n, and is clipped to Cauchy-Schwarz when round-off breaks it."""
    rng = np.random.default_rng(1)
    light = rng.gamma(2.0, 1.0, size=(16, 5, 1))  # one path brightness shared by R, G, B
    samples = light * rng.uniform(0.2, 1.0, size=(16, 5, 3)) + rng.gamma(1.0, 0.1, (16, 5, 3))
    m1, m2 = samples.mean(0), (samples**2).mean(0)
    m11 = (samples * np.roll(samples, -1, axis=-1)).mean(0)
    variance = integrators.variance_of_mean(m1, m2, 16)
    expected = np.stack([np.cov(samples[:, p, a], samples[:, p, (a + 1) % 3])[0, 1] / 16
                         for p in range(5) for a in range(3)]).reshape(5, 3)
    np.testing.assert_allclose(integrators.covariance_of_mean(m1, m11, variance, 16), expected,
                               rtol=1e-10)
    assert (expected > 0).all()  # the shared brightness correlates the channels
    bound = np.sqrt(variance * np.roll(variance, -1, axis=-1))
    clipped = integrators.covariance_of_mean(m1, m11 + 1.0, variance, 16)
    np.testing.assert_allclose(clipped, bound, rtol=1e-12)


def test_render_frame_colour_equals_plain_path_with_derived_seed(cornell, cornell_frame):
    sensor = cornell.sensors()[0]
    plain = np.array(mi.render(cornell, sensor=sensor, integrator=integrators.path_integrator(8),
                               seed=core.derive_seed(5, "color", 0), spp=8))
    np.testing.assert_allclose(cornell_frame.color, plain, rtol=1e-6, atol=1e-7)


def test_derived_seeds_are_distinct_and_deterministic():
    seeds = {core.derive_seed(s, p, i) for s in range(50) for p in ("color", "aov")
             for i in range(3)}
    assert len(seeds) == 300 and all(0 <= s < 2**32 for s in seeds)
    # Against the documented derivation, computed here independently: the little-endian
    # 32-bit BLAKE2b digest of "jaxden:{seed}:{purpose}:{index}" ...
    import hashlib

    for seed, purpose, index in ((7, "aov", 0), (5, "color", 1), (2**40 + 3, "color", 17)):
        text = f"jaxden:{seed}:{purpose}:{index}".encode()
        want = int.from_bytes(hashlib.blake2b(text, digest_size=4).digest(), "little")
        assert core.derive_seed(seed, purpose, index) == want
    # ... and pinned values: datasets are rebuilt from (config, seed), so a change of the
    # derivation changes every rendered file and must be deliberate.
    assert core.derive_seed(7, "aov") == 1291298942
    assert core.derive_seed(0, "color", 0) == 2617655944
    assert core.derive_seed(5, "color", 1) == 458976730


def test_split_passes():
    assert core.split_passes(64, 256 * 256) == [64]
    assert core.split_passes(10, 100, max_samples=300) == [3, 3, 2, 2]
    assert core.split_passes(3000, 4, max_spp=1024) == [1000, 1000, 1000]
    assert core.split_passes(2, 10, max_samples=1) == [1, 1]  # never a pass with 0 spp
    for spp, pixels in ((1, 1), (7, 1000), (4097, 65536)):
        passes = core.split_passes(spp, pixels, max_samples=100_000)
        assert sum(passes) == spp and max(passes) - min(passes) <= 1


def test_passes_combine_moments_exactly(cornell):
    """spp=8 in two passes of 4 equals the hand-combined moments of two 4-spp renders."""
    pixels = 32 * 24
    frame = render_frame(cornell, spp=8, seed=11, max_samples_per_pass=4 * pixels)
    moment = integrators.moment_integrator(max_depth=8)
    images = [np.array(mi.render(cornell, integrator=moment, seed=core.derive_seed(11, "color", i),
                                 spp=4), dtype=np.float64) for i in range(2)]
    m1 = (images[0][..., :3] + images[1][..., :3]) / 2
    m2 = (images[0][..., 3:6] + images[1][..., 3:6]) / 2
    m11 = (images[0][..., 6:9] + images[1][..., 6:9]) / 2
    np.testing.assert_allclose(frame.color, m1, rtol=1e-6, atol=1e-7)
    variance = np.maximum(m2 - m1**2, 0) / 7
    np.testing.assert_allclose(frame.variance, variance, rtol=1e-5, atol=1e-9)
    bound = np.sqrt(variance * np.roll(variance, -1, -1))
    np.testing.assert_allclose(frame.covariance,
                               np.clip((m11 - m1 * np.roll(m1, -1, -1)) / 7, -bound, bound),
                               rtol=1e-4, atol=1e-9)


# ---------------------------------------------------------------------------- render_frame
def test_frame_shapes_types_and_validation(cornell_frame):
    frame = cornell_frame
    assert isinstance(frame, Frame)
    shapes = {"color": 3, "variance": 3, "albedo": 3, "normal": 3, "depth": 1, "position": 3}
    for name, channels in shapes.items():
        array = getattr(frame, name)
        assert isinstance(array, np.ndarray) and array.dtype == np.float32, name
        assert array.shape == (24, 32, channels), name
    assert frame.motion is None
    assert frame.spp == np.float32(8) and isinstance(frame.spp, np.float32)
    frame.validated("cornell")  # finite, variance >= 0


def test_features_on_the_cornell_box(cornell_frame):
    frame = cornell_frame
    hit = frame.depth[..., 0] > 0
    assert hit.mean() > 0.6  # the box fills the view but for strips left and right (4:3 film)
    assert (frame.albedo >= 0).all() and (frame.albedo <= 1).all()
    # Most hit pixels show exactly one of the scene's three diffuse reflectances.
    distance = np.abs(frame.albedo[hit][:, None, :] - CORNELL_ALBEDOS[None]).max(-1).min(-1)
    assert (distance < 1e-5).mean() > 0.7
    norms = np.linalg.norm(frame.normal, axis=-1)
    np.testing.assert_allclose(norms[hit], 1.0, atol=1e-5)
    assert (frame.normal[~hit] == 0).all() and (frame.position[~hit] == 0).all()
    assert (frame.depth[~hit] == 0).all()
    # Depth is the distance from the camera (0, 0, 3.9) to the hit point: check on pixels
    # where position and depth average consistently (interior of flat walls).
    distance = np.linalg.norm(frame.position - np.array([0.0, 0.0, 3.9]), axis=-1)
    relative = np.abs(distance[hit] - frame.depth[..., 0][hit]) / frame.depth[..., 0][hit]
    assert np.median(relative) < 1e-3
    # The back wall (z = -1) faces +z.
    back = hit & (np.abs(frame.position[..., 2] + 1.0) < 1e-3)
    assert back.sum() > 50
    np.testing.assert_allclose(frame.normal[back], np.tile([0.0, 0.0, 1.0], (back.sum(), 1)),
                               atol=1e-4)


def test_specular_chain_features_equal_first_hit_without_delta_surfaces(cornell, cornell_frame):
    # The Cornell box has only diffuse surfaces: the chain integrator stops at the first hit,
    # so it must reproduce Mitsuba's own aov integrator exactly (same seed, same rays).
    chain = render_frame(cornell, spp=8, seed=5, aux="specular-chain")
    first = render_frame(cornell, spp=8, seed=5, aux="first-hit")
    np.testing.assert_array_equal(chain.color, first.color)
    for name in ("albedo", "normal", "depth", "position"):
        np.testing.assert_allclose(getattr(chain, name), getattr(first, name),
                                   atol=1e-6, err_msg=name)
    # The default is the chain.
    np.testing.assert_array_equal(cornell_frame.albedo, chain.albedo)


def _mirror_scene(reflectance: float, behind: float):
    """A camera at the origin looking down -z at a perfect mirror (z = -2, facing +z) that
    reflects a large diffuse wall behind the camera (z = +5, facing -z)."""
    variant.ensure_variant()
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 20.0,
                   "to_world": T().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 10}},
        "mirror": {"type": "rectangle", "to_world": T().translate([0, 0, -2]).scale(3.0),
                   "bsdf": {"type": "conductor", "material": "none",
                            "specular_reflectance": {"type": "rgb", "value": [reflectance] * 3}}},
        "wall": {"type": "rectangle",
                 "to_world": T().translate([0, 0, 5]).rotate([0, 1, 0], 180).scale(50.0),
                 "bsdf": {"type": "diffuse",
                          "reflectance": {"type": "rgb", "value": [behind] * 3}}},
        "light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
    }


def test_specular_chain_takes_albedo_and_normal_behind_a_mirror():
    scene = load_scene(_mirror_scene(0.5, 0.6))
    first = render_frame(scene, spp=4, seed=1, aux="first-hit")
    chain = render_frame(scene, spp=4, seed=1)
    # First hit: a conductor, whose diffuse reflectance Mitsuba reports as 0, facing +z.
    np.testing.assert_allclose(first.albedo, 0.0, atol=1e-7)
    np.testing.assert_allclose(first.normal, np.broadcast_to([0, 0, 1], first.normal.shape),
                               atol=1e-6)
    # Through the chain: the wall's reflectance times the mirror's, and the wall's normal.
    np.testing.assert_allclose(chain.albedo, 0.5 * 0.6, rtol=1e-5)
    np.testing.assert_allclose(chain.normal, np.broadcast_to([0, 0, -1], chain.normal.shape),
                               atol=1e-5)
    # Depth and position stay first-hit (the mirror at z = -2).
    np.testing.assert_allclose(chain.depth, first.depth, rtol=1e-6)
    np.testing.assert_allclose(chain.position[..., 2], -2.0, atol=1e-5)
    # (Mitsuba's camera rays start on the near clip plane, 0.01 in front of the camera.)
    np.testing.assert_allclose(chain.depth[..., 0], np.linalg.norm(chain.position, axis=-1),
                               atol=0.015)


def test_specular_chain_on_glass_fills_the_dark_albedo():
    # glossy-glass has smooth glass and metal: first-hit albedo is 0 on them.
    scene = load_scene("glossy-glass", size=(48, 48))
    first = render_frame(scene, spp=8, seed=2, aux="first-hit")
    chain = render_frame(scene, spp=8, seed=2, aux="specular-chain")
    hit = first.depth[..., 0] > 0
    dark_first = (hit & (first.albedo.max(-1) < 1e-3)).mean()
    dark_chain = (hit & (chain.albedo.max(-1) < 1e-3)).mean()
    assert dark_first > 0.05 and dark_chain < 0.5 * dark_first, (dark_first, dark_chain)
    assert (chain.albedo >= 0).all() and (chain.albedo <= 1).all()
    np.testing.assert_array_equal(chain.depth, first.depth)


@pytest.mark.slow  # ~16 s of Mitsuba compilation and rendering
def test_feature_spp_sets_the_feature_samples(cornell, cornell_frame):
    # At spp = 8 the features average min(8, feature_spp) = 8 samples for any feature_spp
    # >= 8: the same render.
    same = render_frame(cornell, spp=8, seed=5, feature_spp=1024)
    for name in ("albedo", "normal", "depth", "position"):
        np.testing.assert_array_equal(getattr(same, name), getattr(cornell_frame, name))
    # More feature samples: less feature noise. Albedo RMSE against a 256-sample feature
    # render, on the finely textured texture-bump scene, of 16-spp renders with 4 and 16
    # feature samples (seeds fixed). Expected ratio 1/2 for 4x the samples (measured 0.48-0.53
    # over 5 seed pairs; the reference's own noise adds ~6 % to the variance), asserted < 0.75.
    scene = load_scene("texture-bump", size=(32, 32))
    truth = render_frame(scene, spp=256, seed=9, feature_spp=256).albedo
    errors = [np.sqrt(np.mean((render_frame(scene, spp=16, seed=s, feature_spp=n).albedo
                               - truth) ** 2)) for s, n in ((1, 4), (2, 16))]
    assert errors[1] < 0.75 * errors[0], errors


@pytest.mark.slow  # ~16 s of Mitsuba compilation and rendering
def test_feature_passes_average_like_one_pass(cornell):
    # A sample budget of 2 x the film forces 32 feature passes at 64 feature spp; interior
    # pixels (one diffuse reflectance exactly) must come out the same as in one pass.
    one = render_frame(cornell, spp=64, seed=4, feature_spp=64)
    split = render_frame(cornell, spp=64, seed=4, feature_spp=64, max_samples_per_pass=2 * 32 * 24)
    hit = one.depth[..., 0] > 0
    interior = hit & (np.abs(one.albedo[..., None, :] - CORNELL_ALBEDOS).max(-1).min(-1) < 1e-6)
    assert interior.mean() > 0.5
    np.testing.assert_allclose(split.albedo[interior], one.albedo[interior], atol=1e-5)
    assert np.abs(split.albedo - one.albedo).max() > 0  # other seeds: edges differ
    with pytest.raises(SceneError, match="feature_spp must be in"):
        render_frame(cornell, spp=2, feature_spp=0)


def test_bad_aux_mode(cornell):
    with pytest.raises(SceneError, match="aux must be one of first-hit, specular-chain"):
        render_frame(cornell, spp=2, aux="next-hit")


def test_render_is_deterministic_in_the_seed(cornell, cornell_frame):
    again = render_frame(cornell, spp=8, seed=5)
    for name in ("color", "variance", "albedo", "normal", "depth", "position"):
        np.testing.assert_array_equal(getattr(again, name), getattr(cornell_frame, name))
    other = render_frame(cornell, spp=8, seed=6)
    assert np.abs(other.color - cornell_frame.color).max() > 1e-2


def test_one_spp_has_no_variance(cornell):
    frame = render_frame(cornell, spp=1, seed=0)
    assert frame.variance is None and frame.spp == 1
    assert np.isfinite(frame.color).all()


def test_crop_renders_only_the_crop_at_the_right_place(cornell, cornell_frame):
    top, left, height, width = 4, 6, 10, 12
    crop = render_frame(cornell, spp=8, seed=9, crop=(top, left, height, width))
    assert crop.color.shape == (10, 12, 3) and crop.depth.shape == (10, 12, 1)
    full = cornell_frame.position

    def mismatch(dy, dx):
        window = full[top + dy:top + dy + height, left + dx:left + dx + width]
        return np.abs(crop.position - window).mean()

    errors = {(dy, dx): mismatch(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)}
    best = errors.pop((0, 0))
    assert best < 0.5 * min(errors.values())


@pytest.mark.parametrize("camera", [
    {},  # the Cornell box's own camera (fov_axis 'smaller')
    {"fov": 35.0, "fov_axis": "y", "principal_point_offset_x": 0.08,
     "principal_point_offset_y": -0.05},
])
def test_crop_camera_equals_mitsuba_film_crop(cornell, camera):
    """The off-centre crop camera gives the same render as Mitsuba's film crop (same seed),
    to float round-off, and reuses one sensor (hence one set of kernels) across offsets."""
    sensor_dict = dict(prepare_scene("cornell-box")["sensor"], **camera)
    source = load.SensorSource(name="test", size=(40, 30), sensor_dict=sensor_dict)
    moment = integrators.moment_integrator(max_depth=8)
    sensors = []
    for crop in [(3, 5, 10, 12), (20, 28, 10, 12), (0, 0, 30, 40)]:
        emulated = source.build((40, 30), crop)
        sensors.append(emulated)
        mine = np.array(mi.render(cornell, sensor=emulated, integrator=moment, seed=4, spp=4))
        film_crop = load.build_sensor(sensor_dict, (40, 30), crop, "test")
        theirs = np.array(mi.render(cornell, sensor=film_crop, integrator=moment, seed=4, spp=4))
        assert mine.shape == theirs.shape == (crop[2], crop[3], integrators.MOMENT_CHANNELS)
        close = np.abs(mine - theirs) <= 1e-4 * (1 + np.abs(theirs))
        assert close.all(-1).mean() > 0.97, crop  # a grazing ray may flip at an edge
    assert sensors[0] is sensors[1]


@pytest.mark.slow  # ~16 s of Mitsuba compilation and rendering
def test_crop_of_an_orthographic_camera_uses_the_film_crop(cornell):
    camera = {"type": "orthographic", "near_clip": 0.01,
              "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 3], target=[0, 0, 0],
                                                         up=[0, 1, 0]),
              "film": {"type": "hdrfilm", "width": 16, "height": 16}}
    full = render_frame(cornell, spp=2, sensor=camera)
    crop = render_frame(cornell, spp=2, sensor=camera, crop=(4, 2, 6, 8))
    assert crop.depth.shape == (6, 8, 1)
    # Orthographic rays start on the near plane and run along -z: depth = 3 - 0.01 - z.
    np.testing.assert_allclose(crop.depth[..., 0], 2.99 - crop.position[..., 2], atol=1e-4)
    # The crop lands where the film crop says: its x, y positions match the full render's
    # window (orthographic: position x, y is the pixel's place on the film plane) better than
    # any window shifted by one pixel.
    def mismatch(dy, dx):
        window = full.position[4 + dy:10 + dy, 2 + dx:10 + dx, :2]
        return np.abs(crop.position[..., :2] - window).mean()

    errors = {(dy, dx): mismatch(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)}
    best = errors.pop((0, 0))
    assert best < 0.5 * min(errors.values())


@pytest.mark.slow  # ~16 s of Mitsuba compilation and rendering
def test_size_override_and_sensor_override(cornell):
    frame = render_frame(cornell, spp=2, seed=0, size=(20, 10))
    assert frame.color.shape == (10, 20, 3)
    camera = {
        "type": "perspective", "fov": 30.0,
        "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0.5, 2.0], target=[0, 0.5, -1.0],
                                                   up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 20, "height": 10, "rfilter": {"type": "gaussian"}},
        "sampler": {"type": "stratified", "sample_count": 4},
    }
    frame = render_frame(cornell, spp=2, seed=0, sensor=camera)
    assert frame.color.shape == (10, 20, 3)
    # The central rays travel straight to the back wall at z = -1: depth 3.
    np.testing.assert_allclose(frame.depth[4:6, 9:11], 3.0, rtol=5e-3)
    frame = render_frame(cornell, spp=2, seed=0, sensor=camera, size=(40, 20),
                         crop=(5, 10, 10, 20))
    assert frame.color.shape == (10, 20, 3)
    built = load.build_sensor(camera, (20, 10), None, "test")
    assert str(built.film().rfilter()).startswith("BoxFilter")
    assert str(built.sampler()).startswith("IndependentSampler")


def test_max_depth_one_sees_only_emitters(cornell):
    """max_depth=1 renders only directly visible emission: black walls, bright light."""
    frame = render_frame(cornell, spp=2, seed=0, max_depth=1)
    assert np.median(frame.color) == 0.0 and frame.color.max() > 10.0


def test_foreign_mitsuba_scene_is_checked():
    scene_dict = {"type": "scene",
                  "sensor": {"type": "perspective",
                             "film": {"type": "hdrfilm", "width": 8, "height": 8,
                                      "rfilter": {"type": "gaussian"}}},
                  "sphere": {"type": "sphere"}, "light": {"type": "constant"}}
    foreign = mi.load_dict(scene_dict)
    with pytest.raises(SceneError, match="box filter"):
        render_frame(foreign, spp=2)
    scene_dict["sensor"]["film"]["rfilter"] = {"type": "box"}
    ok = mi.load_dict(scene_dict)
    assert render_frame(ok, spp=2).color.shape == (8, 8, 3)  # no integrator: path is used
    with pytest.raises(SceneError, match="cannot be resized or cropped"):
        render_frame(ok, spp=2, crop=(0, 0, 2, 2))




def test_jaxden_holds_no_scene_it_loaded_and_still_resizes_it():
    """load_scene's memory keeps the sensor, not the scene: every live scene's BSDFs, shapes and
    emitters are traced into each render's kernels (a cold 8-scene sequence of renders took
    105 s with the scenes held, 27 s without), so a dropped scene must be freed at once. The
    memory must still resize and crop the scenes it knows, and must not mistake a new scene
    for an old one."""
    scene = load_scene("cornell-box", size=(16, 12))
    baseline = sys.getrefcount(scene)
    frame = render_frame(scene, spp=1, size=(8, 6), crop=(1, 2, 3, 4))
    assert frame.color.shape == (3, 4, 3)
    for seed in range(3):  # other scenes loaded since: this one is still known
        load_scene(f"procedural:{seed}", size=(8, 8))
    assert load.sensor_source(scene) is not None
    assert sys.getrefcount(scene) == baseline == 2  # the local name and getrefcount's argument
    foreign = mi.load_dict({"type": "scene", "sensor": {
        "type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4,
                                        "rfilter": {"type": "box"}}}})
    assert load.sensor_source(foreign) is None  # not loaded by jaxden: nothing borrowed
    # Only the last rendered spec's scene stays loaded by render_frame(spec).
    render_frame("procedural:1", spp=1, size=(8, 8))
    render_frame("cornell-box", spp=1, size=(8, 8))
    assert [key[1] for key in core._spec_scenes] == ["cornell-box"]
# ---------------------------------------------------------------------------- scene library
def test_list_scenes():
    listed = list_scenes()
    assert tuple(listed) == BUILTIN
    assert all(isinstance(d, str) and d and "\n" not in d for d in listed.values())


# One film size and spp for the scene-library tests (crops included): Dr.Jit compiles kernels
# per scene, film size and spp, so sharing them keeps the tests fast on a cold kernel cache.
LIBRARY_SIZE = (48, 24)
LIBRARY_SPP = 4


@pytest.fixture(scope="module")
def library():
    """name -> (scene, frame) at LIBRARY_SIZE and LIBRARY_SPP, rendered once per module."""
    cache = {}

    def get(name):
        if name not in cache:
            scene = load_scene(name, size=LIBRARY_SIZE)
            cache[name] = scene, render_frame(scene, spp=LIBRARY_SPP, seed=0)
        return cache[name]

    return get


@pytest.mark.parametrize("name", [  # cornell-box by default, the others with --runslow
    pytest.param(n, marks=pytest.mark.slow) if n != "cornell-box" else n
    for n in BUILTIN])
def test_builtin_scene_loads_and_renders(name, library):
    scene, frame = library(name)
    sensor = scene.sensors()[0]
    assert tuple(sensor.film().size()) == LIBRARY_SIZE
    assert str(sensor.film().rfilter()).startswith("BoxFilter")
    assert str(sensor.sampler()).startswith("IndependentSampler")
    frame.validated(name)  # finite everywhere, variance >= 0
    assert frame.color.mean() > 0.01


def test_env_sun_has_sky_on_misses(library):
    _, frame = library("env-sun")
    miss = frame.depth[..., 0] == 0
    assert miss.mean() > 0.15  # the sky fills the upper part of the view
    assert (frame.color[miss].mean(-1) > 0.05).all()  # lit: colour on every miss (ground 0.1)
    assert frame.color[:4].mean() > 0.5  # the upper rows are all bright sky


def test_texture_bump_has_fine_albedo_and_bumped_normals():
    """Floor crop: neighbouring pixels' albedo differs strongly (fine texture); back wall: flat
    geometry (normal +z) but varying shading normals (bump map)."""
    # Crops of the default 256 x 256 film, of LIBRARY_SIZE: they reuse the library kernels.
    floor = render_frame("texture-bump", spp=LIBRARY_SPP, seed=0, crop=(216, 100, 24, 48))
    assert (np.abs(floor.position[..., 1]) < 1e-3).all()  # all floor (y = 0)
    step = np.abs(np.diff(floor.albedo, axis=1)).mean()
    assert step > 0.05, f"mean neighbour albedo difference {step:.4f}"
    wall = render_frame("texture-bump", spp=LIBRARY_SPP, seed=0, crop=(40, 104, 24, 48))
    assert (np.abs(wall.position[..., 2] + 2.0) < 1e-3).all()  # all back wall (z = -2)
    assert np.abs(np.diff(wall.albedo, axis=1)).max() < 1e-6  # uniform albedo there
    tilt = np.linalg.norm(wall.normal[..., :2], axis=-1)  # 0 for the geometric normal
    assert tilt.mean() > 0.05 and tilt.std() > 0.02


def test_glossy_glass_has_glossy_and_dielectric_materials():
    scene = load_scene("glossy-glass", size=(8, 8))
    kinds = {str(shape.bsdf()).split("[")[0] for shape in scene.shapes()}
    assert {"RoughConductor", "RoughPlastic", "SmoothDielectric"} <= kinds, kinds


def test_small_lights_are_tiny_and_bright(library):
    scene, frame = library("small-lights")
    areas = [shape.surface_area() for shape in scene.shapes() if shape.emitter() is not None]
    assert len(areas) == 4 and max(np.array(a).ravel()[0] for a in areas) < 0.02
    assert len(scene.emitters()) == 4  # no environment: the bulbs are the only light
    bright = (frame.color.max(-1) > 20).sum()
    assert 1 <= bright <= 0.01 * frame.color[..., 0].size  # bulbs cover a few pixels


def test_procedural_scene_spec():
    frame = render_frame("procedural:3", spp=2, seed=0, size=(12, 10))
    assert frame.color.shape == (10, 12, 3)
    frame.validated("procedural:3")
    scene = prepare_scene("procedural:3", size=(12, 10))
    assert scene["sensor"]["film"]["rfilter"] == {"type": "box"}
    assert scene["sensor"]["sampler"]["type"] == "independent"


def test_prepare_scene_enforces_box_independent_and_size():
    original = {"type": "scene",
                "cam": {"type": "perspective",
                        "film": {"type": "hdrfilm", "width": 5, "height": 5,
                                 "rfilter": {"type": "tent"}, "crop_width": 2},
                        "sampler": {"type": "multijitter", "sample_count": 9}},
                "s": {"type": "sphere"}}
    patched = prepare_scene(original, size=(7, 3))
    film = patched["cam"]["film"]
    assert film["rfilter"] == {"type": "box"} and (film["width"], film["height"]) == (7, 3)
    assert "crop_width" not in film
    assert patched["cam"]["sampler"] == {"type": "independent", "sample_count": 9}
    assert original["cam"]["film"]["rfilter"] == {"type": "tent"}  # the input is not modified


# ---------------------------------------------------------------------------- XML scenes
XML_SCENE = """<scene version="3.0.0">
  <default name="resx" value="40"/>
  <default name="resy" value="30"/>
  <integrator type="path"><integer name="max_depth" value="4"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <sampler type="stratified"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="$resx"/><integer name="height" value="$resy"/>
      <rfilter type="gaussian"/>
    </film>
  </sensor>
  <default name="spp" value="4"/>
  <shape type="rectangle">
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
      <string name="filename" value="textures/stripes.exr"/>
      <string name="filter_type" value="nearest"/>
    </texture></bsdf>
  </shape>
  <emitter type="constant"/>
</scene>
"""


@pytest.fixture(scope="module")
def xml_path(tmp_path_factory):
    """An XML scene with a gaussian filter, a stratified sampler, $defaults and a texture
    referenced by a path relative to the XML file."""
    folder = tmp_path_factory.mktemp("xmlscene")
    (folder / "textures").mkdir()
    stripes = np.zeros((8, 8, 3), np.float32)
    stripes[:, ::2] = 0.9
    mi.Bitmap(stripes).write(str(folder / "textures" / "stripes.exr"))
    path = folder / "scene.xml"
    path.write_text(XML_SCENE)
    return path


@pytest.fixture(scope="module")
def xml_scene(xml_path):
    return load_scene(xml_path)


def test_xml_scene_enforces_box_independent_and_defaults(xml_path, xml_scene):
    resolver = mi.file_resolver()
    resolver_before = [str(resolver[i]) for i in range(len(resolver))]
    load_scene(xml_path)
    assert [str(resolver[i]) for i in range(len(resolver))] == resolver_before  # restored
    sensor = xml_scene.sensors()[0]
    assert tuple(sensor.film().size()) == (40, 30)  # from the <default> parameters
    assert str(sensor.film().rfilter()).startswith("BoxFilter")
    assert str(sensor.sampler()).startswith("IndependentSampler")
    frame = render_frame(xml_scene, spp=4, seed=0)
    assert frame.color.shape == (30, 40, 3)
    # The relative texture loaded: the rectangle's albedo alternates 0.9 / 0 stripes.
    hit = frame.depth[..., 0] > 0
    assert hit.sum() > 100 and frame.albedo[hit].max() > 0.8 and frame.albedo[hit].min() < 0.1


def test_xml_scene_size_override_and_crop(xml_path, xml_scene):
    scene = load_scene(str(xml_path), size=(20, 12))
    assert tuple(scene.sensors()[0].film().size()) == (20, 12)
    assert str(scene.sensors()[0].film().rfilter()).startswith("BoxFilter")
    # A crop and a resized render of one scene object with one film size share kernels.
    assert render_frame(xml_scene, spp=4, crop=(2, 3, 12, 20)).color.shape == (12, 20, 3)
    assert render_frame(xml_scene, spp=4, size=(20, 12)).color.shape == (12, 20, 3)


def test_render_frame_reuses_the_scene_of_a_spec(xml_path):
    core._spec_scenes.clear()
    for spec in ("cornell-box", xml_path):
        first = core._load_cached(spec, (8, 8))
        assert core._load_cached(spec, (8, 8)) is first
        assert core._load_cached(spec, (8, 6)) is not first
    os.utime(xml_path, ns=(0, 0))  # an edited file is loaded again
    assert core._load_cached(xml_path, (8, 8)) is not first


# ---------------------------------------------------------------------------- errors
def test_unknown_scene_lists_the_valid_ones():
    with pytest.raises(SceneError, match="unknown scene 'cornel-box'.*cornell-box.*env-sun"):
        load_scene("cornel-box")


def test_missing_xml_file(tmp_path):
    with pytest.raises(SceneError, match=r"nope\.xml does not exist"):
        load_scene(tmp_path / "nope.xml")


def test_malformed_xml_file(tmp_path):
    path = tmp_path / "broken.xml"
    path.write_text("<scene version='3.0.0'><sensor type='perspective'></scene>")
    with pytest.raises(SceneError, match=r"broken\.xml: invalid XML: mismatched tag"):
        load_scene(path)


def test_xml_mitsuba_rejects_is_one_line(tmp_path):
    path = tmp_path / "bad_plugin.xml"
    path.write_text('<scene version="3.0.0"><sensor type="perspective"/>'
                    '<shape type="blob"/></scene>')
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert "bad_plugin.xml: Mitsuba could not load the scene" in message and "blob" in message
    assert "\n" not in message


def test_xml_without_sensor(tmp_path):
    path = tmp_path / "nosensor.xml"
    path.write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.raises(SceneError, match=r"nosensor\.xml: the scene has no <sensor>"):
        load_scene(path)


def test_dict_without_sensor():
    with pytest.raises(SceneError, match="no sensor"):
        load_scene({"type": "scene", "s": {"type": "sphere"}})
    with pytest.raises(SceneError, match="type 'scene'"):
        load_scene({"type": "sphere"})


@pytest.mark.parametrize("spp", [0, -4, 2.5, True, "8"])
def test_bad_spp(cornell, spp):
    with pytest.raises(SceneError, match="spp"):
        render_frame(cornell, spp=spp)


@pytest.mark.parametrize("size", [(0, 16), (16, -1), (16,), (10**6, 10), (8.0, 8), "64x64"])
def test_bad_size(cornell, size):
    with pytest.raises(SceneError, match="size"):
        render_frame(cornell, spp=2, size=size)
    with pytest.raises(SceneError, match="size"):
        load_scene("cornell-box", size=size)


@pytest.mark.parametrize("crop", [(0, 0, 25, 4), (-1, 0, 4, 4), (0, 30, 4, 4), (0, 0, 0, 4),
                                  (0, 0, 4), (0, 0, 4.0, 4)])
def test_bad_crop(cornell, crop):
    with pytest.raises(SceneError, match="crop"):
        render_frame(cornell, spp=2, crop=crop)


def test_bad_seed_and_max_depth(cornell):
    with pytest.raises(SceneError, match="seed"):
        render_frame(cornell, spp=2, seed=-1)
    with pytest.raises(SceneError, match="max_depth"):
        render_frame(cornell, spp=2, max_depth=0)


@pytest.mark.parametrize("spec", ["procedural:", "procedural:abc", "procedural:-1",
                                  "procedural", "procedural:1.5"])
def test_malformed_procedural_spec(spec):
    with pytest.raises(SceneError, match="malformed.*procedural:SEED"):
        load_scene(spec)


def test_bad_sensor_type():
    with pytest.raises(SceneError, match="sensor type 'radiancemeter' is not supported"):
        load_scene({"type": "scene", "s": {"type": "sphere"},
                    "cam": {"type": "radiancemeter"}})


# ---------------------------------------------------------------------------- import, bench
def test_importing_jaxden_render_does_not_import_mitsuba():
    code = "import sys, jaxden.render; assert 'mitsuba' not in sys.modules"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]


def test_bench_registry_run_table_and_json(monkeypatch, capsys):
    from jaxden import bench

    assert "render" in bench.names()  # discovery imported jaxden.bench.render
    monkeypatch.setattr(bench, "_REGISTRY", dict(bench._REGISTRY))  # "dummy" goes after

    @bench.register("dummy")
    def dummy(quick: bool) -> dict:
        return {"ratio": 0.5 if quick else 2.0, "peer_s": 1.25}

    result = bench.run("dummy", as_json=True, quick=True)
    out, err = capsys.readouterr()
    assert result["ratio"] == 0.5
    assert json.loads(out) == {"bench": "dummy", "peer_s": 1.25, "ratio": 0.5}  # alone
    assert any("ratio" in line and "0.5" in line for line in err.splitlines())  # the table
    bench.run("dummy", as_json=False)
    assert not capsys.readouterr().out.strip().splitlines()[-1].startswith("{")
    with pytest.raises(JaxdenError, match="unknown benchmark 'nope'; valid: .*dummy.*render"):
        bench.run("nope")


def test_bench_frame_is_rendered_or_read_from_the_environment(tmp_path, monkeypatch):
    """bench_frame renders the Cornell box (4 spp, seed 1), or reads $JAXDEN_BENCH_FRAME on a
    machine without Mitsuba; a file of another size or without variance is refused."""
    from jaxden.bench import BENCH_FRAME_ENV, bench_frame
    from jaxden.io.exr import write_frame

    monkeypatch.delenv(BENCH_FRAME_ENV, raising=False)
    rendered = bench_frame((24, 16))
    assert rendered.color.shape == (16, 24, 3) and rendered.variance is not None
    path = tmp_path / "frame.exr"
    write_frame(path, rendered)
    monkeypatch.setenv(BENCH_FRAME_ENV, str(path))
    read = bench_frame((24, 16))
    np.testing.assert_array_equal(read.color, rendered.color)
    np.testing.assert_array_equal(read.variance, rendered.variance)
    with pytest.raises(JaxdenError, match=r"frame.exr: the frame is 24x16, the benchmark needs "
                                          r"1280x720"):
        bench_frame((1280, 720))
    write_frame(path, rendered.replace(variance=None, covariance=None))
    with pytest.raises(JaxdenError, match="variance"):
        bench_frame((24, 16))


@pytest.mark.slow
def test_render_bench_quick(capsys):
    from jaxden import bench

    result = bench.run("render", as_json=True, quick=True)
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # Structure only: speed is the benchmark's business, never a unit test's.
    assert last == json.loads(json.dumps(result))
    assert all(math.isfinite(result[k]) and result[k] > 0
               for k in ("ratio", "cpu_ratio", "ratio_legacy_features", "cpu_ratio_legacy_features"))
