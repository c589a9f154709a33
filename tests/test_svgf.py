"""SVGF (jaxden.denoise.svgf) against slow NumPy references written from BASELINES.md 1.x.

Every reference loops over pixels and taps with Falcor's formulas; the JAX functions must agree
to float32 round-off. Frames are 16 x 16 (a few 24 x 24), so the file runs in seconds.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.testing import assert_allclose

from jaxden.denoise import load_denoiser, make_denoiser
from jaxden.denoise import svgf as S
from jaxden.errors import ConfigError
from jaxden.frame import Frame

LUM = np.array([0.2126, 0.7152, 0.0722])
H1 = (1.0, 2.0 / 3.0, 1.0 / 6.0)
G3 = ((1 / 4, 1 / 8), (1 / 8, 1 / 16))


# ------------------------------------------------------------------------ NumPy references
def np_one_sided(img, y, x, axis):
    """Smaller (by norm) of the forward and backward difference at (y, x)."""
    h, w = img.shape[:2]
    dy, dx = (1, 0) if axis == 0 else (0, 1)
    cands = []
    if 0 <= y + dy < h and 0 <= x + dx < w:
        cands.append(img[y + dy, x + dx] - img[y, x])
    if 0 <= y - dy < h and 0 <= x - dx < w:
        cands.append(img[y, x] - img[y - dy, x - dx])
    if not cands:
        return np.zeros_like(img[y, x])
    return min(cands, key=lambda d: float(np.sum(d * d)))


def np_slope(depth):
    h, w = depth.shape[:2]
    out = np.zeros((h, w, 1))
    for y in range(h):
        for x in range(w):
            out[y, x, 0] = max(abs(np_one_sided(depth, y, x, 1)[0]),
                               abs(np_one_sided(depth, y, x, 0)[0]))
    return out


def np_nwidth(normal):
    h, w = normal.shape[:2]
    out = np.zeros((h, w, 1))
    for y in range(h):
        for x in range(w):
            f = np.abs(np_one_sided(normal, y, x, 1)) + np.abs(np_one_sided(normal, y, x, 0))
            out[y, x, 0] = np.sqrt(np.sum(f * f))
    return out


def np_weight(zp, zq, phi_z, n_p, n_q, phi_n, lp, lq, phi_l):
    wn = max(0.0, min(1.0, float(np.dot(n_p, n_q)))) ** phi_n
    az = 0.0 if phi_z == 0 else abs(zp - zq) / phi_z
    return np.exp(-abs(lp - lq) / phi_l - az) * wn


def np_atrous(color, var, depth, normal, step, cfg):
    h, w = color.shape[:2]
    lum = color @ LUM
    slope = np_slope(depth)
    out_c, out_v = color.copy(), var.copy()
    for y in range(h):
        for x in range(w):
            if depth[y, x, 0] <= 0:
                continue
            vg = 0.0
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if 0 <= y + dy < h and 0 <= x + dx < w:
                        vg += G3[abs(dy)][abs(dx)] * var[y + dy, x + dx, 0]
            phi_l = cfg.phi_color * np.sqrt(max(0.0, 1e-10 + vg))
            phi_z = cfg.phi_depth * max(slope[y, x, 0], 1e-8) * step
            sw, sc, sv = 1.0, color[y, x].copy(), var[y, x, 0]
            for j in range(-2, 3):
                for i in range(-2, 3):
                    qy, qx = y + j * step, x + i * step
                    if (i == 0 and j == 0) or not (0 <= qy < h and 0 <= qx < w):
                        continue
                    wt = np_weight(depth[y, x, 0], depth[qy, qx, 0], phi_z * np.hypot(i, j),
                                   normal[y, x], normal[qy, qx], cfg.phi_normal, lum[y, x],
                                   lum[qy, qx], phi_l) * H1[abs(i)] * H1[abs(j)]
                    sw += wt
                    sc = sc + wt * color[qy, qx]
                    sv += wt * wt * var[qy, qx, 0]
            out_c[y, x] = sc / sw
            out_v[y, x, 0] = sv / sw**2
    return out_c, out_v


def np_spatial(color, moments, var, hist, depth, normal, cfg):
    h, w = color.shape[:2]
    r = cfg.spatial_radius
    lum = color @ LUM
    slope = np_slope(depth)
    out_c, out_v = color.copy(), var.copy()
    for y in range(h):
        for x in range(w):
            if hist[y, x, 0] >= cfg.history_threshold or depth[y, x, 0] <= 0:
                continue
            phi_z = max(slope[y, x, 0], 1e-8) * 3.0
            sw, sc, sm = 0.0, np.zeros(3), np.zeros(2)
            for j in range(-r, r + 1):
                for i in range(-r, r + 1):
                    qy, qx = y + j, x + i
                    if not (0 <= qy < h and 0 <= qx < w):
                        continue
                    wt = np_weight(depth[y, x, 0], depth[qy, qx, 0], phi_z * np.hypot(i, j),
                                   normal[y, x], normal[qy, qx], cfg.phi_normal, lum[y, x],
                                   lum[qy, qx], cfg.phi_color)
                    sw += wt
                    sc += wt * color[qy, qx]
                    sm += wt * moments[qy, qx]
            sw = max(sw, 1e-6)
            m = sm / sw
            out_c[y, x] = sc / sw
            out_v[y, x, 0] = max(0.0, m[1] - m[0] ** 2) * cfg.history_threshold / max(
                hist[y, x, 0], 1.0)
    return out_c, out_v


def np_reproject(state, depth, normal, motion, cfg):
    """Falcor's reprojection (bilinear taps, then the 3 x 3 fallback)."""
    sc, sm, sh, sd, sn = (np.asarray(a, np.float64) for a in state)
    h, w = depth.shape[:2]
    slope, nw = np_slope(depth), np_nwidth(normal)
    color, moments, hist = np.zeros((h, w, 3)), np.zeros((h, w, 2)), np.zeros((h, w, 1))
    valid = np.zeros((h, w, 1), bool)

    def ok(y, x, ty, tx):
        if not (0 <= ty < h and 0 <= tx < w) or sh[ty, tx, 0] <= 0:
            return False
        dz = abs(sd[ty, tx, 0] - depth[y, x, 0]) / (slope[y, x, 0] + 1e-2)
        dn = np.linalg.norm(sn[ty, tx] - normal[y, x]) / (nw[y, x, 0] + 1e-2)
        return dz <= cfg.depth_tolerance and dn <= cfg.normal_tolerance

    for y in range(h):
        for x in range(w):
            px, py = x + motion[y, x, 0], y + motion[y, x, 1]
            x0, y0 = int(np.floor(px)), int(np.floor(py))
            fx, fy = px - x0, py - y0
            taps = [(y0, x0, (1 - fx) * (1 - fy)), (y0, x0 + 1, fx * (1 - fy)),
                    (y0 + 1, x0, (1 - fx) * fy), (y0 + 1, x0 + 1, fx * fy)]
            kept = [(ty, tx, wt) for ty, tx, wt in taps if ok(y, x, ty, tx)]
            total = sum(wt for _, _, wt in kept)
            if total >= 0.01:
                kept = [(ty, tx, wt / total) for ty, tx, wt in kept]
            elif cfg.reprojection_fallback:
                near = [(y0 + j, x0 + i) for j in (-1, 0, 1) for i in (-1, 0, 1)
                        if ok(y, x, y0 + j, x0 + i)]
                kept = [(ty, tx, 1.0 / len(near)) for ty, tx in near]
            else:
                kept = []
            if kept:
                valid[y, x] = True
                for ty, tx, wt in kept:
                    color[y, x] += wt * sc[ty, tx]
                    moments[y, x] += wt * sm[ty, tx]
                    hist[y, x] += wt * sh[ty, tx]
    return color, moments, hist, valid


def np_accumulate(illum, pc, pm, ph, valid, cfg):
    h = np.where(valid, np.minimum(cfg.history_cap, ph + 1), 1.0)
    ac = np.where(valid, np.maximum(cfg.alpha_color, 1 / h), 1.0)
    am = np.where(valid, np.maximum(cfg.alpha_moments, 1 / h), 1.0)
    lum = illum @ LUM
    cur = np.stack([lum, lum**2], -1)
    m = am * cur + (1 - am) * pm
    c = ac * illum + (1 - ac) * pc
    return c, m, np.maximum(0, m[..., 1:] - m[..., :1] ** 2), h


def np_guarded(albedo, floor):
    """SVGF's divisor: WSKP's safe albedo (the ramp to 1 below the floor), or max(a, 1e-3)."""
    if floor == 0:
        return np.maximum(albedo, 1e-3)
    return np.where(albedo >= floor, albedo, 1 - (1 - floor) * np.clip(albedo, 0, None) / floor)


def np_svgf_spatial(color, albedo, depth, normal, cfg):
    illum = color / np_guarded(albedo, cfg.albedo_floor)
    lum = illum @ LUM
    moments = np.stack([lum, lum**2], -1)
    hist = np.ones(lum.shape + (1,))
    c, v = np_spatial(illum, moments, np.zeros_like(hist), hist, depth, normal, cfg)
    for i in range(cfg.iterations):
        c, v = np_atrous(c, v, depth, normal, 2**i, cfg)
    return c * np_guarded(albedo, cfg.albedo_floor)


# ------------------------------------------------------------------------ inputs
def scene(seed=0, h=16, w=16, miss=True):
    """Colour, albedo, depth (a ramp with a step, and a missed corner), normals (two planes
    with some jitter)."""
    rng = np.random.default_rng(seed)
    color = rng.gamma(2.0, 0.5, (h, w, 3))
    albedo = rng.uniform(0.0, 1.0, (h, w, 3))
    albedo[0, 0] = 0.0  # the guard
    ys, xs = np.mgrid[:h, :w]
    depth = (2.0 + 0.05 * xs + 0.02 * ys + np.where(xs >= w // 2, 1.5, 0.0))[..., None]
    normal = np.zeros((h, w, 3))
    normal[..., 2] = 1.0
    normal[xs >= w // 2] = [0.6, 0.0, 0.8]
    normal += rng.normal(0, 0.05, normal.shape)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    if miss:
        depth[:3, -3:] = 0.0
        normal[:3, -3:] = 0.0
    return color, albedo, depth, normal


def as_frame(color, albedo, depth, normal, motion=None):
    f32 = lambda a: None if a is None else jnp.asarray(a, jnp.float32)
    return Frame(color=f32(color), albedo=f32(albedo), depth=f32(depth), normal=f32(normal),
                 motion=f32(motion))


CONFIGS = [pytest.param(S.SVGF_PAPER, id="paper"), pytest.param(S.SVGF_FALCOR, id="falcor"),
           pytest.param(dataclasses.replace(S.SVGF_FALCOR, albedo_floor=0.0),
                        id="falcor-guard")]


# ------------------------------------------------------------------------ tests
def test_presets_and_config_checks():
    assert (S.SVGF_PAPER.alpha_color, S.SVGF_PAPER.phi_color, S.SVGF_PAPER.iterations,
            S.SVGF_PAPER.feedback_iteration) == (0.2, 4.0, 5, 0)
    assert (S.SVGF_FALCOR.alpha_color, S.SVGF_FALCOR.alpha_moments, S.SVGF_FALCOR.phi_color,
            S.SVGF_FALCOR.iterations, S.SVGF_FALCOR.feedback_iteration) == (0.05, 0.2, 10.0, 4, 1)
    with pytest.raises(ConfigError, match="feedback_iteration"):
        S.SVGFConfig(iterations=2, feedback_iteration=2)
    with pytest.raises(ConfigError, match="alpha_color"):
        S.SVGFConfig(alpha_color=0.0)


def test_demodulation_guard_and_inverse():
    color, albedo, _, _ = scene()
    illum = np.asarray(S.demodulate(jnp.asarray(color), jnp.asarray(albedo)))
    assert_allclose(illum[0, 0], color[0, 0] / 1e-3, rtol=1e-6)
    assert_allclose(np.asarray(S.remodulate(illum, jnp.asarray(albedo))), color, rtol=1e-5)
    nan = S.demodulate(jnp.full((1, 1, 3), jnp.nan), jnp.ones((1, 1, 3)))
    assert np.all(np.asarray(nan) == 0)


def test_slopes_match_reference():
    _, _, depth, normal = scene(1)
    assert_allclose(np.asarray(S.depth_slope(jnp.asarray(depth))), np_slope(depth), atol=1e-6)
    assert_allclose(np.asarray(S.normal_width(jnp.asarray(normal))), np_nwidth(normal),
                    atol=1e-5)
    # the step at w // 2 is a jump beside the pixel, not its own slope
    assert_allclose(np.asarray(S.depth_slope(jnp.asarray(depth)))[8, 7:9, 0], 0.05, rtol=1e-4)


@pytest.mark.parametrize("step", [1, 4])
def test_atrous_iteration_matches_numpy(step):
    color, _, depth, normal = scene(2)
    var = np.random.default_rng(3).uniform(0.01, 0.5, depth.shape)
    cfg = S.SVGF_FALCOR
    c, v = S.atrous_iteration(jnp.asarray(color, jnp.float32), jnp.asarray(var, jnp.float32),
                              jnp.asarray(depth, jnp.float32), jnp.asarray(normal, jnp.float32),
                              step, cfg)
    rc, rv = np_atrous(color, var, depth, normal, step, cfg)
    assert_allclose(np.asarray(c), rc, rtol=2e-5, atol=1e-6)
    assert_allclose(np.asarray(v), rv, rtol=2e-5, atol=1e-7)
    assert not np.allclose(rc, color)  # it filtered
    assert_allclose(np.asarray(c)[:3, -3:], color[:3, -3:], rtol=1e-6)  # misses pass through


def test_spatial_variance_matches_numpy():
    color, _, depth, normal = scene(4)
    lum = color @ LUM
    moments = np.stack([lum, lum**2 * 1.3], -1)
    var = np.full(depth.shape, 0.123)
    hist = np.random.default_rng(5).integers(1, 7, depth.shape).astype(float)
    cfg = S.SVGF_PAPER
    f = lambda a: jnp.asarray(a, jnp.float32)
    c, v = S.spatial_variance(f(color), f(moments), f(var), f(hist), f(depth), f(normal), cfg)
    rc, rv = np_spatial(color, moments, var, hist, depth, normal, cfg)
    assert_allclose(np.asarray(c), rc, rtol=2e-5, atol=1e-6)
    assert_allclose(np.asarray(v), rv, rtol=1e-4, atol=1e-6)
    long = hist[..., 0] >= 4
    assert long.any() and (~long).any()
    assert_allclose(np.asarray(v)[long], 0.123, rtol=1e-6)


def random_state(seed, depth, normal, h=16, w=16):
    rng = np.random.default_rng(seed)
    return S.SVGFState(
        color=jnp.asarray(rng.uniform(0, 2, (h, w, 3)), jnp.float32),
        moments=jnp.asarray(rng.uniform(0, 2, (h, w, 2)), jnp.float32),
        history=jnp.asarray(rng.integers(1, 10, (h, w, 1)), jnp.float32),
        depth=jnp.asarray(depth, jnp.float32), normal=jnp.asarray(normal, jnp.float32))


@pytest.mark.parametrize("fallback", [True, False])
def test_reprojection_matches_numpy(fallback):
    _, _, depth, normal = scene(6)
    rng = np.random.default_rng(7)
    state = random_state(8, depth, normal)
    # the previous frame: a depth jump in one block (occluder gone), history 0 in another
    prev_depth = depth.copy()
    prev_depth[4:8, 2:6] += 3.0
    state = state._replace(depth=jnp.asarray(prev_depth, jnp.float32),
                           history=state.history.at[10:12, 10:12].set(0.0))
    motion = rng.uniform(-2.5, 2.5, (16, 16, 2))
    cfg = dataclasses.replace(S.SVGF_FALCOR, reprojection_fallback=fallback)
    out = S.reproject(state, jnp.asarray(depth, jnp.float32), jnp.asarray(normal, jnp.float32),
                      jnp.asarray(motion, jnp.float32), cfg)
    ref = np_reproject(state, depth, normal, motion, cfg)
    assert_allclose(np.asarray(out[3]), ref[3])
    assert ref[3].any() and (~ref[3]).any()
    for got, want in zip(out[:3], ref[:3], strict=True):
        assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)


def test_translation_shifts_history_exactly():
    _, _, _, normal = scene(9, miss=False)
    depth = np.full((16, 16, 1), 3.0)
    normal[:] = [0.0, 0.0, 1.0]
    state = random_state(10, depth, normal)
    motion = np.broadcast_to(np.array([2.0, -1.0]), (16, 16, 2))  # prev_xy = xy + (2, -1)
    color, moments, hist, valid = S.reproject(state, jnp.asarray(depth, jnp.float32),
                                              jnp.asarray(normal, jnp.float32),
                                              jnp.asarray(motion, jnp.float32), S.SVGF_PAPER)
    assert_allclose(np.asarray(color)[1:, :-2], np.asarray(state.color)[:-1, 2:], rtol=1e-6)
    assert_allclose(np.asarray(moments)[1:, :-2], np.asarray(state.moments)[:-1, 2:], rtol=1e-6)
    assert_allclose(np.asarray(hist)[1:, :-2], np.asarray(state.history)[:-1, 2:])
    assert np.asarray(valid)[1:, :-2].all()
    # half-pixel motion: the average of two neighbours
    half = np.broadcast_to(np.array([0.5, 0.0]), (16, 16, 2))
    color, *_ = S.reproject(state, jnp.asarray(depth, jnp.float32),
                            jnp.asarray(normal, jnp.float32), jnp.asarray(half, jnp.float32),
                            S.SVGF_PAPER)
    c = np.asarray(state.color)
    assert_allclose(np.asarray(color)[:, :-1], (c[:, :-1] + c[:, 1:]) / 2, rtol=1e-5)


def test_occlusion_drops_taps_and_resets_history():
    color, albedo, depth, normal = scene(11, miss=False)
    state = random_state(12, depth, normal)
    new_depth = depth.copy()
    new_depth[4:10, 4:10] = 0.5  # an occluder in front: every tap fails the depth test
    f = lambda a: jnp.asarray(a, jnp.float32)
    pc, pm, ph, valid = S.reproject(state, f(new_depth), f(normal), jnp.zeros((16, 16, 2)),
                                    S.SVGF_FALCOR)
    valid = np.asarray(valid)[..., 0]
    assert not valid[4:10, 4:10].any()
    assert valid[12:, 12:].all()
    illum = S.demodulate(f(color), f(albedo))
    c, _m, v, h = S.accumulate(illum, pc, pm, ph, valid[..., None], S.SVGF_FALCOR)
    assert_allclose(np.asarray(h)[4:10, 4:10], 1.0)
    assert_allclose(np.asarray(c)[4:10, 4:10], np.asarray(illum)[4:10, 4:10], rtol=1e-6)
    assert_allclose(np.asarray(v)[4:10, 4:10], 0.0, atol=1e-4)
    assert_allclose(np.asarray(h)[12:, 12:], np.minimum(32, np.asarray(state.history)[12:, 12:] + 1))


@pytest.mark.parametrize("cfg", CONFIGS)
def test_accumulation_matches_numpy(cfg):
    rng = np.random.default_rng(13)
    illum = rng.uniform(0, 3, (16, 16, 3))
    pc, pm = rng.uniform(0, 3, (16, 16, 3)), rng.uniform(0, 3, (16, 16, 2))
    ph = rng.integers(0, 40, (16, 16, 1)).astype(float)
    valid = rng.random((16, 16, 1)) < 0.8
    out = S.accumulate(*(jnp.asarray(a, jnp.float32) for a in (illum, pc, pm, ph)),
                       jnp.asarray(valid), cfg)
    for got, want in zip(out, np_accumulate(illum, pc, pm, ph, valid, cfg), strict=True):
        assert_allclose(np.asarray(got), want, rtol=1e-5, atol=1e-5)
    # 1 / h while h < 1 / alpha: a plain mean of the frames
    h = np.asarray(out[3])
    short = valid & (h < 1 / cfg.alpha_color)
    want = illum / h + (1 - 1 / h) * pc
    assert_allclose(np.asarray(out[0])[short[..., 0]], want[short[..., 0]], rtol=1e-5)


@pytest.mark.parametrize("cfg", CONFIGS)
def test_single_frame_svgf_matches_numpy_composition(cfg):
    color, albedo, depth, normal = scene(14)
    want = np_svgf_spatial(color, albedo, depth, normal, cfg)
    # float64: the albedo guard amplifies float32 round-off by up to 1000 on dark albedo
    with jax.enable_x64(True):
        frame = Frame(color=jnp.asarray(color), albedo=jnp.asarray(albedo),
                      depth=jnp.asarray(depth), normal=jnp.asarray(normal))
        got = np.asarray(S.svgf_spatial(frame, cfg))
    assert got.dtype == np.float64
    assert_allclose(got, want, rtol=1e-9, atol=1e-9)


def test_registered_denoiser():
    color, albedo, depth, normal = scene(15)
    frame = as_frame(color, albedo, depth, normal)
    den = make_denoiser("svgf")
    assert den.config == S.SVGF_PAPER and den.definition.differentiable
    assert set(den.definition.required(den.config)) == {"albedo", "normal", "depth"}
    assert den.definition.tiling(den.config).radius == 2 * (1 + 2 + 4 + 8 + 16) + 3
    assert_allclose(np.asarray(den(frame)), np.asarray(S.svgf_spatial(frame)), rtol=1e-5,
                    atol=1e-6)
    falcor = load_denoiser("svgf:preset=falcor")
    assert falcor.config == S.SVGF_FALCOR
    assert falcor.definition.tiling(falcor.config).radius == 2 * 15 + 3
    with pytest.raises(ConfigError, match="preset"):
        load_denoiser("svgf:preset=nope")
    # batch dimensions, and a finite gradient w.r.t. the colour (SURE's jvp)
    batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a[::-1]]), frame)
    out = den(batch)
    assert_allclose(np.asarray(out[1]), np.asarray(den(jax.tree_util.tree_map(
        lambda a: a[::-1], frame))), rtol=1e-5, atol=1e-6)
    grad = jax.grad(lambda c: jnp.sum(den.function()(frame.replace(color=c))))(frame.color)
    assert np.isfinite(np.asarray(grad)).all()


def test_step_feedback_and_state():
    color, albedo, depth, normal = scene(16)
    frame = as_frame(color, albedo, depth, normal, np.zeros((16, 16, 2)))
    cfg = S.SVGF_FALCOR
    image, state = S.svgf_step(None, frame, cfg)
    assert image.shape == (16, 16, 3) and state.history.shape == (16, 16, 1)
    assert_allclose(np.asarray(state.history), 1.0)
    # first frame: the feedback is the output of pass 1 of the spatial pipeline
    illum = S.demodulate(frame.color, frame.albedo, cfg.albedo_floor)
    lum = S.luminance(illum)
    moments = jnp.concatenate([lum, lum * lum], -1)
    c, v = S.spatial_variance(illum, moments, jnp.zeros_like(lum), jnp.ones_like(lum),
                              frame.depth, frame.normal, cfg)
    for i in range(2):
        c, v = S.atrous_iteration(c, v, frame.depth, frame.normal, 2**i, cfg)
    assert_allclose(np.asarray(state.color), np.asarray(c), rtol=1e-5, atol=1e-6)
    assert_allclose(np.asarray(image), np.asarray(S.svgf_spatial(frame, cfg)), rtol=1e-5,
                    atol=1e-6)
    _, state2 = S.svgf_step(state, frame, cfg)
    assert_allclose(np.asarray(state2.history)[depth[..., 0] > 0], 2.0)


def static_sequence(frames, seed, h=24, w=24):
    """A static scene (no motion): constant illumination under a textured albedo, frames with
    independent multiplicative noise (gamma, mean 1, standard deviation 1)."""
    rng = np.random.default_rng(seed)
    xs = np.arange(w)[None, :]
    illum = np.broadcast_to(np.array([0.9, 0.7, 0.5]), (h, w, 3))
    albedo = rng.uniform(0.2, 0.9, (h, w, 3))
    depth = np.broadcast_to((2.0 + 0.01 * xs)[..., None], (h, w, 1))
    normal = np.broadcast_to([0.0, 0.0, 1.0], (h, w, 3))
    reference = illum * albedo
    noisy = [reference * rng.gamma(1.0, 1.0, (h, w, 1)) for _ in range(frames)]
    return reference, [as_frame(c, albedo, depth, normal, np.zeros((h, w, 2))) for c in noisy]


def rmse_per_frame(images, reference):
    return [float(np.sqrt(np.mean((np.asarray(im) - reference) ** 2))) for im in images]


@pytest.mark.parametrize("cfg", CONFIGS)
def test_static_sequence_error_falls(cfg):
    reference, frames = static_sequence(8, seed=17)
    errors = rmse_per_frame(S.svgf_sequence(frames, cfg), reference)
    noisy = float(np.sqrt(np.mean((np.asarray(frames[0].color) - reference) ** 2)))
    assert errors[0] < 0.2 * noisy
    # not monotone: at history 4 the spatial estimate hands over to the temporal variance
    assert np.mean(errors[4:]) < 0.85 * errors[0], errors


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("cfg", CONFIGS)
def test_static_sequence_error_falls_seeds(cfg, seed):
    reference, frames = static_sequence(16, seed=100 + seed, h=32, w=32)
    errors = rmse_per_frame(S.svgf_sequence(frames, cfg), reference)
    assert np.mean(errors[8:]) < 0.85 * errors[0], errors


def test_receptive_field_is_the_tiling_radius():
    """A change at one pixel reaches exactly ``svgf_radius`` pixels (Chebyshev) and no
    further: what tiles must overlap by."""
    cfg = dataclasses.replace(S.SVGF_FALCOR, iterations=2)
    radius = S.svgf_radius(cfg)
    assert radius == 2 * (1 + 2) + 3
    color, albedo, depth, normal = scene(18, h=24, w=24, miss=False)
    depth = np.full_like(depth, 2.0)
    normal[:] = [0.0, 0.0, 1.0]
    frame = as_frame(color, albedo, depth, normal)
    bumped = frame.replace(color=frame.color.at[12, 12].add(0.5))
    delta = np.abs(np.asarray(S.svgf_spatial(bumped, cfg) - S.svgf_spatial(frame, cfg)))
    ys, xs = np.nonzero(delta.max(-1) > 0)
    assert max(np.abs(ys - 12).max(), np.abs(xs - 12).max()) == radius


def test_the_registered_svgf_runs_a_sequence_as_svgf_sequence_does():
    """`load_denoiser("svgf")` carries SVGF's temporal form: Denoiser.sequence over frames
    equals svgf_sequence (the history carried, not the spatial form per frame), and its
    emission-separated form adds each frame's emission to the filtered rest."""
    reference, frames = static_sequence(4, seed=23, h=16, w=16)
    den = load_denoiser("svgf")
    assert den.temporal
    got = den.sequence(frames)
    for g, w in zip(got, S.svgf_sequence(frames)):
        assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-6)
    spatial = np.asarray(den(frames[3]))
    assert not np.allclose(np.asarray(got[3]), spatial, rtol=1e-3)
    emission = [np.zeros((16, 16, 3), np.float32) for _ in frames]
    emission[2][5, 6] = 50.0
    lit = [f.replace(color=np.asarray(f.color) + e, emission=e) for f, e in zip(frames, emission)]
    separated = load_denoiser("svgf:emission=separate").sequence(lit)
    for t in range(4):
        assert_allclose(np.asarray(separated[t]) - emission[t], np.asarray(got[t]),
                        rtol=1e-4, atol=1e-5)


def test_dark_albedo_does_not_spread_into_the_history():
    """A static scene where a fifth of the pixels have a black albedo channel (0) and the rest
    are textured: with the safe albedo (floor 0.05, the default) the sequence's error falls
    below the noisy input's; Falcor's guard max(albedo, 0.001) amplifies those pixels' noise
    1000x into their neighbours' history (seed 31, 24 x 24, 8 frames)."""
    reference, frames = static_sequence(8, seed=31)
    rng = np.random.default_rng(31)
    dark = rng.uniform(size=(24, 24)) < 0.2
    frames = [f.replace(albedo=np.where(dark[..., None], [0.0, 0.5, 0.5], np.asarray(f.albedo)))
              for f in frames]
    noisy = float(np.sqrt(np.mean((np.asarray(frames[-1].color) - reference) ** 2)))
    safe = rmse_per_frame(S.svgf_sequence(frames, S.SVGF_PAPER), reference)
    guard = rmse_per_frame(S.svgf_sequence(
        frames, dataclasses.replace(S.SVGF_PAPER, albedo_floor=0.0)), reference)
    assert safe[-1] < 0.5 * noisy, (safe, noisy)
    assert guard[-1] > 2 * safe[-1], (guard, safe)
