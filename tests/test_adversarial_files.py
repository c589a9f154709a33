"""Broken files that jaxden itself wrote (or a user edited): the SURE cache manifest, a run's
recorded config and metrics log, a sweep run's result.json, the Mitsuba variant cache and a
dataset's manifest. Each is read through :func:`jaxden.fileio.read_json` (or ``read_jsonl``), so
malformed or wrongly typed content is one line ``jaxden: error: ...`` naming the file and the
field (exit 2, no traceback, inputs unchanged), or, for files jaxden can regenerate (a sweep's
result, the variant cache), a redo or a miss, never a silently wrong result. Dataset
manifests are mutated by Hypothesis (types, values, deleted keys, paths leaving the folder,
truncation) and must verify, load or fail in one line.

Data: a tiny Mitsuba-free dataset (``synthetic_render``) and a 2-step KP model. Also here:
a checkpoint whose state files were cut short, and an EXR whose header declares 12000 x 12000
pixels read under an address-space limit (``ulimit -v``), both in a subprocess: one line, no
traceback.
"""

from __future__ import annotations

import json
import resource
import shutil
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from helpers import (
    assert_one_error_line,
    build_tiny_dataset,
    cli_env,
    drop,
    fill_disk,
    json_paths,
    run_cli,
    set_or_delete,
    small_tmpfs,
    snapshot,
    write_train_config,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from jaxden import cli
from jaxden.errors import JaxdenError


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return build_tiny_dataset(tmp_path_factory.mktemp("files") / "tiny")


@pytest.fixture()
def full_disk(tmp_path):
    """A 64 KiB tmpfs (root only; skipped otherwise), unmounted afterwards."""
    with small_tmpfs(tmp_path / "full", "64k") as folder:
        yield folder


# ------------------------------------------------------------------ SURE cache manifest
GOOD_CACHE = {"format": "jaxden-sure-cache", "format_version": 1, "cache_key": "k",
              "identity": {"dataset": {}, "denoiser": {}, "settings": {}}, "complete": False,
              "items": {"i": {"path": "s000/c000/spp00002.exr", "sha256": "0" * 64,
                              "bytes": 10, "source_sha256": "1" * 64, "seed": 3,
                              "seconds": 0.5}}}


def _cache(change):
    """GOOD_CACHE as text, after ``change`` (which edits the dict or returns the text)."""
    data = json.loads(json.dumps(GOOD_CACHE))
    text = change(data)
    return text if isinstance(text, str) else json.dumps(data)


CACHE_CASES = {
    "malformed": (lambda d: "{", "not valid JSON"),
    "truncated": (lambda d: json.dumps(d)[:50], "not valid JSON"),
    "list": (lambda d: "[]", "must be an object"),
    "not-utf8": (lambda d: "\udcff", "cannot read"),
    "format-missing": (lambda d: drop(d, "format"), "not a jaxden SURE cache manifest"),
    "version-text": (lambda d: d.__setitem__("format_version", "1"), "'format_version'"),
    "items-list": (lambda d: d.__setitem__("items", []), "'items' must be an object"),
    "identity-missing": (lambda d: drop(d, "identity"), "'identity' is missing"),
    "settings-list": (lambda d: d["identity"].__setitem__("settings", []), "'settings'"),
    "record-string": (lambda d: d["items"].__setitem__("i", "x"), "item 'i'"),
    "record-bytes-text": (lambda d: d["items"]["i"].__setitem__("bytes", "10"), "'bytes'"),
    "record-no-path": (lambda d: drop(d["items"]["i"], "path"), "'path' is missing"),
    "record-path-outside": (lambda d: d["items"]["i"].__setitem__("path", "../../x.exr"),
                            "leaves the cache folder"),
    "record-path-absolute": (lambda d: d["items"]["i"].__setitem__("path", "/etc/passwd"),
                             "leaves the cache folder"),
    "complete-text": (lambda d: d.__setitem__("complete", "yes"), "'complete'"),
}


@pytest.mark.parametrize("case", sorted(CACHE_CASES))
def test_broken_sure_cache_manifest_is_one_line(case, dataset, tmp_path, capsys):
    data = tmp_path / "d"
    shutil.copytree(dataset, data)
    cache = data / "derived" / "oidn"
    cache.mkdir(parents=True)
    change, words = CACHE_CASES[case]
    text = _cache(change)
    (cache / "sure-cache.json").write_bytes(text.encode("utf-8", "surrogateescape"))
    before = snapshot(tmp_path)
    code, lines, _ = run_cli(["dataset", "sure-cache", data, "--denoiser", "oidn"], capsys)
    assert_one_error_line(code, lines, str(cache / "sure-cache.json"), words)
    assert snapshot(tmp_path) == before


def test_sure_cache_reader_refuses_a_record_outside_the_folder(dataset, tmp_path):
    """Opening a cache for reading (a mixer's training, the PD report) checks the records
    too: an item path leaving the folder is never read."""
    from jaxden.errors import DatasetError
    from jaxden.progressive.cache import SureCache

    data = _cache(lambda d: d["items"]["i"].__setitem__("path", "../../../etc/passwd"))
    (tmp_path / "sure-cache.json").write_text(data)
    with pytest.raises(DatasetError, match="item 'i': path '../../../etc/passwd' leaves"):
        SureCache(dataset, tmp_path)


# ------------------------------------------------------------- a run's recorded files
@pytest.fixture(scope="module")
def finished_run(dataset, tmp_path_factory):
    """A finished 2-step KP run: (train config, workdir)."""
    folder = tmp_path_factory.mktemp("run")
    config = write_train_config(folder, dataset)
    assert cli.main(["train", str(config), "--workdir", str(folder / "run")]) == 0
    return config, folder / "run"


@pytest.mark.parametrize("text, words", [
    ("{", "not valid JSON"),
    ("[1]", "must be an object"),
])
def test_a_broken_recorded_config_is_one_line(finished_run, tmp_path, capsys, text, words):
    config, run = finished_run
    workdir = tmp_path / "run"
    shutil.copytree(run, workdir)
    (workdir / "config.json").write_text(text)
    before = snapshot(tmp_path)
    code, lines, _ = run_cli(["train", config, "--workdir", workdir], capsys)
    assert_one_error_line(code, lines, str(workdir / "config.json"), words)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("line, words", [
    ('{"step": 1, "loss": 0.5', "line 2 of the metrics log is not valid JSON"),
    ("[1, 2]", "line 2 of the metrics log: expected an object"),
    ('{"step": "one"}', "line 2 of the metrics log: field 'step' must be a whole number"),
    ("\udcff", "line 2 of the metrics log is not valid JSON"),
])
def test_garbage_inside_the_metrics_log_is_one_line(finished_run, tmp_path, capsys, line,
                                                    words):
    """Resuming a run whose metrics.jsonl has a broken line that is not the last: an error
    naming the file and the line (nothing is dropped or rewritten)."""
    config, run = finished_run
    workdir = tmp_path / "run"
    shutil.copytree(run, workdir)
    log = workdir / "metrics.jsonl"
    lines = log.read_text().splitlines()
    broken = [lines[0], line, *lines[1:]]
    log.write_bytes(("\n".join(broken) + "\n").encode("utf-8", "surrogateescape"))
    before = snapshot(tmp_path)
    code, err, _ = run_cli(["train", config, "--workdir", workdir], capsys)
    assert_one_error_line(code, err, str(log), words)
    assert snapshot(tmp_path) == before


def test_metrics_log_drops_a_cut_last_line_and_later_steps(tmp_path):
    """What a kill mid-write leaves (the last line without its newline, not JSON) is dropped
    on resume, with the entries after the resumed checkpoint; a complete last line without
    a newline is kept; nothing is kept when the run starts over (no checkpoint)."""
    from jaxden.train.workdir import MetricsLog

    log = tmp_path / "metrics.jsonl"
    full = [{"step": 0, "val_loss": 1.0}, {"step": 1, "loss": 0.5}, {"step": 2, "loss": 0.25},
            {"step": 3, "loss": 0.125}]
    text = "".join(json.dumps(r) + "\n" for r in full)
    log.write_text(text + '{"step": 4, "lo')
    MetricsLog(log, 3)
    assert log.read_text() == text
    log.write_text(text + '{"step": 4, "lo')
    MetricsLog(log, 2)
    assert [json.loads(x) for x in log.read_text().splitlines()] == full[:3]
    log.write_text(text.rstrip("\n"))  # cut right before the newline: a whole entry
    MetricsLog(log, 3)
    assert [json.loads(x) for x in log.read_text().splitlines()] == full
    log.write_text(text)
    MetricsLog(log, 0)
    assert log.read_text() == ""
    before = text.encode() + b"\xff\xfe"  # a cut multi-byte character
    log.write_bytes(before)
    MetricsLog(log, 3)
    assert log.read_text() == text
    untouched = log.stat().st_mtime_ns
    MetricsLog(log, 3)  # nothing to drop: the file is not rewritten
    assert log.stat().st_mtime_ns == untouched


def test_metrics_log_appends_whole_lines_or_nothing(full_disk):
    """On a full disk an entry is not half written: the error names the file and the log
    ends as before."""
    from jaxden.errors import OutputError
    from jaxden.train.workdir import MetricsLog

    log = full_disk / "metrics.jsonl"
    metrics = MetricsLog(log, 0)
    metrics.write({"step": 1, "loss": 0.5})
    fill_disk(full_disk / "filler")
    with pytest.raises(OutputError, match=f"cannot write {log}: No space left on device"):
        metrics.write({"step": 2, "loss": 0.25, "note": "x" * 20000})
    assert log.read_text() == '{"step": 1, "loss": 0.5}\n'


# ------------------------------------------------------------------ sweep result.json
RESULT_DAMAGE = {
    "truncated": lambda text: text[: len(text) // 2],
    "list": lambda text: "[]",
    "train-text": lambda text: json.dumps({**json.loads(text), "train": "x"}),
    "no-evaluations": lambda text: json.dumps(
        {k: v for k, v in json.loads(text).items() if k != "evaluations"}),
    "val-loss-text": lambda text: json.dumps(
        {**json.loads(text), "train": {**json.loads(text)["train"], "val_loss": "low"}}),
}


def test_a_damaged_sweep_result_is_redone_with_a_note(dataset, tmp_path, capsys):
    """A sweep run whose result.json is damaged counts as not finished: a rerun says so in one
    note, redoes the run from its final checkpoint (no training) and writes the same result
    again; the other run is skipped. jaxden writes result.json atomically, so damage comes
    from outside; the trained model is in the checkpoints, so redoing is cheap and better
    than stopping a sweep of many runs on one damaged record."""
    from jaxden.sweep import run_sweep

    base = write_train_config(tmp_path, dataset)
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{base}"\n[axes]\nseed = [0, 1]\n')
    workdir = tmp_path / "w"
    first = run_sweep(sweep, workdir, progress=False)
    result = workdir / "seed=1" / "result.json"
    good = result.read_text()
    log = (workdir / "seed=1" / "metrics.jsonl").read_text()
    for name, damage in RESULT_DAMAGE.items():
        result.write_text(damage(good))
        capsys.readouterr()
        again = run_sweep(sweep, workdir, progress=False)
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert [r["skipped"] for r in again] == [True, False], name
        assert len(err) == 1 and err[0].startswith(f"jaxden: note: {result}: "), (name, err)
        assert "redoing the run" in err[0]
        assert result.read_text() == good, name  # the same evaluation of the same model
        assert (workdir / "seed=1" / "metrics.jsonl").read_text() == log  # nothing retrained
    assert again[1]["train"] == first[1]["train"]


# ---------------------------------------------------------------- Mitsuba variant cache
@pytest.mark.parametrize("content", [
    "[]", '{"key": 3, "variant": "scalar_rgb"}', '{"variant": "scalar_rgb"}',
    '{"key": "K", "variant": null}', '{"key": "K", "variant": "scalar_rgb", "reason": [1]}',
    '{"key": "K", "variant": "scalar_rgb", "reason": "x"', "\udcff",
])
def test_a_broken_variant_cache_is_a_miss(monkeypatch, tmp_path, content):
    from jaxden.render import variant

    monkeypatch.setenv("JAXDEN_CACHE_DIR", str(tmp_path))
    (tmp_path / variant.CACHE_FILE_NAME).write_bytes(
        content.encode("utf-8", "surrogateescape"))
    assert variant._read_cache("K") is None
    (tmp_path / variant.CACHE_FILE_NAME).write_text(
        '{"key": "K", "variant": "scalar_rgb", "reason": "probe died"}')
    assert variant._read_cache("K") == ("scalar_rgb", "probe died")


def test_variant_cache_write_on_a_full_disk_leaves_nothing(monkeypatch, full_disk):
    from jaxden.render import variant

    monkeypatch.setenv("JAXDEN_CACHE_DIR", str(full_disk / "cache"))
    (full_disk / "cache").mkdir()
    fill_disk(full_disk / "filler")
    variant._write_cache("K", "scalar_rgb", "x" * 10000)  # no error: it is only a cache
    assert list((full_disk / "cache").iterdir()) == []


# ------------------------------------------------------------ dataset manifest mutations
JUNK = st.one_of(
    st.none(), st.booleans(), st.integers(-10**30, 10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
    st.sampled_from(["../outside.exr", "/etc/passwd", "~/x.exr", "", ".", "s000-cornell-box",
                     "s000-cornell-box/c000/spp00008.exr", "reference", "input", "val"]),
    st.lists(st.integers(-3, 40), max_size=5),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))


@pytest.fixture(scope="module")
def manifest_case(dataset, tmp_path_factory):
    """A private copy of the tiny dataset, its manifest and every key path in it."""
    folder = tmp_path_factory.mktemp("mutated") / "d"
    shutil.copytree(dataset, folder)
    text = (folder / "manifest.json").read_text()
    return folder, text, list(json_paths(json.loads(text)))


def _mutated(text: str, paths, draw) -> str:
    data = json.loads(text)
    kind = draw(st.sampled_from(["set", "set", "delete", "truncate", "escape"]))
    if kind == "truncate":
        return text[: draw(st.integers(0, len(text) - 1))]
    if kind == "escape":  # an item path that leaves the folder, or names another item
        item = draw(st.integers(0, len(data["items"]) - 1))
        data["items"][item]["path"] = draw(st.sampled_from(
            ["../d/" + data["items"][item]["path"], "../../etc/passwd", "/etc/passwd",
             "s000-cornell-box/../../x.exr", data["items"][-1 - item]["path"], "~/x.exr"]))
        return json.dumps(data)
    return set_or_delete(data, paths, draw, JUNK, delete=kind == "delete")


_KP = {"model": "kp", "model_config": {"num_layers": 1, "width": 8, "kernel_size": 3},
       "data": {"dataset": "", "crop_size": 16, "batch_size": 1}}


def _loader_entry(directory: Path) -> None:
    """What `jaxden train` does with a dataset before its first step: both loaders and the
    first batch of each."""
    from jaxden.train.config import load_train_config
    from jaxden.train.loop import _loaders, batches_from
    from jaxden.train.tasks import make_task

    config = load_train_config({**_KP, "data": {**_KP["data"], "dataset": str(directory)}})
    train, val = _loaders(config, make_task(config))
    next(iter(batches_from(train, 0)))
    next(iter(val.epoch(0)))


@settings(max_examples=120, deadline=None, derandomize=True, database=None,
          phases=[Phase.explicit, Phase.generate],  # each example is one mutation: no shrinking
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_dataset_manifests_verify_and_load_or_give_one_line(manifest_case, capsys,
                                                                   data):
    """`jaxden dataset verify DIR` ends in 0 (OK), 1 (problems listed on stdout, nothing on
    stderr) or 2 with one `jaxden: error:` line; the training data path (both loaders and
    their first batches) works or raises one jaxden error of one line; the folder is left as
    it was."""
    folder, text, paths = manifest_case
    mutated = _mutated(text, paths, data.draw)
    (folder / "manifest.json").write_text(mutated)
    try:
        before = snapshot(folder)
        code, lines, out = run_cli(["dataset", "verify", folder], capsys)
        if code == 2:
            assert_one_error_line(code, lines)
        else:
            assert code in (0, 1) and lines == [], (code, lines)
            assert ("OK" in out) == (code == 0), out
        try:
            _loader_entry(folder)
        except JaxdenError as error:
            assert "\n" not in str(error) and str(error)
        assert snapshot(folder) == before
    finally:
        (folder / "manifest.json").write_text(text)


# ------------------------------------------------------------ a truncated checkpoint
def test_a_truncated_checkpoint_state_is_one_line_without_orbax_noise(finished_run, tmp_path):
    """Resuming from a checkpoint whose array data files were cut in half: one error line
    that says so, and nothing after it (no "Event loop is closed" tracebacks from TensorStore
    reads finishing after the failed restore: tests/test_checkpoint.py shows that race)."""
    config, run = finished_run
    workdir = tmp_path / "run"
    shutil.copytree(run, workdir)
    state = workdir / "2" / "state"
    data = [p for p in state.rglob("*") if p.is_file() and p.parent.name == "d"]
    assert data
    for path in data:
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    result = subprocess.run([sys.executable, "-m", "jaxden.cli", "train", str(config),
                             "--workdir", str(workdir)], env=cli_env(tmp_path / "cache"),
                            capture_output=True, text=True, timeout=300, check=False)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("jaxden: error: "), result.stderr
    assert str(workdir / "2") in lines[0] and "cannot be read" in lines[0]
    assert "Traceback" not in result.stderr and "Event loop is closed" not in result.stderr


# --------------------------------------------------- a huge EXR under an address-space limit
def _attribute(name: str, kind: str, value: bytes) -> bytes:
    return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value


def zip_exr_of_a_constant(path: Path, width: int, height: int, channels, value=0.5) -> None:
    """A scanline EXR, ZIP-compressed, HALF channels, every pixel ``value``, written by hand
    (OpenEXR's layout: header, chunk offset table, chunks of 16 scanlines each of which holds
    every channel's row in name order; ZIP: the bytes split into even and odd halves, a delta
    predictor, zlib). One compressed chunk serves all rows: 12000 x 12000 takes ~1 MB."""
    names = sorted(channels)
    assert height % 16 == 0
    chlist = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1) for n in names)
    box = struct.pack("<4i", 0, 0, width - 1, height - 1)
    header = (b"\x76\x2f\x31\x01" + struct.pack("<i", 2)
              + _attribute("channels", "chlist", chlist + b"\0")
              + _attribute("compression", "compression", b"\x03")
              + _attribute("dataWindow", "box2i", box)
              + _attribute("displayWindow", "box2i", box)
              + _attribute("lineOrder", "lineOrder", b"\x00")
              + _attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0))
              + _attribute("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0))
              + _attribute("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")
    raw = np.frombuffer(np.full((16, len(names), width), value, np.float16).tobytes(), np.uint8)
    halves = np.concatenate([raw[0::2], raw[1::2]]).astype(np.int16)
    halves[1:] = (np.diff(halves) + 128) & 0xFF
    block = zlib.compress(halves.astype(np.uint8).tobytes(), 9)
    count = height // 16
    first = len(header) + 8 * count
    offsets = struct.pack(f"<{count}Q", *(first + i * (8 + len(block)) for i in range(count)))
    with open(path, "wb") as handle:
        handle.write(header + offsets)
        handle.writelines(struct.pack("<ii", 16 * index, len(block)) + block
                          for index in range(count))


FRAME_CHANNELS = ("R", "G", "B", "albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y",
                  "normal.Z")


def test_the_hand_written_exr_reads_back(tmp_path):
    from jaxden.io.exr import read_channels

    zip_exr_of_a_constant(tmp_path / "small.exr", 40, 48, FRAME_CHANNELS, value=0.25)
    channels, _ = read_channels(tmp_path / "small.exr")
    assert sorted(channels) == sorted(FRAME_CHANNELS)
    for pixels in channels.values():
        assert pixels.shape == (48, 40) and np.all(pixels == 0.25)


def _address_space_10g() -> None:
    """``preexec_fn``: ``ulimit -v 10G`` (the soft limit; one system call)."""
    resource.setrlimit(resource.RLIMIT_AS, (10 << 30, resource.getrlimit(resource.RLIMIT_AS)[1]))


def test_a_declared_huge_exr_under_ulimit_v_is_refused_in_one_line(tmp_path):
    """12000 x 12000 pixels x 9 channels would need ~10 GiB to decode: more than the 10 GiB
    address space leaves beside what the process maps. JAXDEN_MEMORY_LIMIT is set far above,
    so only the address-space limit can refuse it, before any pixel is decoded."""
    big = tmp_path / "big.exr"
    zip_exr_of_a_constant(big, 12000, 12000, FRAME_CHANNELS)
    assert big.stat().st_size < 8 << 20
    result = subprocess.run(
        [sys.executable, "-m", "jaxden.cli", "denoise", str(big), "--model", "oidn",
         "--out", str(tmp_path / "out.exr")],
        env=cli_env(tmp_path / "cache", JAXDEN_MEMORY_LIMIT="4096G"),
        preexec_fn=_address_space_10g, capture_output=True, text=True, timeout=300, check=False)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("jaxden: error: "), result.stderr
    assert str(big) in lines[0] and "12000x12000" in lines[0]
    assert "address-space limit (ulimit -v)" in lines[0]
    assert not (tmp_path / "out.exr").exists()
