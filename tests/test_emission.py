"""Emission: the renderer's emission channel, Frame.emission in files and datasets, and
denoisers that keep it out of the filter (``SPEC:emission=separate``).

References: Mitsuba's own ``path`` at ``max_depth=1`` (only directly visible emitters), the
moment integrator without the emission AOVs (the renderer before them), and direct
computations of ``D(colour - emission) + emission`` and of D's divergence by central
differences. Renders are tiny (a lamp facing the camera, 24 x 20 pixels).
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import run_cli

from jaxden.errors import ConfigError, DatasetError, FrameError
from jaxden.frame import CHANNELS, Frame

LAMP = np.float32([4.0, 2.0, 1.0])  # radiance of the lamp of lamp_scene()
SKY = np.float32([0.2, 0.3, 0.4])  # the constant environment


def lamp_scene() -> dict:
    """A square lamp facing the camera, a grey wall behind it, a constant sky around."""
    import mitsuba as mi

    from jaxden.render.variant import ensure_variant

    ensure_variant()
    transform = mi.ScalarTransform4f
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40.0,
                   "to_world": transform().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                   up=[0, 1, 0])},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": SKY.tolist()}},
        "lamp": {"type": "rectangle", "to_world": transform().scale([0.6, 0.6, 1.0]),
                 "emitter": {"type": "area",
                             "radiance": {"type": "rgb", "value": LAMP.tolist()}}},
        "wall": {"type": "rectangle",
                 "to_world": transform().translate([0.3, 0.0, -1.0]).scale([1.2, 1.2, 1.0]),
                 "bsdf": {"type": "diffuse"}},
    }


@pytest.fixture(scope="module")
def scene():
    from jaxden.render import load_scene

    return load_scene(lamp_scene(), size=(24, 20))


@pytest.fixture(scope="module")
def frame16(scene):
    from jaxden.render import render_frame

    return render_frame(scene, spp=16, seed=3, feature_spp=16)


# ---------------------------------------------------------------------------- renderer
def test_emission_is_the_lamps_radiance_where_it_covers_the_pixel_and_0_off_it(scene,
                                                                             frame16):
    from scipy.ndimage import binary_dilation, binary_erosion

    from jaxden.render import render_frame

    # Mitsuba's path at max_depth 1 sees only emitters (the lamp, and the sky on misses): the
    # lamp's coverage of each pixel, from 64 samples of another seed.
    only = render_frame(scene, spp=64, seed=99, max_depth=1, feature_spp=1).color
    full = binary_erosion(np.all(only == LAMP, -1), np.ones((3, 3)))
    # Without the lamp a pixel holds f SKY (f: its share of misses), same f in R and B.
    touched = np.abs(only[..., 0] / SKY[0] - only[..., 2] / SKY[2]) > 1e-4
    off = ~binary_dilation(touched, np.ones((3, 3)))
    emission = frame16.emission
    assert full.sum() >= 9 and off.sum() >= 100
    np.testing.assert_array_equal(emission[full], np.broadcast_to(LAMP, emission[full].shape))
    assert np.all(emission[off] == 0)
    assert np.any(frame16.color[off] == SKY) and np.any(frame16.color[off] > 0)  # sky, wall
    # Elsewhere k of the 16 samples hit the lamp: emission = (k / 16) LAMP.
    hits = emission[..., 0] / LAMP[0] * 16
    np.testing.assert_allclose(hits, np.round(hits), atol=1e-4)
    np.testing.assert_allclose(emission, np.round(hits)[..., None] / 16 * LAMP, rtol=1e-6)
    assert np.any((hits > 0.5) & (hits < 15.5))  # partly covered pixels exist


def test_emission_equals_the_colour_when_only_emitters_are_seen(scene):
    from jaxden.render import render_frame

    frame = render_frame(scene, spp=4, seed=8, max_depth=1, feature_spp=1)
    # The rest is the sky seen by k of the 4 samples (misses: the sky is not emission).
    share = (frame.color - frame.emission) / SKY
    np.testing.assert_allclose(share, np.round(share[..., :1] * 4) / 4 + 0 * share, atol=1e-6)
    no_sky = np.all(share == 0, -1)
    np.testing.assert_array_equal(frame.emission[no_sky], frame.color[no_sky])
    assert frame.emission.max() > 0 and np.any(share == 1)


def test_emission_is_between_0_and_the_colour_bit_for_bit(frame16):
    # Same samples, and float addition is monotone: the rest of the radiance is never negative.
    assert frame16.emission.dtype == np.float32
    assert np.all(frame16.emission >= 0)
    assert np.all(frame16.color - frame16.emission >= 0)
    lamp = frame16.emission.max(-1) > 0
    assert np.any(frame16.color[lamp] - frame16.emission[lamp] > 0)  # the lamp reflects the sky


@pytest.mark.parametrize("seed, spp", [(0, 1), (7, 8)])
def test_colour_variance_covariance_are_bit_identical_to_a_render_without_emission(
        scene, seed, spp):
    import mitsuba as mi

    from jaxden.render import core, integrators, render_frame

    inner, _ = core._integrators(scene, None)
    sensor = scene.sensors()[0]
    before = integrators.moment_integrator(inner, emission=False)  # the integrator before
    after = integrators.moment_integrator(inner)
    old = np.array(mi.render(scene, sensor=sensor, integrator=before, seed=seed, spp=spp))
    new = np.array(mi.render(scene, sensor=sensor, integrator=after, seed=seed, spp=spp))
    assert old.shape[-1] == 9 and new.shape[-1] == integrators.MOMENT_CHANNELS == 12
    np.testing.assert_array_equal(new[..., :9], old)
    # Through render_frame: its colour, variance and covariance are those of the 9 channels
    # of the old integrator at the same derived seed.
    frame = render_frame(scene, spp=spp, seed=seed, feature_spp=1)
    first = np.array(mi.render(scene, sensor=sensor, integrator=before,
                               seed=core.derive_seed(seed, "color", 0), spp=spp), np.float64)
    np.testing.assert_array_equal(frame.color, first[..., :3].astype(np.float32))
    if spp > 1:
        variance = integrators.variance_of_mean(first[..., :3], first[..., 3:6], spp)
        covariance = integrators.covariance_of_mean(first[..., :3], first[..., 6:9], variance,
                                                    spp)
        np.testing.assert_array_equal(frame.variance, variance.astype(np.float32))
        np.testing.assert_array_equal(frame.covariance, covariance.astype(np.float32))


def test_the_scalar_variant_gives_the_same_emission(tmp_path):
    """scalar_rgb calls the integrator per sample with Python bools (its own branch)."""
    import os
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent("""
        import numpy as np, mitsuba as mi
        from jaxden.render import render_frame
        frame = render_frame("cornell-box", spp=4, seed=1, size=(16, 12), max_depth=1,
                             feature_spp=1)
        assert mi.variant() == "scalar_rgb", mi.variant()
        assert frame.emission.max() > 1 and np.array_equal(frame.emission, frame.color)
        print("OK")
    """)
    env = dict(os.environ, JAXDEN_MITSUBA_VARIANT="scalar_rgb")
    result = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                            text=True, timeout=300, check=False)
    assert result.returncode == 0 and "OK" in result.stdout, result.stderr[-2000:]


def test_an_integrator_that_hides_emitters_gives_no_emission(scene):
    import mitsuba as mi

    from jaxden.render import integrators

    hidden = mi.load_dict({"type": "path", "max_depth": 8, "hide_emitters": True})
    image = np.array(mi.render(scene, sensor=scene.sensors()[0],
                               integrator=integrators.moment_integrator(hidden), seed=1, spp=2))
    assert np.all(image[..., 9:12] == 0)


def test_a_colour_frame_keeps_its_emission_or_its_lack(scene, frame16):
    from jaxden.render import render_frame

    again = render_frame(scene, spp=16, seed=3, colour=frame16, feature_spp=16)
    np.testing.assert_array_equal(again.emission, frame16.emission)
    older = render_frame(scene, spp=16, seed=3, colour=frame16.replace(emission=None),
                         feature_spp=16)
    assert older.emission is None


# ---------------------------------------------------------------------- frame and files
def small_frame(height=12, width=10, seed=0) -> Frame:
    rng = np.random.default_rng(seed)
    shape = (height, width)
    emission = np.zeros(shape + (3,), np.float32)
    emission[4:6, 3:5] = [30.0, 20.0, 10.0]  # a lamp
    emission[6, 3] = [15.0, 10.0, 5.0]  # half covered
    rest = rng.uniform(0.05, 0.6, shape + (3,)).astype(np.float32)
    normal = np.zeros(shape + (3,), np.float32)
    normal[..., 2] = 1
    return Frame(color=rest + emission,
                 variance=rng.uniform(1e-3, 2e-2, shape + (3,)).astype(np.float32),
                 albedo=rng.uniform(0.2, 0.9, shape + (3,)).astype(np.float32),
                 normal=normal, depth=rng.uniform(1, 2, shape + (1,)).astype(np.float32),
                 spp=np.float32(16), emission=emission)


def test_exr_round_trip_and_channel_names(tmp_path, frame16):
    from jaxden.io.exr import read_frame, read_header, write_frame

    write_frame(tmp_path / "f.exr", frame16)
    assert set(CHANNELS["emission"]) == {"emission.R", "emission.G", "emission.B"}
    assert set(CHANNELS["emission"]) <= set(read_header(tmp_path / "f.exr")["channels"])
    back = read_frame(tmp_path / "f.exr")
    np.testing.assert_array_equal(back.emission, frame16.emission)
    np.testing.assert_array_equal(back.color, frame16.color)


def test_a_cycles_emit_pass_maps_to_the_emission(tmp_path):
    from jaxden.io.exr import read_frame, write_channels

    frame = small_frame()
    channels = {f"ViewLayer.Combined.{c}": frame.color[..., i] for i, c in enumerate("RGB")}
    channels |= {f"ViewLayer.Emit.{c}": frame.emission[..., i] for i, c in enumerate("RGB")}
    write_channels(tmp_path / "cycles.exr", channels)
    back = read_frame(tmp_path / "cycles.exr", channel_map={
        "color": [f"ViewLayer.Combined.{c}" for c in "RGB"],
        "emission": [f"ViewLayer.Emit.{c}" for c in "RGB"]})
    np.testing.assert_array_equal(back.emission, frame.emission)


def test_validation_refuses_negative_emission_but_not_emission_above_the_colour():
    frame = small_frame()
    bad = frame.emission.copy()
    bad[0, 0, 1] = -0.5
    with pytest.raises(FrameError, match=r"emission .* must be >= 0 .* \(first at index "
                                         r"\(0, 0, 1\): -0.5\).*nonfinite='zero'"):
        frame.replace(emission=bad).validated()
    repaired = frame.replace(emission=bad).validated(nonfinite="zero")
    assert repaired.emission[0, 0, 1] == 0
    # Another renderer's combined pass may be clamped below its Emit pass: allowed.
    frame.replace(emission=frame.color + 1).validated()
    with pytest.raises(FrameError, match=r"'emission' must have shape \(\.\.\., H, W, 3\)"):
        frame.replace(emission=frame.emission[..., :2]).validated()


# ---------------------------------------------------------------------------- denoisers
def test_spec_options_parse_and_refuse_unknown_keys_and_values():
    from jaxden.denoise import emission_separated, load_denoiser, split_spec

    assert split_spec("wskp-6:emission=separate") == ("wskp-6", {"emission": "separate"})
    assert split_spec("wskp-6") == ("wskp-6", {})
    plain = load_denoiser("wskp-6:emission=filter")
    assert plain.name == "wskp"
    separated = load_denoiser("wskp-6:emission=separate")
    assert separated.name == "wskp+emission-separate"
    assert separated.definition is emission_separated(plain.definition)  # one object: caches
    assert "emission" in separated.definition.required(separated.config)
    with pytest.raises(ConfigError, match="expected options KEY=VALUE after the last ':' with "
                                          "KEY one of emission, got 'emision=separate'"):
        load_denoiser("wskp-6:emision=separate")
    with pytest.raises(ConfigError, match="emission must be one of filter, separate, got 'x'"):
        load_denoiser("oidn:emission=x")


@pytest.fixture(scope="module")
def tiny_wskp():
    """A 1-layer WSKP with random weights (no activation: smooth in the colour), the JAX
    denoiser D of these tests; parameters drawn in NumPy (no init to compile), one object for
    the module so its jitted forms compile once."""
    import jax

    from jaxden.denoise import get_definition, make_denoiser
    from jaxden.denoise.nn.wskp import WSKPConfig

    config = WSKPConfig(num_layers=1, width=4, kernel_sizes=(3, 5))
    shapes = jax.eval_shape(lambda: get_definition("wskp").init(jax.random.PRNGKey(0), config))
    rng = np.random.default_rng(1)
    params = jax.tree_util.tree_map(
        lambda leaf: (0.3 * rng.standard_normal(leaf.shape)).astype(np.float32), shapes)
    return make_denoiser("wskp", config, params)


@pytest.fixture(scope="module")
def tiny_wskp_separated(tiny_wskp):
    from jaxden.denoise import with_options

    return with_options(tiny_wskp, emission="separate")


@pytest.mark.parametrize("kind", ["jax", "oidn"])
def test_separated_denoiser_is_D_of_the_rest_plus_the_emission(kind, request):
    from jaxden.denoise import load_denoiser, with_options

    frame = small_frame()
    if kind == "jax":
        base, separated = (request.getfixturevalue(name)
                           for name in ("tiny_wskp", "tiny_wskp_separated"))
    else:
        base = load_denoiser("oidn")
        separated = with_options(base, emission="separate")
    assert separated.name == f"{base.name}+emission-separate"
    direct = np.asarray(base(frame.replace(color=frame.color - frame.emission))) + frame.emission
    np.testing.assert_allclose(np.asarray(separated(frame)), direct, rtol=1e-6, atol=1e-6)
    # The lamp comes back exactly: D's output plus its own emission, no bleed beyond it.
    plain = np.asarray(base(frame))
    beside = np.zeros(frame.shape, bool)
    beside[2:9, 1:7] = True
    beside[frame.emission.max(-1) > 0] = False
    rest = frame.color - frame.emission
    assert (np.abs(np.asarray(separated(frame)) - rest)[beside].mean()
            < np.abs(plain - rest)[beside].mean())


def test_the_separated_wskp6_keeps_a_cycles_lamp_at_its_value():
    """Blender's Denoising Albedo holds the lamps' emission (up to 200 on the lamp pixels of
    tests/data/cycles/passes-seed1.exr, 4 spp, a lamp of strength 400). Read by `--from
    cycles` it is clipped to [0, 1], and WSKP-6:emission=separate gives the lamp pixels their
    colour back within 2 %; fed the raw albedo, the separated filter's rest is multiplied by
    the emission on remodulation and the lamp comes out 30 % too bright (jaxden issue 48)."""
    from pathlib import Path

    from jaxden.denoise import load_denoiser
    from jaxden.io.exr import read_channels, read_frame

    path = Path(__file__).parent / "data" / "cycles" / "passes-seed1.exr"
    frame = read_frame(path, convention="cycles")
    stored, _ = read_channels(path)
    raw = np.stack([stored[f"ViewLayer.Denoising Albedo.{c}"] for c in "RGB"], axis=-1)
    lamp = frame.emission.max(axis=-1) > 0
    assert lamp.sum() == 2 and raw[lamp].max() > 100 and frame.albedo.max() <= 1
    separated = load_denoiser("wskp-6:emission=separate")
    colour = frame.color[lamp].mean()
    read = float(np.asarray(separated(frame))[lamp].mean())
    raw_out = float(np.asarray(separated(frame.replace(albedo=raw)))[lamp].mean())
    assert abs(read / colour - 1) < 0.02
    assert raw_out / colour > 1.25


def test_the_rest_is_clamped_at_0_with_derivative_1_where_it_is_not():
    import jax
    import jax.numpy as jnp

    from jaxden.denoise.emission import rest_of_radiance

    color = jnp.float32([1.0, 2.0, 3.0])
    emission = jnp.float32([0.5, 2.0, 4.0])
    np.testing.assert_array_equal(rest_of_radiance(color, emission), [0.5, 0.0, 0.0])
    _, tangent = jax.jvp(lambda c: rest_of_radiance(c, emission), (color,), (jnp.ones(3),))
    np.testing.assert_array_equal(tangent, [1.0, 1.0, 0.0])


def test_a_frame_without_emission_is_a_clear_error(tmp_path, capsys):
    import jax

    from jaxden.denoise import load_denoiser
    from jaxden.io.exr import write_frame
    from jaxden.sure import denoise_with_sure

    frame = small_frame().replace(emission=None)
    for spec in ("wskp-6:emission=separate", "oidn:emission=separate"):
        denoiser = load_denoiser(spec)
        with pytest.raises(FrameError, match=r"needs the frame feature\(s\) emission \(EXR "
                                             r"channels emission: emission.R/emission.G/"
                                             r"emission.B\)"):
            denoiser(frame)
        with pytest.raises(FrameError, match="emission"):
            denoise_with_sure(denoiser, frame, jax.random.PRNGKey(0))
    # Past the registry's check too (a caller of the bare function): the apply refuses it.
    with pytest.raises(FrameError, match="keeps the emission out of the filter and needs the "
                                         "frame feature emission .EXR channels "
                                         "emission.R/emission.G/emission.B"):
        denoiser.function()(frame)
    write_frame(tmp_path / "old.exr", frame)
    code, lines, _ = run_cli(["denoise", tmp_path / "old.exr", "--model",
                              "wskp-6:emission=separate", "--out", tmp_path / "o.exr"], capsys)
    assert code == 2 and len(lines) == 1
    assert "missing feature(s) emission (emission needs emission.R, emission.G, emission.B)" \
        in lines[0]
    assert not (tmp_path / "o.exr").exists()


def test_sure_of_the_separated_denoiser_is_D_alone_at_the_rest_and_matches_differences(
        tiny_wskp, tiny_wskp_separated):
    import jax
    import jax.numpy as jnp

    from jaxden.sure import draw_probes, sure
    from jaxden.sure.denoiser import denoise_with_sure

    frame = small_frame(seed=1)
    key = jax.random.PRNGKey(3)
    base, separated = tiny_wskp, tiny_wskp_separated
    result, _ = denoise_with_sure(separated, frame, key, num_probes=2, method="jvp")
    rest = frame.replace(color=frame.color - frame.emission)  # D ignores the emission
    of_d = sure(base.function(), rest, key, 2, "jvp")
    # Same probes (colour only: the emission is a fixed feature), so D's divergence term.
    np.testing.assert_allclose(result.divergence_term, of_d.divergence_term, rtol=1e-5,
                               atol=1e-9)
    np.testing.assert_allclose(result.denoised, np.asarray(of_d.denoised) + frame.emission,
                               rtol=1e-6, atol=1e-6)
    # Central differences of D alone along the same probes.
    probes = draw_probes(key, jnp.asarray(frame.variance), 2)
    d = base.function()
    eps = 3e-2
    differences = [b * (np.asarray(d(rest.replace(color=rest.color + eps * b)))
                        - np.asarray(d(rest.replace(color=rest.color - eps * b)))) / (2 * eps)
                   for b in np.asarray(probes, np.float32)]
    expected = np.mean(differences, axis=0)
    scale = np.abs(expected).mean()
    assert np.abs(np.asarray(result.divergence_term) - expected).mean() < 0.02 * scale


def test_every_command_takes_the_option(tmp_path, capsys):
    from jaxden.io.exr import read_image, write_frame

    frame = small_frame()
    write_frame(tmp_path / "in.exr", frame)
    for argv in (["denoise", tmp_path / "in.exr", "--model", "wskp-6:emission=separate",
                  "--out", tmp_path / "d.exr"],
                 ["sure", tmp_path / "in.exr", "--denoiser", "oidn:emission=separate",
                  "--probes", 1, "--out", tmp_path / "s.exr"],
                 ["progressive", tmp_path / "in.exr", "--denoiser", "oidn:emission=separate",
                  "--mixer", "closed-form", "--probes", 1, "--out", tmp_path / "p.exr"]):
        code, lines, out = run_cli(argv, capsys)
        assert code == 0, lines
        assert "+emission-separate" in out
    lamp = frame.emission.max(-1) > 0
    denoised = read_image(tmp_path / "d.exr")
    assert np.all(denoised[lamp] >= frame.emission[lamp])


def test_cycles_channels_on_the_command_line(tmp_path, capsys):
    from jaxden.io.exr import read_image, write_channels

    frame = small_frame()
    channels = {c: frame.color[..., i] for i, c in enumerate("RGB")}
    channels |= {f"ViewLayer.Emit.{c}": frame.emission[..., i] for i, c in enumerate("RGB")}
    write_channels(tmp_path / "cycles.exr", channels)
    code, lines, _ = run_cli(["denoise", tmp_path / "cycles.exr", "--model",
                              "oidn:emission=separate", "--channels",
                              "emission=ViewLayer.Emit.R,ViewLayer.Emit.G,ViewLayer.Emit.B",
                              "--out", tmp_path / "d.exr"], capsys)
    assert code == 0, lines
    lamp = frame.emission.max(-1) > 0
    assert np.all(read_image(tmp_path / "d.exr")[lamp] >= frame.emission[lamp])


# ------------------------------------------------------------------------------ datasets
def with_emission(scene, spp, seed=0, size=None, *, crop=None):
    """The synthetic renderer with an emission channel (a lamp in each crop's corner)."""
    from jaxden.render.synthetic import synthetic_render

    frame = synthetic_render(scene, spp, seed, size, crop=crop)
    emission = np.zeros_like(frame.color)
    emission[:2, :2] = 5.0
    return frame.replace(color=frame.color + emission, emission=emission,
                         covariance=None if frame.variance is None
                         else np.zeros_like(frame.variance))


def test_datasets_record_the_emission_and_older_ones_still_load(tmp_path):
    import dataclasses

    from jaxden.data import DatasetLoader, build_dataset
    from jaxden.data.config import DatasetConfig
    from jaxden.data.verify import (
        check_emission_recorded,
        check_renderer_fields_recorded,
        verify_dataset,
    )
    from jaxden.io.exr import read_frame, read_header
    from jaxden.render.synthetic import synthetic_render

    config = DatasetConfig(name="e", scenes=("s",), size=(16, 16), crop_size=8,
                           crops_per_scene=1, spp=(2, 4), reference_spp=8, seed=1)
    new = build_dataset(config, tmp_path / "new", executor="serial", render_fn=with_emission,
                        progress=False)
    for item in new.items:
        assert set(CHANNELS["emission"]) <= set(read_header(tmp_path / "new" /
                                                            item.path)["channels"])
    check_renderer_fields_recorded(tmp_path / "new", new.items)
    assert verify_dataset(tmp_path / "new").ok
    loader = DatasetLoader(tmp_path / "new", "all", batch_size=1,
                           features=("color", "emission"))
    batch = next(iter(loader))
    assert batch.input.emission.shape[-1] == 3 and np.any(batch.input.emission > 0)

    old = build_dataset(dataclasses.replace(config, name="o"), tmp_path / "old",
                        executor="serial", render_fn=synthetic_render, progress=False)
    assert verify_dataset(tmp_path / "old").ok  # no emission anywhere: fine
    batch = next(iter(DatasetLoader(tmp_path / "old", "all", batch_size=1)))
    assert batch.input.emission is None and batch.input.albedo is not None
    with pytest.raises(DatasetError, match=r"old: 3 of its 3 finished files \(.*\.exr, "
                                           r"\.\.\.\) have no emission \(channels "
                                           r"emission.R/emission.G/emission.B\)"):
        check_emission_recorded(tmp_path / "old", old.items)
    # A mixed dataset (one file of an older jaxden) fails verification on that file.
    item = new.items[0]
    older = read_frame(tmp_path / "new" / item.path).replace(emission=None)
    from jaxden.io.exr import write_frame

    header = read_header(tmp_path / "new" / item.path)
    write_frame(tmp_path / "new" / item.path, older, attributes={
        k: header[k] for k in ("seed", "scene", "item", "crop", "dataset")})
    report = verify_dataset(tmp_path / "new", checksums=False)
    assert [p.item for p in report.problems] == [item.id]
    assert "no emission (emission.R/emission.G/emission.B) while" in report.problems[0].message
