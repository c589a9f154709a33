"""Temporal accumulation of noisy frames (the WSKP paper's preprocessing, Sec. 5.1).

For each pixel p of frame t, its surface point was at ``p + motion(p)`` in frame t-1 (jaxden's
motion convention: ``prev_xy = xy + motion``, pixel centres at integer + 0.5, x right, y down).
The accumulated history is sampled there with the four bilinear taps; a tap is rejected when
its world position or normal disagree with the current pixel's (disocclusion, or a different
surface), and the surviving taps are renormalised. The history is blended with the current
frame with weight ``alpha = max(1 / (n + 1), min_alpha)`` where n counts the frames already
accumulated at that pixel (an exponential moving average once n >= 1 / min_alpha - 1);
pixels without a valid tap restart with n = 0.

Everything is a pure function of arrays, jit-able and vmap-able over sequences.
Departure from the authors' code: the position test is relative to the pixel's depth
(``|x_t - x_{t-1}| <= position_tolerance * depth``) so one tolerance fits scenes of any scale.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxden.config import bounded
from jaxden.frame import Frame


@dataclasses.dataclass(frozen=True)
class TemporalConfig:
    position_tolerance: float = bounded(0.02, low=0, high=10)  # relative to depth
    normal_cosine: float = bounded(0.9, low=-1, high=1)  # minimum cosine between normals
    min_alpha: float = bounded(0.2, low=0, low_open=True, high=1)


class History(NamedTuple):
    """Accumulated state carried from frame to frame (all (H, W, C) arrays)."""

    color: jax.Array  # (H, W, 3) accumulated colour
    position: jax.Array  # (H, W, 3) world position of the pixel's surface in that frame
    normal: jax.Array  # (H, W, 3)
    count: jax.Array  # (H, W, 1) number of frames accumulated


def bilinear_taps(motion: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Integer tap coordinates and weights for sampling at ``xy + motion``.

    Returns ``rows (H, W, 4)``, ``cols (H, W, 4)`` (not clipped) and ``weights (H, W, 4)``.
    """
    height, width = motion.shape[-3], motion.shape[-2]
    ys, xs = jnp.meshgrid(jnp.arange(height), jnp.arange(width), indexing="ij")
    # Pixel i's centre is at i + 0.5 and moves to i + 0.5 + motion; bilinear interpolation
    # between centres works in index units, i.e. at i + motion.
    src_x = xs + motion[..., 0]
    src_y = ys + motion[..., 1]
    x0 = jnp.floor(src_x)
    y0 = jnp.floor(src_y)
    fx = src_x - x0
    fy = src_y - y0
    rows = jnp.stack([y0, y0, y0 + 1, y0 + 1], -1).astype(jnp.int32)
    cols = jnp.stack([x0, x0 + 1, x0, x0 + 1], -1).astype(jnp.int32)
    weights = jnp.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    return rows, cols, weights


def _gather(image: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
    """image (H, W, C), rows/cols (H, W, 4) clipped -> (H, W, 4, C)."""
    height, width = image.shape[0], image.shape[1]
    return image[jnp.clip(rows, 0, height - 1), jnp.clip(cols, 0, width - 1)]


def reproject(
    history: History, frame: Frame, config: TemporalConfig = TemporalConfig()
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Sample the history at this frame's reprojected positions with consistency tests.

    Returns ``(color (H, W, 3), count (H, W, 1), valid (H, W, 1))`` where ``valid`` says at
    least one tap survived.
    """
    frame.require("position", "normal", "depth", "motion", who="temporal reprojection")
    height, width = frame.color.shape[-3], frame.color.shape[-2]
    rows, cols, weights = bilinear_taps(frame.motion)
    inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
    prev_position = _gather(history.position, rows, cols)
    prev_normal = _gather(history.normal, rows, cols)
    distance = jnp.linalg.norm(prev_position - frame.position[..., None, :], axis=-1)
    position_ok = distance <= config.position_tolerance * jnp.maximum(frame.depth, 1e-6)
    cosine = jnp.sum(prev_normal * frame.normal[..., None, :], axis=-1)
    normal_ok = cosine >= config.normal_cosine
    hit = frame.depth[..., 0:1] > 0  # (H, W, 1): misses (background) never accumulate
    accepted = inside & position_ok & normal_ok & hit
    w = jnp.where(accepted, weights, 0.0)
    total = jnp.sum(w, axis=-1, keepdims=True)
    valid = total > 1e-4
    w = w / jnp.where(valid, total, 1.0)
    color = jnp.sum(w[..., None] * _gather(history.color, rows, cols), axis=-2)
    count = jnp.sum(w[..., None] * _gather(history.count, rows, cols), axis=-2)
    return color, jnp.where(valid, count, 0.0), valid


def start_history(frame: Frame) -> History:
    """History after the first frame: the frame itself, count 1."""
    frame.require("position", "normal", who="temporal accumulation")
    return History(
        color=jnp.asarray(frame.color),
        position=jnp.asarray(frame.position),
        normal=jnp.asarray(frame.normal),
        count=jnp.ones(frame.color.shape[:-1] + (1,), jnp.float32),
    )


def accumulate(
    history: History, frame: Frame, config: TemporalConfig = TemporalConfig()
) -> tuple[jax.Array, History]:
    """One step: blend the reprojected history with ``frame``; returns (colour, new history)."""
    previous, count, valid = reproject(history, frame, config)
    alpha = jnp.maximum(1.0 / (count + 1.0), config.min_alpha)
    alpha = jnp.where(valid, alpha, 1.0)
    color = alpha * frame.color + (1.0 - alpha) * previous
    new = History(
        color=color,
        position=jnp.asarray(frame.position),
        normal=jnp.asarray(frame.normal),
        count=jnp.where(valid, count + 1.0, 1.0),
    )
    return color, new


def accumulate_sequence(frames: Frame, config: TemporalConfig = TemporalConfig()) -> jax.Array:
    """Accumulate a stacked sequence (T, H, W, C fields) with ``lax.scan``: (T, H, W, 3)."""
    first = jax.tree_util.tree_map(lambda a: a[0], frames)
    rest = jax.tree_util.tree_map(lambda a: a[1:], frames)

    def step(history, frame):
        color, history = accumulate(history, frame, config)
        return history, color

    _, colors = jax.lax.scan(step, start_history(first), rest)
    return jnp.concatenate([jnp.asarray(first.color)[None], colors], axis=0)
