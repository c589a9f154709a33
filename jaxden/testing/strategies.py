"""Hypothesis strategies for jaxden's data: frames as :class:`jaxden.frame.Frame` expects them and
Monte Carlo noise around them.

Hypothesis is a test dependency (``pip install jaxden[test]``), imported when a strategy is
built, not when this module is: ``import jaxden.testing`` and ``import
jaxden.testing.strategies`` work without it, and calling a strategy without it raises an
ImportError that says how to install it.

Hypothesis draws the parameters (shape, radiance and noise ranges, sample count, seed) and
NumPy builds the arrays from them (:func:`jaxden.testing.synthetic.synthetic_frame`): frames
stay heterogeneous at every pixel (a frame that repeats one value cannot show where a
variance went wrong), drawing them is cheap at any size, and a failure shrinks towards small,
plain frames and seed 0.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from jaxden.errors import ConfigError
from jaxden.frame import Frame

#: The image fields :func:`frames` can include besides the colour.
FRAME_FEATURES = ("variance", "albedo", "normal", "depth", "covariance")


def _hypothesis():
    try:
        from hypothesis import strategies
    except ImportError as error:  # pragma: no cover - hypothesis is in the test extra
        raise ImportError("jaxden.testing.strategies needs hypothesis: pip install "
                          "'jaxden[test]' (or pip install hypothesis)") from error
    return strategies


def _sizes(st, value, name: str):
    """A strategy of sizes from an int, a (low, high) range or a strategy."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        if value < 1:
            raise ConfigError(f"frames: {name} must be >= 1, got {value}")
        return st.just(int(value))
    if isinstance(value, tuple) and len(value) == 2:
        low, high = (int(v) for v in value)
        if not 1 <= low <= high:
            raise ConfigError(f"frames: {name} range must have 1 <= low <= high, got {value}")
        return st.integers(low, high)
    if hasattr(value, "example"):  # a strategy
        return value
    raise ConfigError(f"frames: {name} must be an int, a (low, high) range or a strategy, "
                      f"got {value!r}")


def frames(*, height=(4, 16), width=(4, 16), batch: Sequence[int] = (),
           features: Sequence[str] = ("variance", "albedo", "normal", "depth"),
           radiance: tuple[float, float] = (1e-3, 1e2),
           relative_std: tuple[float, float] = (1e-3, 2.0),
           spp: tuple[int, int] = (2, 4096), misses: bool = True):
    """A strategy of clean frames: float32 NumPy, shapes (*batch, H, W, C) per field as
    :class:`jaxden.frame.Frame` documents, values that :meth:`Frame.validated` accepts.

    Args:
      height, width: an int, an inclusive (low, high) range, or a strategy of ints.
      batch: leading dimensions (each image drawn on its own).
      features: fields besides the colour, from :data:`FRAME_FEATURES` (``covariance``
        needs ``variance``; its correlation per channel pair is drawn in [0, 0.99]).
      radiance: the range the colour's radiance spans (each frame draws a sub-range of it,
        log-uniformly: linear HDR radiance, > 0).
      relative_std: the range of the relative standard deviation of the pixel mean (each
        frame draws a sub-range of it, log-uniformly).
      spp: range of the sample count (a power of two, one per image; ``spp`` is set when
        ``variance`` is present; the variance does not follow it).
      misses: allow pixels where the camera ray hit nothing (normal, depth, albedo 0).

    The variance is that of the pixel mean (> 0, see :func:`synthetic_frame`), albedo in
    [0, 0.9], normals unit length (0 on misses), depth in [1, 10] (0 on misses).
    """
    st = _hypothesis()
    unknown = sorted(set(features) - set(FRAME_FEATURES))
    if unknown:
        raise ConfigError(f"frames: unknown feature(s) {unknown}; choose from "
                          f"{', '.join(FRAME_FEATURES)}")
    if "covariance" in features and "variance" not in features:
        raise ConfigError("frames: 'covariance' needs 'variance'")
    heights, widths = _sizes(st, height, "height"), _sizes(st, width, "width")
    low_spp, high_spp = (int(v) for v in spp)
    if not 1 <= low_spp <= high_spp:
        raise ConfigError(f"frames: spp range must have 1 <= low <= high, got {spp}")
    exponents = [e for e in range(31) if low_spp <= 2**e <= high_spp] or [
        int(np.log2(low_spp))]
    batch = tuple(int(n) for n in batch)
    log_r = np.log10(radiance)
    log_s = np.log10(relative_std)

    def log_range(draw, low, high):
        a = draw(st.floats(low, high, allow_nan=False))
        b = draw(st.floats(low, high, allow_nan=False))
        return 10.0 ** min(a, b), 10.0 ** max(a, b)

    @st.composite
    def one_image(draw, h, w):
        from jaxden.testing.synthetic import synthetic_frame

        correlation = (draw(st.floats(0.0, 0.99)) if "covariance" in features else None)
        frame = synthetic_frame(
            draw(st.integers(0, 2**32 - 1)), h, w,
            radiance=log_range(draw, *log_r), relative_std=log_range(draw, *log_s),
            spp=float(2 ** draw(st.sampled_from(exponents))),
            miss_fraction=draw(st.sampled_from([0.0, 0.1, 0.5])) if misses else 0.0,
            correlation=correlation)
        kept = {name: getattr(frame, name) for name in features}
        spp_value = frame.spp if "variance" in features else None
        return Frame(color=frame.color, spp=spp_value, **kept)

    @st.composite
    def build(draw):
        from jaxden.frame import stack

        h, w = draw(heights), draw(widths)
        count = int(np.prod(batch)) if batch else 1
        images = [draw(one_image(h, w)) for _ in range(count)]
        if not batch:
            return images[0]
        stacked = stack(images)
        return stacked.map(lambda a: a.reshape(batch + a.shape[1:])).replace(
            spp=None if stacked.spp is None else stacked.spp.reshape(batch))

    return build()


def noisy_frames(clean=None, *, kinds: Sequence[str] = ("gaussian", "gamma")):
    """A strategy of ``(clean, noisy)`` frame pairs: a clean frame drawn from ``clean`` (a
    strategy of single-image frames with a variance; default ``frames()``) and Monte Carlo
    noise around it of a kind drawn from ``kinds`` (:func:`jaxden.testing.synthetic.
    monte_carlo_noise`: ``"gaussian"``, SURE's model, or ``"gamma"``, a render's skewed,
    non-negative pixel mean with a sample variance), from a drawn seed."""
    from jaxden.testing.synthetic import NOISE_KINDS, monte_carlo_noise

    st = _hypothesis()
    unknown = sorted(set(kinds) - set(NOISE_KINDS))
    if unknown or not kinds:
        raise ConfigError(f"noisy_frames: kinds must be some of {', '.join(NOISE_KINDS)}, "
                          f"got {list(kinds)}")
    clean = frames(spp=(2, 256)) if clean is None else clean

    @st.composite
    def build(draw):
        frame = draw(clean)
        kind = draw(st.sampled_from(tuple(kinds)))
        spp = None
        if kind == "gamma":
            spp = int(np.asarray(frame.spp)) if frame.spp is not None and np.ndim(
                frame.spp) == 0 and float(frame.spp) >= 2 else 4
            spp = min(spp, 64)  # the samples are drawn one by one
        noisy = monte_carlo_noise(frame, draw(st.integers(0, 2**32 - 1)), kind, spp)
        return frame, noisy

    return build()
