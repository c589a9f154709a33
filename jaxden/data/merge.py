"""K independent renders of one image, merged into one frame with the variance of its mean.

Most renderers (Cycles among them) write no variance. Rendering the same frame K times with
different seeds gives it: the K buffer means are independent estimates of the pixel, so their
spread estimates the variance of one buffer's mean, and that over K the variance of the merged
mean (K - 1 degrees of freedom: noisy for small K, unbiased for any K >= 2). Buffers that carry
a variance of their own (jaxden's) are pooled exactly instead, as one render of all K m samples
(:func:`combine_buffers`; K m - 1 degrees of freedom). The merged frame records which in
``Frame.variance_dof``, for the error guard's bound on the variance
(:mod:`jaxden.progressive.guard`).

    merged = merge_renders([read_frame(p, convention="cycles", refuse_denoised=True)
                            for p in paths])

Only raw Monte Carlo means are merged: a denoised render gives its raw colour (Cycles' Noisy
Image pass), and a denoised image named by hand is refused (``refuse_denoised``). Renders made
with adaptive sampling (seen in Cycles' Debug Sample Count pass) merge as any others: each is
one draw of the same random estimate, so the spread of K of them still estimates the variance
of their mean, whatever each pixel's sample count was; they record no sample count, and the
merged frame none either. Two renders that are one render twice (equal, or equal but for
rounding, as Cycles repeats a seed: :func:`same_render`) are refused.

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
from jaxden.render.integrators import boxcox_of_samples


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
            said = ["no sample count" if n is None else f"{n:g} spp" for n in (spp, first_spp)]
            raise FrameError(f"merge: {name} has {said[0]}, {names[0]} {said[1]}: merge "
                             f"renders of one setup (equal sample counts, adaptive sampling "
                             f"on in all or none)")
    colours = [np.asarray(f.color) for f in frames]
    for i in range(len(frames)):
        for j in range(i):
            if same_render(colours[i], colours[j], first.spp):
                raise FrameError(f"merge: {names[j]} and {names[i]} are the same image (rendered "
                                 f"with the same seed?): their spread would say the variance "
                                 f"is about 0")


def same_render(a, b, spp=None) -> bool:
    """Whether colours ``a`` and ``b`` (of renders of ``spp`` samples; None: unknown) are one
    render twice: equal, or equal but for rounding. Blender 5.0.1's Cycles renders one seed
    again with 30-70 % of the values changed by float rounding: over the changed ones, the
    median of |a - b| / (|a| + |b|) was 0..4e-5 in 17 of 20 pairs of reruns and 1e-4..2e-4 in
    2 (tests/data/cycles' scene at 4 spp; the 20th differed as two seeds do), where renders of
    two seeds differ by about 0.5 CV / sqrt(spp) (0.07..0.4 there at 4..16 spp). The bound is
    1e-3 / sqrt(spp) (1e-5 when ``spp`` is unknown): an independent pair falls below it only
    where the median pixel's coefficient of variation per sample is under 0.002."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    differ = a != b
    if not differ.any():
        return True
    relative = np.abs(a - b)[differ] / (np.abs(a) + np.abs(b))[differ]
    bound = 1e-5 if spp is None else 1e-3 / np.sqrt(float(spp))
    return bool(np.median(relative) < bound)


def combine_buffers(buffers) -> Frame:
    """One frame from K equal-spp sub-buffer frames of the same image (independent samples).

    Colour: the mean of the buffers' colours. Variance of the mean: the pooled sample variance
    of all K * m samples over K * m, from each buffer's variance of its mean (m samples each;
    the frames must have ``spp``) and the spread of the buffer means, exactly as if one
    render had taken all the samples; the covariance between channels likewise when every
    buffer has one (else none); ``boxcox`` pooled exactly likewise (:func:`pool_boxcox`) when
    every buffer has it (else none). Features (albedo, normal, ...): the mean over the
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
    boxcox = [f.boxcox for f in frames]
    if all(b is not None for b in boxcox):
        features["boxcox"] = pool_boxcox(boxcox, [f.statistics_count() for f in frames])
    for name in frames[0].features():
        if name in ("color", "variance", "covariance", "boxcox"):
            continue
        if any(getattr(f, name) is None for f in frames):
            raise FrameError(f"combine_buffers: {name} is in buffer 0 but not in every buffer")
        features[name] = np.mean([np.asarray(getattr(f, name), np.float64) for f in frames],
                                 axis=0)
    return frames[0].replace(color=mean, variance=squares / (n - 1) / n, **features,
                             spp=np.full(np.shape(frames[0].spp), n, np.float32),
                             variance_dof=_pooled_dof(frames, m))


def pool_boxcox(statistics, counts) -> np.ndarray:
    """``Frame.boxcox`` of all the samples of K renders from each one's (..., 9) statistics
    and sample count n_k (``Frame.statistics_count``), exactly (Chan et al.'s pairwise update
    of the mean and the second and third central moments, all at once): with d_k = mean_k -
    mean, M2 = sum n_k (m2_k + d_k^2) and M3 = sum n_k (m3_k + 3 m2_k d_k + d_k^3), returned as
    M2 / n and M3 / n, n = sum n_k. float64."""
    stats = np.stack([np.asarray(b, np.float64) for b in statistics])
    n_k = np.stack([np.broadcast_to(np.asarray(c, np.float64), np.shape(stats[0])[:-3])
                    for c in counts])[..., None, None, None]
    n = n_k.sum(axis=0)
    mean = (n_k * stats[..., 0:3]).sum(axis=0) / n
    d = stats[..., 0:3] - mean
    second = (n_k * (stats[..., 3:6] + d * d)).sum(axis=0) / n
    third = (n_k * (stats[..., 6:9] + 3.0 * stats[..., 3:6] * d + d ** 3)).sum(axis=0) / n
    return np.concatenate([mean, second, third], axis=-1)


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
    ``boxcox`` (StatMC's statistics): pooled exactly where the variance is and every render
    has them; from the spread, the statistics of the K colours as K samples (Box-Cox of
    each render's mean: valid for the test, which compares means of K i.i.d. values, but with
    K - 1 degrees of freedom it accepts far more: the limit for renderers that cannot write
    per-sample moments).
    ``names`` (e.g. the file paths) label the messages. Raises FrameError for fewer than 2
    renders, other sizes, fields or sample counts, a variance in some renders but not all, and
    one render given twice (equal, or equal but for rounding: :func:`same_render`).
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
    # The statistics of the K renders' means, as K samples (their count, K, is the variance's
    # K - 1 degrees of freedom plus one): whatever per-sample statistics the renders carry.
    fields["boxcox"] = boxcox_of_samples(colours)
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
#: and the convention (and layer) they were read by, where not jaxden's own, and the channels
#: named by hand (``--channels``; a JSON object field -> names), where any were.
BUFFER_FILES_KEY = "buffer_files"
BUFFER_DIGESTS_KEY = "buffer_sha256"
BUFFER_CONVENTION_KEY = "buffer_convention"
BUFFER_LAYER_KEY = "buffer_layer"
BUFFER_CHANNELS_KEY = "buffer_channels"


def colour_digest(color) -> str:
    """sha256 (hex) of a colour image's bytes as little-endian float32, (H, W, 3) row-major:
    names a buffer by its content (the colour as :func:`jaxden.io.exr.read_frame` returns it)."""
    array = np.ascontiguousarray(np.asarray(color), dtype="<f4")
    return hashlib.sha256(array.tobytes()).hexdigest()


@dataclasses.dataclass(frozen=True)
class BufferList:
    """The K buffers a frame was made from: file names as given when it was made, the
    :func:`colour_digest` of each, the convention and layer they were read by (None:
    jaxden's channels) and the channels named by hand (``channels``: (field, names) pairs;
    empty: none)."""

    files: tuple[str, ...]
    digests: tuple[str, ...]
    convention: str | None = None
    layer: str | None = None
    channels: tuple[tuple[str, tuple[str, ...]], ...] = ()

    def attributes(self) -> dict[str, str]:
        """The header attributes that record the list (for :func:`jaxden.io.exr.write_frame`)."""
        attributes = {BUFFER_FILES_KEY: json.dumps(list(self.files)),
                      BUFFER_DIGESTS_KEY: ";".join(self.digests)}
        if self.convention is not None:
            attributes[BUFFER_CONVENTION_KEY] = self.convention
        if self.layer is not None:
            attributes[BUFFER_LAYER_KEY] = self.layer
        if self.channels:
            attributes[BUFFER_CHANNELS_KEY] = json.dumps(
                {field: list(names) for field, names in self.channels})
        return attributes

    def reading(self) -> dict[str, Any]:
        """The keywords of :func:`jaxden.io.exr.read_frame` that read the buffers as they
        were read when merged (``convention``, ``layer``, ``channel_map``)."""
        return {"convention": self.convention, "layer": self.layer,
                "channel_map": dict(self.channels) or None}


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
    channels = _channels_record(header.get(BUFFER_CHANNELS_KEY), where)
    convention, layer = (header.get(k) for k in (BUFFER_CONVENTION_KEY, BUFFER_LAYER_KEY))
    return BufferList(tuple(str(f) for f in files), digests,
                      None if convention is None else str(convention),
                      None if layer is None else str(layer), channels)


def _channels_record(text, where: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    """The (field, names) pairs of a ``jaxden.buffer_channels`` attribute (empty: none)."""
    if text is None:
        return ()
    try:
        record = json.loads(text)
    except (TypeError, ValueError):
        record = None
    if not (isinstance(record, dict) and all(
            isinstance(names, list) and all(isinstance(n, str) for n in names)
            for names in record.values())):
        raise ExrError(f"{where}: the header's record of the buffers' channels "
                       f"(jaxden.{BUFFER_CHANNELS_KEY}) is malformed: {text!r}")
    return tuple((str(field), tuple(names)) for field, names in record.items())


def read_buffer_list(path: str | os.PathLike) -> BufferList | None:
    """The buffers the EXR at ``path`` records it was made from (its header only), or None."""
    from jaxden.io.exr import read_header

    return buffer_list(read_header(path), str(path))
