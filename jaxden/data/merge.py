"""K independent renders of one image, merged into one frame with the variance of its mean.

Most renderers (Cycles among them) write no variance. Rendering the same frame K times with
different seeds gives it: the K buffer means are independent estimates of the pixel, so their
spread estimates the variance of one buffer's mean, and that over K the variance of the merged
mean (K - 1 degrees of freedom: noisy for small K, unbiased for any K >= 2). Buffers that carry
a variance of their own (jaxden's) are pooled exactly instead, as one render of all K m samples
(:func:`jaxden.sure.buffers.combine_buffers`).

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


def merge_renders(frames: Sequence[Frame], names: Sequence[str] | None = None) -> Frame:
    """One frame from K >= 2 independent renders (different seeds) of the same frame.

    Colour and features: the mean over the renders. Variance of the mean: pooled exactly when
    every render carries its variance and spp (:func:`jaxden.sure.buffers.combine_buffers`),
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
        from jaxden.sure.buffers import combine_buffers

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
