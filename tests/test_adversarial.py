"""Bad input, table-driven: every case must end in exit status 2 with exactly one line
`jaxden: error: ...` on stderr, no traceback, no file left behind and the inputs unchanged.

Each case is (id, setup) where ``setup(tmp)`` writes the inputs it needs into ``tmp`` and returns
the command line (``{tmp}`` in words is replaced by the folder). The command runs in process
(``jaxden.cli.main``), so a traceback is an exception that fails the test. The folder's files
and bytes are compared before and after. Disk-full cases run on a small tmpfs where the tests
run as root (skipped otherwise). Hypothesis mutates valid configs and metadata files and
checks that loading them either works or raises the one jaxden error class for that file.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxden import cli
from jaxden.io.exr import write_channels, write_frame
from jaxden.render.synthetic import synthetic_render

ROOT = Path(__file__).resolve().parent.parent
SCENE = """<scene version="3.0.0">
    <default name="res" value="16"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0,0,3" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="$res"/><integer name="height" value="$res"/></film>
    </sensor>
    <shape type="sphere"/>
    <emitter type="constant"/>
</scene>
"""


def frame_file(tmp: Path, name="f.exr", size=(12, 10), spp=16, **replace):
    frame = synthetic_render("adversarial", spp, seed=3, size=size).numpy()
    if replace:
        frame = frame.replace(**replace)
    write_frame(tmp / name, frame)
    return tmp / name


def raw_channels(tmp: Path, name: str, channels: dict, **attrs):
    write_channels(tmp / name, channels, attributes=attrs, allow_nonfinite=True)
    return tmp / name


def weights(tmp: Path, name="w", mutate=None, meta=None):
    """A tiny WSKP's released weights (a .msgpack and its .json meta), optionally broken."""
    import jax

    from jaxden.checkpoint import save_weights
    from jaxden.config import config_to_dict
    from jaxden.denoise.registry import make_denoiser

    den = make_denoiser("wskp3", key=jax.random.PRNGKey(0))
    params = den.params if mutate is None else jax.tree_util.tree_map(mutate, den.params)
    record = {"kind": "denoiser", "model": "wskp3", "model_config": config_to_dict(den.config)}
    save_weights(tmp / f"{name}.msgpack", params, record)
    if meta is not None:
        (tmp / f"{name}.json").write_text(meta)
    return tmp / f"{name}.msgpack"


def denoise(tmp, model="oidn", name="f.exr"):
    return ["denoise", str(tmp / name), "--model", str(model), "--out", str(tmp / "out.exr")]


def train_config(tmp: Path, text: str = "") -> Path:
    path = tmp / "t.toml"
    path.write_text('model = "wskp"\n[data]\ndataset = "' + str(tmp / "nodata") + '"\n' + text)
    return path


def nan_color(tmp):
    color = np.ones((10, 12), np.float32)
    color[3, 4] = np.nan
    raw_channels(tmp, "f.exr", {"R": color, "G": color, "B": color})
    return denoise(tmp)


def neg_variance(tmp):
    ones = np.ones((10, 12), np.float32)
    raw_channels(tmp, "f.exr", {"R": ones, "G": ones, "B": ones, "variance.R": -ones,
                                "variance.G": ones, "variance.B": ones}, spp=4.0)
    return ["sure", str(tmp / "f.exr"), "--denoiser", "oidn", "--out", str(tmp / "out.exr")]


def spp_text(tmp):
    ones = np.ones((10, 12), np.float32)
    raw_channels(tmp, "f.exr", {"R": ones, "G": ones, "B": ones, "variance.R": ones,
                                "variance.G": ones, "variance.B": ones}, spp="abc")
    return ["sure", str(tmp / "f.exr"), "--denoiser", "oidn", "--sample-variance",
            "--out", str(tmp / "out.exr")]


def huge_color(tmp):
    frame_file(tmp, color=np.full((10, 12, 3), 3e38, np.float32))
    return ["sure", str(tmp / "f.exr"), "--denoiser", "oidn", "--probes", "1",
            "--out", str(tmp / "out.exr")]


def fifo(tmp):
    os.mkfifo(tmp / "f.exr")
    return denoise(tmp)


def xml(tmp, text, *extra):
    (tmp / "s.xml").write_text(text)
    return ["render", str(tmp / "s.xml"), "--spp", "1", "--out", str(tmp / "out.exr"), *extra]


def manifest(tmp, change):
    """A tiny built dataset whose manifest ``change`` breaks."""
    from jaxden.data.builder import build_dataset
    from jaxden.data.config import DatasetConfig, SplitConfig

    config = DatasetConfig(name="adv", scenes=("a",), size=(16, 16), crop_size=16,
                           crops_per_scene=1, spp=(2,), reference_spp=4,
                           splits=SplitConfig(train=1.0, val=0.0))
    build_dataset(config, tmp / "d", render_fn=synthetic_render, progress=False)
    path = tmp / "d" / "manifest.json"
    data = json.loads(path.read_text())
    text = change(data)
    path.write_text(text if isinstance(text, str) else json.dumps(data))
    return ["dataset", "verify", str(tmp / "d")]


def sweep(tmp, body):
    train_config(tmp)
    (tmp / "s.toml").write_text('base = "t.toml"\n' + body)
    return ["sweep", str(tmp / "s.toml"), "--workdir", str(tmp / "w")]


CASES = {
    # ------------------------------------------------------------------------ EXR inputs
    "exr-missing": lambda t: denoise(t, name="nope.exr"),
    "exr-empty": lambda t: ((t / "f.exr").write_bytes(b""), denoise(t))[1],
    "exr-truncated": lambda t: (frame_file(t), (t / "f.exr").write_bytes(
        (t / "f.exr").read_bytes()[:300]), denoise(t))[2],
    "exr-text": lambda t: ((t / "f.exr").write_text("not an image"), denoise(t))[1],
    "exr-folder": lambda t: ((t / "f.exr").mkdir(), denoise(t))[1],
    "exr-fifo": fifo,
    "exr-no-colour": lambda t: (raw_channels(t, "f.exr", {"albedo.R": np.ones((4, 4), np.float32)}),
                                denoise(t))[1],
    "exr-nan-colour": nan_color,
    "exr-negative-variance": neg_variance,
    "exr-spp-not-a-number": spp_text,
    "exr-huge-colour-sure": huge_color,
    "exr-sure-no-variance": lambda t: (frame_file(t, spp=1), ["sure", str(t / "f.exr"),
                                       "--denoiser", "oidn", "--out", str(t / "out.exr")])[1],
    "exr-progressive-no-variance": lambda t: (frame_file(t, spp=1), [
        "progressive", str(t / "f.exr"), "--denoiser", "oidn", "--out", str(t / "out.exr")])[1],
    "exr-buffers-other-size": lambda t: (frame_file(t), frame_file(t, "b0.exr", size=(8, 8)),
                                         frame_file(t, "b1.exr", size=(8, 8)), [
        "sure", str(t / "f.exr"), "--denoiser", "oidn", "--buffers", str(t / "b0.exr"),
        str(t / "b1.exr"), "--out", str(t / "out.exr")])[3],
    "exr-out-is-folder": lambda t: (frame_file(t), (t / "o").mkdir(), [
        "denoise", str(t / "f.exr"), "--model", "oidn", "--out", str(t / "o")])[2],
    "exr-out-missing-folder": lambda t: (frame_file(t), [
        "denoise", str(t / "f.exr"), "--model", "oidn", "--out", str(t / "no" / "o.exr")])[1],
    "exr-out-not-exr": lambda t: (frame_file(t), [
        "denoise", str(t / "f.exr"), "--model", "oidn", "--out", str(t / "o.png")])[1],
    "exr-out-is-input": lambda t: (frame_file(t), [
        "denoise", str(t / "f.exr"), "--model", "oidn", "--out", str(t / "f.exr")])[1],
    "exr-channels-unknown-field": lambda t: (frame_file(t), denoise(t) + [
        "--channels", "colour=R,G,B"])[1],
    "exr-channels-absent": lambda t: (frame_file(t), denoise(t) + [
        "--channels", "albedo=A.R,A.G,A.B"])[1],
    "exr-nonfinite-policy-bad": lambda t: (frame_file(t), denoise(t) + ["--nonfinite", "ok"])[1],
    # ----------------------------------------------------------------------- scene XML
    "xml-missing-include": lambda t: xml(t, SCENE.replace("<shape", '<include filename="x.xml"/><shape')),
    "xml-include-cycle": lambda t: xml(t, SCENE.replace("<shape", '<include filename="s.xml"/><shape')),
    "xml-undefined-name": lambda t: xml(t, SCENE.replace('value="$res"/></film>', 'value="$rez"/></film>')),
    "xml-unused-parameter": lambda t: xml(t, SCENE, "-D", "spp=4"),
    "xml-bad-parameter": lambda t: xml(t, SCENE, "-D", "res"),
    "xml-huge-film": lambda t: xml(t, SCENE.replace('value="16"', 'value="40000"')),
    "xml-malformed": lambda t: xml(t, SCENE[:-20]),
    "xml-root-not-scene": lambda t: xml(t, "<sensor/>"),
    "xml-no-sensor": lambda t: xml(t, '<scene version="3.0.0"><shape type="sphere"/></scene>'),
    "xml-missing-path": lambda t: xml(t, SCENE.replace("<shape", '<path value="nowhere"/><shape')),
    "render-size-zero": lambda t: ["render", "cornell-box", "--spp", "1", "--size", "0x10",
                                   "--out", str(t / "out.exr")],
    "render-size-huge": lambda t: ["render", "cornell-box", "--spp", "1", "--size",
                                   "16000x16000", "--out", str(t / "out.exr")],
    "render-unknown-scene": lambda t: ["render", "cornel-box", "--spp", "1", "--out",
                                       str(t / "out.exr")],
    "render-spp-zero": lambda t: ["render", "cornell-box", "--spp", "0", "--out", str(t / "o.exr")],
    # ------------------------------------------------------------ weights and checkpoints
    "weights-nan": lambda t: (frame_file(t), denoise(t, weights(t, mutate=lambda a: a * np.nan)))[1],
    "weights-1e30": lambda t: (frame_file(t), denoise(t, weights(t, mutate=lambda a: a + 1e30)))[1],
    "weights-int8": lambda t: (frame_file(t), denoise(t, weights(
        t, mutate=lambda a: np.asarray(a).astype(np.int8))))[1],
    "weights-json-list": lambda t: (frame_file(t), denoise(t, weights(t, meta="[1, 2]")))[1],
    "weights-json-malformed": lambda t: (frame_file(t), denoise(t, weights(t, meta="{")))[1],
    "weights-json-model-config-string": lambda t: (frame_file(t), denoise(t, weights(
        t, meta='{"kind": "denoiser", "model": "wskp3", "model_config": "x.toml"}')))[1],
    "weights-json-unknown-model": lambda t: (frame_file(t), denoise(t, weights(
        t, meta='{"kind": "denoiser", "model": "wsk", "model_config": {}}')))[1],
    "weights-json-kind-number": lambda t: (frame_file(t), denoise(t, weights(
        t, meta='{"kind": 3, "model": "wskp3"}')))[1],
    "weights-no-json": lambda t: (frame_file(t), weights(t), (t / "w.json").unlink(),
                                  denoise(t, t / "w.msgpack"))[3],
    "weights-corrupt": lambda t: (frame_file(t), weights(t), (t / "w.msgpack").write_bytes(
        b"\x00" * 10), denoise(t, t / "w.msgpack"))[3],
    "weights-mixer-as-denoiser": lambda t: (frame_file(t), denoise(
        t, ROOT / "jaxden" / "weights" / "oidn-pd.msgpack"))[1],
    "weights-denoiser-as-mixer": lambda t: (frame_file(t), weights(t), [
        "progressive", str(t / "f.exr"), "--denoiser", "oidn", "--mixer", str(t / "w.msgpack"),
        "--out", str(t / "out.exr")])[2],
    "weights-shape-mismatch": lambda t: (frame_file(t), weights(t, meta=json.dumps(
        {"kind": "denoiser", "model": "wskp", "model_config": {}})), denoise(t, t / "w.msgpack"))[2],
    # ----------------------------------------------------------- configs and overrides
    "config-unknown-key": lambda t: ["train", str(train_config(t, "lerning_rate = 1\n")),
                                     "--workdir", str(t / "w")],
    "config-wrong-type": lambda t: ["train", str(train_config(t)), "optim.steps=abc",
                                    "--workdir", str(t / "w")],
    "config-grad-clip-negative": lambda t: ["train", str(train_config(t)),
                                            "optim.grad_clip_norm=-1", "--workdir", str(t / "w")],
    "config-grad-clip-zero": lambda t: ["train", str(train_config(t)),
                                        "optim.grad_clip_norm=0", "--workdir", str(t / "w")],
    "config-seed-huge": lambda t: ["train", str(train_config(t)), "seed=100000000000000000000000",
                                   "--workdir", str(t / "w")],
    "config-lr-nan": lambda t: ["train", str(train_config(t)), "optim.learning_rate=nan",
                                "--workdir", str(t / "w")],
    "config-missing-file": lambda t: ["train", str(t / "nope.toml"), "--workdir", str(t / "w")],
    "config-not-toml": lambda t: ((t / "t.toml").write_text("model = = 1"),
                                  ["train", str(t / "t.toml"), "--workdir", str(t / "w")])[1],
    "config-model-config-typo": lambda t: ["train", str(train_config(t, "[model_config]\nnum_layer = 3\n")),
                                           "--workdir", str(t / "w")],
    "config-crops-huge": lambda t: ["dataset", "build", str(ROOT / "experiments" / "configs" /
                                    "dataset-tiny.toml"), "crops_per_scene=1000000000",
                                    "--out", str(t / "d")],
    "config-dataset-spp-empty": lambda t: ["dataset", "build", str(ROOT / "experiments" / "configs" /
                                           "dataset-tiny.toml"), "spp=[]", "--out", str(t / "d")],
    "config-closed-form-sigma-huge": lambda t: (frame_file(t), [
        "progressive", str(t / "f.exr"), "--denoiser", "oidn", "--mixer",
        "closed-form:sigma=1e9", "--out", str(t / "out.exr")])[1],
    "config-closed-form-unknown-option": lambda t: (frame_file(t), [
        "progressive", str(t / "f.exr"), "--denoiser", "oidn", "--mixer",
        "closed-form:sigm=2", "--out", str(t / "out.exr")])[1],
    "config-mixer-missing": lambda t: (frame_file(t), [
        "progressive", str(t / "f.exr"), "--denoiser", "oidn", "--mixer", str(t / "none"),
        "--out", str(t / "out.exr")])[1],
    # -------------------------------------------------------------------------- sweeps
    "sweep-no-axes": lambda t: sweep(t, ""),
    "sweep-bad-axis": lambda t: sweep(t, "[axes]\nseed = 3\n"),
    "sweep-missing-base": lambda t: ((t / "s.toml").write_text('base = "no.toml"\n[axes]\nseed = [0]\n'),
                                     ["sweep", str(t / "s.toml"), "--workdir", str(t / "w")])[1],
    "sweep-bad-override": lambda t: sweep(t, '[axes]\n"optim.stepz" = [1]\n'),
    # ------------------------------------------------------------------------ datasets
    "dataset-verify-missing": lambda t: ["dataset", "verify", str(t / "nope")],
    "dataset-manifest-malformed": lambda t: manifest(t, lambda d: "{"),
    "dataset-manifest-item-outside": lambda t: manifest(
        t, lambda d: d["items"][0].__setitem__("path", "../../etc/passwd")),
    "dataset-manifest-item-absolute": lambda t: manifest(
        t, lambda d: d["items"][0].__setitem__("path", "/etc/passwd")),
    "dataset-manifest-items-string": lambda t: manifest(t, lambda d: d.__setitem__("items", "x")),
    "dataset-manifest-list": lambda t: manifest(t, lambda d: "[]"),
    "dataset-out-is-file": lambda t: ((t / "d").write_text("x"), [
        "dataset", "build", str(ROOT / "experiments" / "configs" / "dataset-tiny.toml"),
        "--out", str(t / "d")])[1],
    "dataset-sure-cache-missing": lambda t: ["dataset", "sure-cache", str(t / "nope"),
                                             "--denoiser", "oidn"],
}


def snapshot(folder: Path) -> dict[str, bytes | None]:
    out = {}
    for path in sorted(folder.rglob("*")):
        if path.is_fifo():
            out[str(path)] = b"fifo"
        elif path.is_file():
            out[str(path)] = path.read_bytes()
        elif path.is_dir():
            out[str(path)] = None
    return out


def run_case(argv, capsys):
    capsys.readouterr()
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exit_:  # argparse's errors
        code = exit_.code
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    return code, lines


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_is_one_line_and_exit_2(case, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = CASES[case](tmp_path)
    before = snapshot(tmp_path)
    code, lines = run_case(argv, capsys)
    errors = [line for line in lines if line.startswith("jaxden: error: ")]
    assert code == 2 and len(errors) == 1, (code, lines)
    assert not any("Traceback" in line for line in lines)
    assert not [line for line in lines if not line.startswith(("jaxden: error:", "jaxden: note:"))], lines
    assert snapshot(tmp_path) == before, "files were left behind or inputs changed"


def test_there_are_at_least_60_cases():
    assert len(CASES) >= 60


# ------------------------------------------------------------------------ disk full
def _small_tmpfs(folder: Path, size: str):
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a small tmpfs")
    folder.mkdir()
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                            capture_output=True, check=False)
    if result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {result.stderr.decode().strip()}")


@pytest.fixture()
def full_disk(tmp_path):
    folder = tmp_path / "full"
    _small_tmpfs(folder, "24k")
    yield folder
    subprocess.run(["umount", str(folder)], check=False)


@pytest.mark.parametrize("command", ["denoise", "render"])
def test_full_disk_is_one_line_and_leaves_nothing(full_disk, tmp_path, capsys, command):
    source = frame_file(tmp_path, size=(64, 64))
    out = full_disk / "out.exr"
    argv = (["denoise", str(source), "--model", "oidn", "--out", str(out)] if command == "denoise"
            else ["render", "cornell-box", "--spp", "1", "--size", "64x64", "--out", str(out)])
    code, lines = run_case(argv, capsys)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("jaxden: error: ")
    assert "No space left on device" in lines[0]
    assert list(full_disk.iterdir()) == []


# ------------------------------------------------------------------- mutated files
VALID_TRAIN = {"model": "wskp", "seed": 0, "log_every": 10,
               "data": {"dataset": "d", "crop_size": 64, "batch_size": 8, "spp": [1]},
               "optim": {"steps": 100, "learning_rate": 1e-3, "loss": "smape"},
               "model_config": {"num_layers": 6, "width": 14}}
JUNK = st.one_of(st.none(), st.booleans(), st.integers(-10**30, 10**30),
                 st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
                 st.lists(st.integers(-3, 3), max_size=3), st.dictionaries(
                     st.text(max_size=4), st.integers(), max_size=2))


def _paths(tree, prefix=()):
    for key, value in tree.items():
        yield prefix + (key,)
        if isinstance(value, dict):
            yield from _paths(value, prefix + (key,))


def _mutate(tree, path, value):
    tree = json.loads(json.dumps(tree))
    node = tree
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return tree


@settings(max_examples=80, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(path=st.sampled_from(list(_paths(VALID_TRAIN))), value=JUNK)
def test_mutated_training_configs_load_or_raise_config_errors(path, value):
    from jaxden.errors import ConfigError
    from jaxden.train.config import load_train_config

    try:
        load_train_config(_mutate(VALID_TRAIN, path, value))
    except ConfigError as error:
        assert "\n" not in str(error)


@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["kind", "model", "model_config", "step", "extra"]), value=JUNK)
def test_mutated_weight_meta_loads_or_raises_checkpoint_errors(tmp_path_factory, key, value):
    from jaxden.denoise.registry import load_denoiser
    from jaxden.errors import CheckpointError, ConfigError

    folder = tmp_path_factory.mktemp("meta")
    path = weights(folder)
    meta = json.loads((folder / "w.json").read_text())
    meta[key] = value
    (folder / "w.json").write_text(json.dumps(meta))
    try:
        load_denoiser(path)
    except (CheckpointError, ConfigError) as error:
        assert "\n" not in str(error)


def test_a_covariance_mixer_on_a_file_without_the_covariance_says_so(tmp_path, capsys):
    # SURE from the covariance falls back to the per-channel form on a file that has none (a
    # renderer other than jaxden's): a note says so; a file with it gets no note.
    import dataclasses

    from jaxden.frame import covariance_bound
    from jaxden.progressive.mixer import load_mixer, save_mixer

    params, config = load_mixer("oidn-pd")
    save_mixer(tmp_path / "cov.msgpack", params, dataclasses.replace(config, sure=config.sure.replace(covariance=True)))
    frame_file(tmp_path)
    argv = ["progressive", str(tmp_path / "f.exr"), "--denoiser", "oidn", "--mixer",
            str(tmp_path / "cov.msgpack"), "--out", str(tmp_path / "o.exr")]
    assert cli.main(argv) == 0
    err = capsys.readouterr().err
    assert "trained on SURE from the colour covariance, but" in err and "f.exr has none" in err
    variance = synthetic_render("adversarial", 16, seed=3, size=(12, 10)).numpy().variance
    frame_file(tmp_path, covariance=(0.5 * covariance_bound(variance)).astype(np.float32))
    assert cli.main(argv) == 0
    assert "colour covariance" not in capsys.readouterr().err
