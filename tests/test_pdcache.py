"""Tests of the SURE cache (jaxden.progressive.cache): it builds, equals direct SURE calls with the same
probes, resumes without recomputing finished items, refuses another denoiser or setting, and
cuts the same windows as the dataset loader.

Data: a tiny Mitsuba-free dataset (jaxden.render.synthetic.synthetic_render, 2 scenes x 2 crops of
32 x 32, spp 1, 4, 16; the spp-1 items have no variance and are skipped by the cache).
Denoisers: OIDN (a black box: finite differences) and a one-parameter JAX blur (jvp).
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.data.item_cache import inverse_dihedral, locate_crop
from jaxden.data.layout import load_manifest
from jaxden.data.loader import DatasetLoader, dihedral
from jaxden.denoise.registry import Denoiser, DenoiserDef, make_denoiser
from jaxden.errors import ConfigError, DatasetError
from jaxden.io.exr import read_frame, read_header
from jaxden.progressive import cache as pdcache
from jaxden.progressive import cache_build
from jaxden.progressive.mixer_config import MixerConfig
from jaxden.render.synthetic import synthetic_render
from jaxden.sure.settings import SureSettings
from jaxden.sure.stein import draw_probes, sure, sure_blackbox

TINY = "experiments/configs/dataset-tiny.toml"


# ------------------------------------------------------------------------ fixtures


@dataclasses.dataclass(frozen=True)
class BlurConfig:
    radius: int = 1


def blur_apply(params, config: BlurConfig, frame):
    """y = (1 - w) x + w * mean of the (2r+1)^2 neighbourhood (edge-padded): a JAX denoiser."""
    x = jnp.asarray(frame.color)
    r = config.radius
    pad = [(0, 0)] * (x.ndim - 3) + [(r, r), (r, r), (0, 0)]
    padded = jnp.pad(x, pad, mode="edge")
    h, w = x.shape[-3], x.shape[-2]
    box = sum(padded[..., dy : dy + h, dx : dx + w, :] for dy in range(2 * r + 1)
              for dx in range(2 * r + 1)) / (2 * r + 1) ** 2
    return (1 - params["w"]) * x + params["w"] * box


BLUR = DenoiserDef(
    name="test-blur", description="test blur", config_cls=BlurConfig,
    required=lambda config: ("color",), apply=blur_apply,
    init=lambda key, config: {"w": jnp.float32(0.5)},
)


def blur_denoiser(w: float = 0.5) -> Denoiser:
    return Denoiser(BLUR, BlurConfig(), {"w": jnp.float32(w)})


def blur_fn(params, frame):  # module level: sure() compiles once for it
    return blur_apply(params, BlurConfig(), frame)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("pdcache") / "tiny"
    config = load_config(TINY, DatasetConfig, ["crops_per_scene=2", "spp=[1, 4, 16]"])
    build_dataset(config, root, executor="serial", render_fn=synthetic_render, progress=False)
    return root


@pytest.fixture(scope="module")
def oidn_cache(dataset):
    return cache_build.build_sure_cache(dataset, "oidn", progress=False)


def input_items(root, min_spp=2):
    return [i for i in load_manifest(root).items if i.kind == "input" and i.spp >= min_spp]


# ------------------------------------------------------------------------ building


def test_cache_has_one_exr_per_input_with_variance(dataset, oidn_cache):
    assert oidn_cache.directory == dataset / "derived" / "oidn"
    assert oidn_cache.complete
    items = input_items(dataset)
    assert len(items) == 8 and set(oidn_cache.records) == {i.id for i in items}
    data = json.loads((oidn_cache.directory / pdcache.CACHE_MANIFEST).read_text())
    assert data["complete"] and data["items_total"] == 8
    assert sorted(data["skipped_no_variance"]) == sorted(
        i.id for i in load_manifest(dataset).items if i.kind == "input" and i.spp == 1)
    settings = data["identity"]["settings"]
    assert settings == {"num_probes": 4, "method": "fd", "eps": 1e-2, "fd_scheme": "forward",
                        "seed": 0, "half": False}
    assert data["identity"]["denoiser"]["name"] == "oidn"
    item = items[0]
    header = read_header(oidn_cache.directory / item.path)
    assert set(header["channels"]) == {"R", "G", "B", "sure.R", "sure.G", "sure.B",
                                       "divergence.R", "divergence.G", "divergence.B"}
    assert header["item"] == item.id and header["source_sha256"] == item.sha256
    assert header["seed"] == pdcache.item_seed(0, item.id)


def test_cached_oidn_sure_equals_direct_blackbox_call(dataset, oidn_cache):
    oidn = make_denoiser("oidn").function()
    for item in input_items(dataset)[:2]:
        frame = read_frame(dataset / item.path, require=("color", "variance"))
        key = jax.random.PRNGKey(pdcache.item_seed(0, item.id))
        probes = np.asarray(draw_probes(key, frame.variance, 4), np.float64)
        direct = sure_blackbox(oidn, frame, probes=probes, eps=1e-2)
        cached = oidn_cache.read(item.id)
        np.testing.assert_array_equal(cached["denoised"], direct.denoised)
        np.testing.assert_array_equal(cached["sure"], direct.sure)
        np.testing.assert_array_equal(cached["divergence"], direct.divergence_term)
        np.testing.assert_array_equal(cached["denoised"], oidn(frame))


def test_cached_jax_sure_equals_direct_jvp_call(dataset, tmp_path):
    cache = cache_build.build_sure_cache(dataset, blur_denoiser(), tmp_path / "blur", seed=7,
                                     progress=False)
    settings = cache.identity["settings"]
    assert settings["method"] == "jvp" and settings["eps"] is None
    params = {"w": jnp.float32(0.5)}
    for item in input_items(dataset)[:3]:
        frame = read_frame(dataset / item.path, require=("color", "variance"))
        direct = sure(blur_fn, frame, jax.random.PRNGKey(pdcache.item_seed(7, item.id)), 4,
                      "jvp", params=params)
        cached = cache.read(item.id)
        scale = float(np.abs(direct.sure).max())
        np.testing.assert_allclose(cached["sure"], direct.sure, rtol=1e-6, atol=1e-7 * scale)
        np.testing.assert_allclose(cached["denoised"], direct.denoised, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(cached["divergence"], direct.divergence_term, rtol=1e-6,
                                   atol=1e-7 * scale)


def _mtimes(directory):
    return {p.relative_to(directory): p.stat().st_mtime_ns for p in directory.rglob("*.exr")}


def test_rerun_recomputes_only_missing_damaged_or_stale_items(dataset, tmp_path, monkeypatch):
    out = tmp_path / "blur"
    cache_build.build_sure_cache(dataset, blur_denoiser(), out, progress=False)
    items = input_items(dataset)
    deleted, truncated, unrecorded, stale = items[0], items[1], items[2], items[3]
    (out / deleted.path).unlink()
    with open(out / truncated.path, "r+b") as handle:
        handle.truncate(100)
    manifest_path = out / pdcache.CACHE_MANIFEST
    data = json.loads(manifest_path.read_text())
    del data["items"][unrecorded.id]  # written after the last manifest save, then killed
    data["items"][stale.id]["source_sha256"] = "0" * 64  # computed from an older dataset file
    manifest_path.write_text(json.dumps(data))
    before = _mtimes(out)

    computed = []
    original = cache_build.denoise_with_sure

    def counting(denoiser, frame, key, **kwargs):
        computed.append(kwargs["where"])
        return original(denoiser, frame, key, **kwargs)

    monkeypatch.setattr(cache_build, "denoise_with_sure", counting)
    cache = cache_build.build_sure_cache(dataset, blur_denoiser(), out, progress=False)
    assert sorted(computed) == sorted(str(dataset / i.path) for i in (deleted, truncated, stale))
    after = _mtimes(out)
    for item in items[4:] + [unrecorded]:
        assert after[out.joinpath(item.path).relative_to(out)] == before[
            out.joinpath(item.path).relative_to(out)]
    assert cache.complete and set(cache.records) == {i.id for i in items}
    assert cache.records[unrecorded.id]["source_sha256"] == unrecorded.sha256

    computed.clear()
    cache_build.build_sure_cache(dataset, blur_denoiser(), out, progress=False)
    assert computed == []  # a complete cache is only checked


def test_refuses_another_denoiser_or_setting(dataset, tmp_path):
    out = tmp_path / "blur"
    cache_build.build_sure_cache(dataset, blur_denoiser(), out, progress=False)
    manifest = (out / pdcache.CACHE_MANIFEST).read_text()
    for spec, options, words in (
        (blur_denoiser(0.25), {}, "params_sha256"),
        ("oidn", {}, "denoiser.name"),
        (blur_denoiser(), {"num_probes": 2}, "num_probes"),
        (blur_denoiser(), {"seed": 1}, "seed"),
        (blur_denoiser(), {"method": "fd"}, "method"),
    ):
        with pytest.raises(DatasetError, match=f"another dataset, denoiser or setting.*{words}"):
            cache_build.build_sure_cache(dataset, spec, out, progress=False, **options)
    assert (out / pdcache.CACHE_MANIFEST).read_text() == manifest


def test_refuses_incomplete_dataset_foreign_folder_and_bad_options(dataset, tmp_path):
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty.*notes.txt"):
        cache_build.build_sure_cache(dataset, blur_denoiser(), foreign, progress=False)
    with pytest.raises(ConfigError, match="black box.*fd"):
        cache_build.build_sure_cache(dataset, "oidn", tmp_path / "x", method="jvp", progress=False)
    with pytest.raises(ConfigError, match="num_probes"):
        cache_build.build_sure_cache(dataset, "oidn", tmp_path / "x", num_probes=0, progress=False)
    partial = tmp_path / "partial"
    shutil.copytree(dataset, partial, ignore=shutil.ignore_patterns("derived"))
    data = json.loads((partial / "manifest.json").read_text())
    data["items"][0]["sha256"] = None
    (partial / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="incomplete"):
        cache_build.build_sure_cache(partial, "oidn", progress=False)
    # SURE from the covariance on a dataset without one (the synthetic renderer records none):
    # refused, naming the item, before anything is written.
    out = tmp_path / "cov"
    with pytest.raises(DatasetError, match=r"\.exr: no colour covariance.*sure\.covariance"):
        cache_build.build_sure_cache(dataset, blur_denoiser(), out, covariance=True,
                                     progress=False)
    assert not list(out.rglob("*.exr"))


def test_the_two_forms_of_sure_have_their_own_default_folders(dataset):
    # SURE per channel and from the colour covariance are different caches of one denoiser:
    # side by side (a study of the two trains mixers on both), never in each other's way.
    plain = cache_build.default_cache_dir(dataset, blur_denoiser())
    covariance = SureSettings(covariance=True)
    assert cache_build.default_cache_dir(dataset, blur_denoiser(), covariance) == (
        plain.with_name(plain.name + "-cov"))


def test_spec_options_give_their_own_cache_folder(tmp_path):
    """A denoiser run with spec options (another output) gets its own derived/ folder; its
    default config keeps the plain name, and equal options share one."""
    from jaxden.denoise.registry import load_denoiser

    folder = lambda spec: cache_build.default_cache_dir(tmp_path, load_denoiser(spec)).name  # noqa: E731
    assert folder("oidn") == "oidn" and folder("oidn:quality=high") == "oidn"
    fast = folder("oidn:quality=fast")
    assert fast.startswith("oidn-c") and fast == folder("oidn:quality=fast")
    assert len({fast, folder("oidn:aux=albedo"), folder("oidn")}) == 3


def test_open_training_cache_without_building(dataset, tmp_path, oidn_cache):
    config = MixerConfig(denoiser="oidn", build_cache=False, cache=str(tmp_path / "none"))
    with pytest.raises(DatasetError, match="no SURE cache.*sure-cache"):
        cache_build.open_training_cache(dataset, config)
    ok = cache_build.open_training_cache(dataset, MixerConfig(denoiser="oidn", build_cache=False))
    assert ok.directory == oidn_cache.directory
    with pytest.raises(DatasetError, match="num_probes"):
        cache_build.open_training_cache(dataset, MixerConfig(build_cache=False,
                                                             sure=SureSettings(probes=1)))


# ------------------------------------------------------------------------ reading


def test_crops_for_cuts_the_loaders_windows(dataset, oidn_cache):
    loader = DatasetLoader(dataset, "all", batch_size=3, crop_size=12, seed=3, spp=[4, 16],
                           features=("color", "variance"), reference_features=("color",))
    for epoch in (0, 1):
        plan = loader.plan_epoch(epoch)
        for number, batch in enumerate(loader.epoch(epoch)):
            denoised, sure_map, windows = oidn_cache.crops_for(batch)
            assert denoised.shape == sure_map.shape == (3, 12, 12, 3)
            for b, (index, top, left, symmetry) in enumerate(plan[3 * number : 3 * number + 3]):
                assert windows[b] == (top, left, symmetry)
                full = oidn_cache.read(loader.samples[index][0].id)
                np.testing.assert_array_equal(
                    denoised[b], dihedral(full["denoised"][top : top + 12, left : left + 12],
                                          symmetry))
                np.testing.assert_array_equal(
                    sure_map[b], dihedral(full["sure"][top : top + 12, left : left + 12], symmetry))


def test_inverse_dihedral_and_locate_crop():
    rng = np.random.default_rng(0)
    full = rng.normal(size=(9, 8, 6)).astype(np.float32)
    for symmetry in range(8):
        window = full[2:7, 1:6]
        np.testing.assert_array_equal(inverse_dihedral(dihedral(window, symmetry), symmetry),
                                      window)
        assert locate_crop(full, dihedral(window, symmetry)) == (2, 1, symmetry)
    # Ties (a window repeated exactly, here everywhere) go to symmetry 0, first position.
    assert locate_crop(np.zeros((9, 8, 6)), np.zeros((4, 4, 6))) == (0, 0, 0)
    with pytest.raises(DatasetError, match="not a window"):
        locate_crop(full, full[2:6, 1:5] + 1)


def test_read_errors_name_the_item(oidn_cache):
    with pytest.raises(DatasetError, match="not in the SURE cache"):
        oidn_cache.read("no-such-item")


def test_cache_folder_permissions_are_shared(oidn_cache):
    path = next(oidn_cache.directory.rglob("*.exr"))
    assert os.stat(path).st_mode & 0o044  # readable by others, like the dataset files
