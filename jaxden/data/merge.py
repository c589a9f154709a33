"""K independent renders of one image, merged into one frame with the variance of its mean.

Most renderers (Cycles among them) write no variance. Rendering the same frame K times with
different seeds gives it: the K buffer means are independent estimates of the pixel, so their
spread estimates the variance of one buffer's mean, and that over K the variance of the merged
mean (K - 1 degrees of freedom: noisy for small K, unbiased for any K >= 2). Buffers that carry
a variance of their own (jaxden's) are pooled exactly instead, as one render of all K m samples
(:func:`combine_buffers`; K m - 1 degrees of freedom). The merged frame records which in
``Frame.variance_dof``, for the error guard's bound on the variance
(:mod:`jaxden.progressive.guard`).

    merged = merge_renders([read_frame(p, convention="cycles") for p in paths])

The merged file records its renders (:class:`BufferList`: their names and a sha256 of each
one's colour), so that sub-buffer SURE (``jaxden sure`` / ``jaxden progressive --buffers``)
can check it is given exactly those.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from jaxden.errors import ExrError, FrameError
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
    must be present in every buffer). ``variance_dof``: None (spp - 1, the sample variance of
    all K m samples) when no buffer records one, else the sum of the buffers' (m - 1 where a
    buffer records none) plus K - 1 for the spread of their means. Returns float64 NumPy
    arrays.
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
                             spp=np.full(np.shape(frames[0].spp), n, np.float32),
                             variance_dof=_pooled_dof(frames, m))


def _pooled_dof(frames, m: int):
    """The degrees of freedom of :func:`combine_buffers`' variance: None when no buffer records
    its own (then spp - 1), else sum_k d_k + K - 1 (d_k = m - 1 where unrecorded)."""
    if all(f.variance_dof is None for f in frames):
        return None
    own = [np.full(np.shape(frames[0].spp), m - 1, np.float64) if f.variance_dof is None
           else np.asarray(f.variance_dof, np.float64) for f in frames]
    return (np.sum(own, axis=0) + len(frames) - 1).astype(np.float32)


def merge_renders(frames: Sequence[Frame], names: Sequence[str] | None = None) -> Frame:
    """One frame from K >= 2 independent renders (different seeds) of the same frame.

    Colour and features: the mean over the renders. Variance of the mean: pooled exactly when
    every render carries its variance and spp (:func:`combine_buffers`),
    else from the spread of the K colours, sum_k (c_k - mean)^2 / ((K - 1) K), and the covariance
    between channels likewise. ``spp``: the renders' sum when they record one, else None.
    ``variance_dof``: the variance's degrees of freedom, always set: K - 1 from the spread,
    K m - 1 pooled (more where the renders record their own; :func:`combine_buffers`).
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
        dof = pooled.variance_dof
        if dof is None:
            dof = np.asarray(pooled.spp, np.float32) - np.float32(1)
        return pooled.replace(**{field: np.asarray(getattr(pooled, field), np.float32)
                                 for field in pooled.features()},
                              variance_dof=np.float32(np.asarray(dof)))
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
    return Frame(**{name: value.astype(np.float32) for name, value in fields.items()}, spp=spp,
                 variance_dof=np.float32(k - 1))


# ------------------------------------------------------------- the buffers a frame is made of
#: Header keys (``jaxden.`` prefixed) of a frame made from K buffers: their file names (a JSON
#: list), the sha256 of each one's colour (:func:`colour_digest`, ";"-separated, same order)
#: and the convention (and layer) they were read by, where not jaxden's own.
BUFFER_FILES_KEY = "buffer_files"
BUFFER_DIGESTS_KEY = "buffer_sha256"
BUFFER_CONVENTION_KEY = "buffer_convention"
BUFFER_LAYER_KEY = "buffer_layer"


def colour_digest(color) -> str:
    """sha256 (hex) of a colour image's bytes as little-endian float32, (H, W, 3) row-major:
    names a buffer by its content (the colour as :func:`jaxden.io.exr.read_frame` returns it)."""
    array = np.ascontiguousarray(np.asarray(color), dtype="<f4")
    return hashlib.sha256(array.tobytes()).hexdigest()


@dataclasses.dataclass(frozen=True)
class BufferList:
    """The K buffers a frame was made from: file names as given when it was made, the
    :func:`colour_digest` of each, and the convention and layer they were read by (None:
    jaxden's channels)."""

    files: tuple[str, ...]
    digests: tuple[str, ...]
    convention: str | None = None
    layer: str | None = None

    def attributes(self) -> dict[str, str]:
        """The header attributes that record the list (for :func:`jaxden.io.exr.write_frame`)."""
        attributes = {BUFFER_FILES_KEY: json.dumps(list(self.files)),
                      BUFFER_DIGESTS_KEY: ";".join(self.digests)}
        if self.convention is not None:
            attributes[BUFFER_CONVENTION_KEY] = self.convention
        if self.layer is not None:
            attributes[BUFFER_LAYER_KEY] = self.layer
        return attributes


def buffer_list(header: Mapping[str, Any], where: str) -> BufferList | None:
    """The :class:`BufferList` a header (of :func:`jaxden.io.exr.read_header` or ``read_channels``)
    records, or None when it records none. A malformed record is an ExrError naming
    ``where`` (the file)."""
    digests = header.get(BUFFER_DIGESTS_KEY)
    if digests is None:
        return None
    problem = None
    digests = tuple(str(digests).split(";"))
    try:
        files = json.loads(header.get(BUFFER_FILES_KEY, "null"))
    except (TypeError, ValueError):
        files = None
    if files is None:
        files = [f"buffer {i}" for i in range(len(digests))]
    if not all(len(d) == 64 and all(c in "0123456789abcdef" for c in d) for d in digests):
        problem = f"jaxden.{BUFFER_DIGESTS_KEY} is not a list of sha256 digests"
    elif not isinstance(files, list) or len(files) != len(digests):
        problem = (f"jaxden.{BUFFER_FILES_KEY} does not name the {len(digests)} buffers of "
                   f"jaxden.{BUFFER_DIGESTS_KEY}")
    if problem is not None:
        raise ExrError(f"{where}: the header's record of the buffers it was made from is "
                       f"malformed ({problem})")
    convention, layer = (header.get(k) for k in (BUFFER_CONVENTION_KEY, BUFFER_LAYER_KEY))
    return BufferList(tuple(str(f) for f in files), digests,
                      None if convention is None else str(convention),
                      None if layer is None else str(layer))


def read_buffer_list(path: str | os.PathLike) -> BufferList | None:
    """The buffers the EXR at ``path`` records it was made from (its header only), or None."""
    from jaxden.io.exr import read_header

    return buffer_list(read_header(path), str(path))
