"""Intel Open Image Denoise as a pure JAX function, with Intel's own weights
(:mod:`jaxden.denoise.oidn_weights`): differentiable, jittable, batched, on any XLA device.

    params, spec = load_oidn(albedo=True, normal=True, clean_aux=True, quality="high")
    y = oidn_denoise(params, spec, color, albedo, normal)        # (..., H, W, 3)

What OIDN 2.5's ``RT`` filter does with ``hdr=True`` (read from its source; checked against
pyoidn on this CPU, tests/test_oidn_jax.py):
- **which weights**: colour only ``rt_hdr``, with albedo ``rt_hdr_alb``, with albedo and normal
  ``rt_hdr_calb_cnrm`` when the features are clean (``clean_aux``), else ``rt_hdr_alb_nrm``;
  quality ``high`` takes the ``_large`` blob where one exists, ``fast`` the ``_small`` one;
- **input scale** (auto-exposure, unless ``input_scale`` is given): the image in bins of
  ceil(H / 16) x ceil(W / 16), per bin the mean luminance (0.212671 R + 0.715160 G + 0.072169
  B, NaN as 0, clamped at 0), the mean of log2 over bins brighter than 1e-8, scale 0.18 / 2^mean
  (1 when no bin is);
- **transfer**: colour times the scale through the perceptual-uniform curve PU, normalised by
  PU(65504); albedo clamped to [0, 1]; normal clamped to [-1, 1] and mapped to n / 2 + 1/2;
  NaN as 0 everywhere;
- **padding**: to multiples of 16 at the bottom and right, zeros in the transformed domain;
- **output**: clamped at 0, the inverse transfer, divided by the scale, cropped;
- **tiles** (:func:`oidn_tile_plan`): above 2160^2 padded pixels OIDN splits the frame into
  overlapping tiles of a bounded buffer size, run one after another; ``tiling="oidn"`` (the
  default) does the same; ``tiling="off"`` runs the whole frame at once. The overlap (96 / 112
  pixels) covers the networks' field, so the two agree: at 4000 x 1300, bit for bit on the
  base network, and both 3.3e-6 relative RMSE from pyoidn on the large one. The tiles bound
  the memory (large network, float32, CPU: about 7 GB for its 1312 x 2112 tile there).

``precision="bfloat16"`` runs the network's convolutions, pools and skips in bfloat16 (inputs,
transfer functions and outputs stay float32): meant for accelerators with bfloat16 units; on
the CPU it runs at about float32's speed. Measured 8e-3 (large network) to 1.3e-2 (base)
relative RMSE from float32.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

from jaxden.denoise.nn.oidn_net import RECEPTIVE_FIELD, OIDNUNet, layers_of
from jaxden.errors import ConfigError, FrameError

QUALITIES = ("high", "balanced", "fast")
PRECISIONS = ("float32", "bfloat16")
#: ``tiling``: "oidn" tiles as OIDN does above its threshold; "off" always runs whole frames.
TILINGS = ("oidn", "off")
#: The auxiliary inputs, as spec values: (albedo, normal).
AUX_INPUTS = {"albedo+normal": (True, True), "albedo": (True, False), "none": (False, False)}
# The perceptual-uniform (PU) curve of OIDN's HDR transfer function.
_PU_A, _PU_B, _PU_C, _PU_D = 1.41283765e3, 1.64593172, 4.31384981e-1, -2.94139609e-3
_PU_E, _PU_F, _PU_G = 1.92653254e-1, 6.26026094e-3, 9.98620152e-1
_PU_Y0, _PU_Y1 = 1.57945760e-06, 3.22087631e-02  # breaks of the forward curve
_PU_X0, _PU_X1 = 2.23151711e-03, 3.70974749e-01  # and of its inverse
HDR_MAX = 65504.0
LUMINANCE = (0.212671, 0.715160, 0.072169)


def pu_forward(y):
    y = jnp.asarray(y)
    return jnp.where(y <= _PU_Y0, _PU_A * y,
                     jnp.where(y <= _PU_Y1, _PU_B * jnp.power(jnp.maximum(y, 0.0), _PU_C) + _PU_D,
                               _PU_E * jnp.log(y + _PU_F) + _PU_G))


def pu_inverse(x):
    x = jnp.asarray(x)
    return jnp.where(x <= _PU_X0, x / _PU_A,
                     jnp.where(x <= _PU_X1,
                               jnp.power(jnp.maximum((x - _PU_D) / _PU_B, 0.0), 1.0 / _PU_C),
                               jnp.exp((x - _PU_G) / _PU_E) - _PU_F))


@functools.cache
def pu_norm() -> float:
    """pu_forward(HDR_MAX), OIDN's normalisation of the PU curve; computed on first use, not
    at import (that would start JAX's backend before ``jax.distributed`` may initialise)."""
    with jax.ensure_compile_time_eval():  # also when first called inside a trace
        return float(pu_forward(np.float32(HDR_MAX)))


@dataclasses.dataclass(frozen=True)
class OIDNSpec:
    """Which of OIDN's networks and inputs: the blob, its size and layer widths."""

    blob: str
    size: str  # "base" or "large"
    widths: tuple[int, ...]
    albedo: bool
    normal: bool


def blob_name(albedo: bool, normal: bool, clean_aux: bool, quality: str,
              available) -> str:
    """OIDN's choice of weights for an HDR ``RT`` filter with these inputs."""
    if quality not in QUALITIES:
        raise ConfigError(f"OIDN quality must be one of {', '.join(QUALITIES)}, got {quality!r}")
    if normal and not albedo:
        raise ConfigError("OIDN takes a normal only together with an albedo")
    base = "rt_hdr" + ("" if not albedo else "_calb_cnrm" if normal and clean_aux
                       else "_alb_nrm" if normal else "_alb")
    suffix = {"high": "_large", "fast": "_small"}.get(quality)
    return base + suffix if suffix and base + suffix in available else base


def load_oidn(*, albedo: bool = False, normal: bool = False, clean_aux: bool = False,
              quality: str = "high", blobs=None):
    """``(params, spec)`` of OIDN's network for these inputs, from the installed library's
    weights (``blobs``: :func:`jaxden.denoise.oidn_weights.load_blobs`, loaded when None)."""
    from jaxden.denoise.oidn_weights import load_blobs

    blobs = load_blobs() if blobs is None else blobs
    name = blob_name(albedo, normal, clean_aux, quality, blobs)
    tensors = blobs[name]
    size = "large" if "enc_conv1a.weight" in tensors else "base"
    layers = layers_of(size)
    missing = [layer for layer, _ in layers if f"{layer}.weight" not in tensors]
    if missing:
        raise ConfigError(f"OIDN weights {name}: no tensors for {', '.join(missing)}")
    params = {layer: {"kernel": jnp.asarray(np.transpose(tensors[f"{layer}.weight"],
                                                         (2, 3, 1, 0))),  # oihw -> hwio
                      "bias": jnp.asarray(tensors[f"{layer}.bias"])}
              for layer, _ in layers}
    widths = tuple(int(tensors[f"{layer}.bias"].shape[0]) for layer, _ in layers)
    channels = tensors[f"{layers[0][0]}.weight"].shape[1]
    expected = 3 * (1 + albedo + normal)
    if channels != expected:
        raise ConfigError(f"OIDN weights {name} take {channels} input channels, not {expected}")
    return {"params": params}, OIDNSpec(name, size, widths, albedo, normal)


def _bin_matrix(length: int) -> np.ndarray:
    """(bins, length) 0/1 matrix of OIDN's auto-exposure bins along one axis."""
    bins = max(1, math.ceil(length / 16))
    matrix = np.zeros((bins, length), np.float32)
    for i in range(bins):
        matrix[i, i * length // bins:(i + 1) * length // bins] = 1.0
    return matrix


def auto_exposure(color):
    """OIDN's input scale of one image (H, W, 3) (see the module docstring)."""
    height, width = color.shape[-3:-1]
    rows, cols = _bin_matrix(height), _bin_matrix(width)
    clean = jnp.maximum(jnp.nan_to_num(color, nan=0.0), 0.0)
    luminance = clean @ jnp.asarray(LUMINANCE, color.dtype)
    sums = jnp.asarray(rows) @ luminance @ jnp.asarray(cols).T
    counts = np.outer(rows.sum(1), cols.sum(1))
    mean = sums / counts
    valid = mean > 1e-8
    log_mean = jnp.sum(jnp.where(valid, jnp.log2(jnp.where(valid, mean, 1.0)), 0.0)) / \
        jnp.maximum(jnp.sum(valid), 1)
    return jnp.where(jnp.any(valid), 0.18 / jnp.exp2(log_mean), 1.0)


def _round_up(n: int, multiple: int = 16) -> int:
    return (n + multiple - 1) // multiple * multiple


# ------------------------------------------------------------------------------ OIDN's tiles
#: OIDN's largest tile buffer with its default memory settings (pixels), its tile alignment
#: on the CPU (pixels; the pooling grid) and its smallest tile side (pixels).
OIDN_MAX_TILE_PIXELS = 2160 * 2160
OIDN_TILE_ALIGNMENT = 16
OIDN_MIN_TILE_SIDE = 768


@dataclasses.dataclass(frozen=True)
class AxisTile:
    """One tile along one axis: it reads ``[start, start + size)`` of the frame into its
    buffer at ``offset`` (zeros before and after) and writes ``[start + begin, start + begin
    + keep)``, read from buffer position ``offset + begin``."""

    start: int
    size: int
    offset: int
    begin: int
    keep: int


@dataclasses.dataclass(frozen=True)
class OIDNTilePlan:
    """OIDN's tiles of an H x W frame: buffers of ``tile`` = (rows, columns) pixels, multiples
    of 16, on a grid of ``rows`` x ``columns`` (:class:`AxisTile` each) with ``overlap``
    pixels between neighbours on each side. One tile: the whole frame, padded."""

    tile: tuple[int, int]
    overlap: int
    rows: tuple[AxisTile, ...]
    columns: tuple[AxisTile, ...]

    @property
    def count(self) -> int:
        return len(self.rows) * len(self.columns)


def _axis_tiles(length: int, tile: int, count: int, overlap: int) -> tuple[AxisTile, ...]:
    step = tile - 2 * overlap
    tiles = []
    for i in range(count):
        start = i * step
        begin = overlap if i > 0 else 0
        end = overlap if i < count - 1 else 0
        size = min(length - start, tile)
        # A short last tile sits at the bottom (right) of its buffer, on the 16-pixel grid.
        tiles.append(AxisTile(start, size, tile - _round_up(size, OIDN_TILE_ALIGNMENT), begin,
                              size - begin - end))
    return tuple(tiles)


def oidn_tile_plan(height: int, width: int, size: str = "large", *,
                   max_tile_pixels: int = OIDN_MAX_TILE_PIXELS) -> OIDNTilePlan:
    """OIDN 2's tiles (``UNetFilter::init``, one CPU device, no ``maxMemoryMB``) of an
    ``height`` x ``width`` frame for its ``size`` ("base" or "large") U-Net.

    The overlap is half the receptive field rounded up to 16 (96 base, 112 large); the buffer
    starts as the frame padded to multiples of 16; while it holds more than
    ``max_tile_pixels``, the longer side (the columns on a tie), if above the smallest side
    max(4 overlap, 768), shrinks to ceil((length + 2 overlap n) / (n + 1)) rounded up to 16,
    n the tiles along it so far (by 16 at least, never below the smallest side), and the
    count along it becomes max(ceil((length - 2 overlap) / (tile - 2 overlap)), 1); the loop
    stops when neither side may shrink. Tile i starts at i (tile - 2 overlap) and keeps all
    but ``overlap`` pixels on each side that has a neighbour."""
    if height < 1 or width < 1:
        raise FrameError(f"OIDN's tiles need a frame of at least 1 x 1 pixels, got "
                         f"{width} x {height}")
    align = OIDN_TILE_ALIGNMENT
    overlap = _round_up(RECEPTIVE_FIELD[size] // 2, align)
    smallest = _round_up(max(4 * overlap, OIDN_MIN_TILE_SIDE), align)
    tile = [_round_up(height, align), _round_up(width, align)]
    count = [1, 1]
    lengths = (height, width)
    while tile[0] * tile[1] > max_tile_pixels:
        if tile[0] > smallest and tile[0] > tile[1]:
            axis = 0
        elif tile[1] > smallest:
            axis = 1
        else:
            break
        length, halo = lengths[axis], 2 * overlap
        wanted = -(-(length + halo * count[axis]) // (count[axis] + 1))
        tile[axis] = min(max(_round_up(wanted, align), smallest), tile[axis] - align)
        count[axis] = max(-(-(length - halo) // (tile[axis] - halo)), 1)
    return OIDNTilePlan((tile[0], tile[1]), overlap,
                        _axis_tiles(height, tile[0], count[0], overlap),
                        _axis_tiles(width, tile[1], count[1], overlap))


def _run_tiled(net, params, inputs, plan: OIDNTilePlan):
    """The network over OIDN's tiles of ``inputs`` (H, W, C), already transferred: each tile
    in its zero-padded buffer, one after another (``lax.map``), its kept part put in place."""
    rows, cols = plan.tile
    buffers = jnp.stack([
        jnp.pad(inputs[r.start:r.start + r.size, c.start:c.start + c.size],
                ((r.offset, rows - r.offset - r.size), (c.offset, cols - c.offset - c.size),
                 (0, 0)))
        for r in plan.rows for c in plan.columns])
    outputs = jax.lax.map(lambda buffer: net.apply(params, buffer[None])[0], buffers)
    bands = []
    for i, r in enumerate(plan.rows):
        pieces = []
        for j, c in enumerate(plan.columns):
            top, left = r.offset + r.begin, c.offset + c.begin
            pieces.append(outputs[i * len(plan.columns) + j, top:top + r.keep,
                                  left:left + c.keep])
        bands.append(jnp.concatenate(pieces, axis=1))
    return jnp.concatenate(bands, axis=0)


@functools.partial(jax.jit, static_argnames=("spec", "precision", "tiling"))
def _denoise_one(params, spec: OIDNSpec, color, albedo, normal, scale, precision: str,
                 tiling: str):
    height, width = color.shape[:2]
    x = jnp.clip(jnp.nan_to_num(color * scale, nan=0.0), 0.0, np.finfo(np.float32).max)
    parts = [pu_forward(x) / pu_norm()]
    if spec.albedo:
        parts.append(jnp.clip(jnp.nan_to_num(albedo, nan=0.0), 0.0, 1.0))
    if spec.normal:
        parts.append(jnp.clip(jnp.nan_to_num(normal, nan=0.0), -1.0, 1.0) * 0.5 + 0.5)
    dtype = jnp.dtype(precision)
    inputs = jnp.concatenate(parts, axis=-1).astype(dtype)
    net = OIDNUNet(spec.size, spec.widths, dtype=dtype)
    plan = oidn_tile_plan(height, width, spec.size)
    if tiling == "oidn" and plan.count > 1:
        out = _run_tiled(net, params, inputs, plan)
    else:
        padded = jnp.pad(inputs, ((0, _round_up(height) - height),
                                  (0, _round_up(width) - width), (0, 0)))
        out = net.apply(params, padded[None])[0, :height, :width]
    out = jnp.maximum(jnp.nan_to_num(out.astype(jnp.float32), nan=0.0), 0.0)
    return pu_inverse(out * pu_norm()) / scale


def oidn_denoise(params, spec: OIDNSpec, color, albedo=None, normal=None, *, input_scale=None,
                 precision: str = "float32", tiling: str = "oidn"):
    """OIDN's HDR denoising of ``color`` (..., H, W, 3), float32, with the features ``spec``
    takes (albedo / normal of the same shape); ``input_scale`` None: OIDN's auto-exposure per
    image. ``precision``: the network's arithmetic, "float32" or "bfloat16" (the output is
    float32 either way); ``tiling``: "oidn" runs frames above OIDN's threshold over its tiles
    (:func:`oidn_tile_plan`), "off" runs every frame whole. Differentiable in every input
    (the auto-exposure scale included)."""
    if precision not in PRECISIONS:
        raise ConfigError(f"OIDN precision must be one of {', '.join(PRECISIONS)}, got "
                          f"{precision!r}")
    if tiling not in TILINGS:
        raise ConfigError(f"OIDN tiling must be one of {', '.join(TILINGS)}, got {tiling!r}")
    color = jnp.asarray(color, jnp.float32)
    if color.ndim < 3 or color.shape[-1] != 3:
        raise FrameError(f"OIDN needs colour of shape (..., H, W, 3), got {color.shape}")
    for name, wanted, value in (("albedo", spec.albedo, albedo), ("normal", spec.normal, normal)):
        if wanted and (value is None or jnp.shape(value) != color.shape):
            raise FrameError(f"OIDN weights {spec.blob} need {name} of shape {color.shape}, got "
                             f"{None if value is None else jnp.shape(value)}")
    lead = color.shape[:-3]
    flat = color.reshape((-1,) + color.shape[-3:])
    features = [None if value is None or not wanted else
                jnp.asarray(value, jnp.float32).reshape(flat.shape)
                for wanted, value in ((spec.albedo, albedo), (spec.normal, normal))]
    if input_scale is None:
        scales = jax.vmap(auto_exposure)(flat)
    else:
        scales = jnp.broadcast_to(jnp.asarray(input_scale, jnp.float32), lead).reshape(-1)
    zeros = jnp.zeros_like(flat)
    run = jax.vmap(lambda c, a, n, s: _denoise_one(params, spec, c, a, n, s, precision, tiling))
    out = run(flat, zeros if features[0] is None else features[0],
              zeros if features[1] is None else features[1], scales)
    return out.reshape(color.shape)


# ------------------------------------------------------------------------------ registration
@dataclasses.dataclass(frozen=True)
class OIDNJaxConfig:
    """OIDN in JAX with Intel's weights: which of OIDN's networks (the inputs it takes and the
    quality), chosen as OIDN chooses (:func:`blob_name`), its arithmetic (``precision``:
    float32 or bfloat16) and ``tiling`` (:func:`oidn_denoise`). Unlike the black box, which
    picks per call from the features a frame carries, the network is fixed by the config, so
    a frame must carry the features the config names (``required``)."""

    quality: str = "high"
    use_albedo: bool = True
    use_normal: bool = True
    clean_aux: bool = True
    precision: Literal["float32", "bfloat16"] = "float32"
    tiling: Literal["oidn", "off"] = "oidn"

    def __post_init__(self) -> None:
        for name, allowed in (("quality", QUALITIES), ("precision", PRECISIONS),
                              ("tiling", TILINGS)):
            if getattr(self, name) not in allowed:
                raise ConfigError(f"oidn-jax {name} must be one of {', '.join(allowed)}, got "
                                  f"{getattr(self, name)!r}")
        if self.use_normal and not self.use_albedo:
            raise ConfigError("oidn-jax: use_normal needs use_albedo (OIDN takes a normal only "
                              "together with an albedo)")


#: Spec options of ``oidn-jax`` (``oidn-jax:KEY=VALUE,...``), the first value the default.
OIDN_JAX_OPTIONS = (("aux", tuple(AUX_INPUTS)), ("clean_aux", ("yes", "no")),
                    ("quality", QUALITIES), ("precision", PRECISIONS), ("tiling", TILINGS))


def configure_oidn_jax(config: OIDNJaxConfig, options: dict[str, str]) -> OIDNJaxConfig:
    """``config`` with spec options (:data:`OIDN_JAX_OPTIONS`, values already checked)."""
    changes: dict = {key: options[key] for key in ("quality", "precision", "tiling")
                     if key in options}
    if "aux" in options:
        changes["use_albedo"], changes["use_normal"] = AUX_INPUTS[options["aux"]]
    if "clean_aux" in options:
        changes["clean_aux"] = options["clean_aux"] == "yes"
    return dataclasses.replace(config, **changes)


@functools.cache
def _weights(albedo: bool, normal: bool, clean_aux: bool, quality: str):
    return load_oidn(albedo=albedo, normal=normal, clean_aux=clean_aux, quality=quality)


def _loaded(config: OIDNJaxConfig):
    return _weights(config.use_albedo, config.use_normal, config.clean_aux, config.quality)


def oidn_jax_init(key, config: OIDNJaxConfig):
    """Intel's weights for ``config`` (``key`` is unused: they are not drawn but read)."""
    del key
    params, _ = _loaded(config)
    return jax.tree_util.tree_map(jnp.array, params)


def oidn_jax_apply(params, config: OIDNJaxConfig, frame):
    _, spec = _loaded(config)
    return oidn_denoise(params, spec, frame.color,
                        frame.albedo if config.use_albedo else None,
                        frame.normal if config.use_normal else None,
                        precision=config.precision, tiling=config.tiling)


#: OIDN's U-Nets' receptive field, pixels each side: the 3 x 3 convolutions at scales 1 to 16
#: (base: 79 pixels; large, two per encoder level: 93; :mod:`jaxden.denoise.nn.oidn_net`),
#: plus a pixel of the current scale per pool and per upsampling (15 + 15).
OIDN_RADIUS = {"base": 79 + 30, "large": 93 + 30}


def _exposure_constants(config: OIDNJaxConfig, frame):
    """The whole frame's auto-exposure (per image), held constant on its tiles."""
    color = jnp.asarray(frame.color, jnp.float32)
    flat = color.reshape((-1,) + color.shape[-3:])
    return jax.vmap(auto_exposure)(flat).reshape(color.shape[:-3])


def oidn_jax_tile_apply(packed, config: OIDNJaxConfig, frame):
    """OIDN in JAX on a tile, with the frame's input scale (see :func:`oidn_jax_tiling`)."""
    _, spec = _loaded(config)
    return oidn_denoise(packed["params"], spec, frame.color,
                        frame.albedo if config.use_albedo else None,
                        frame.normal if config.use_normal else None,
                        input_scale=packed["constants"], precision=config.precision,
                        tiling=config.tiling)


def oidn_jax_tiling(config: OIDNJaxConfig):
    """Tiles of OIDN in JAX: its U-Net's field, on its 16-pixel grid, with the whole frame's
    auto-exposure held constant. Departure: on tiles, jvp SURE leaves out the exposure's own
    derivative (a mean over the frame's 16 x 16 bins: O(1 / pixels) per pixel, below float32
    rounding on frames worth tiling)."""
    from jaxden.tiling import TileSpec

    _, spec = _loaded(config)
    return TileSpec(radius=OIDN_RADIUS["large" if spec.size == "large" else "base"],
                    multiple=16, constants=_exposure_constants, apply=oidn_jax_tile_apply)


def _register() -> None:
    from jaxden.denoise.registry import DenoiserDef, register

    register(DenoiserDef(
        name="oidn-jax",
        description="Intel Open Image Denoise 2 in JAX with Intel's weights from the installed "
                    "library (differentiable: SURE by jvp)",
        config_cls=OIDNJaxConfig,
        required=lambda config: ("color", *(("albedo",) if config.use_albedo else ()),
                                 *(("normal",) if config.use_normal else ())),
        apply=oidn_jax_apply,
        init=oidn_jax_init,
        pretrained=True,
        tiling=oidn_jax_tiling,
        options=OIDN_JAX_OPTIONS,
        configure=configure_oidn_jax,
    ))


_register()
