"""SureSettings: SURE's options as one validated value, passed whole from the command line, a
mixer's config and an evaluator's options to `jaxden.sure.sure`; "unset: the mixer's" said one
way (`over`); the older flat keys of stored mixer configs mapped in one place; the flags made
from the fields; the older keyword form of the functions still working; and the one-line
warning when a trained mixer mixes another denoiser."""

from __future__ import annotations

import argparse
import dataclasses
import json
import warnings

import jax
import numpy as np
import pytest

from jaxden.config import config_to_dict, dump_config, load_config
from jaxden.errors import ConfigError, FrameError
from jaxden.frame import Frame
from jaxden.progressive.mixer_config import (
    LEGACY_SURE_KEYS,
    MIXER_SURE,
    MixerConfig,
    upgrade_mixer_config,
)
from jaxden.sure import SureSettings, sure
from jaxden.sure.settings import DEFAULTS, UNSET, resolve_settings


def _frame(seed=0, size=(6, 5)):
    rng = np.random.default_rng(seed)
    return Frame(color=rng.uniform(0.1, 2.0, (*size, 3)).astype(np.float32),
                 variance=rng.uniform(1e-3, 5e-2, (*size, 3)).astype(np.float32))


def _blur(frame):
    return 0.5 * frame.color + 0.25 * (jax.numpy.roll(frame.color, 1, axis=0)
                                       + jax.numpy.roll(frame.color, -1, axis=1))


# --------------------------------------------------------------------------------- the value
@pytest.mark.parametrize("changes, message", [
    ({"probes": 0}, "SURE option probes must be an integer >= 1, got 0"),
    ({"probes": 2.5}, "probes must be an integer"),
    ({"probes": True}, "probes must be an integer"),
    ({"method": "adjoint"}, "method must be one of auto, jvp, fd, got 'adjoint'"),
    ({"eps": 0.0}, "eps must be a finite number > 0, got 0.0"),
    ({"eps": float("nan")}, "eps must be a finite number"),
    ({"fd_scheme": "backward"}, "fd_scheme must be one of forward, central"),
    ({"probe_batch": 0}, "probe_batch must be an integer >= 1"),
    ({"probe_dist": "uniform"}, "probe_dist must be one of normal, rademacher, got 'uniform'"),
    ({"covariance": "yes"}, "covariance must be true or false"),
    ({"seed": -1}, r"seed must be an integer in \[0, 4294967295\]"),
])
def test_a_bad_option_is_one_line_naming_it(changes, message):
    with pytest.raises(ConfigError, match=message) as raised:
        SureSettings(**changes)
    assert "\n" not in str(raised.value)


def test_unset_over_base_resolved():
    assert SureSettings() == UNSET and UNSET.given() == {} and repr(UNSET) == "SureSettings()"
    given = SureSettings(probes=np.int64(2), eps=np.float32(0.5))  # NumPy scalars: Python's
    assert type(given.probes) is int and type(given.eps) is float
    mixer = MIXER_SURE.replace(probes=1, probe_dist="rademacher", seed=3)
    both = given.over(mixer)
    assert (both.probes, both.eps, both.probe_dist, both.seed, both.covariance) == (
        2, 0.5, "rademacher", 3, False)
    assert UNSET.over(mixer) == mixer and given.over(None) == given
    assert DEFAULTS == UNSET.resolved()
    assert DEFAULTS.given() == {"probes": 4, "method": "auto", "fd_scheme": "forward",
                                "probe_dist": "normal", "covariance": True, "seed": 0}
    # the one rule of the functions: loose keywords over `sure` over the base over DEFAULTS
    settings = resolve_settings(SureSettings(probes=3, method="fd"), mixer, num_probes=5,
                                eps=None)
    assert (settings.probes, settings.method, settings.probe_dist, settings.fd_scheme) == (
        5, "fd", "rademacher", "forward")
    with pytest.raises(ConfigError, match="SURE option num_probes must be"):  # as written
        resolve_settings(num_probes=0)
    with pytest.raises(ConfigError, match="must be a SureSettings"):
        resolve_settings({"probes": 2})


def test_the_older_keyword_form_of_sure_gives_the_same_result():
    frame, key = _frame(), jax.random.PRNGKey(3)
    older = sure(_blur, frame, key, 3, "fd", 1e-3, fd_scheme="central", probe_dist="rademacher")
    settings = SureSettings(probes=3, method="fd", eps=1e-3, fd_scheme="central",
                            probe_dist="rademacher")
    newer = sure(_blur, frame, key, settings=settings)
    for a, b in zip(older, newer, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a keyword overrides its field of the value
    two = sure(_blur, frame, key, settings=settings, num_probes=2)
    np.testing.assert_array_equal(np.asarray(two.sure),
                                  np.asarray(sure(_blur, frame, key, settings=settings.replace(
                                      probes=2)).sure))


def test_covariance_off_is_the_per_channel_form():
    frame = _frame(2)
    frame = frame.replace(covariance=np.full(frame.color.shape, 1e-3, np.float32))
    key = jax.random.PRNGKey(1)
    with_cov = sure(_blur, frame, key, settings=SureSettings(probes=2))
    off = sure(_blur, frame, key, settings=SureSettings(probes=2, covariance=False))
    plain = sure(_blur, frame.replace(covariance=None), key, 2)
    np.testing.assert_array_equal(np.asarray(off.sure), np.asarray(plain.sure))
    assert not np.allclose(np.asarray(with_cov.sure), np.asarray(off.sure))


# ------------------------------------------------------------------------- a mixer's settings
def test_a_mixers_settings_are_one_table_and_unset_fields_are_the_mixers(tmp_path):
    config = MixerConfig(sure=SureSettings(probes=1))  # partial: the rest is MIXER_SURE's
    assert config.sure == MIXER_SURE.replace(probes=1) and config.sure.covariance is False
    toml = tmp_path / "m.toml"
    toml.write_text('denoiser = "wskp-6"\n[sure]\nprobes = 1\nprobe_dist = "rademacher"\n')
    loaded = load_config(toml, MixerConfig)
    assert loaded.sure == MIXER_SURE.replace(probes=1, probe_dist="rademacher")
    text = dump_config(config)
    assert "[sure]" in text and "sure_probes" not in text
    (tmp_path / "dumped.toml").write_text(text)
    assert load_config(tmp_path / "dumped.toml", MixerConfig) == config
    assert load_config(MixerConfig(), MixerConfig, ["sure.covariance=true"]).sure.covariance
    (toml.parent / "bad.toml").write_text("[sure]\nprobes = 0\n")
    with pytest.raises(ConfigError, match=r"bad\.toml.*SURE option probes must be"):
        load_config(toml.parent / "bad.toml", MixerConfig)


def test_the_older_flat_keys_load_the_same_config():
    flat = {"denoiser": "oidn", "sure_probes": 2, "sure_method": "fd", "sure_eps": None,
            "sure_seed": 5, "sure_probe_dist": "rademacher", "width": 8}
    upgraded = upgrade_mixer_config(flat)
    assert not set(LEGACY_SURE_KEYS) & set(upgraded)
    config = load_config(upgraded, MixerConfig)
    assert config.sure == MIXER_SURE.replace(probes=2, method="fd", seed=5,
                                             probe_dist="rademacher")
    assert load_config(MixerConfig.upgrade_config(flat), MixerConfig) == config  # the hook
    assert upgrade_mixer_config(config_to_dict(config)) == config_to_dict(config)  # today's
    with pytest.raises(ConfigError, match="sure_probes and sure.probes both given"):
        upgrade_mixer_config({"sure_probes": 2, "sure": {"probes": 3}})


def test_checkpoints_recorded_with_flat_keys_still_load(tmp_path):
    from jaxden.progressive import load_mixer, mixer_init, save_mixer

    config = MixerConfig(width=4, sure=SureSettings(probes=2, covariance=True))
    params = mixer_init(jax.random.PRNGKey(0), config)
    path = tmp_path / "m.msgpack"
    save_mixer(path, params, config)
    meta = json.loads(path.with_suffix(".json").read_text())
    table = meta["model_config"].pop("sure")
    meta["model_config"] |= {f"sure_{k}": v for k, v in table.items()
                             if f"sure_{k}" in LEGACY_SURE_KEYS}
    path.with_suffix(".json").write_text(json.dumps(meta))
    assert load_mixer(str(path))[1] == config
    # the shipped mixers, whose records hold the flat keys: the settings they were trained on
    for name, probes in (("oidn-pd", 4), ("wskp-6-pd", 1)):
        shipped = json.loads(_weights(name).read_text())
        assert "sure_probes" in shipped["model_config"]
        assert load_mixer(name)[1].sure == MIXER_SURE.replace(probes=probes)


def _weights(name):
    from jaxden.denoise.registry import WEIGHTS_DIR

    return WEIGHTS_DIR / f"{name}.json"


def test_the_twin_takes_its_sure_over_the_mixers():
    from jaxden.progressive.pipeline import TWIN_SURE, load_shipped_mixer

    _, config = load_shipped_mixer("oidn")
    _, twin = load_shipped_mixer("oidn-jax")
    assert twin.sure == TWIN_SURE["oidn-jax"].over(config.sure)
    assert (twin.sure.probes, twin.sure.method, twin.sure.probe_dist) == (1, "jvp",
                                                                          "rademacher")
    assert dataclasses.replace(twin, sure=config.sure) == config


def test_the_cache_identity_keeps_its_keys():
    from jaxden.denoise.registry import load_denoiser
    from jaxden.progressive.cache_build import cache_settings

    oidn = load_denoiser("oidn")
    assert cache_settings(MIXER_SURE, oidn) == {
        "num_probes": 4, "method": "fd", "eps": 1e-2, "fd_scheme": "forward", "seed": 0,
        "half": False}  # what caches built before the value recorded: their key holds
    other = cache_settings(MIXER_SURE.replace(covariance=True, probe_dist="rademacher",
                                              probe_batch=1), oidn, half=True)
    assert other["covariance"] is True and other["probe_dist"] == "rademacher"
    assert "probe_batch" not in other and other["half"] is True


# ------------------------------------------------------------------------------ command line
def test_the_flags_are_made_from_the_fields():
    from jaxden.cli.options import add_sure_options, sure_settings

    parser = argparse.ArgumentParser()
    add_sure_options(parser, inherit="the mixer's")
    flags = {a.dest: a for a in parser._actions if a.dest != "help"}
    assert set(flags) == {f.name for f in dataclasses.fields(SureSettings)}
    assert all(a.default is None and "the mixer's" in a.help for a in flags.values())
    assert sure_settings(parser.parse_args([])) == UNSET
    args = parser.parse_args(["--probes", "2", "--method", "fd", "--eps", "0.01",
                              "--fd-scheme", "central", "--probe-batch", "1",
                              "--probe-dist", "rademacher", "--no-covariance", "--seed", "7"])
    assert sure_settings(args) == SureSettings(probes=2, method="fd", eps=0.01,
                                               fd_scheme="central", probe_batch=1,
                                               probe_dist="rademacher", covariance=False,
                                               seed=7)
    for argv in (["--probes", "0"], ["--eps", "-1"], ["--seed", "x"], ["--method", "adjoint"]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)


def test_progressive_cli_takes_unset_options_from_the_mixer(tmp_path, capsys):
    from jaxden.cli import main
    from jaxden.io.exr import read_header, write_frame
    from jaxden.render.synthetic import synthetic_render

    source = tmp_path / "in.exr"
    write_frame(source, synthetic_render("settings", 8, seed=2, size=(12, 10)).numpy())
    out = tmp_path / "out.exr"
    assert main(["progressive", str(source), "--denoiser", "oidn", "--mixer",
                 "closed-form", "--probe-dist", "rademacher", "--out", str(out)]) == 0
    header = read_header(out)
    assert (header["probes"], header["probe_dist"], header["seed"]) == (4, "rademacher", 0)


# ------------------------------------------------------------------- a mixer over another base
def test_another_denoiser_is_said_once_per_pair_and_twins_are_not(recwarn):
    from jaxden.denoise.registry import Denoiser, load_denoiser
    from jaxden.progressive import pipeline
    from jaxden.progressive.pipeline import MixerDenoiserWarning, warn_if_other_denoiser

    pipeline._WARNED.clear()
    oidn_pd = MixerConfig(denoiser="oidn", width=4)
    wskp6 = load_denoiser("wskp-6")
    with pytest.warns(MixerDenoiserWarning, match="trained on the output of denoiser 'oidn'; "
                                                  "mixing 'wskp' instead"):
        assert warn_if_other_denoiser(oidn_pd, wskp6, "wskp-6") is not None
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_if_other_denoiser(oidn_pd, wskp6) is None  # once per process and pair
        twin = Denoiser.from_function(lambda f: f.color, name="oidn-jax")
        assert warn_if_other_denoiser(oidn_pd, twin) is None
        # the same network and weights under another name (a shipped name's model is "wskp")
        assert warn_if_other_denoiser(MixerConfig(denoiser="wskp-6", width=4), wskp6) is None
        assert warn_if_other_denoiser(MixerConfig(kind="closed_form"), wskp6) is None


# ------------------------------------------------------------------------------- sub-buffers
def test_sub_buffer_checks_name_the_parameter_and_the_files():
    from jaxden.data.merge import BufferList, colour_digest
    from jaxden.sure.buffers import check_sub_buffers

    rng = np.random.default_rng(0)
    parts = [rng.uniform(0, 1, (4, 3, 3)).astype(np.float32) for _ in range(3)]
    color = np.mean(parts, axis=0)
    names = ["a.exr", "b.exr", "c.exr"]
    assert check_sub_buffers(color, parts).shape == (3, 4, 3, 3)
    with pytest.raises(FrameError, match="^buffers: need K >= 2 sub-buffers, got 1$"):
        check_sub_buffers(color, parts[:1], where="buffers")
    with pytest.raises(FrameError, match="b.exr and c.exr are identical"):
        check_sub_buffers(color, [parts[0], parts[1], parts[1]], names=names)
    with pytest.raises(FrameError, match=r"equal spp, got 4 \(a.exr\), 8 \(c.exr\)"):
        check_sub_buffers(color, parts, names=names, spp=[4, None, 8])
    made = BufferList(("x.exr", "y.exr", "z.exr"), tuple(colour_digest(p) for p in parts))
    check_sub_buffers(color, parts, names=names, made_from=made)
    with pytest.raises(FrameError, match="names 2 files, but in.exr was made from 3 buffers"):
        check_sub_buffers(color, parts[:2], names=names[:2], made_from=made,
                          frame_name="in.exr")
    other = [parts[0], parts[1], parts[2] + 1e-3]
    with pytest.raises(FrameError, match="c.exr is not one of the 3 buffers"):
        check_sub_buffers(np.mean(other, axis=0), other, names=names, made_from=made)
    with pytest.raises(FrameError, match="the colour of in.exr is not the mean"):
        check_sub_buffers(color + 1, parts, frame_name="in.exr")
