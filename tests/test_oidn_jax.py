"""OIDN as a JAX function: Intel's weights read from the installed library, and the output
against pyoidn's own (float32 rounding, about 1e-6 relative RMSE, is the target; 2e-5 the
tolerance) at odd sizes, for the filter configurations jaxden uses (every quality with
--runslow)."""

import struct

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.denoise.oidn_jax import blob_name, load_oidn, oidn_denoise, pu_forward, pu_inverse
from jaxden.denoise.oidn_weights import TZA_MAGIC, find_library, load_blobs, parse_tza
from jaxden.errors import CheckpointError

pyoidn = pytest.importorskip("pyoidn")
TOLERANCE = 2e-5


@pytest.fixture(scope="module")
def blobs():
    return load_blobs()


def _scene(height, width, seed=0):
    """A noisy HDR image with features: smooth gradients, a bright spot, noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    base = np.stack([0.2 + xx, 0.3 + yy, 0.5 + 0 * xx], -1)
    color = base * rng.gamma(2.0, 0.5, (height, width, 3))
    color[height // 3, width // 2] = 40.0
    albedo = np.clip(base / 1.5, 0, 1)
    normal = np.stack([xx - 0.5, yy - 0.5, np.ones_like(xx)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return (color.astype(np.float32), albedo.astype(np.float32), normal.astype(np.float32))


def _relative_rmse(x, y):
    return float(np.sqrt(np.mean((x - y) ** 2) / np.mean(y ** 2)))


def _against_pyoidn(blobs, albedo, normal, clean, quality, size):
    color, alb, nrm = _scene(*size)
    params, spec = load_oidn(albedo=albedo, normal=normal, clean_aux=clean, quality=quality,
                             blobs=blobs)
    ours = np.asarray(oidn_denoise(params, spec, color, alb if albedo else None,
                                   nrm if normal else None))
    theirs = pyoidn.denoise(color, alb if albedo else None, nrm if normal else None, hdr=True,
                            clean_aux=clean, quality=quality)
    return _relative_rmse(ours, theirs), spec


def test_reader_finds_every_blob_jaxden_uses(blobs):
    for name in ("rt_hdr", "rt_hdr_alb", "rt_hdr_calb_cnrm_large", "rt_hdr_alb_nrm"):
        assert name in blobs
    assert blobs["rt_hdr"]["enc_conv0.weight"].shape == (32, 3, 3, 3)
    assert blobs["rt_hdr_calb_cnrm_large"]["enc_conv1a.weight"].shape == (64, 9, 3, 3)


def test_corrupt_blobs_are_refused():
    """A toy TZA blob: header (12 bytes), a table of one tensor 'w' (22 bytes), its 4 fp16
    values at offset 34."""
    table = (struct.pack("<IH", 1, 1) + b"w" + struct.pack("<BI", 1, 4) + b"xh"
             + struct.pack("<Q", 34))
    blob = struct.pack("<HBBQ", TZA_MAGIC, 2, 0, 12) + table + np.arange(4, dtype="<f2").tobytes()
    np.testing.assert_array_equal(parse_tza(blob, "toy")["w"], [0, 1, 2, 3])
    with pytest.raises(CheckpointError, match="runs outside the blob"):
        parse_tza(blob[:-2], "toy")
    with pytest.raises(CheckpointError, match="not a TZA 2.x blob"):
        parse_tza(b"\0\0" + blob[2:], "toy")
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        parse_tza(blob[:20], "toy")


def test_a_file_that_is_no_library_is_one_error(tmp_path):
    fake = tmp_path / "libOpenImageDenoise_core.so"
    fake.write_bytes(b"not an ELF file at all")
    with pytest.raises(CheckpointError, match="not a 64-bit little-endian ELF"):
        load_blobs(fake)
    assert find_library().is_file()


def test_weights_choice_follows_oidn(blobs):
    assert blob_name(False, False, False, "high", blobs) == "rt_hdr"
    assert blob_name(True, True, True, "high", blobs) == "rt_hdr_calb_cnrm_large"
    assert blob_name(True, True, False, "high", blobs) == "rt_hdr_alb_nrm"
    assert blob_name(True, False, True, "fast", blobs) == "rt_hdr_alb_small"
    assert blob_name(True, True, True, "balanced", blobs) == "rt_hdr_calb_cnrm"


def test_transfer_function_round_trips():
    y = jnp.asarray(np.geomspace(1e-8, 6e4, 200), jnp.float32)
    np.testing.assert_allclose(pu_inverse(pu_forward(y)), y, rtol=2e-5)


def test_bit_close_to_pyoidn_with_clean_features(blobs):
    """jaxden's default OIDN call (albedo + normal, clean) at an odd size: the large net."""
    error, spec = _against_pyoidn(blobs, True, True, True, "high", (37, 23))
    assert spec.blob == "rt_hdr_calb_cnrm_large" and error < TOLERANCE


@pytest.mark.slow
@pytest.mark.parametrize("quality", ["high", "balanced", "fast"])
@pytest.mark.parametrize("albedo, normal, clean", [(False, False, False), (True, False, False),
                                                   (True, True, True), (True, True, False)])
@pytest.mark.parametrize("size", [(61, 47), (16, 16), (9, 130)])
def test_bit_close_to_pyoidn_everywhere(blobs, quality, albedo, normal, clean, size):
    error, _ = _against_pyoidn(blobs, albedo, normal, clean, quality, size)
    assert error < TOLERANCE


@pytest.mark.slow  # ~6 s (two compiles of the base net and its jvp)
def test_differentiable_and_batched(blobs):
    """jvp through OIDN matches a central finite difference along a relative perturbation
    (measured 0.75 % apart at step 1e-3: larger steps cross ReLU kinks, smaller ones drown in
    float32 rounding; tolerance 2 %), and a batch equals its images."""
    params, spec = load_oidn(blobs=blobs)
    color = _scene(16, 16, seed=1)[0]
    direction = np.random.default_rng(2).standard_normal(color.shape).astype(np.float32) * color

    def f(c):
        return oidn_denoise(params, spec, c, input_scale=1.0)

    _, tangent = jax.jvp(f, (jnp.asarray(color),), (jnp.asarray(direction),))
    eps = 1e-3
    fd = (f(color + eps * direction) - f(color - eps * direction)) / (2 * eps)
    assert _relative_rmse(np.asarray(tangent), np.asarray(fd)) < 0.02
    batch = np.stack([color, 2 * color])
    np.testing.assert_allclose(oidn_denoise(params, spec, batch)[1],
                               oidn_denoise(params, spec, 2 * color), rtol=1e-5, atol=1e-6)


def test_weight_gradients_match_finite_differences(blobs):
    """What fine-tuning OIDN takes: the gradient of an L1 loss in the weights, along a random
    direction in every tensor and in one decoder conv alone, against a central finite
    difference of the same float32 forward at a step of 1e-4 of each tensor's spread (larger
    steps cross ReLU kinks, smaller ones drown in float32 rounding; measured 0.2 % apart over
    every tensor; tolerance 1 %)."""
    params, spec = load_oidn(blobs=blobs)
    color = _scene(16, 16, seed=3)[0]
    target = _scene(16, 16, seed=4)[0]

    def loss(p):
        return jnp.mean(jnp.abs(oidn_denoise(p, spec, color, input_scale=1.0) - target))

    grads = jax.tree_util.tree_leaves(jax.grad(loss)(params))
    leaves, tree = jax.tree_util.tree_flatten(params)
    names = [jax.tree_util.keystr(path) for path, _ in jax.tree_util.tree_leaves_with_path(params)]
    one = next(i for i, name in enumerate(names) if "dec_conv1" in name and "kernel" in name)
    rng = np.random.default_rng(5)
    for only in (None, one):
        step = [rng.standard_normal(np.shape(leaf)).astype(np.float32) * 1e-4
                * float(np.std(leaf) or 1.0) if only in (None, i) else np.zeros_like(leaf)
                for i, leaf in enumerate(leaves)]
        along = sum(float(np.vdot(g, d)) for g, d in zip(grads, step))
        shifted = [jax.tree_util.tree_unflatten(tree, [leaf + sign * d for leaf, d in
                                                       zip(leaves, step)]) for sign in (1, -1)]
        fd = (float(loss(shifted[0])) - float(loss(shifted[1]))) / 2
        assert abs(along - fd) <= 1e-2 * abs(fd), (names[one] if only else "all", along, fd)


@pytest.mark.slow  # ~5 s; the bit-closeness test in the default suite catches a mis-mapping
def test_a_weight_on_the_wrong_layer_shows(blobs):
    """Two layers of one shape swapped (enc_conv5b and dec_conv3b of rt_hdr, both 96 x 96 x
    3 x 3) move the output far beyond the tolerance: the test above would catch a mis-mapping."""
    color = _scene(20, 18, seed=3)[0]
    params, spec = load_oidn(blobs=blobs)
    swapped = {"params": dict(params["params"])}
    inner = swapped["params"]
    inner["enc_conv5b"], inner["dec_conv3b"] = inner["dec_conv3b"], inner["enc_conv5b"]
    good = np.asarray(oidn_denoise(params, spec, color))
    bad = np.asarray(oidn_denoise(swapped, spec, color))
    assert _relative_rmse(bad, good) > 100 * TOLERANCE


def test_registered_and_loaded_by_name():
    """`--denoiser oidn-jax`: Intel's weights by name, differentiable (SURE takes its jvp),
    the features its config names required; the same output as the function."""
    from jaxden.denoise.registry import load_denoiser
    from jaxden.frame import Frame

    denoiser = load_denoiser("oidn-jax")
    assert denoiser.differentiable and denoiser.definition.required(denoiser.config) == (
        "color", "albedo", "normal")
    color, albedo, normal = _scene(20, 18, seed=4)
    frame = Frame(color=color, albedo=albedo, normal=normal)
    params, spec = load_oidn(albedo=True, normal=True, clean_aux=True)
    np.testing.assert_allclose(np.asarray(denoiser(frame)),
                               np.asarray(oidn_denoise(params, spec, color, albedo, normal)),
                               rtol=2e-5, atol=1e-6)  # two jit fusions: float32 rounding


def test_unknown_names_list_shipped_models_and_suggest():
    from jaxden.denoise.registry import load_denoiser

    with pytest.raises(CheckpointError, match=r"did you mean 'wskp-6'.*by name: .*wskp-6.*"
                                              r"oidn-jax.*; architectures .*wskp_mr"):
        load_denoiser("wskp6")
    with pytest.raises(CheckpointError, match="runs/wskp: no such file or folder"):
        load_denoiser("runs/wskp")


@pytest.mark.slow  # OIDN's U-Net at 288 x 256, whole and over tiles: ~30 s here
def test_over_tiles_equals_the_whole_frame():
    """OIDN in JAX over tiles (the large net's field, 123 px, on its 16-pixel grid; the
    frame's auto-exposure held constant) equals the whole frame."""
    from jaxden.denoise.registry import load_denoiser
    from jaxden.denoise.tiled import denoise_frame
    from jaxden.render.synthetic import synthetic_render

    frame = synthetic_render("oidn-tiles", 4, seed=2, size=(288, 256))
    denoiser = load_denoiser("oidn-jax")
    assert denoiser.tile_spec().radius == 123 and denoiser.tile_spec().multiple == 16
    whole, _ = denoise_frame(denoiser, frame, tile=0)
    tiled, plan = denoise_frame(denoiser, frame, tile=48)
    assert plan.tile == 48
    relative = np.sqrt(np.mean((tiled - whole) ** 2) / np.mean(whole ** 2))
    assert relative < 1e-5, relative


# ------------------------------------------------------------------------------ OIDN's tiles
def test_tile_grid_follows_oidn_by_hand():
    """OIDN 2's tile loop (UNetFilter::init) worked by hand. 4000 x 1300, large net: overlap
    round_up(202 / 2, 16) = 112; 1312 x 4000 padded > 2160^2, so the wider side shrinks to
    round_up(ceil((4000 + 224) / 2), 16) = 2112, count ceil((4000 - 224) / (2112 - 224)) = 2;
    1312 x 2112 fits. 3010 x 1600, base net: overlap 96; columns to round_up(ceil(3202 / 2),
    16) = 1616, count ceil(2818 / 1424) = 2; the last tile (1586 wide) sits 1616 -
    round_up(1586, 16) = 16 pixels from its buffer's left edge."""
    from jaxden.denoise.oidn_jax import AxisTile, oidn_tile_plan

    plan = oidn_tile_plan(1300, 4000, "large")
    assert plan.tile == (1312, 2112) and plan.overlap == 112 and plan.count == 2
    assert plan.rows == (AxisTile(0, 1300, 0, 0, 1300),)
    assert plan.columns == (AxisTile(0, 2112, 0, 0, 2000), AxisTile(1888, 2112, 0, 112, 2000))
    plan = oidn_tile_plan(1600, 3010, "base")
    assert plan.tile == (1600, 1616) and plan.overlap == 96
    assert plan.columns == (AxisTile(0, 1616, 0, 0, 1520), AxisTile(1424, 1586, 16, 96, 1490))
    # The threshold: 2160 x 2160 padded pixels run whole, one more column of 16 does not.
    assert oidn_tile_plan(2160, 2160).count == 1 and oidn_tile_plan(2160, 2161).count == 2
    # Every tiling covers its frame once: the kept parts abut and sum to the frame.
    for height, width, size in ((4320, 7680, "large"), (777, 9000, "base"), (5000, 800, "base")):
        plan = oidn_tile_plan(height, width, size)
        assert plan.tile[0] * plan.tile[1] <= 2160 * 2160
        for length, tiles in ((height, plan.rows), (width, plan.columns)):
            assert [t.start + t.begin for t in tiles] == [0] + [
                t.start + t.begin + t.keep for t in tiles[:-1]]
            assert sum(t.keep for t in tiles) == length


@pytest.mark.slow  # a 2176 x 2160 frame through the base net, pyoidn and ours: ~1-2 min here
def test_tiled_like_pyoidn_above_its_threshold(blobs):
    """Above 2160^2 padded pixels OIDN tiles (here 2 x 1 tiles of 2160 x 1184, overlap 96):
    over the same tiles OIDN in JAX matches pyoidn as on small frames (a tile misplaced or
    cropped wrongly moves whole bands of pixels). Peak memory about 4 GB."""
    from jaxden.denoise.oidn_jax import oidn_tile_plan

    color = np.tile(_scene(540, 544, seed=5)[0], (4, 4, 1))
    params, spec = load_oidn(blobs=blobs)  # rt_hdr: the base net
    assert oidn_tile_plan(*color.shape[:2], spec.size).count == 2
    theirs = pyoidn.denoise(color, hdr=True, quality="high")
    tiled = np.asarray(oidn_denoise(params, spec, color))
    assert _relative_rmse(tiled, theirs) < TOLERANCE


# ------------------------------------------------------------------------- options, precision
def test_spec_options_choose_oidns_network():
    """`oidn-jax:KEY=VALUE,...` sets the inputs, the features' cleanliness, the quality, the
    precision and the tiling; `oidn` takes the same inputs, clean_aux and quality."""
    from jaxden.denoise.registry import load_denoiser

    denoiser = load_denoiser("oidn-jax:aux=albedo,clean_aux=no,quality=fast,precision=bfloat16")
    config = denoiser.config
    assert (config.use_albedo, config.use_normal, config.clean_aux, config.quality,
            config.precision, config.tiling) == (True, False, False, "fast", "bfloat16", "oidn")
    assert denoiser.definition.required(config) == ("color", "albedo")
    assert denoiser.params["params"]["enc_conv0"]["kernel"].shape == (3, 3, 6, 32)  # _small: 6 in
    colour_only = load_denoiser("oidn-jax:aux=none,tiling=off")
    assert colour_only.definition.required(colour_only.config) == ("color",)
    assert colour_only.params["params"]["enc_conv0"]["kernel"].shape[2] == 3
    black_box = load_denoiser("oidn:aux=albedo,clean_aux=auto,quality=balanced")
    assert (black_box.config.use_albedo, black_box.config.use_normal, black_box.config.clean_aux,
            black_box.config.quality) == (True, False, "auto", "balanced")
    assert load_denoiser("oidn-jax:emission=separate,quality=balanced").config.quality == \
        "balanced"


@pytest.mark.parametrize("spec, message", [
    ("oidn-jax:qualty=fast", ("with KEY one of emission, aux, clean_aux, quality, precision, "
                              "tiling, got 'qualty=fast'")),
    ("oidn-jax:precision=float16", "precision must be one of float32, bfloat16, got 'float16'"),
    ("oidn-jax:aux=normal", "aux must be one of albedo\\+normal, albedo, none, got 'normal'"),
    ("oidn:precision=bfloat16", ("with KEY one of emission, aux, clean_aux, quality, got "
                                 "'precision=bfloat16'")),
])
def test_wrong_spec_options_are_one_line_listing_the_valid_ones(spec, message):
    from jaxden.denoise.registry import load_denoiser
    from jaxden.errors import ConfigError

    with pytest.raises(ConfigError, match=message) as caught:
        load_denoiser(spec)
    assert "\n" not in str(caught.value)


def test_bfloat16_close_to_float32(blobs):
    """precision=bfloat16 (8-bit mantissa: 2e-3 relative rounding per operation, through 19
    layers and OIDN's inverse transfer) against pyoidn's float32 output, jaxden's default
    network (albedo + normal, clean, large) at 37 x 23: measured 8e-3 relative RMSE (the base
    net 1.2e-2) at 16 x 16 to 96 x 64 here; tolerance 3e-2. It does differ (more than 1e-4,
    against 4e-6 in float32: the network ran in bfloat16) and returns float32."""
    params, spec = load_oidn(albedo=True, normal=True, clean_aux=True, blobs=blobs)
    color, albedo, normal = _scene(37, 23, seed=6)
    theirs = pyoidn.denoise(color, albedo, normal, hdr=True, clean_aux=True, quality="high")
    half = oidn_denoise(params, spec, color, albedo, normal, precision="bfloat16")
    assert half.dtype == jnp.float32
    assert 1e-4 < _relative_rmse(np.asarray(half), theirs) < 3e-2
