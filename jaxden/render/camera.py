"""Pinhole cameras, Mitsuba-exact projection, and camera paths for animated sequences.

Conventions (all measured against Mitsuba 3.9's ``perspective`` sensor, and asserted by
tests/test_sequence.py against the position AOV of real renders):

* The camera-to-world matrix is Mitsuba's ``look_at(origin, target, up)``: columns
  ``left = normalize(up x dir)``, ``up' = dir x left``, ``dir = normalize(target - origin)``,
  ``origin``. Camera space looks along +z; camera +x (the viewer's *left*) maps to *decreasing*
  image x and camera +y to *decreasing* image y (rows grow downwards). So in images, as usual,
  x = column grows to the viewer's right and y = row grows downwards.
* ``fov_deg`` is the horizontal field of view (Mitsuba's default ``fov_axis='x'``); the vertical
  one follows from the aspect ratio width / height.
* Continuous pixel coordinates: pixel (row i, column j) covers [j, j+1) x [i, i+1) and its
  centre is (x, y) = (j + 0.5, i + 0.5). For a point at camera-space (cx, cy, cz):
  ``x = (1 - cx / (cz tan(fov/2))) W / 2`` and ``y = (1 - cy W / (cz tan(fov/2) H)) H / 2``.
* ``project`` returns depth *along the view axis* (camera z). Note that the Frame's ``depth``
  AOV is Mitsuba's ray distance (|p - origin|), which is larger off-axis.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from jaxden.errors import SceneError

Vec3 = tuple[float, float, float]


def _vec3(value, name: str) -> Vec3:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise SceneError(f"Camera: {name} must be 3 numbers, got {value!r}") from None
    if array.shape != (3,) or not np.all(np.isfinite(array)):
        raise SceneError(f"Camera: {name} must be 3 finite numbers, got {value!r}")
    return (float(array[0]), float(array[1]), float(array[2]))


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``origin`` looks at ``target`` with ``up``; ``fov_deg`` horizontal.

    Positions are world-space tuples of 3 floats; the field of view is in degrees, in (0, 180).
    Construction validates (SceneError): finite values, origin != target, up not parallel to the
    viewing direction.
    """

    origin: Vec3
    target: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_deg: float = 45.0

    def __post_init__(self) -> None:
        origin = _vec3(self.origin, "origin")
        target = _vec3(self.target, "target")
        up = _vec3(self.up, "up")
        try:
            fov = float(self.fov_deg)
        except (TypeError, ValueError):
            raise SceneError(f"Camera: fov_deg must be a number, got {self.fov_deg!r}") from None
        if not (0.0 < fov < 180.0):
            raise SceneError(f"Camera: fov_deg must be in (0, 180) degrees, got {self.fov_deg!r}")
        direction = np.subtract(target, origin)
        distance = float(np.linalg.norm(direction))
        if distance < 1e-9:
            raise SceneError(f"Camera: origin and target coincide at {origin}")
        up_norm = float(np.linalg.norm(up))
        if up_norm < 1e-12:
            raise SceneError("Camera: up must not be the zero vector")
        sine = np.linalg.norm(np.cross(direction / distance, np.asarray(up) / up_norm))
        if sine < 1e-6:
            raise SceneError(f"Camera: up {up} is parallel to the viewing direction")
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "target", target)
        object.__setattr__(self, "up", up)
        object.__setattr__(self, "fov_deg", fov)

    # ------------------------------------------------------------------ geometry
    @property
    def direction(self) -> np.ndarray:
        """Unit viewing direction (3,), world space."""
        return _normalize(np.subtract(self.target, self.origin))

    def to_world_matrix(self) -> np.ndarray:
        """The (4, 4) float64 camera-to-world matrix, identical to Mitsuba's ``look_at``."""
        direction = self.direction
        left = _normalize(np.cross(self.up, direction))
        new_up = np.cross(direction, left)
        matrix = np.eye(4)
        matrix[:3, 0], matrix[:3, 1], matrix[:3, 2] = left, new_up, direction
        matrix[:3, 3] = self.origin
        return matrix

    def world_to_camera_matrix(self) -> np.ndarray:
        """(4, 4) float64 inverse of :meth:`to_world_matrix` (rigid, so a transpose)."""
        to_world = self.to_world_matrix()
        rotation = to_world[:3, :3]
        matrix = np.eye(4)
        matrix[:3, :3] = rotation.T
        matrix[:3, 3] = -rotation.T @ to_world[:3, 3]
        return matrix

    def to_sensor_dict(self, size: tuple[int, int] | None = None, **extra) -> dict:
        """A Mitsuba ``perspective`` sensor dict (look_at transform, horizontal fov).

        With ``size = (width, height)`` it also carries an ``hdrfilm`` with a box pixel filter and
        an ``independent`` sampler (the settings denoising data needs). ``extra`` entries (e.g.
        ``near_clip``) are added to the dict as they are.
        """
        import mitsuba as mi

        _ensure_variant()
        sensor = {
            "type": "perspective",
            "fov": self.fov_deg,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(
                origin=list(self.origin), target=list(self.target), up=list(self.up)
            ),
        }
        if size is not None:
            width, height = film_size_pair(size, "Camera.to_sensor_dict")
            sensor["film"] = {
                "type": "hdrfilm",
                "width": width,
                "height": height,
                "rfilter": {"type": "box"},
            }
            sensor["sampler"] = {"type": "independent"}
        sensor.update(extra)
        return sensor

    def replace(self, **changes) -> Camera:
        return dataclasses.replace(self, **changes)


def _ensure_variant() -> None:
    """Select a Mitsuba variant if none is set (jaxden.render.variant's choice when present)."""
    try:
        from jaxden.render.variant import ensure_variant
    except ImportError:  # the variant module is optional for this file
        import mitsuba as mi

        if mi.variant() is None:
            mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
        return
    ensure_variant()


def film_size_pair(size, where: str) -> tuple[int, int]:
    try:
        width, height = size
    except (TypeError, ValueError):
        raise SceneError(f"{where}: size must be (width, height), got {size!r}") from None
    for value in (width, height):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise SceneError(f"{where}: size must be two integers >= 1, got {size!r}")
    return int(width), int(height)


# ---------------------------------------------------------------------------- Mitsuba scenes
def from_scene(scene) -> Camera:
    """The Camera of a loaded ``mi.Scene``'s first sensor (its world transform and x fov).

    Raises SceneError if the scene has no sensor, the sensor is not a perspective camera, or its
    transform is not a rigid look-at (e.g. a mirroring scale, common in converted XML scenes) or
    it has a shifted principal point: those are not representable by :class:`Camera`.
    """
    import mitsuba as mi

    sensors = scene.sensors()
    if not sensors:
        raise SceneError("from_scene: the scene has no sensor")
    params = mi.traverse(sensors[0])
    if "x_fov" not in params or "to_world" not in params:
        raise SceneError(
            f"from_scene: the first sensor is not a perspective camera (parameters: "
            f"{', '.join(sorted(params.keys()))})"
        )
    fov = float(np.asarray(params["x_fov"]).reshape(-1)[0])
    for key in ("principal_point_offset_x", "principal_point_offset_y"):
        if key in params and abs(float(np.asarray(params[key]).reshape(-1)[0])) > 1e-6:
            raise SceneError(f"from_scene: the sensor has a shifted principal point ({key})")
    matrix = np.asarray(params["to_world"].matrix, dtype=np.float64).reshape(4, 4)
    rotation = matrix[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        raise SceneError(
            "from_scene: the sensor's to_world is not a rigid look-at transform (it scales or "
            f"mirrors: {np.round(matrix, 4).tolist()})"
        )
    origin = matrix[:3, 3]
    return Camera(
        origin=origin, target=origin + rotation[:, 2], up=rotation[:, 1], fov_deg=fov
    )


# ---------------------------------------------------------------------------- projection
def project(
    camera: Camera, points_world, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into ``camera``'s image of ``width`` x ``height`` pixels.

    Args:
      points_world: (..., 3) world-space positions.
    Returns:
      pixel_xy: (..., 2) float64 continuous pixel coordinates (x = column, y = row; pixel
        (i, j) has its centre at (j + 0.5, i + 0.5)); NaN for points at or behind the camera
        plane (depth <= 0), which have no image.
      depth: (...) float64 distance along the viewing axis (camera-space z), world units.
    Exactly Mitsuba's perspective projection; see the module docstring for the formula.
    """
    width, height = film_size_pair((width, height), "project")
    points = np.asarray(points_world, dtype=np.float64)
    if points.ndim < 1 or points.shape[-1] != 3:
        raise SceneError(f"project: points must have shape (..., 3), got {points.shape}")
    world_to_camera = camera.world_to_camera_matrix()
    local = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    depth = local[..., 2]
    tan_half = math.tan(math.radians(camera.fov_deg) / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        safe = np.where(depth > 0, depth, np.nan)
        x = (1.0 - local[..., 0] / (safe * tan_half)) * (0.5 * width)
        y = (1.0 - local[..., 1] * (width / height) / (safe * tan_half)) * (0.5 * height)
    return np.stack([x, y], axis=-1), depth


def pixel_centres(width: int, height: int) -> np.ndarray:
    """(H, W, 2) float64 pixel-centre coordinates (x, y) = (column + 0.5, row + 0.5)."""
    width, height = film_size_pair((width, height), "pixel_centres")
    ys, xs = np.meshgrid(np.arange(height) + 0.5, np.arange(width) + 0.5, indexing="ij")
    return np.stack([xs, ys], axis=-1)


# ---------------------------------------------------------------------------- camera paths
def _frames(num_frames, where: str) -> int:
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) \
            or num_frames < 1:
        raise SceneError(f"{where}: num_frames must be an integer >= 1, got {num_frames!r}")
    return int(num_frames)


def _rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """(3, 3) right-handed rotation about the unit ``axis`` (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle_rad) * k + (1.0 - math.cos(angle_rad)) * (k @ k)


def orbit_path(
    camera: Camera,
    num_frames: int,
    total_angle_deg: float,
    *,
    axis: Sequence[float] | None = None,
    center: Sequence[float] | None = None,
) -> list[Camera]:
    """Orbit the camera origin (and up) around ``axis`` through ``center``; frame 0 = ``camera``.

    ``axis`` defaults to the camera's up, ``center`` to its target; the rotation is right-handed
    about ``axis`` and spreads ``total_angle_deg`` uniformly over the frames.
    """
    num_frames = _frames(num_frames, "orbit_path")
    axis_vec = _normalize(np.asarray(camera.up if axis is None else _vec3(axis, "axis")))
    center_vec = np.asarray(camera.target if center is None else _vec3(center, "center"))
    cameras = []
    for i in range(num_frames):
        fraction = i / (num_frames - 1) if num_frames > 1 else 0.0
        rotation = _rotation(axis_vec, math.radians(total_angle_deg * fraction))
        origin = center_vec + rotation @ (np.asarray(camera.origin) - center_vec)
        target = center_vec + rotation @ (np.asarray(camera.target) - center_vec)
        cameras.append(camera.replace(origin=origin, target=target, up=rotation @ camera.up))
    return cameras


def dolly_path(camera: Camera, num_frames: int, distance: float) -> list[Camera]:
    """Move the origin ``distance`` world units towards the (fixed) target, uniformly.

    A negative distance moves away. Raises SceneError if the camera would reach the target.
    """
    num_frames = _frames(num_frames, "dolly_path")
    current = float(np.linalg.norm(np.subtract(camera.target, camera.origin)))
    if distance >= current:
        raise SceneError(
            f"dolly_path: distance {distance} would reach the target (only {current:.4g} away)"
        )
    cameras = []
    for i in range(num_frames):
        fraction = i / (num_frames - 1) if num_frames > 1 else 0.0
        origin = np.asarray(camera.origin) + camera.direction * distance * fraction
        cameras.append(camera.replace(origin=origin))
    return cameras


def _catmull_rom(points: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Uniform Catmull-Rom spline through ``points`` (K, D) at parameters ``s`` in [0, K-1].

    End tangents come from reflected phantom points, so two keyframes give a straight line
    traversed at constant speed.
    """
    count = points.shape[0]
    if count == 1:
        return np.repeat(points, len(s), axis=0)
    padded = np.concatenate([2 * points[:1] - points[1:2], points, 2 * points[-1:] - points[-2:-1]])
    segment = np.clip(np.floor(s).astype(int), 0, count - 2)
    t = (s - segment)[:, None]
    p0, p1, p2, p3 = (padded[segment + k] for k in range(4))
    return 0.5 * (
        2 * p1
        + (p2 - p0) * t
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
        + (3 * p1 - p0 - 3 * p2 + p3) * t**3
    )


def interpolate_path(keyframes: Sequence[Camera], num_frames: int) -> list[Camera]:
    """A smooth (C1) path through the keyframe cameras, sampled at ``num_frames`` frames.

    Origins, targets, ups and fovs follow uniform Catmull-Rom splines, with keyframe k reached
    at frame k (num_frames - 1) / (K - 1); the first and last frames equal the first and last
    keyframes.
    """
    num_frames = _frames(num_frames, "interpolate_path")
    keyframes = list(keyframes)
    if not keyframes or not all(isinstance(k, Camera) for k in keyframes):
        raise SceneError("interpolate_path: keyframes must be a non-empty list of Camera")
    data = np.array([[*k.origin, *k.target, *k.up, k.fov_deg] for k in keyframes])
    s = np.linspace(0.0, len(keyframes) - 1, num_frames) if num_frames > 1 else np.zeros(1)
    curve = _catmull_rom(data, s)
    return [
        Camera(origin=row[0:3], target=row[3:6], up=row[6:9], fov_deg=float(row[9]))
        for row in curve
    ]


def random_path(
    camera: Camera,
    num_frames: int,
    seed: int,
    *,
    translation: float = 0.1,
    rotation_deg: float = 10.0,
    num_keyframes: int = 4,
) -> list[Camera]:
    """A smooth seeded random camera path starting at ``camera``.

    ``num_keyframes`` keyframes (the first is ``camera``) each orbit the target by up to
    ``rotation_deg`` and move the origin and target by up to ``translation`` times the camera's
    distance to its target; the frames follow :func:`interpolate_path` through them. Uses only
    ``np.random.default_rng(seed)``, so the same seed gives the same path.
    """
    num_frames = _frames(num_frames, "random_path")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise SceneError(f"random_path: seed must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    distance = float(np.linalg.norm(np.subtract(camera.target, camera.origin)))
    keys = [camera]
    for _ in range(max(int(num_keyframes), 2) - 1):
        angle = math.radians(float(rng.uniform(-rotation_deg, rotation_deg)))
        rotation = _rotation(_normalize(np.asarray(camera.up)), angle)
        offset = rotation @ np.subtract(camera.origin, camera.target)
        shift = rng.uniform(-1.0, 1.0, size=3) * translation * distance
        jitter = rng.uniform(-1.0, 1.0, size=3) * translation * distance * 0.5
        target = np.asarray(camera.target) + jitter
        keys.append(camera.replace(origin=target + offset + shift, target=target))
    return interpolate_path(keys, num_frames)
