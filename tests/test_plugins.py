"""Plugins (jaxden/plugins.py, jaxden/registry.py): a user's module, outside the package and
not on sys.path, named by --plugin, JAXDEN_PLUGINS or a config's ``plugins``, fills the
registries in every process jaxden starts; clashes and failing imports are one line; what a
plugin computes is recorded (provenance) and keys derived data (the SURE cache identity).

The outside module is tests/data/plugins/lab_denoisers.py, copied into a temporary folder so
that nothing but the plugin mechanism can find it."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxden import plugins
from jaxden.cli import main
from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.denoise import REGISTRY, Denoiser
from jaxden.errors import ConfigError
from jaxden.registry import PluginClashError, Registry
from jaxden.render.synthetic import synthetic_render

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = ROOT / "tests" / "data" / "plugins" / "lab_denoisers.py"
TINY = ROOT / "experiments" / "configs" / "dataset-tiny.toml"


@pytest.fixture(autouse=True)
def _forget_loaded_plugins():
    """Other test files in this process must not see these tests' plugins in provenance."""
    loaded = dict(plugins._LOADED)
    yield
    plugins._LOADED.clear()
    plugins._LOADED.update(loaded)


@pytest.fixture
def clean_env(monkeypatch):
    """JAXDEN_PLUGINS as a test found it, restored afterwards (loading writes to it)."""
    monkeypatch.setenv(plugins.ENV, "")  # recorded, so that teardown restores it ...
    monkeypatch.delenv(plugins.ENV)  # ... even where it was unset
    monkeypatch.setenv("PYTHONPATH", "")
    return monkeypatch


@pytest.fixture(scope="module")
def outside(tmp_path_factory):
    """A folder outside the package with the plugin module and a tiny synthetic dataset."""
    folder = tmp_path_factory.mktemp("outside")
    shutil.copy(PLUGIN, folder / "lab_denoisers.py")
    config = load_config(TINY, DatasetConfig, ["crops_per_scene=2"])
    build_dataset(config, folder / "tiny", executor="serial", render_fn=synthetic_render,
                  progress=False)
    (folder / "train.toml").write_text(
        'plugins = ["lab_denoisers.py"]\nmodel = "lab-tinyconv"\neval_every = 2\n'
        'checkpoint_every = 2\n[data]\ndataset = "tiny"\ncrop_size = 32\nbatch_size = 2\n'
        '[optim]\nsteps = 2\nloss = "lab-charbonnier"\n')
    return folder


# --------------------------------------------------------------------------- the registry
def test_registry_refuses_a_name_another_module_holds():
    table = Registry("widget")
    table.add("a", 1, owner="jaxden.widgets")
    table.add("a", 2, owner="jaxden.widgets")  # the same module again: replaced
    assert table["a"] == 2
    with pytest.raises(PluginClashError, match="'a' from module 'mine' clashes with jaxden's "
                                               "built-in widget 'a'"):
        table.add("a", 3, owner="mine")
    table.add("b", 1, owner="theirs")
    with pytest.raises(PluginClashError, match="the widget of module 'theirs'"):
        table.add("b", 1, owner="mine")
    with pytest.raises(ConfigError, match="without spaces or ':'"):
        table.add("x:y", 1, owner="mine")
    assert table.from_plugins() == {"b": 1}


def test_a_plugin_cannot_take_a_built_in_or_shipped_name():
    for name in ("wskp", "oidn", "wskp-6", "oidn-pd"):
        with pytest.raises(PluginClashError, match=f"'{name}' from module '{__name__}'"):
            Denoiser.from_function(lambda frame: frame.color, name=name, register=True)
    from jaxden.train.tasks import Trainable, register_trainable

    with pytest.raises(PluginClashError, match="trainable model name 'mixer'|'wskp'"):
        register_trainable(Trainable("wskp", "denoiser", dict, None, None, None))


# ------------------------------------------------------------------------------- loading
def test_the_outside_module_is_not_importable_by_default(outside):
    assert importlib.util.find_spec("lab_denoisers") is None or "lab_denoisers" in sys.modules


def test_a_failing_or_missing_plugin_is_one_line(tmp_path, clean_env, capsys):
    broken = tmp_path / "broken_plugin.py"
    broken.write_text("import math\n\nvalue = math.sqrt(-1)\n")
    assert main(["--plugin", str(broken), "denoise", "--help"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("jaxden: error: plugin ")
    assert "ValueError: math domain error" in err and f"{broken}, line 3" in err
    assert main(["denoise", "--plugin", "no_such_plugin_module", "--help"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "no module named 'no_such_plugin_module'" in err
    clash = tmp_path / "clashing_plugin.py"
    clash.write_text("from jaxden.denoise import Denoiser\n"
                     "Denoiser.from_function(lambda f: f.color, name='unet', register=True)\n")
    clean_env.setenv(plugins.ENV, str(clash))
    assert main(["scenes"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("jaxden: error: denoiser name 'unet' from module 'clashing_plugin' clashes "
                   "with jaxden's built-in denoiser 'unet'; register it under another name")


def test_loaded_plugins_reach_child_processes_and_provenance(outside, clean_env):
    loaded = plugins.load([str(outside / "lab_denoisers.py")])
    assert [p.module for p in loaded] == ["lab_denoisers"]
    assert REGISTRY.owner("lab-xbilateral") == "lab_denoisers"
    # children inherit the absolute path, from any folder
    assert str(outside / "lab_denoisers.py") in plugins.split_specs(
        __import__("os").environ[plugins.ENV])
    code = ("from jaxden.denoise import get_definition; "
            "print(get_definition('lab-tinyconv').description)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd="/", check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "residual two-layer CNN (test plugin)"
    from jaxden.provenance import run_identity

    record = run_identity([], program="x")["plugins"]
    digest = __import__("hashlib").sha256(PLUGIN.read_bytes()).hexdigest()
    assert {"module": "lab_denoisers", "sha256": digest,
            "file": str(outside / "lab_denoisers.py")} in record


def test_a_worker_without_the_file_runs_the_carried_source(tmp_path, clean_env):
    source = ("from jaxden.denoise import Denoiser\n"
              "Denoiser.from_function(lambda f: 2 * f.color, name='carried-double', "
              "register=True)\n")
    plugins.load_payload([(str(tmp_path / "gone" / "carried_plugin.py"), "carried_plugin",
                           source)])
    assert REGISTRY.owner("carried-double") == "carried_plugin"


def test_plugin_options_are_taken_anywhere_on_the_command_line():
    assert plugins.take_plugin_options(["train", "--plugin", "a", "c.toml", "--plugin=b.py",
                                        "x=1"]) == (["a", "b.py"], ["train", "c.toml", "x=1"])
    assert plugins.split_specs("a, b:c.py") == ["a", "b", "c.py"]


# ------------------------------------------------------------------------------ identity
def _function_from_source(source: str):
    namespace: dict = {}
    exec(compile(source, "user_code.py", "exec"), namespace)  # noqa: S102 - test code
    return Denoiser.from_function(namespace["smooth"], name="user-smooth")


def test_changing_the_code_changes_the_sure_cache_key():
    """Same name, same (no) weights: a changed computation is another SURE cache identity;
    a changed comment or docstring is not."""
    from jaxden.data.item_cache import denoiser_identity, identity_key

    first = "import jax.numpy as jnp\ndef smooth(frame):\n    return 0.5 * frame.color\n"
    documented = ("import jax.numpy as jnp\n# a comment\n\ndef smooth(frame):\n"
                  "    '''Halves the colour.'''\n    return 0.5 * frame.color\n")
    changed = "import jax.numpy as jnp\ndef smooth(frame):\n    return 0.6 * frame.color\n"
    keys = [identity_key({"denoiser": denoiser_identity(_function_from_source(text))})
            for text in (first, documented, changed)]
    assert keys[0] == keys[1] != keys[2]


def test_a_sure_cache_is_recomputed_when_the_denoisers_code_changes(outside, capsys):
    """The mixer's SURE cache of a denoiser (same name, no weights) built with one code is
    recomputed, in place, once the code computes something else; a documentation edit
    keeps it."""
    from jaxden.progressive.cache_build import build_sure_cache
    from jaxden.sure import SureSettings

    first = "def smooth(frame):\n    return 0.5 * frame.color\n"
    documented = 'def smooth(frame):\n    """Halves."""\n    return 0.5 * frame.color\n'
    changed = "def smooth(frame):\n    return 0.6 * frame.color\n"
    folder = outside / "tiny" / "derived" / "user-smooth-test"
    settings = SureSettings(probes=1)

    def build(source):
        cache = build_sure_cache(outside / "tiny", _function_from_source(source), folder,
                                 sure=settings, progress=False)
        return {item: cache.read(item)["denoised"].copy() for item in sorted(cache.records)}

    before = build(first)
    assert before and "recomputing" not in capsys.readouterr().err
    assert all(np.array_equal(before[k], v) for k, v in build(documented).items())
    assert "recomputing" not in capsys.readouterr().err
    after = build(changed)
    assert "the denoiser's code changed since this SURE cache was built; recomputing it" in (
        capsys.readouterr().err)
    item = next(iter(before))
    np.testing.assert_allclose(after[item], before[item] * 1.2, rtol=1e-5)


def test_a_black_box_is_keyed_by_its_source_without_its_comments():
    from jaxden.denoise.identity import code_text_sha256

    base = "def f(x):\n    return x + 1\n"
    assert code_text_sha256(base) == code_text_sha256("# note\ndef f(x):\n    '''doc'''\n"
                                                      "    return x + 1\n")
    assert code_text_sha256(base) != code_text_sha256("def f(x):\n    return x + 2\n")


# -------------------------------------------------------------------- every command, CLI
def test_an_outside_module_works_through_every_command(outside, clean_env, capsys,
                                                       monkeypatch):
    """train (config plugins), evaluate denoise (--plugin), evaluate pd (JAXDEN_PLUGINS),
    sure and progressive (--plugin), a mixer of the plugin's network trained on the plugin
    denoiser and run by progressive, and a two-run sweep on the local executor, whose spawned
    workers import the plugin themselves."""
    monkeypatch.chdir(outside)
    plugin = str(outside / "lab_denoisers.py")
    assert main(["train", "train.toml", "--workdir", "run"]) == 0
    meta = json.loads((outside / "run" / "config.json").read_text())
    assert meta["model"] == "lab-tinyconv" and meta["plugins"] == ["lab_denoisers.py"]
    assert main(["evaluate", "denoise", "--plugin", plugin, "--data", "tiny", "--split", "val",
                 "--spp", "8", "--denoiser", "run", "--out", "ev-den"]) == 0
    result = json.loads((outside / "ev-den.json").read_text())
    assert result["provenance"]["plugins"][0]["module"] == "lab_denoisers"
    monkeypatch.setenv(plugins.ENV, plugin)
    assert main(["evaluate", "pd", "--data", "tiny", "--split", "val", "--spp", "8",
                 "--denoiser", "lab-xbilateral", "--mixer", "closed-form",
                 "--out", "ev-pd"]) == 0
    frame = next(p for p in (outside / "tiny").rglob("spp00008.exr") if "derived" not in p.parts)
    assert main(["sure", str(frame), "--plugin", plugin, "--denoiser", "lab-xbilateral",
                 "--out", "s.exr"]) == 0
    assert main(["progressive", str(frame), "--plugin", plugin, "--denoiser",
                 "lab-xbilateral", "--mixer", "closed-form", "--out", "p.exr"]) == 0
    # a mixer of the plugin's network, trained on the plugin denoiser's SURE cache
    (outside / "mixer.toml").write_text(
        f'plugins = ["{plugin}"]\nmodel = "mixer"\neval_every = 2\ncheckpoint_every = 2\n'
        '[model_config]\ndenoiser = "lab-xbilateral"\nnetwork = "lab-mixnet"\n'
        '[model_config.sure]\nprobes = 1\n'
        '[data]\ndataset = "tiny"\ncrop_size = 16\nbatch_size = 2\n[optim]\nsteps = 2\n')
    assert main(["train", "mixer.toml", "--workdir", "mixer-run"]) == 0
    assert main(["progressive", str(frame), "--plugin", plugin, "--denoiser", "lab-xbilateral",
                 "--mixer", "mixer-run", "--out", "p-mixer.exr"]) == 0
    (outside / "sweep.toml").write_text(f'base = "train.toml"\nplugins = ["{plugin}"]\n'
                                        "[axes]\nseed = [0, 1]\n")
    monkeypatch.delenv(plugins.ENV)
    assert main(["sweep", "sweep.toml", "--workdir", "sw", "--executor", "local",
                 "--workers", "2"]) == 0
    summary = json.loads((outside / "sw" / "summary.json").read_text())
    assert summary["provenance"]["plugins"][0]["module"] == "lab_denoisers"
    assert sorted(p.parent.name for p in (outside / "sw").glob("*/result.json")) == [
        "seed=0", "seed=1"]
    out = capsys.readouterr()
    assert "Traceback" not in out.err


def test_a_function_is_a_denoiser_everywhere(key):
    """A plain JAX function goes where a registered denoiser goes: SURE, progressive
    denoising (closed-form mixer), and over tiles (its declared radius) equal to the whole
    frame."""
    from jaxden.frame import Frame
    from jaxden.sure import sure

    rng = np.random.default_rng(0)
    color = rng.uniform(0, 1, (24, 24, 3)).astype(np.float32)
    frame = Frame(color=color, variance=np.full_like(color, 0.01), spp=np.float32(16))

    def blur(frame):  # a 5-tap cross, edges clamped: receptive field 1 pixel
        padded = jax.numpy.pad(frame.color, ((1, 1), (1, 1), (0, 0)), mode="edge")
        height, width = frame.color.shape[:2]
        taps = ((1, 1), (1, 2), (2, 1), (1, 0), (0, 1))
        return sum(padded[dy:dy + height, dx:dx + width] for dy, dx in taps) / 5

    den = Denoiser.from_function(blur, radius=1)
    assert den.name == "blur"
    direct = sure(blur, frame, key, num_probes=2, method="jvp")
    wrapped = sure(den.function(), frame, key, num_probes=2, method="jvp")
    np.testing.assert_array_equal(np.asarray(direct.sure), np.asarray(wrapped.sure))

    from jaxden.progressive import closed_form_mixer, progressive_denoise, progressive_frame

    params, config = closed_form_mixer()
    z, _, extras = progressive_denoise(frame, blur, params, config, key)
    np.testing.assert_allclose(np.asarray(extras["denoised"]), np.asarray(blur(frame)),
                               rtol=1e-6)
    whole = progressive_frame(frame, den, params, config, key, tile=0)[0]["z"]
    np.testing.assert_allclose(whole, np.asarray(z), rtol=1e-5, atol=1e-6)
    # SURE over 8 x 8 tiles (each reading its window grown by the declared radius, its probes
    # the window of the whole frame's) equals SURE of the whole frame
    from jaxden.sure import sure_frame

    full, _ = sure_frame(den, frame, key, tile=0, num_probes=2)
    tiles, side = sure_frame(den, frame, key, tile=8, num_probes=2)
    assert side == 8
    np.testing.assert_allclose(tiles.sure, full.sure, rtol=1e-5, atol=1e-7)


RAY_DRIVER = r"""
import json, shutil, sys
from pathlib import Path

from jaxden.cli import main
from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.render.synthetic import synthetic_render

root, plugin, tiny = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
shutil.copy(plugin, root / "lab_denoisers.py")
build_dataset(load_config(tiny, DatasetConfig, ["crops_per_scene=2"]), root / "tiny",
              executor="serial", render_fn=synthetic_render, progress=False)
(root / "train.toml").write_text(
    'model = "lab-tinyconv"\neval_every = 2\ncheckpoint_every = 2\n[data]\n'
    f'dataset = "{root / "tiny"}"\ncrop_size = 32\nbatch_size = 2\n[optim]\nsteps = 2\n')
(root / "sweep.toml").write_text(f'base = "train.toml"\nplugins = ["{root / "lab_denoisers.py"}"]'
                                 '\n[axes]\nseed = [0, 1]\n')
code = main(["sweep", str(root / "sweep.toml"), "--workdir", str(root / "sw"), "--executor", "ray",
             "--ray-address", "local", "--workers", "2"])
runs = sorted(p.parent.name for p in (root / "sw").glob("*/result.json"))
print("REPORT " + json.dumps({"code": code, "runs": runs}))
"""


@pytest.mark.slow  # a private Ray on this machine, in a loopback-only namespace: ~1 min
def test_a_two_run_sweep_on_ray_imports_the_plugin_in_its_workers(tmp_path):
    import os

    from test_distributed import FAST_COMPILE, loopback_namespace_reason, run_in_loopback

    pytest.importorskip("ray", reason="Ray is not installed: pip install 'jaxden[ray]'")
    if loopback_namespace_reason() is not None:
        pytest.skip(str(loopback_namespace_reason()))
    driver = tmp_path / "driver.py"
    driver.write_text(RAY_DRIVER)
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "JAXDEN_CPU_DEVICES": "1",
           "XLA_FLAGS": FAST_COMPILE, "JAXDEN_CACHE_DIR": str(tmp_path / "cache")}
    for name in ("RAY_ADDRESS", plugins.ENV, "PYTHONPATH"):
        env.pop(name, None)
    done = run_in_loopback(driver, str(tmp_path), str(PLUGIN), str(TINY), env=env, timeout=900)
    assert "REPORT " in done.stdout, (done.stdout[-3000:], done.stderr[-5000:])
    report = json.loads(done.stdout.split("REPORT ", 1)[1])
    assert report == {"code": 0, "runs": ["seed=0", "seed=1"]}, done.stderr[-3000:]
