"""K independent renders of one image, merged into one frame with the variance of its mean.

Most renderers (Cycles among them) write no variance. Rendering the same frame K times with
different seeds gives it: the K buffer means are independent estimates of the pixel, so their
spread estimates the variance of one buffer's mean, and that over K the variance of the merged
mean (K - 1 degrees of freedom: noisy for small K, unbiased for any K >= 2). Buffers that carry
a variance of their own (jaxden's) are pooled exactly instead, as one render of all K m samples
(:func:`combine_buffers`).

    merged = merge_renders([read_frame(p, convention="cycles") for p in paths])
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxden.errors import FrameError
from jaxden.frame import Frame


def _check_buffers(frames: Sequence[Frame], names: Sequence[str]) -> None:
    if len(frames) < 2:
        raise FrameError(f"merge: need at least 2 independent renders of the frame for a "
                         f"variance, got {len(frames)}")
    first = frames[0]
    estimates = {"variance", "covariance"}  # checked apart, with their own message
    fields = set(first.features()) - estimates
    for name, frame in zip(names[1:], frames[1:], strict=True):
        if np.shape(frame.color) != np.shape(first.color):
            raise FrameError(f"merge: {name} is {np.shape(frame.color)[:2]} pixels, {names[0]} "
                             f"{np.shape(first.color)[:2]}")
        if set(frame.features()) - estimates != fields:
            raise FrameError(f"merge: {name} has the fields "
                             f"{sorted(set(frame.features()) - estimates)}, "
                             f"{names[0]} {sorted(fields)}: renders of one setup have the same")
        spp, first_spp = (None if f.spp is None else float(np.asarray(f.spp))
                          for f in (frame, first))
        if spp != first_spp:
            raise FrameError(f"merge: {name} has {spp} spp, {names[0]} {first_spp}: merge "
                             f"renders of equal sample counts")
    colours = [np.asarray(f.color) for f in frames]
    for i in range(len(frames)):
        for j in range(i):
            if np.array_equal(colours[i], colours[j]):
                raise FrameError(f"merge: {names[j]} and {names[i]} are the same image (rendered "
                                 f"with the same seed?): their spread would say the variance "
                                 f"is 0")


def combine_buffers(buffers) -> Frame:
    """One frame from K equal-spp sub-buffer frames of the same image (independent samples).

    Colour: the mean of the buffers' colours. Variance of the mean: the pooled sample variance
    of all K * m samples over K * m, from each buffer's variance of its mean (m samples each;
    the frames must have ``spp``) and the spread of the buffer means, exactly as if one
    render had taken all the samples; the covariance between channels likewise when every
    buffer has one (else none). Features (albedo, normal, ...): the mean over the
    buffers (per-sample averages, as one render of all samples gives them; a present feature
    must be present in every buffer). Returns float64 NumPy arrays.
    """
    frames = [b.numpy() if isinstance(b, Frame) else b for b in buffers]
    if len(frames) < 2 or not all(isinstance(f, Frame) for f in frames):
        raise FrameError(f"combine_buffers: need at least 2 Frames, got {len(frames)}")
    spps = [None if f.spp is None else np.unique(np.asarray(f.spp)) for f in frames]
    if any(s is None or s.size != 1 for s in spps) or len({float(s[0]) for s in spps}) != 1:
        raise FrameError(f"combine_buffers: buffers need one common spp, got "
                         f"{[None if s is None else s.tolist() for s in spps]}")
    m = int(spps[0][0])
    if m < 2:
        raise FrameError(f"combine_buffers: each buffer needs >= 2 spp for a variance, got {m}")
    for i, f in enumerate(frames):
        if f.variance is None:
            raise FrameError(f"combine_buffers: buffer {i} has no variance")
        if np.shape(f.color) != np.shape(frames[0].color):
            raise FrameError(f"combine_buffers: buffer {i} has shape {np.shape(f.color)}, "
                             f"buffer 0 {np.shape(frames[0].color)}")
    k = len(frames)
    means = np.stack([np.asarray(f.color, np.float64) for f in frames])
    var_means = np.stack([np.asarray(f.variance, np.float64) for f in frames])
    mean = means.mean(axis=0)
    squares = (var_means * m * (m - 1)).sum(axis=0) + m * np.square(means - mean).sum(axis=0)
    n = k * m
    features = {}
    if all(f.covariance is not None for f in frames):  # the same pooling, per channel pair
        means_next = np.roll(means, -1, axis=-1)
        cross = (np.stack([np.asarray(f.covariance, np.float64) for f in frames]).sum(axis=0)
                 * m * (m - 1)
                 + m * ((means - mean) * (means_next - np.roll(mean, -1, axis=-1))).sum(axis=0))
        features["covariance"] = cross / (k * m - 1) / (k * m)
    for name in frames[0].features():
        if name in ("color", "variance", "covariance"):
            continue
        if any(getattr(f, name) is None for f in frames):
            raise FrameError(f"combine_buffers: {name} is in buffer 0 but not in every buffer")
        features[name] = np.mean([np.asarray(getattr(f, name), np.float64) for f in frames],
                                 axis=0)
    return frames[0].replace(color=mean, variance=squares / (n - 1) / n, **features,
                             spp=np.full(np.shape(frames[0].spp), n, np.float32))


def merge_renders(frames: Sequence[Frame], names: Sequence[str] | None = None) -> Frame:
    """One frame from K >= 2 independent renders (different seeds) of the same frame.

    Colour and features: the mean over the renders. Variance of the mean: pooled exactly when
    every render carries its variance and spp (:func:`combine_buffers`),
    else from the spread of the K colours, sum_k (c_k - mean)^2 / ((K - 1) K), and the covariance
    between channels likewise. ``spp``: the renders' sum when they record one, else None.
    ``names`` (e.g. the file paths) label the messages. Raises FrameError for fewer than 2
    renders, other sizes, fields or sample counts, a variance in some renders but not all, and
    two identical renders (the same seed).
    """
    frames = [f.numpy() for f in frames]
    names = [str(n) for n in (names or [f"render {i}" for i in range(len(frames))])]
    _check_buffers(frames, names)
    with_variance = [f.variance is not None for f in frames]
    if all(with_variance) and frames[0].spp is not None:
        pooled = combine_buffers(frames)
        return pooled.replace(**{field: np.asarray(getattr(pooled, field), np.float32)
                                 for field in pooled.features()})
    if any(with_variance):
        raise FrameError(f"merge: {names[with_variance.index(False)]} has no variance but "
                         f"{names[with_variance.index(True)]} has one")
    k = len(frames)
    colours = np.stack([np.asarray(f.color, np.float64) for f in frames])
    mean = colours.mean(axis=0)
    deviation = colours - mean
    fields = {"color": mean,
              "variance": np.square(deviation).sum(axis=0) / ((k - 1) * k),
              "covariance": (deviation * np.roll(deviation, -1, axis=-1)).sum(axis=0)
              / ((k - 1) * k)}
    for field in frames[0].features():
        if field not in fields:
            fields[field] = np.mean([np.asarray(getattr(f, field), np.float64) for f in frames],
                                    axis=0)
    spp = None if frames[0].spp is None else np.float32(k * float(np.asarray(frames[0].spp)))
    return Frame(**{name: value.astype(np.float32) for name, value in fields.items()}, spp=spp)
