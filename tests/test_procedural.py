"""Tests of the procedural textures and the seeded random scene generator."""

from __future__ import annotations

import numpy as np
import pytest

from jaxden.errors import SceneError
from jaxden.render import textures
from jaxden.render.procedural import (
    LIGHT_KINDS,
    MATERIAL_KINDS,
    SHAPE_KINDS,
    generate_scene,
    scene_summary,
)

TEXTURE_SHAPE = (64, 64)


def _ensure_variant():
    from jaxden.render.variant import ensure_variant

    ensure_variant()


def canonical(value):
    """Mitsuba objects -> NumPy arrays, recursively, so dicts compare by content."""
    import mitsuba as mi

    if isinstance(value, dict):
        return {key: canonical(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(item) for item in value]
    if isinstance(value, mi.Bitmap):
        return ("bitmap", str(value.pixel_format()), np.array(value))
    if isinstance(value, mi.ScalarTransform4f):
        return ("transform", np.array(value.matrix))
    assert isinstance(value, (str, int, float, bool, np.floating, np.integer)), type(value)
    return value


def assert_same(a, b, path="scene"):
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if isinstance(a, dict):
        assert a.keys() == b.keys(), f"{path}: keys differ"
        for key in a:
            assert_same(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for index, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{index}]")
    elif isinstance(a, np.ndarray):
        assert a.shape == b.shape and a.dtype == b.dtype, path
        assert np.array_equal(a, b), f"{path}: arrays differ"
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def mean_abs_laplacian(image: np.ndarray) -> float:
    """Mean |5-point Laplacian| with periodic borders, per texel (a high-frequency measure)."""
    lap = (np.roll(image, 1, 0) + np.roll(image, -1, 0) + np.roll(image, 1, 1)
           + np.roll(image, -1, 1) - 4 * image)
    return float(np.mean(np.abs(lap)))


# ---------------------------------------------------------------------------- textures
def seam_ratio(image: np.ndarray) -> float:
    """Mean |Laplacian| (periodic borders) on the wrap-around seam rows/columns divided by the
    largest such mean on any interior row/column. A periodic image has no special seam (ratio
    <= ~1); a non-periodic one has a jump there (ratio >> 1 when the image is smooth)."""
    lap = np.abs(np.roll(image, 1, 0) + np.roll(image, -1, 0) + np.roll(image, 1, 1)
                 + np.roll(image, -1, 1) - 4 * image)
    columns, rows = lap.mean(axis=0), lap.mean(axis=1)
    seam = max(columns[0], columns[-1], rows[0], rows[-1])
    interior = max(columns[1:-1].max(), rows[1:-1].max())
    return float(seam / interior)


@pytest.mark.parametrize("kind", textures.PATTERN_KINDS)
def test_patterns_are_seeded_bounded_and_periodic(kind):
    shape = (256, 256)  # >= 8 texels per lattice cell: smooth inside, so a seam would show
    a = textures.pattern(kind, shape, np.random.default_rng(5))
    b = textures.pattern(kind, shape, np.random.default_rng(5))
    c = textures.pattern(kind, shape, np.random.default_rng(6))
    assert a.shape == shape and a.dtype == np.float32
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.min() >= 0.0 and a.max() <= 1.0 and a.std() > 0.05
    assert seam_ratio(a) < 1.5, seam_ratio(a)


def test_seam_ratio_detects_a_non_periodic_pattern():
    # Control for the periodicity check above: the same noise cut off at 3/4 of its period.
    full = textures.fbm((256, 256), np.random.default_rng(5), base_frequency=4)
    assert seam_ratio(full) < 1.5
    assert seam_ratio(full[:192, :192]) > 3.0


def test_constant_noise_at_frequency_one():
    # One lattice cell wraps onto itself: all four corners are the same value.
    flat = textures.value_noise((8, 8), 1, np.random.default_rng(0))
    assert np.allclose(flat, flat[0, 0])


def test_checker_and_stripes_against_direct_formulas():
    board = textures.checker((8, 8), 4)  # 2x2-texel squares
    rows, cols = np.indices((8, 8))
    assert np.array_equal(board, ((rows // 2 + cols // 2) % 2).astype(np.float32))
    band = textures.stripes((4, 8), (0, 2), duty=0.5)  # vertical stripes, period 4 texels
    assert np.array_equal(band[0], np.array([1, 1, 0, 0, 1, 1, 0, 0], np.float32))
    assert np.array_equal(band, np.repeat(band[:1], 4, axis=0))


def test_cellular_is_distance_to_nearest_point():
    rng = np.random.default_rng(3)
    values = textures.cellular((16, 16), 1, np.random.default_rng(3))
    point = rng.random((1, 2))[0]
    y, x = np.meshgrid((np.arange(16) + 0.5) / 16, (np.arange(16) + 0.5) / 16, indexing="ij")
    dy, dx = np.abs(y - point[0]), np.abs(x - point[1])
    distance = np.hypot(np.minimum(dy, 1 - dy), np.minimum(dx, 1 - dx))
    expected = (distance - distance.min()) / (distance.max() - distance.min())
    np.testing.assert_allclose(values, expected, atol=1e-6)


def test_textures_have_high_frequency_content():
    """Generated colour textures and height maps are far busier than a smooth texture.

    Reference: a smooth periodic texture (one cosine period across the image), whose mean
    |Laplacian| is (2 pi / 64)^2 * 2/pi ~ 0.006 per unit amplitude. Every generated texture
    must exceed 3x that, and the median 10x (measured: median ~20x).
    """
    y, x = np.indices(TEXTURE_SHAPE) / TEXTURE_SHAPE[0]
    smooth = 0.5 + 0.5 * np.cos(2 * np.pi * x)
    reference = mean_abs_laplacian(smooth)
    ratios = []
    for seed in range(24):
        rng = np.random.default_rng(seed)
        colour, _ = textures.color_texture(TEXTURE_SHAPE, rng)
        height, _ = textures.height_map(TEXTURE_SHAPE, rng)
        luminance = colour.mean(axis=-1)
        # Normalise by the texture's range so contrast alone cannot pass the test.
        for image in (luminance, height):
            span = float(image.max() - image.min())
            assert span > 0.05
            ratios.append(mean_abs_laplacian(image / span) / reference)
    ratios = np.array(ratios)
    assert ratios.min() > 3.0, ratios.min()
    assert np.median(ratios) > 10.0, np.median(ratios)


def test_environment_map_is_hdr_and_positive():
    image = textures.environment_map((32, 64), np.random.default_rng(1))
    assert image.shape == (32, 64, 3) and image.dtype == np.float32
    assert np.isfinite(image).all() and image.min() > 0
    assert abs(image.mean() - 1.0) < 1e-3
    assert image.max() > 10 * np.median(image)  # a sun: high dynamic range


def test_texture_bad_inputs():
    rng = np.random.default_rng(0)
    with pytest.raises(SceneError, match="frequency"):
        textures.value_noise((8, 8), 0, rng)
    with pytest.raises(SceneError, match="shape"):
        textures.fbm((8,), rng)
    with pytest.raises(SceneError, match="unknown texture pattern"):
        textures.pattern("plaid", (8, 8), rng)
    with pytest.raises(SceneError, match="wave vector"):
        textures.stripes((8, 8), (0, 0))


# ---------------------------------------------------------------------------- the generator
def test_same_seed_same_dict_and_different_seeds_differ():
    a = canonical(generate_scene(11, size=(32, 24)))
    b = canonical(generate_scene(11, size=(32, 24)))
    assert_same(a, b)
    c = canonical(generate_scene(12, size=(32, 24)))
    with pytest.raises(AssertionError):
        assert_same(a, c)
    film = a["sensor"]["film"]
    assert (film["width"], film["height"]) == (32, 24)
    assert film["rfilter"] == {"type": "box"} and a["sensor"]["sampler"]["type"] == "independent"
    assert "integrator" not in a


def test_generator_covers_its_claims():
    """Over 40 seeds every shape, material and light kind appears, with textures and bumps."""
    shapes, materials, lights = set(), set(), set()
    textured = bumped = walls = 0
    for seed in range(40):
        summary = scene_summary(generate_scene(seed, size=(8, 8)))
        assert 3 <= sum(summary["shapes"].values()) <= 10
        assert sum(summary["lights"].values()) >= 1  # never a black scene
        shapes |= set(summary["shapes"])
        materials |= set(summary["materials"])
        lights |= set(summary["lights"])
        textured += summary["textures"] > 0
        bumped += summary["bump_maps"] > 0
        walls += summary["walls"] > 0
    assert shapes == set(SHAPE_KINDS)
    assert materials == set(MATERIAL_KINDS)
    assert lights == set(LIGHT_KINDS)
    assert textured >= 35 and bumped >= 20 and 5 <= walls <= 35, (textured, bumped, walls)


def test_textures_are_bitmaps_in_the_dict():
    import mitsuba as mi

    found = []

    def walk(node):
        if isinstance(node, dict):
            if node.get("type") in ("bitmap", "envmap"):
                found.append(node["bitmap"])
            for value in node.values():
                walk(value)

    for seed in range(6):
        walk(generate_scene(seed, size=(8, 8)))
    assert found and all(isinstance(b, mi.Bitmap) for b in found)
    assert all(np.isfinite(np.array(b)).all() for b in found)


@pytest.mark.parametrize("seed", [-1, 1.5, "3", True, None])
def test_bad_seed_is_a_scene_error(seed):
    with pytest.raises(SceneError, match="seed"):
        generate_scene(seed)


def test_bad_size_is_a_scene_error():
    with pytest.raises(SceneError, match="size"):
        generate_scene(0, size=(0, 32))
    with pytest.raises(SceneError, match="size"):
        generate_scene(0, size=32)


# ---------------------------------------------------------------------------- renders
@pytest.fixture(scope="module")
def renders():
    """render_frame of procedural scenes at 24 x 24, 4 spp: seed -> Frame."""
    _ensure_variant()
    from jaxden.render.core import render_frame

    return {seed: render_frame(f"procedural:{seed}", 4, seed=0, size=(24, 24))
            for seed in (0, 1, 2)}


def test_renders_are_finite_and_sanely_exposed(renders):
    """Mean radiance in [0.02, 5] (measured over seeds 0-19 at 48 x 48, 16 spp: 0.09-3.9)."""
    for seed, frame in renders.items():
        frame.validated(f"procedural:{seed}")  # raises on NaN/inf, bad shapes
        mean = float(np.mean(frame.color))
        assert 0.02 <= mean <= 5.0, (seed, mean)
        assert (frame.depth > 0).mean() > 0.5, seed  # the camera sees content, not just sky
    means = [float(np.mean(f.color)) for f in renders.values()]
    assert len(set(means)) == len(means)  # different seeds, different images


def test_same_seed_renders_identically(renders):
    from jaxden.render.core import render_frame

    again = render_frame("procedural:2", 4, seed=0, size=(24, 24))
    np.testing.assert_array_equal(again.color, renders[2].color)
    np.testing.assert_array_equal(again.position, renders[2].position)
