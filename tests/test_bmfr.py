"""BMFR (jaxden.denoise.bmfr) against slow NumPy references written from BASELINES.md 2.x.

The references loop over blocks, rows and pixels with the authors' formulas (mirrored work
area, per-block min / max scaling, the hashed feature noise, np.linalg.lstsq per block, the
bilinear reprojection with its tests, YCoCg TAA); the JAX functions must agree to round-off.
Frames are 48 x 56 (12 blocks of the work area; one wider one for tiles), so the file runs in seconds.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose

from jaxden.denoise import bmfr as B
from jaxden.denoise import load_denoiser, make_denoiser
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame

UINT_MAX = np.float32(4294967295)


# ------------------------------------------------------------------------ NumPy references
def np_hash(a):
    """Robert Jenkins' 32-bit mix, uint32 arithmetic wrapping as in C."""
    a = np.asarray(a, np.uint64) & 0xFFFFFFFF
    m = lambda v: v & 0xFFFFFFFF
    a = m(m(a + 0x7ED55D16) + m(a << 12))
    a = m((a ^ 0xC761C23C) ^ (a >> 19))
    a = m(m(a + 0x165667B1) + m(a << 5))
    a = m(m(a + 0xD3A2646C) ^ m(a << 9))
    a = m(m(a + 0xFD7046C5) + m(a << 3))
    a = m((a ^ 0xB55A4F09) ^ (a >> 16))
    return a.astype(np.float32) / UINT_MAX


def np_mirror(i, n):
    """The authors' mirror (|i| - 1 below, 2n - i - 1 above), repeated until inside."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - i - 1
    return i


def np_features(n, p):
    return np.concatenate([[1.0], n, p, p * p])


def np_scale(v, lo, hi):
    return (v - lo) / (hi - lo) if hi - lo > 1.0 else v - lo


def np_block_fit(color, normal, position, frame_index, cfg, unfit=None):
    """Per block of the shifted work area: rows from mirrored pixels, position features scaled
    by the block's min / max over its hits, hashed noise on columns 1..9, lstsq of
    [w X; sqrt(ridge) I] against [w Y; 0] (w: 0 on rows with an unfit channel); then per
    pixel its block's fit, clamped at 0, or its colour in the unfit channels."""
    h, w = color.shape[:2]
    off = B.BLOCK_OFFSETS[frame_index % 16]
    nby, nbx = -(-h // 32) + 1, -(-w // 32) + 1
    miss = np.sum(normal**2, -1) == 0
    if unfit is None:
        unfit = np.broadcast_to(miss[..., None], color.shape)
    if not cfg.pass_through:
        miss, unfit = np.zeros_like(miss), np.zeros_like(unfit)
    row, feature = np.meshgrid(np.arange(1024), np.arange(10), indexing="ij")
    u = np_hash(row + 1024 * feature + 13 * 1024 * frame_index)  # row: raster index in block
    noise = np.float32(cfg.noise_amount) * np.float32(2) * (u - np.float32(0.5))
    betas, lows, highs = {}, {}, {}
    for by in range(nby):
        for bx in range(nbx):
            rows, targets, hits, weights = [], [], [], []
            for jy in range(32):
                for jx in range(32):
                    y = np_mirror(32 * by + jy - 16 + off[1], h)
                    x = np_mirror(32 * bx + jx - 16 + off[0], w)
                    rows.append(np_features(normal[y, x], position[y, x]))
                    targets.append(color[y, x])
                    hits.append(not miss[y, x])
                    weights.append(~unfit[y, x])
            X, Y, hit, Wt = np.array(rows), np.array(targets), np.array(hits), np.array(weights)
            lo, hi = np.zeros(6), np.zeros(6)
            if hit.any():
                lo, hi = X[hit, 4:].min(0), X[hit, 4:].max(0)
            for k in range(6):
                X[:, 4 + k] = [np_scale(v, lo[k], hi[k]) for v in X[:, 4 + k]]
            X[:, 1:] += noise[:, 1:]
            used = Wt.all(-1, keepdims=True)  # a pixel with an unfit channel: out of the fit
            A = np.concatenate([X * used, np.sqrt(cfg.ridge) * np.eye(10)])
            b = np.concatenate([Y * used, np.zeros((10, 3))])
            betas[by, bx] = np.linalg.lstsq(A, b, rcond=None)[0]
            lows[by, bx], highs[by, bx] = lo, hi
    out = np.zeros_like(color)
    for y in range(h):
        for x in range(w):
            key = ((y + 16 - off[1]) // 32, (x + 16 - off[0]) // 32)
            f = np_features(normal[y, x], position[y, x])
            f[4:] = [np_scale(v, lows[key][k], highs[key][k]) for k, v in enumerate(f[4:])]
            out[y, x] = np.where(unfit[y, x], color[y, x], np.maximum(f @ betas[key], 0.0))
    return out, betas


def np_step_accumulation(illum, filtered, prev, normal, position, dark, motion, frame_number,
                         cfg):
    """accumulate_noisy_data + accumulate_filtered_data per pixel, with motion vectors in
    place of the camera matrix and jaxden's test of dark albedo channels (the same in tap and
    pixel). ``prev``: dict of the previous frame's buffers."""
    h, w = illum.shape[:2]
    noisy, count = np.zeros_like(illum), np.zeros((h, w, 1))
    acc = np.zeros_like(filtered)
    for y in range(h):
        for x in range(w):
            px, py = x + motion[y, x, 0], y + motion[y, x, 1]
            x0, y0 = int(np.floor(px)), int(np.floor(py))
            fx, fy = px - x0, py - y0
            taps = [(y0, x0, (1 - fx) * (1 - fy)), (y0, x0 + 1, fx * (1 - fy)),
                    (y0 + 1, x0, (1 - fx) * fy), (y0 + 1, x0 + 1, fx * fy)]
            alpha, spp, colour, total, kept = 1.0, 0.0, np.zeros(3), 0.0, []
            if frame_number > 0:
                for ty, tx, wt in taps:
                    if not (0 <= ty < h and 0 <= tx < w):
                        continue
                    dp = prev["position"][ty, tx] - position[y, x]
                    dn = prev["normal"][ty, tx] - normal[y, x]
                    same = np.array_equal(prev["dark"][ty, tx], dark[y, x])
                    if (dp @ dp < cfg.position_limit_squared
                            and dn @ dn < cfg.normal_limit_squared and same):
                        kept.append((ty, tx, wt))
                        spp += wt * prev["count"][ty, tx, 0]
                        colour = colour + wt * prev["noisy"][ty, tx]
                        total += wt
                if total > 0:
                    colour, spp = colour / total, spp / total
                    alpha = max(1 / (spp + 1), cfg.blend_alpha)
            if alpha < 1:
                new = (min(np.round(spp), 254) + 1 if cfg.sample_count == "integer"
                       else spp + 1)
            else:
                new = 1.0
            count[y, x] = new
            noisy[y, x] = alpha * illum[y, x] + (1 - alpha) * colour
            alpha2, previous = 1.0, np.zeros(3)
            total = sum(wt for _, _, wt in kept)
            if kept and total > 0:
                previous = sum(wt * prev["filtered"][ty, tx] for ty, tx, wt in kept) / total
                alpha2 = max(1 / new, cfg.filtered_blend_alpha)
            acc[y, x] = alpha2 * filtered[y, x] + (1 - alpha2) * previous
    return noisy, count, acc


def np_ycocg(c):
    return np.array([c[0] + 2 * c[1] + c[2], 2 * c[0] - 2 * c[2], -c[0] + 2 * c[1] - c[2]])


def np_rgb(v):
    return 0.25 * np.array([v[0] + v[1] - v[2], v[0] + v[2], v[0] - v[1] - v[2]])


def np_taa(image, previous, motion, frame_number, cfg):
    h, w = image.shape[:2]
    out = image.copy()
    for y in range(h):
        for x in range(w):
            px, py = x + motion[y, x, 0], y + motion[y, x, 1]
            x0, y0 = int(np.floor(px)), int(np.floor(py))
            if frame_number == 0 or x0 < -1 or y0 < -1 or x0 >= w or y0 >= h:
                continue
            box = [np_ycocg(image[y + j, x + i]) for j in (-1, 0, 1) for i in (-1, 0, 1)
                   if 0 <= y + j < h and 0 <= x + i < w]
            cross = [np_ycocg(image[y + j, x + i]) for j, i in
                     ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))
                     if 0 <= y + j < h and 0 <= x + i < w]
            lo = (np.min(box, 0) + np.min(cross, 0)) / 2
            hi = (np.max(box, 0) + np.max(cross, 0)) / 2
            fx, fy = px - x0, py - y0
            hist, total = np.zeros(3), 0.0
            for ty, tx, wt in ((y0, x0, (1 - fx) * (1 - fy)), (y0, x0 + 1, fx * (1 - fy)),
                               (y0 + 1, x0, (1 - fx) * fy), (y0 + 1, x0 + 1, fx * fy)):
                if 0 <= ty < h and 0 <= tx < w:
                    hist += wt * previous[ty, tx]
                    total += wt
            if total <= 0:
                continue
            clamped = np_rgb(np.clip(np_ycocg(hist / total), lo, hi))
            out[y, x] = cfg.taa_blend_alpha * image[y, x] + (1 - cfg.taa_blend_alpha) * clamped
    return out


# ------------------------------------------------------------------------ inputs
def scene(seed=0, h=48, w=56, miss=True):
    """Colour, albedo, normals (smooth, jittered), world positions on a curved sheet whose
    x-extent per block is > 1 (scaled) and y-extent < 1 (shifted only), a missed corner."""
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[:h, :w].astype(np.float64)
    position = np.stack([0.05 * xs, 0.02 * ys, 2.0 + 0.3 * np.sin(0.15 * xs + 0.1 * ys)], -1)
    normal = np.stack([0.3 * np.sin(0.2 * xs), 0.2 * np.cos(0.13 * ys), np.ones_like(xs)], -1)
    normal += rng.normal(0, 0.05, normal.shape)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    color = rng.gamma(2.0, 0.5, (h, w, 3))
    albedo = rng.uniform(0.1, 0.9, (h, w, 3))
    if miss:
        normal[:5, -6:] = 0.0
        position[:5, -6:] = 0.0
    return color, albedo, normal, position


def as_frame(color, albedo, normal, position, motion=None, dtype=jnp.float32):
    f = lambda a: None if a is None else jnp.asarray(a, dtype)
    return Frame(color=f(color), albedo=f(albedo), normal=f(normal), position=f(position),
                 motion=f(motion))


spatial = jax.jit(B.bmfr_spatial, static_argnames="config")


# ------------------------------------------------------------------------ tests
def test_presets_and_config_checks():
    assert (B.BMFR_CL.noise_amount, B.BMFR_CL.blend_alpha, B.BMFR_CL.filtered_blend_alpha,
            B.BMFR_CL.taa_blend_alpha, B.BMFR_CL.sample_count) == (0.01, 0.2, 0.1, 0.2, "integer")
    assert B.BMFR_WSKP.sample_count == "float"
    assert set(B.BMFR_PRESETS) == {"bmfr-cl", "wskp"}
    assert B.WSKP_SCENE_LIMITS["living-room"] == (0.0009, 0.04)
    with pytest.raises(ConfigError, match="noise_amount"):
        B.BMFRConfig(noise_amount=0.0, ridge=0.0)
    with pytest.raises(ConfigError, match="blend_alpha"):
        B.BMFRConfig(blend_alpha=0.0)
    with pytest.raises(ConfigError, match="sample_count"):
        B.BMFRConfig(sample_count="half")


def test_noise_is_the_authors_hash_and_grid_helpers():
    noise = np.asarray(B.regularisation_noise(5, 0.01))
    rows, feats = np.meshgrid(np.arange(1024), np.arange(10), indexing="ij")
    want = np.float32(0.01) * 2 * (np_hash(rows + 1024 * feats + 13 * 1024 * 5) - np.float32(0.5))
    want[:, 0] = 0
    assert_allclose(noise, want, rtol=0, atol=1e-9)
    assert np.abs(noise).max() <= 0.01 and np.abs(noise[:, 1:]).mean() > 0.004
    assert not np.allclose(noise, np.asarray(B.regularisation_noise(6, 0.01)))
    assert_allclose(np.asarray(B.mirror(jnp.arange(-40, 50), 16)),
                    [np_mirror(i, 16) for i in range(-40, 50)])
    assert B.block_grid(720, 1280) == (24, 41)
    assert tuple(np.asarray(B.block_offset(17))) == (4, -6)
    # blocks and back: from_blocks(to_blocks(work_area(image))) is the image, for any offset
    image = jnp.asarray(np.random.default_rng(0).normal(size=(40, 56, 2)), jnp.float32)

    @jax.jit
    def round_trip(image, frame_index):
        offset = B.block_offset(frame_index)
        return B.from_blocks(B.to_blocks(B.work_area(image, offset)), 40, 56, offset)

    for frame_index in range(16):
        assert_allclose(np.asarray(round_trip(image, frame_index)), np.asarray(image))


def test_fit_blocks_matches_lstsq_block_by_block():
    rng = np.random.default_rng(1)
    design = rng.uniform(0, 1, (5, 1024, 10)).astype(np.float32)
    design[:, :, 0] = 1.0
    design[3, :, 5] = design[3, :, 4]  # collinear: the ridge alone decides
    design[2, :, 7] = -design[2, :, 7]  # negative pivots: the reflector's other sign
    target = (design @ rng.normal(size=(5, 10, 3)) + rng.normal(0, 0.1, (5, 1024, 3)))
    design[1, 300:] = 0.0  # rows kept out (weight 0)
    target[1, 300:] = 0.0
    design[4] = 0.0  # a block without rows: the ridge keeps it finite, at 0
    ridge = 1e-3
    f = lambda a: jnp.asarray(a, jnp.float32)
    got = np.asarray(jax.jit(B.fit_blocks)(f(design), f(target), ridge))
    for b in range(5):
        A = np.concatenate([design[b], np.sqrt(ridge) * np.eye(10)]).astype(np.float64)
        want = np.linalg.lstsq(A, np.concatenate([target[b], np.zeros((10, 3))]), rcond=None)[0]
        # float32 QR: the fitted values to 2e-5 of the target's scale, the weights to 2e-3
        # of their size
        assert_allclose(design[b] @ got[b], design[b] @ want, rtol=0,
                        atol=2e-5 * np.abs(target[b]).max())
        assert_allclose(got[b], want, rtol=0, atol=2e-3 * np.abs(want).max() + 1e-4)
    assert_allclose(got[4], 0.0, atol=1e-4)  # |y| ~ 3 through 1 / sqrt(ridge) ~ 30


@pytest.mark.parametrize("frame_index, pass_through", [(0, True), (9, False), (13, True)])
def test_block_fit_matches_numpy_lstsq(frame_index, pass_through):
    """The whole filter (mirroring, scaling, noise, per-channel fit, per-pixel evaluation) in
    float64 against the per-block lstsq reference, with misses and dark albedo channels."""
    color, albedo, normal, position = scene(2)
    color = color - 1.0  # some fits go below 0: the clamp
    albedo[30:34, 3:9, 1] = 0.005  # a dark channel: the pixels out of the fit
    miss = np.sum(normal**2, -1, keepdims=True) == 0
    unfit = miss | (albedo < 0.01)
    cfg = dataclasses.replace(B.BMFR_CL, pass_through=pass_through, ridge=1e-6)
    want, _ = np_block_fit(color, normal, position, frame_index, cfg, unfit)
    with jax.enable_x64(True):
        assert_allclose(np.asarray(B.unfit_mask(jnp.asarray(normal), jnp.asarray(albedo),
                                                0.01)), unfit)
        got = np.asarray(jax.jit(B.block_fit, static_argnames="config")(
            jnp.asarray(color), jnp.asarray(normal), jnp.asarray(position), frame_index,
            config=cfg, unfit=jnp.asarray(unfit)))
    assert got.dtype == np.float64
    assert_allclose(got, want, rtol=1e-7, atol=1e-8)
    assert (got == 0).mean() > 0.01  # the clamp at 0
    emission = np.zeros_like(color)
    emission[10:13, 20:22, 0] = 5.0  # a lamp seen directly: every channel out of the fit
    with_lamp = np.asarray(B.unfit_mask(normal, albedo, 0.01, emission))
    assert_allclose(with_lamp, unfit | (emission.max(-1, keepdims=True) > 0))
    if pass_through:
        assert_allclose(got[unfit], color[unfit])
        assert not np.allclose(got[30:34, 3:9, 0], color[30:34, 3:9, 0])  # fitted channels


def blockwise_linear(frame_index=3, h=48, w=56, seed=3):
    """Colour exactly linear in (1, n, P, P^2) with its own weights in every block of frame
    ``frame_index``'s grid. With offset (8, 0) and this size every block's mirrored rows copy
    pixels of the same block, so each block's rows follow its own linear function."""
    rng = np.random.default_rng(seed)
    _, albedo, normal, position = scene(seed, h, w, miss=False)
    off = B.BLOCK_OFFSETS[frame_index]
    assert off == (8, 0)
    ys, xs = np.mgrid[:h, :w]
    block = ((ys + 16 - off[1]) // 32) * 10 + (xs + 16 - off[0]) // 32
    assert len(np.unique(block)) == 4
    weights = {b: rng.normal(0, 1, (10, 3)) for b in np.unique(block)}
    feats = np.concatenate([np.ones((h, w, 1)), normal, position, position**2], -1)
    illum = np.einsum("hwk,hwkc->hwc", feats, np.stack([[weights[b] for b in row]
                                                        for row in block]))
    illum += 8.0 - illum.min()  # positive: the clamp at 0 stays out of it
    return illum, albedo, normal, position


def test_single_frame_recovers_a_blockwise_linear_colour():
    illum, albedo, normal, position = blockwise_linear()
    frame = as_frame(illum * albedo, albedo, normal, position)
    exact = B.BMFRConfig(noise_amount=0.0, ridge=1e-9, frame_index=3)
    got = np.asarray(spatial(frame, config=exact))
    assert_allclose(got, illum * albedo, rtol=2e-4, atol=1e-4)
    # the authors' noise biases the fit a little, not more
    noisy = np.asarray(spatial(frame, config=dataclasses.replace(B.BMFR_CL, frame_index=3)))
    relative = np.abs(noisy - illum * albedo) / (illum * albedo)
    assert relative.max() < 0.02 and relative.mean() < 0.002, (relative.max(), relative.mean())


def random_history(seed, normal, position, frame_number=4):
    rng = np.random.default_rng(seed)
    h, w = normal.shape[:2]
    prev_normal, prev_position = normal.copy(), position.copy()
    prev_position[10:16, 10:20] += 0.3  # disocclusion: fails the position test
    prev_normal[20:26, 30:40] = [1.0, 0.0, 0.0]  # another surface: fails the normal test
    dark = np.zeros((h, w, 3))
    dark[30:36, 40:50, 1] = 1.0  # a dark green channel there: fails against other kinds
    return {
        "noisy": rng.uniform(0, 2, (h, w, 3)), "filtered": rng.uniform(0, 2, (h, w, 3)),
        "count": rng.integers(1, 40, (h, w, 1)).astype(float) + (rng.random((h, w, 1)) < 0.05)
        * 300.0,
        "output": rng.uniform(0, 2, (h, w, 3)), "normal": prev_normal,
        "position": prev_position, "dark": dark, "frame": frame_number}


def state_of(history):
    f = lambda k: jnp.asarray(history[k], jnp.float32)
    return B.BMFRState(noisy=f("noisy"), count=f("count"), filtered=f("filtered"),
                       output=f("output"), normal=f("normal"), position=f("position"),
                       dark=f("dark"), frame=jnp.asarray(history["frame"], jnp.int32))


@functools.partial(jax.jit, static_argnames="cfg")
def accumulation(state, illum, filtered, normal, position, dark, motion, cfg):
    """Steps 2 and 4 of a frame: the noisy and the filtered accumulation, and the taps."""
    taps = B.reproject(state, normal, position, motion, cfg, dark)
    noisy, count = B.accumulate_noisy(illum, state, taps, cfg)
    return noisy, count, B.accumulate_filtered(filtered, state, taps, count, cfg), taps


@pytest.mark.parametrize("cfg", [pytest.param(B.BMFR_CL, id="bmfr-cl"),
                                 pytest.param(B.BMFR_WSKP, id="wskp")])
@pytest.mark.parametrize("frame_number", [0, 4])
def test_accumulation_matches_numpy(cfg, frame_number):
    color, _, normal, position = scene(4, miss=False)
    rng = np.random.default_rng(5)
    motion = rng.uniform(-2.5, 2.5, color.shape[:2] + (2,))
    filtered = rng.uniform(0, 2, color.shape)
    history = random_history(6, normal, position, frame_number)
    dark = np.zeros_like(color)
    dark[33:45, 5:15, 1] = 1.0  # dark here, not in the history
    want = np_step_accumulation(color, filtered, history, normal, position, dark, motion,
                                frame_number, cfg)
    f = lambda a: jnp.asarray(a, jnp.float32)
    *got, taps = accumulation(state_of(history), f(color), f(filtered), f(normal), f(position),
                              f(dark), f(motion), cfg=cfg)
    for g, w_ in zip(got, want, strict=True):
        assert_allclose(np.asarray(g), w_, rtol=1e-4, atol=1e-5)
    valid = np.asarray(taps.valid)[..., 0]
    if frame_number == 0:
        assert not valid.any()
    else:
        assert 0.5 < valid.mean() < 0.95
        # pixels whose four taps all land on the moved or turned surface keep no history
        h, w = valid.shape
        x0 = np.floor(np.arange(w) + motion[..., 0]).astype(int)
        y0 = np.floor(np.arange(h)[:, None] + motion[..., 1]).astype(int)
        inside = lambda r0, r1, c0, c1: (y0 >= r0) & (y0 + 1 < r1) & (x0 >= c0) & (x0 + 1 < c1)
        moved, turned = inside(10, 16, 10, 20), inside(20, 26, 30, 40)
        darkened = inside(30, 36, 40, 50) | (dark[..., 1] > 0) & inside(0, h, 0, w)
        for region in (moved, turned, darkened):
            assert region.sum() > 5
            assert not valid[region].any()
        assert (np.asarray(got[1]) == 255).any() == (cfg.sample_count == "integer")


def test_accumulation_is_the_running_mean_then_ema():
    """Static camera: the noisy accumulation is the plain mean while 1 / (n + 1) >= 0.2."""
    _, _, normal, position = scene(7, miss=False)
    rng = np.random.default_rng(8)
    illums = rng.uniform(0, 2, (7,) + normal.shape)
    dark = np.zeros_like(normal)
    state = B.initial_state(*normal.shape[:2])
    f = lambda a: jnp.asarray(a, jnp.float32)
    zero = jnp.zeros(normal.shape[:2] + (2,))
    means = []
    for t in range(7):
        noisy, count, _, _ = accumulation(state, f(illums[t]), f(illums[t]), f(normal),
                                          f(position), f(dark), zero, cfg=B.BMFR_CL)
        state = state._replace(noisy=noisy, count=count, normal=f(normal), position=f(position),
                               frame=state.frame + 1)
        means.append(np.asarray(noisy))
        assert_allclose(np.asarray(count), t + 1)
    for t in range(5):
        assert_allclose(means[t], illums[: t + 1].mean(0), rtol=1e-5)
    assert_allclose(means[6], 0.2 * illums[6] + 0.8 * means[5], rtol=1e-5)


def test_taa_matches_numpy():
    rng = np.random.default_rng(9)
    image, previous = rng.uniform(0, 2, (24, 28, 3)), rng.uniform(0, 2, (24, 28, 3))
    motion = rng.uniform(-3, 3, (24, 28, 2))
    motion[0, :4] = [-1.5, -1.5]  # off-screen: floor(x + motion) < -1 at the corner
    run = jax.jit(B.taa, static_argnames="config")
    f = lambda a: jnp.asarray(a, jnp.float32)
    got = run(f(image), f(previous), f(motion), jnp.asarray(False), config=B.BMFR_CL)
    want = np_taa(image, previous, motion, 1, B.BMFR_CL)
    assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)
    assert_allclose(np.asarray(got)[0, :2], image[0, :2], rtol=1e-6)
    first = run(f(image), f(previous), f(motion), jnp.asarray(True), config=B.BMFR_CL)
    assert_allclose(np.asarray(first), image, rtol=1e-6)
    colour = rng.uniform(0, 2, (5, 3))
    assert_allclose(np.asarray(B.ycocg_to_rgb(B.rgb_to_ycocg(jnp.asarray(colour)))), colour,
                    rtol=1e-6)


@functools.cache
def bmfr():
    """The registered denoiser, one object (one compiled program) for the file."""
    return make_denoiser("bmfr")


def test_step_matches_its_stages():
    """bmfr_step = reproject, accumulate, fit on the accumulated colour with the frame's
    grid, post-accumulate, remodulate, TAA; the state carries them. The first frame of a
    sequence is the registered single-frame filter."""
    color, albedo, normal, position = scene(10)
    albedo[5:9, 20:30, 2] = 0.004  # a dark blue channel: passed through, its pixels unfit
    rng = np.random.default_rng(11)
    motion = rng.uniform(-1, 1, color.shape[:2] + (2,))
    history = random_history(12, normal, position, frame_number=6)
    state = state_of(history)
    frame = as_frame(color, albedo, normal, position, motion)
    (image,), new = B.bmfr_sequence([frame], state=state, return_state=True)

    @jax.jit
    def stages(state, frame):
        illum = B.demodulate(frame.color, frame.albedo)
        dark = B.dark_channels(frame.albedo, 0.01)
        taps = B.reproject(state, frame.normal, frame.position, frame.motion, B.BMFR_CL, dark)
        noisy, count = B.accumulate_noisy(illum, state, taps)
        filtered = B.block_fit(noisy, frame.normal, frame.position, state.frame, B.BMFR_CL,
                               B.unfit_mask(frame.normal, frame.albedo, 0.01))
        acc = B.accumulate_filtered(filtered, state, taps, count)
        return B.taa(B.remodulate(acc, frame.albedo), state.output, frame.motion, False), acc

    want, acc = stages(state, frame)
    assert_allclose(np.asarray(image), np.asarray(want), rtol=1e-4, atol=1e-5)
    assert_allclose(np.asarray(new.filtered), np.asarray(acc), rtol=1e-4, atol=1e-5)
    assert_allclose(np.asarray(new.output), np.asarray(image))
    assert int(new.frame) == 7
    assert_allclose(np.asarray(new.dark)[..., 2], albedo[..., 2] < 0.01)
    # the first frame (no state, no motion): no history, no TAA, frame 0's grid
    (image0,), state0 = B.bmfr_sequence([frame.replace(motion=None)], return_state=True)
    assert_allclose(np.asarray(image0), np.asarray(bmfr()(frame)), rtol=1e-4, atol=1e-5)
    assert_allclose(np.asarray(state0.count), 1.0)


def static_sequence(frames, seed, h=48, w=56):
    """A static camera over a curved sheet: smooth illumination (a function of position and
    normal) times a textured albedo, frames with independent multiplicative gamma noise."""
    rng = np.random.default_rng(seed)
    _, _, normal, position = scene(seed, h, w, miss=False)
    illum = (0.6 + 0.4 * normal[..., 2:3] * np.array([1.0, 0.8, 0.6])
             + 0.1 * np.sin(position[..., :1] * 2.0))
    albedo = rng.uniform(0.2, 0.9, (h, w, 3))
    reference = illum * albedo
    noisy = [reference * rng.gamma(1.0, 1.0, (h, w, 1)) for _ in range(frames)]
    motion = np.zeros((h, w, 2))
    return reference, [as_frame(c, albedo, normal, position, motion) for c in noisy]


def rmse(image, reference):
    return float(np.sqrt(np.mean((np.asarray(image) - reference) ** 2)))


def test_static_sequence_converges():
    reference, frames = static_sequence(12, seed=13)
    errors = [rmse(im, reference) for im in B.bmfr_sequence(frames)]
    noisy = rmse(frames[0].color, reference)
    assert errors[0] < 0.2 * noisy, (errors[0], noisy)
    assert np.all(np.diff(errors) < 0), errors  # falls with every frame
    assert np.mean(errors[8:]) < 0.6 * errors[0], errors
    # compiled once for the whole sequence, whatever fields the frames carry
    size = B._jitted_step._cache_size()
    B.bmfr_sequence([frames[0].replace(motion=None), *frames[1:3]])
    assert B._jitted_step._cache_size() == size


def test_the_registered_bmfr_runs_a_sequence_as_bmfr_sequence_does():
    """`make_denoiser("bmfr")` carries BMFR's temporal form: Denoiser.sequence (history
    carried) equals bmfr_sequence, not the single-frame form applied to each frame."""
    _, frames = static_sequence(3, seed=18)
    den = bmfr()
    assert den.temporal
    got = den.sequence(frames)
    for g, w in zip(got, B.bmfr_sequence(frames), strict=True):
        assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(got[2]), np.asarray(den(frames[2])), rtol=1e-3)


def test_error_below_the_noisy_input():
    """One noisy frame (gamma noise, standard deviation = mean) of the static scene: the
    single-frame filter's RMSE is a fraction of the input's (seed 14)."""
    reference, frames = static_sequence(1, seed=14)
    noisy = rmse(frames[0].color, reference)
    denoised = rmse(bmfr()(frames[0]), reference)
    assert denoised < 0.2 * noisy, (denoised, noisy)


def test_registered_denoiser_batches_and_gradients():
    color, albedo, normal, position = scene(15)
    frame = as_frame(color, albedo, normal, position)
    den = bmfr()
    assert den.config == B.BMFR_CL and den.definition.differentiable
    assert set(den.definition.required(den.config)) == {"albedo", "normal", "position"}
    assert den.fields_read() == ("albedo", "normal", "position", "emission")
    assert load_denoiser("bmfr:preset=wskp").config == B.BMFR_WSKP
    with pytest.raises(ConfigError, match="preset"):
        load_denoiser("bmfr:preset=nope")
    # batch dimensions; a finite gradient w.r.t. the colour (SURE's jvp)
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a[::-1]]), frame)
    flipped = jax.tree_util.tree_map(lambda a: a[::-1], frame)
    assert_allclose(np.asarray(den(batch)[1]), np.asarray(den(flipped)), rtol=1e-5, atol=1e-5)
    grad = jax.grad(lambda c: jnp.sum(den.function()(frame.replace(color=c))))(frame.color)
    assert np.isfinite(np.asarray(grad)).all() and np.abs(np.asarray(grad)).max() > 0


def test_tiles_on_the_block_grid_reproduce_the_whole_frame():
    from jaxden.denoise.tiled import denoise_frame

    color, albedo, normal, position = scene(16, h=48, w=128)
    frame = as_frame(color, albedo, normal, position).numpy()
    whole = np.asarray(bmfr()(frame))
    tiled, plan = denoise_frame(bmfr(), frame, tile=64)
    assert plan.tile == 64 and plan.halo == 31
    assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5)


def test_missing_features_are_named():
    color, albedo, normal, _ = scene(17)
    frame = as_frame(color, albedo, normal, None)
    with pytest.raises(FrameError, match="position"):
        make_denoiser("bmfr")(frame)
    with pytest.raises(FrameError, match="position"):
        B.bmfr_sequence([frame])
    with pytest.raises(FrameError, match="albedo, position"):
        B.bmfr_spatial(frame.replace(albedo=None))


def tone_mapped_rmse(image, reference):
    tm = lambda x: np.clip(np.maximum(np.asarray(x), 0.0) ** (1 / 2.2), 0.0, 1.0)
    return float(np.sqrt(np.mean((tm(image) - tm(reference)) ** 2)))


@pytest.mark.slow
def test_rendered_frame_error_falls():
    """A 1-spp 64 x 64 render of the Cornell box against 256 spp (seeds 0 / 1): BMFR has a
    lower RMSE than the input, and less than 0.6 of it tone-mapped (measured: 0.457 / 0.470
    linear, 0.063 / 0.131 tone-mapped), because the lamp (``emission`` > 0) is kept out of the
    fit: without the emission channel the fit spreads the lamp over its block."""
    from jaxden.render import render_frame

    noisy = render_frame("cornell-box", spp=1, seed=0, size=(64, 64))
    reference = np.asarray(render_frame("cornell-box", spp=256, seed=1, size=(64, 64)).color)
    out = bmfr()(noisy)
    assert rmse(out, reference) < rmse(noisy.color, reference)
    assert tone_mapped_rmse(out, reference) < 0.6 * tone_mapped_rmse(noisy.color, reference)
    assert_allclose(np.asarray(load_denoiser("bmfr:emission=separate")(noisy)), out,
                    rtol=1e-3, atol=1e-3)
    lamp_spread = bmfr()(noisy.replace(emission=None))
    assert rmse(lamp_spread, reference) > 1.5 * rmse(noisy.color, reference)


@pytest.mark.slow
def test_rendered_sequence_error_falls():
    """A procedural scene (dark and textured materials) along an 8-frame camera path, 1 spp
    64 x 64 against 256 spp: the registered temporal form (motion vectors, history carried)
    beats the single-frame form and halves the input's RMSE over frames 1..7 (measured:
    0.025 against 0.044 single-frame and 0.050 input)."""
    from jaxden.render.camera import from_scene, random_path
    from jaxden.render.load import load_scene
    from jaxden.render.sequence import render_sequence

    scene = load_scene("procedural:11", size=(64, 64))
    cameras = random_path(from_scene(scene), 8, 7, translation=0.1, rotation_deg=10.0,
                          num_keyframes=3)
    frames, references = render_sequence(scene, cameras, spp=1, seed=0, size=(64, 64),
                                         reference_spp=256)
    den = bmfr()
    errors = lambda images: np.mean([rmse(image, ref.color) for image, ref in
                                     zip(images[1:], references[1:], strict=True)])
    temporal = errors(den.sequence(frames))
    single = errors([den(frame) for frame in frames])
    noisy = errors([frame.color for frame in frames])
    assert temporal < 0.8 * single and temporal < 0.6 * noisy, (temporal, single, noisy)


@pytest.mark.slow  # ~40 s: renders a 6-frame sequence, then two CLI runs per method
@pytest.mark.parametrize("model", ["svgf", "bmfr"])
def test_jaxden_denoise_beats_the_input_on_a_frame_and_on_a_sequence(tmp_path, capsys, model):
    """`jaxden denoise --model svgf|bmfr` on the 1-spp frames of a rendered camera path
    (procedural:11, 64 x 64, 6 frames, references at 256 spp, seed 4): each frame alone and
    the frames as one `--sequence` both have a lower RMSE than the 1-spp input over frames
    1..5 (frame 0 has no history), and the history helps (sequence below single frames)."""
    from helpers import run_cli

    from jaxden.data.sequences import SequenceConfig, build_sequences, load_sequence, read_manifest
    from jaxden.io.exr import read_image, write_frame

    data = tmp_path / "seq"
    build_sequences(SequenceConfig(scenes=("procedural:11",), size=(64, 64), frames=6, spp=1,
                                   reference_spp=256, seed=4), data, progress=False)
    key = read_manifest(data)["sequences"][0] if isinstance(read_manifest(data)["sequences"],
                                                           list) else next(iter(
        read_manifest(data)["sequences"]))
    frames, references = load_sequence(data, key)
    paths = []
    for t, frame in enumerate(frames):
        paths.append(tmp_path / "in" / f"f{t:02d}.exr")
        paths[-1].parent.mkdir(exist_ok=True)
        write_frame(paths[-1], frame)
    for form, extra in (("alone", []), ("sequence", ["--sequence"])):
        code, lines, _ = run_cli(["denoise", *paths, "--model", model, *extra, "--out-dir",
                                  tmp_path / form], capsys)
        assert code == 0, lines

    def rmse(images):
        return float(np.mean([np.sqrt(np.mean((np.asarray(i) - np.asarray(r.color)) ** 2))
                              for i, r in zip(images[1:], references[1:])]))

    noisy = rmse([f.color for f in frames])
    alone = rmse([read_image(tmp_path / "alone" / p.name) for p in paths])
    sequence = rmse([read_image(tmp_path / "sequence" / p.name) for p in paths])
    assert sequence < alone < noisy, (noisy, alone, sequence)
