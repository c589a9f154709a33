"""Temporal accumulation: exact averages, exact reprojection, rejection of disocclusions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.errors import FrameError
from jaxden.frame import Frame, stack
from jaxden.denoise.temporal import TemporalConfig, accumulate, accumulate_sequence, start_history


def plane_frame(color, shift=(0, 0), motion=None):
    """A fronto-parallel textured plane at depth 5; pixel (y, x) sees world point x + shift."""
    h, w = color.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    position = np.stack([xs + shift[0], ys + shift[1], np.full_like(xs, 5.0)], -1) * 0.01
    normal = np.zeros((h, w, 3), np.float32)
    normal[..., 2] = 1
    if motion is None:
        motion = np.zeros((h, w, 2), np.float32)
    return Frame(color=color.astype(np.float32), position=position, normal=normal,
                 depth=np.full((h, w, 1), 5.0, np.float32), motion=motion.astype(np.float32),
                 spp=np.float32(1))


def test_static_sequence_is_the_running_mean_then_ema():
    rng = np.random.default_rng(0)
    colors = rng.normal(size=(8, 6, 7, 3)).astype(np.float32)
    frames = stack([plane_frame(c) for c in colors])
    out = np.asarray(jax.jit(accumulate_sequence)(frames))
    for t in range(5):  # alpha = 1 / (n + 1) >= 0.2: the exact running mean
        np.testing.assert_allclose(out[t], colors[: t + 1].mean(0), rtol=1e-5, atol=1e-6)
    for t in range(5, 8):  # then an exponential moving average with alpha = 0.2
        np.testing.assert_allclose(out[t], 0.2 * colors[t] + 0.8 * out[t - 1], rtol=1e-5, atol=1e-6)


def test_integer_motion_reprojects_exactly_and_disocclusions_restart():
    rng = np.random.default_rng(1)
    texture = rng.uniform(size=(10, 14, 3)).astype(np.float32)
    first = plane_frame(texture[:, :10])
    # Camera pans right by 2 pixels: pixel x now sees what pixel x + 2 saw before.
    motion = np.zeros((10, 10, 2), np.float32)
    motion[..., 0] = 2
    second_color = texture[:, 2:12] + 1.0
    second = plane_frame(second_color, shift=(2, 0), motion=motion)
    color, history = accumulate(start_history(first), second)
    color = np.asarray(color)
    # Columns 0..7 find their history (the same world point): mean of the two observations.
    np.testing.assert_allclose(color[:, :8], (texture[:, 2:10] + second_color[:, :8]) / 2, rtol=1e-6)
    # Columns 8, 9 reproject outside the previous image: they restart from the current frame.
    np.testing.assert_allclose(color[:, 8:], second_color[:, 8:], rtol=1e-6)
    assert np.all(np.asarray(history.count)[:, :8] == 2) and np.all(np.asarray(history.count)[:, 8:] == 1)


def test_position_and_normal_tests_reject_other_surfaces():
    rng = np.random.default_rng(2)
    first = plane_frame(rng.uniform(size=(6, 6, 3)))
    moved = plane_frame(rng.uniform(size=(6, 6, 3)))
    far = moved.position.copy()
    far[:3] += np.array([0, 0, 1.0], np.float32)  # top half is now a different surface
    flipped = moved.normal.copy()
    flipped[:, :2] = [1, 0, 0]  # left columns face another way
    second = moved.replace(position=far, normal=flipped)
    color, _ = accumulate(start_history(first), second, TemporalConfig())
    color = np.asarray(color)
    np.testing.assert_allclose(color[:3], second.color[:3], rtol=1e-6)
    np.testing.assert_allclose(color[3:, :2], second.color[3:, :2], rtol=1e-6)
    np.testing.assert_allclose(color[3:, 2:], (first.color[3:, 2:] + second.color[3:, 2:]) / 2, rtol=1e-6)


def test_fractional_motion_is_bilinear():
    rng = np.random.default_rng(3)
    first = plane_frame(rng.uniform(size=(5, 6, 3)))
    motion = np.zeros((5, 6, 2), np.float32)
    motion[..., 0] = 0.25
    # Same plane, tiny shift well inside the tolerance: all taps valid.
    second = plane_frame(np.zeros((5, 6, 3)), motion=motion)
    color, _ = accumulate(start_history(first), second)
    expected = 0.75 * first.color[:, :5] + 0.25 * first.color[:, 1:]
    np.testing.assert_allclose(np.asarray(color)[:, :5], expected / 2, rtol=1e-5, atol=1e-7)


def test_missing_features_are_named():
    frame = Frame(color=jnp.zeros((4, 4, 3)))
    with pytest.raises(FrameError, match="position, normal"):
        start_history(frame)


def test_accumulation_on_a_rendered_camera_path_approaches_the_reference():
    """A 1-spp sequence of the generator (camera orbiting the Cornell box by 0.5 degrees per
    frame): after 8 frames the accumulated image is much closer to the last frame's
    reference than the last 1-spp frame alone (relMSE over all pixels)."""
    from jaxden.metrics import relmse
    from jaxden.render.camera import from_scene, orbit_path
    from jaxden.render.load import load_scene
    from jaxden.render.sequence import render_sequence

    size = (48, 48)
    scene = load_scene("cornell-box", size)
    cameras = orbit_path(from_scene(scene), 8, 4.0)
    frames, references = render_sequence("cornell-box", cameras, spp=1, seed=3, size=size,
                                         reference_spp=256)
    accumulated = np.asarray(jax.jit(accumulate_sequence)(stack(frames)))
    reference = references[-1].color
    single = float(relmse(frames[-1].color, reference))
    temporal = float(relmse(accumulated[-1], reference))
    assert temporal < 0.5 * single, (temporal, single)
