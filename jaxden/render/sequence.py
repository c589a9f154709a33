"""Animated sequences: one Frame per camera of a path, with motion vectors.

Geometry, materials and lights are static; only the camera moves (a camera path from
:mod:`jaxden.render.camera`). That covers the temporal-accumulation setting of the WSKP paper
(reprojection of the previous frame) without animated objects, which this module does not
produce.

Motion-vector convention (the one of :mod:`jaxden.frame`): ``motion[i, j] = (dx, dy)`` in
pixels, x along columns (right) and y along rows (down), such that the surface point seen at
pixel (i, j) of frame t was at ``prev_xy = xy + motion`` in frame t-1, where xy = (j + 0.5,
i + 0.5) is the pixel centre and prev_xy is a continuous pixel coordinate of frame t-1 (whose
pixel centres are also at +0.5). To fetch frame t-1 data for pixel (i, j), sample it bilinearly
at row ``i + dy``, column ``j + dx`` (array indices).

Motion is 0 on misses (no surface: the environment) and for points at or behind the previous
camera's image plane (they had no image in frame t-1); consumers must reject those by
comparing reprojected positions/normals, as temporal accumulation does anyway.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Sequence

import numpy as np

from jaxden.errors import FrameError, SceneError
from jaxden.frame import Frame
from jaxden.render.camera import Camera, film_size_pair, pixel_centres, project
from jaxden.render.variant import ensure_variant


def motion_vectors(
    position,
    valid,
    prev_camera: Camera,
    width: int,
    height: int,
    *,
    camera: Camera | None = None,
) -> np.ndarray:
    """Motion vectors (H, W, 2) float32, in pixels, from frame t to frame t-1.

    Args:
      position: (H, W, 3) world-space first-hit positions of frame t (the position AOV).
      valid: (H, W) bool, True where the pixel saw a surface (e.g. ``depth[..., 0] > 0``).
      prev_camera: the camera of frame t-1.
      width, height: image size in pixels; must match ``position``.
      camera: the camera of frame t (optional, recommended). With it, each position is also
        projected with the *current* camera and the motion is the image-space displacement
        of that surface point: ``motion = project(prev_camera, P) - project(camera, P)``.
        The position AOV of a pixel is an average over sub-pixel samples (with 1 spp, one
        random point in the pixel), not the point under the pixel centre, so this removes up
        to half a pixel of sampling jitter; what remains is the variation of the flow across
        one pixel (far below 0.01 px for camera motion). Without it, ``motion = prev_xy -
        pixel_centre``, exact only when the position was sampled at the pixel centre.
    Returns:
      motion (H, W, 2) with prev_xy = xy + motion (see the module docstring); 0 where ``valid``
      is False or the point is at or behind ``prev_camera``.
    Raises FrameError for mismatched shapes.
    """
    width, height = film_size_pair((width, height), "motion_vectors")
    position = np.asarray(position)
    valid = np.asarray(valid)
    if position.shape != (height, width, 3):
        raise FrameError(
            f"motion_vectors: position must have shape (height, width, 3) = "
            f"({height}, {width}, 3), got {position.shape}"
        )
    if valid.shape != (height, width):
        raise FrameError(
            f"motion_vectors: valid must have shape (height, width) = ({height}, {width}), got "
            f"{valid.shape}"
        )
    if not isinstance(prev_camera, Camera) or not isinstance(camera, (Camera, type(None))):
        raise SceneError("motion_vectors: prev_camera and camera must be jaxden Camera objects")
    prev_xy, prev_depth = project(prev_camera, position, width, height)
    if camera is None:
        xy = pixel_centres(width, height)
    else:
        xy, _ = project(camera, position, width, height)
    motion = prev_xy - xy
    keep = valid.astype(bool) & (prev_depth > 0) & np.all(np.isfinite(motion), axis=-1)
    return np.where(keep[..., None], motion, 0.0).astype(np.float32)


def sequence_seed(seed: int, frame_index: int, purpose: str = "frame") -> int:
    """A render seed for frame ``frame_index`` of a sequence: hash of (seed, index, purpose).

    ``purpose`` is 'frame' or 'reference', so noisy frames and references never share samples
    and no two frames of a sequence do. Returns an int in [0, 2**56).
    """
    digest = hashlib.blake2b(
        f"jaxden-sequence:{int(seed)}:{int(frame_index)}:{purpose}".encode(), digest_size=7
    ).digest()
    return int.from_bytes(digest, "little")


def _check_int(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise SceneError(f"render_sequence: {name} must be an integer >= {low}, got {value!r}")
    return int(value)


def _check_cameras(cameras) -> list[Camera]:
    try:
        cameras = list(cameras)
    except TypeError:
        raise SceneError(
            f"render_sequence: cameras must be a list of Camera, got {type(cameras).__name__}"
        ) from None
    if not cameras:
        raise SceneError("render_sequence: the camera list is empty; give at least one Camera")
    for index, camera in enumerate(cameras):
        if not isinstance(camera, Camera):
            raise SceneError(
                f"render_sequence: cameras[{index}] must be a jaxden Camera, got "
                f"{type(camera).__name__}"
            )
    return cameras


def _with_motion(frame: Frame, camera: Camera, prev_camera: Camera | None) -> Frame:
    if prev_camera is None:
        return frame.replace(motion=np.zeros((frame.height, frame.width, 2), np.float32))
    valid = np.asarray(frame.depth)[..., 0] > 0
    motion = motion_vectors(frame.position, valid, prev_camera, frame.width, frame.height,
                            camera=camera)
    return frame.replace(motion=motion)


def iter_sequence(
    scene,
    cameras: Sequence[Camera],
    spp: int = 1,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    reference_spp: int | None = None,
    *,
    max_depth: int | None = None,
) -> Iterator[Frame | tuple[Frame, Frame]]:
    """Render a camera path lazily: yields one Frame per camera (or (frame, reference) pairs).

    Same arguments as :func:`render_sequence`; only one frame (and reference) is held at a
    time, so long sequences at high resolution need no more memory than a single frame.
    Arguments are checked at the call, before the first frame is rendered.
    """
    cameras = _check_cameras(cameras)
    spp = _check_int(spp, "spp", 1)
    seed = _check_int(seed, "seed", 0)
    if reference_spp is not None:
        reference_spp = _check_int(reference_spp, "reference_spp", 1)
    if size is not None:
        size = film_size_pair(size, "render_sequence")
    return _generate(scene, cameras, spp, seed, size, reference_spp, max_depth)


def _generate(scene, cameras, spp, seed, size, reference_spp, max_depth):
    import mitsuba as mi

    ensure_variant()  # mi.Scene exists only once a variant is set

    from jaxden.render.core import render_frame
    from jaxden.render.load import load_scene

    # Load (and for procedural scenes, generate) the scene once for the whole sequence.
    mi_scene = scene if isinstance(scene, mi.Scene) else load_scene(scene, size)
    if size is None:
        size = tuple(int(v) for v in mi_scene.sensors()[0].film().size())
    prev_camera = None
    for index, camera in enumerate(cameras):
        sensor = camera.to_sensor_dict()
        frame = render_frame(mi_scene, spp, sequence_seed(seed, index, "frame"), size,
                             sensor=sensor, max_depth=max_depth)
        frame = _with_motion(frame, camera, prev_camera)
        if reference_spp is None:
            yield frame
        else:
            reference = render_frame(mi_scene, reference_spp,
                                     sequence_seed(seed, index, "reference"), size,
                                     sensor=sensor, max_depth=max_depth)
            yield frame, _with_motion(reference, camera, prev_camera)
        prev_camera = camera


def render_sequence(
    scene,
    cameras: Sequence[Camera],
    spp: int = 1,
    seed: int = 0,
    size: tuple[int, int] | None = None,
    reference_spp: int | None = None,
    *,
    max_depth: int | None = None,
) -> list[Frame] | tuple[list[Frame], list[Frame]]:
    """Render one Frame per camera of a path, with motion vectors; static scene.

    Args:
      scene: anything :func:`jaxden.render.render_frame` accepts; loaded once for all frames.
      cameras: the camera of each frame (e.g. from :func:`jaxden.render.camera.orbit_path`);
        they replace the scene's own sensor.
      spp: samples per pixel of each frame (1 spp frames are cheap: a 64 x 64 frame costs
        mostly Mitsuba's per-render overhead).
      seed: sequence seed; frame t renders with :func:`sequence_seed` (seed, t), so frames have
        distinct, deterministic sample streams.
      size: (width, height) in pixels; default the scene's film size.
      reference_spp: if given, also render a reference of that many spp per frame (with its
        own seeds and its own motion vectors).
      max_depth: path length of the colour integrator (render_frame's default if None).
    Returns:
      A list of Frames (float32 NumPy, motion (H, W, 2) filled; frame 0 gets zeros), or a pair
      (frames, references) when ``reference_spp`` is given. Features follow render_frame (at
      spp = 1, the position and depth are those of one random sample inside each pixel).
    Raises SceneError for an empty camera list, a non-Camera entry, a bad spp, seed or size.
    Memory: every frame is kept; use :func:`iter_sequence` for long sequences.
    """
    items = list(iter_sequence(scene, cameras, spp, seed, size, reference_spp,
                               max_depth=max_depth))
    if reference_spp is None:
        return items
    return [frame for frame, _ in items], [reference for _, reference in items]
