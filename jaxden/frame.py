"""Frame: the one feature pytree used everywhere in jaxden.

A Frame holds one rendered image (or a batch, with leading dimensions) in linear HDR radiance,
NHWC float32:

=========  ============  =====================================================================
field      shape         meaning
=========  ============  =====================================================================
color      (..., H, W, 3)  mean radiance per pixel (the Monte Carlo estimate)
variance   (..., H, W, 3)  variance of the pixel *mean* (sample variance / spp), per channel
albedo     (..., H, W, 3)  diffuse reflectance of the first hit, in [0, 1] on diffuse surfaces
normal     (..., H, W, 3)  world-space shading normal of the first hit, unit length (0 on misses)
depth      (..., H, W, 1)  distance along the ray to the first hit (0 on misses)
position   (..., H, W, 3)  world-space position of the first hit (0 on misses)
motion     (..., H, W, 2)  pixel offset (dx, dy) from this pixel to where its surface point was
                           in the previous frame: prev_xy = xy + motion
covariance (..., H, W, 3)  covariance of the pixel *mean* between channels (R, G), (G, B),
                           (B, R): the off-diagonal of its 3 x 3 covariance (needs variance)
emission   (..., H, W, 3)  radiance emitted by the surface each camera ray hits first (directly
                           visible emitters, Le at the first hit), averaged over the colour's
                           own samples; the environment on camera-ray misses is not in it
                           (Cycles' ``Emit`` pass; the background is its own pass there)
boxcox     (..., H, W, 9)  per-pixel sample statistics of the Box-Cox(0.5) transformed radiance
                           b = (sqrt(L) - 1) / 0.5 of each sample, per channel: the mean of b
                           (R, G, B), its second and third central moments about that mean,
                           mean((b - mean b)^2) and mean((b - mean b)^3) (R, G, B each), i.e.
                           M2 / n and M3 / n of the online (Welford) form; n is the statistics'
                           sample count, ``variance_dof + 1`` where that is set (a frame merged
                           from K renders by their spread has K: the statistics of the K
                           renders' means), else ``spp``. What StatMC's pairwise test reads
                           (:mod:`jaxden.denoise.statmc`, :mod:`jaxden.render.integrators`)
spp        (...)           samples per pixel (a float array so batches can mix spp levels)
variance_dof (...)         degrees of freedom of the variance estimate per pixel (None: spp - 1,
                           a sample variance of the pixel's own samples); a frame merged from K
                           renders by their spread has K - 1 (:mod:`jaxden.data.merge`)
=========  ============  =====================================================================

Monte Carlo noise is strongly correlated across R, G and B (one path carries all three), so a
frame may carry the covariance as well as the variance: SURE then draws its probes from the
full 3 x 3 covariance (``jaxden.sure``), which a denoiser that mixes channels needs.

With ``emission`` from the same samples as the colour, ``color - emission`` is the rest of the
radiance (everything but directly seen emitters): a denoiser can filter it alone and add the
emission back (``jaxden.denoise.emission``), so bright lamps are not spread onto dark pixels.

Every field but ``color`` is optional (None). Frames are registered as JAX pytrees, so they pass
through ``jit``, ``vmap`` and ``jvp`` unchanged; construction does no checking (it must work on
tracers), and :meth:`Frame.validated` performs the user-facing checks with clear errors.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.errors import FrameError

# Field name -> EXR channel names, in order. The single source of truth for channel naming.
CHANNELS: dict[str, tuple[str, ...]] = {
    "color": ("R", "G", "B"),
    "variance": ("variance.R", "variance.G", "variance.B"),
    "albedo": ("albedo.R", "albedo.G", "albedo.B"),
    "normal": ("normal.X", "normal.Y", "normal.Z"),
    "depth": ("depth.Z",),
    "position": ("position.X", "position.Y", "position.Z"),
    "motion": ("motion.X", "motion.Y"),
    "covariance": ("covariance.RG", "covariance.GB", "covariance.BR"),
    "emission": ("emission.R", "emission.G", "emission.B"),
    "boxcox": ("boxcox.mean.R", "boxcox.mean.G", "boxcox.mean.B",
               "boxcox.m2.R", "boxcox.m2.G", "boxcox.m2.B",
               "boxcox.m3.R", "boxcox.m3.G", "boxcox.m3.B"),
}
#: The Box-Cox exponent of ``Frame.boxcox`` (StatMC's lambda).
BOXCOX_LAMBDA = 0.5
#: How a frame gets a field no renderer writes by default (said when the field is missing).
FIELD_HINTS: dict[str, str] = {
    "boxcox": "jaxden renders them with `jaxden render --statistics`, "
              "render_frame(..., statistics=True) or a dataset config with statistics = true",
}
IMAGE_FIELDS: tuple[str, ...] = tuple(CHANNELS)
NonFinitePolicy = Literal["error", "zero"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Frame:
    """A rendered frame with its auxiliary features. See the module docstring for shapes."""

    color: Any
    variance: Any = None
    albedo: Any = None
    normal: Any = None
    depth: Any = None
    position: Any = None
    motion: Any = None
    spp: Any = None
    covariance: Any = None
    emission: Any = None
    variance_dof: Any = None
    boxcox: Any = None

    # ------------------------------------------------------------------ accessors
    @property
    def shape(self) -> tuple[int, ...]:
        """(..., H, W) of the frame."""
        return tuple(np.shape(self.color)[:-1])

    @property
    def height(self) -> int:
        return self.shape[-2]

    @property
    def width(self) -> int:
        return self.shape[-1]

    def features(self) -> tuple[str, ...]:
        """Names of the image fields that are present."""
        return tuple(name for name in IMAGE_FIELDS if getattr(self, name) is not None)

    def statistics_count(self):
        """n of the ``boxcox`` statistics: ``variance_dof + 1`` where that is set (K for a
        frame merged from K renders by their spread; the pooled sample count for a frame
        pooled exactly), else ``spp``; None when neither is known. Shape (...)."""
        if self.variance_dof is not None:
            return self.variance_dof + 1
        return self.spp

    def replace(self, **changes: Any) -> Frame:
        return dataclasses.replace(self, **changes)

    def map(self, fn) -> Frame:
        """Apply ``fn`` to every present image field (not spp or variance_dof), e.g. a crop or
        a flip."""
        return self.replace(
            **{name: fn(getattr(self, name)) for name in IMAGE_FIELDS if getattr(self, name) is not None}
        )

    def crop(self, top: int, left: int, height: int, width: int) -> Frame:
        """Spatial crop [top:top+height, left:left+width] of every image field."""
        if top < 0 or left < 0 or top + height > self.height or left + width > self.width:
            raise FrameError(
                f"crop ({top}, {left}, {height}x{width}) does not fit in a frame of "
                f"{self.height}x{self.width}"
            )
        return self.map(lambda a: a[..., top : top + height, left : left + width, :])

    def is_valid_on_device(self) -> bool:
        """True when every image field is a JAX array on an accelerator
        (``DEVICE_CHECK_PLATFORMS``; on the CPU a host copy costs nothing and the jitted check
        would only add compiles), with the shapes and dtypes :meth:`validated` asks for, and its values pass every check
        of :meth:`validated` strictly (one jitted reduction, one bool to the host): the frame
        then comes back unchanged, without copying it to the host. Anything else (a NumPy
        field, a value that fails or is borderline) goes the NumPy way, which words the error
        or repairs."""
        fields = {name: getattr(self, name) for name in IMAGE_FIELDS
                  if getattr(self, name) is not None}
        if not all(isinstance(a, jax.Array) and not isinstance(a, jax.core.Tracer)
                   and all(d.platform in DEVICE_CHECK_PLATFORMS for d in a.devices())
                   for a in fields.values()):
            return False
        base = fields["color"].shape[:-1]
        for name, array in fields.items():
            if (array.ndim < 3 or array.shape[-1] != len(CHANNELS[name])
                    or array.shape[:-1] != base
                    or not jnp.issubdtype(array.dtype, jnp.floating)):
                return False
        for count in (self.spp, self.variance_dof):
            if count is not None:
                values = np.asarray(count)
                if not np.all(np.isfinite(values)) or np.any(values <= 0):
                    return False
        return bool(_fields_pass(fields))

    def numpy(self) -> Frame:
        """A copy with every field as a float32 NumPy array (for I/O)."""
        return jax.tree_util.tree_map(lambda a: np.asarray(a, dtype=np.float32), self)

    def require(self, *names: str, who: str = "this operation") -> None:
        """Raise FrameError naming the missing features if any of ``names`` is absent."""
        missing = [n for n in names if getattr(self, n) is None]
        if missing:
            channels = "; ".join(f"{n}: {'/'.join(CHANNELS[n])}" for n in missing
                                 if n in CHANNELS)
            raise FrameError(
                f"{who} needs the frame feature(s) {', '.join(missing)}"
                + (f" (EXR channels {channels})" if channels else "")
                + f", but the frame has only {', '.join(self.features())}"
                + "".join(f"; {FIELD_HINTS[n]}" for n in missing if n in FIELD_HINTS)
            )

    # ------------------------------------------------------------------ validation
    def validated(self, where: str = "frame", nonfinite: NonFinitePolicy = "error") -> Frame:
        """Check shapes and values; return the frame (repaired if ``nonfinite='zero'``).

        Checks: every present field is an array of shape (..., H, W, C) with the field's channel
        count and the colour's (..., H, W); variance, emission and boxcox's second moments
        are >= 0; all fields are
        finite; ``spp`` and ``variance_dof``, where given, are finite and > 0.
        ``emission <= color`` is not checked: it holds for jaxden's renders (the same samples),
        but not per pixel for other renderers (a clamped or differently filtered combined
        pass), and the emission-separating denoisers clamp ``color - emission`` at 0.

        ``nonfinite``: ``'error'`` (default) raises on NaN or inf anywhere. ``'zero'`` is the
        documented repair policy of the authors' pipeline: NaN and inf are replaced by 0 and
        negative variance is clipped to 0 (e.g. round-off in m2 - m1^2 of another renderer);
        it still raises on variance below -1e-6 * (1 + |colour|^2), which is not round-off but
        a wrong file. Negative emission (a pixel filter with negative lobes) is an error, or
        clipped to 0 with ``'zero'``.

        ``where`` names the source (a file path, a function) in error messages.
        """
        if nonfinite not in ("error", "zero"):
            raise FrameError(f"nonfinite policy must be 'error' or 'zero', got {nonfinite!r}")
        if self.color is None:
            raise FrameError(f"{where}: the frame has no colour")
        if self.is_valid_on_device():
            return self
        arrays: dict[str, np.ndarray] = {}
        for name in IMAGE_FIELDS:
            value = getattr(self, name)
            if value is None:
                continue
            array = np.asarray(value)
            channels = len(CHANNELS[name])
            if array.ndim < 3 or array.shape[-1] != channels:
                raise FrameError(
                    f"{where}: field '{name}' must have shape (..., H, W, {channels}), "
                    f"got {array.shape}"
                )
            if not np.issubdtype(array.dtype, np.floating):
                raise FrameError(f"{where}: field '{name}' must be floating point, got {array.dtype}")
            arrays[name] = array
        base = arrays["color"].shape[:-1]
        for name, array in arrays.items():
            if array.shape[:-1] != base:
                raise FrameError(
                    f"{where}: field '{name}' has size {array.shape[:-1]} (... H, W) but the "
                    f"colour has {base}"
                )
        repaired: dict[str, np.ndarray] = {}
        for name, array in arrays.items():
            bad = ~np.isfinite(array)
            if bad.any():
                if nonfinite == "error":
                    index = tuple(int(i) for i in np.argwhere(bad)[0])
                    raise FrameError(
                        f"{where}: field '{name}' has {int(bad.sum())} non-finite value(s) "
                        f"(first at index {index}: {array[index]}); pass nonfinite='zero' "
                        f"(CLI: --nonfinite zero) to replace them by 0"
                    )
                array = np.where(bad, 0.0, array).astype(array.dtype)
                repaired[name] = array
        if "variance" in arrays:
            variance = repaired.get("variance", arrays["variance"])
            color = repaired.get("color", arrays["color"])
            tolerance = 1e-6 * (1.0 + np.square(color))
            negative = variance < 0
            if negative.any():
                index = tuple(int(i) for i in np.argwhere(negative)[0])
                if nonfinite == "error" or (variance < -tolerance).any():
                    raise FrameError(
                        f"{where}: variance must be >= 0 but {int(negative.sum())} value(s) are "
                        f"negative (first at index {index}: {variance[index]:.6g})"
                        + ("; pass nonfinite='zero' (CLI: --nonfinite zero) to clip round-off"
                           if nonfinite == "error" else "")
                    )
                repaired["variance"] = np.maximum(variance, 0.0).astype(variance.dtype)
        if "emission" in arrays:
            emission = repaired.get("emission", arrays["emission"])
            negative = emission < 0
            if negative.any():
                index = tuple(int(i) for i in np.argwhere(negative)[0])
                if nonfinite == "error":
                    raise FrameError(
                        f"{where}: emission (emitted radiance) must be >= 0 but "
                        f"{int(negative.sum())} value(s) are negative (first at index {index}: "
                        f"{emission[index]:.6g}); pass nonfinite='zero' (CLI: --nonfinite zero) "
                        f"to clip them to 0")
                repaired["emission"] = np.maximum(emission, 0.0).astype(emission.dtype)
        if "boxcox" in arrays:
            statistics = repaired.get("boxcox", arrays["boxcox"])
            second = statistics[..., 3:6]
            tolerance = 1e-5 * (1.0 + np.square(statistics[..., 0:3]))
            if (second < -tolerance).any() or (nonfinite == "error" and (second < 0).any()):
                index = tuple(int(i) for i in np.argwhere(second < 0)[0])
                raise FrameError(
                    f"{where}: boxcox's second central moments (boxcox.m2.R/G/B) must be >= 0 "
                    f"but {int((second < 0).sum())} value(s) are negative (first at index "
                    f"{index}: {second[index]:.6g})"
                    + ("; pass nonfinite='zero' (CLI: --nonfinite zero) to clip round-off"
                       if nonfinite == "error" else ""))
            if (second < 0).any():
                repaired["boxcox"] = np.concatenate(
                    [statistics[..., 0:3], np.maximum(second, 0.0), statistics[..., 6:9]],
                    axis=-1).astype(statistics.dtype)
        if "covariance" in arrays:
            repaired.update(_checked_covariance(
                repaired.get("covariance", arrays["covariance"]),
                repaired.get("variance", arrays.get("variance")), where, nonfinite))
        for name in ("spp", "variance_dof"):
            count = getattr(self, name)
            if count is not None:
                values = np.asarray(count)
                if not np.all(np.isfinite(values)) or np.any(values <= 0):
                    raise FrameError(f"{where}: {name} must be > 0, got {values}")
        return self.replace(**repaired) if repaired else self


#: Platforms whose arrays :meth:`Frame.validated` checks where they are (no host copy).
DEVICE_CHECK_PLATFORMS = ("gpu", "cuda", "rocm", "tpu")


@jax.jit
def _fields_pass(fields: dict) -> jax.Array:
    """The value checks of :meth:`Frame.validated`, strictly (no repair would change a value):
    every field finite, variance and emission >= 0, |covariance| within (1 - 1e-5) of
    sqrt(var_a var_b)."""
    ok = jnp.array(True)
    for array in fields.values():
        ok &= jnp.all(jnp.isfinite(array))
    for name in ("variance", "emission"):
        if name in fields:
            ok &= jnp.all(fields[name] >= 0)
    if "boxcox" in fields:
        ok &= jnp.all(fields["boxcox"][..., 3:6] >= 0)
    if "covariance" in fields:
        if "variance" not in fields:
            return jnp.array(False)
        variance = jnp.maximum(fields["variance"], 0.0)
        bound = jnp.sqrt(variance * jnp.roll(variance, -1, axis=-1))
        ok &= jnp.all(jnp.abs(fields["covariance"]) <= (1.0 - 1e-5) * bound)
    return ok


#: Relative slack of the Cauchy-Schwarz check |cov_ab| <= sqrt(var_a var_b): float32 files
#: and the clipping of round-off in the variance make a bound met to this much still valid.
COVARIANCE_SLACK = 1e-3


def covariance_bound(variance) -> np.ndarray:
    """sqrt(var_a var_b) for the channel pairs of ``Frame.covariance``: (R, G), (G, B), (B, R)."""
    variance = np.maximum(np.asarray(variance, np.float64), 0.0)
    return np.sqrt(variance * np.roll(variance, -1, axis=-1))


def _checked_covariance(covariance, variance, where: str, nonfinite: str) -> dict:
    """The covariance checked against the variance (Cauchy-Schwarz): {} when it holds, the
    clipped covariance when it fails by round-off only and ``nonfinite='zero'``."""
    if variance is None:
        raise FrameError(f"{where}: field 'covariance' needs the variance (the 3 x 3 covariance "
                         f"of the pixel mean has the variance on its diagonal)")
    bound = covariance_bound(variance)
    excess = np.abs(np.asarray(covariance, np.float64)) - bound
    slack = COVARIANCE_SLACK * bound + 1e-12
    over = excess > slack
    if over.any():
        index = tuple(int(i) for i in np.argwhere(over)[0])
        pair = ("R, G", "G, B", "B, R")[index[-1]]
        raise FrameError(
            f"{where}: covariance is not a covariance of the variance given: |cov({pair})| > "
            f"sqrt(var var) at {int(over.sum())} value(s) (first at index {index}: "
            f"{float(np.asarray(covariance)[index]):.6g}, bound {bound[index]:.6g}); are "
            f"covariance.RG/GB/BR and variance.R/G/B of the same render and both of the mean?")
    if nonfinite == "zero" and (excess > 0).any():
        dtype = np.asarray(covariance).dtype
        return {"covariance": np.clip(covariance, -bound, bound).astype(dtype)}
    return {}


def stack(frames: list[Frame]) -> Frame:
    """Stack frames with the same features into a batched frame (new leading axis)."""
    if not frames:
        raise FrameError("cannot stack an empty list of frames")
    features = frames[0].features()
    for i, frame in enumerate(frames):
        if frame.features() != features:
            raise FrameError(
                f"cannot stack frames with different features: frame 0 has {features}, "
                f"frame {i} has {frame.features()}"
            )
    for name in ("spp", "variance_dof"):
        given = getattr(frames[0], name) is not None
        if any((getattr(f, name) is not None) != given for f in frames):
            raise FrameError(f"cannot stack frames where only some have {name}")
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *frames)
