"""Broken sequence sets (jaxden.data.sequences): a ``sequences.json`` that is not UTF-8, not
JSON, of the wrong shape or types, with a path leaving the folder, a frame index out of place
or an unfinished build, and frame files that are missing or changed. Every entry point that
reads a sequence set - the resumed build (``jaxden dataset sequences``), the evaluation that
``jaxden sweep`` runs (``jaxden.evaluate.denoise.evaluate_sequences``) and ``jaxden sweep``
itself - either succeeds or gives one line ``jaxden: error: ...`` naming the file and the field
(exit 2, no traceback), and leaves the folder as it was (a build that succeeds re-renders the
set byte for byte). Hypothesis mutates the manifest (types, values, deleted keys, renamed
sequences, paths leaving the folder, truncation).

Data: one Mitsuba sequence of 3 frames of 20 x 16 pixels (under a second to render), a tiny
Mitsuba-free training dataset (``synthetic_render``) and a 2-step KP model for the sweep.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path
from unittest import mock

import pytest
from helpers import (
    assert_one_error_line,
    build_tiny_dataset,
    drop,
    json_paths,
    run_cli,
    set_or_delete,
    snapshot,
    write_train_config,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from jaxden import cli
from jaxden.data.sequences import MANIFEST_NAME, SequenceConfig, load_sequence_config
from jaxden.errors import JaxdenError

KEY = "s000-cornell-box"
CONFIG_TOML = """name = "adv"
scenes = ["cornell-box"]
size = [20, 16]
frames = 3
spp = 2
reference_spp = 4
seed = 5
rotation_deg = 20.0
"""


# ------------------------------------------------------------------------------- helpers
def _identity():
    """A denoiser that returns its input colour (no compile, no weights): the evaluation's
    reading of the set is what is under test."""
    from jaxden.denoise.registry import Denoiser, DenoiserDef

    return Denoiser(DenoiserDef("identity", "the input", type(None), lambda config: ("color",),
                                lambda params, config, frame: frame.color,
                                differentiable=False), None)


def evaluate(folder: Path) -> str | None:
    """``evaluate_sequences`` on ``folder``: None when it succeeds, else its one-line error
    (anything but a JaxdenError fails the test)."""
    from jaxden.evaluate.denoise import evaluate_sequences

    try:
        rows = evaluate_sequences(folder, _identity())
    except JaxdenError as error:
        message = str(error)
        assert message and "\n" not in message, message
        return message
    assert len(rows) == 2 and all(r["sequence"] == KEY for r in rows)  # frames 1 and 2
    return None


def build(folder: Path, config: Path, capsys) -> tuple[int, list[str], str]:
    return run_cli(["dataset", "sequences", config, "--out", folder, "--quiet"], capsys)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``(folder, config file, snapshot)`` of a built sequence set."""
    root = tmp_path_factory.mktemp("seq")
    config = root / "seq.toml"
    config.write_text(CONFIG_TOML)
    assert isinstance(load_sequence_config(config), SequenceConfig)
    folder = root / "set"
    assert cli.main(["dataset", "sequences", str(config), "--out", str(folder), "--quiet"]) == 0
    return folder, config, snapshot(folder)


def test_the_intact_set_evaluates_and_rebuilds_unchanged(built, capsys):
    folder, config, original = built
    assert evaluate(folder) is None
    code, lines, out = build(folder, config, capsys)
    assert code == 0 and lines == [] and "sequences complete" in out
    assert snapshot(folder) == original


def test_dataset_verify_on_a_sequence_set_is_one_line(built, capsys):
    """`jaxden dataset verify` checks crop datasets, not sequence sets: one line saying so."""
    folder, _, original = built
    code, lines, _ = run_cli(["dataset", "verify", folder], capsys)
    assert_one_error_line(code, lines, "not a jaxden dataset", "manifest.json")
    assert snapshot(folder) == original


# ------------------------------------------------------------------- table of damage
def _edit(change):
    """A damage that loads the manifest, applies ``change`` (which edits the dict, or returns
    the new text or bytes) and writes it back."""

    def damage(folder: Path) -> None:
        path = folder / MANIFEST_NAME
        data = json.loads(path.read_text())
        result = change(data)
        if isinstance(result, str):
            result = result.encode("utf-8")
        path.write_bytes(result if isinstance(result, bytes) else
                         json.dumps(data, indent=1).encode())
    return damage


def _frames(data) -> list:
    return data["sequences"][KEY]["frames"]


def _file(data, t: int, f: int) -> dict:
    return _frames(data)[t]["files"][f]


def _rename(data, new: str) -> None:
    data["sequences"][new] = data["sequences"].pop(KEY)


def _exr(name: str, how):
    def damage(folder: Path) -> None:
        how(folder / KEY / name)
    return damage


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[:300])


def _into_folder(path: Path) -> None:
    path.unlink()
    path.mkdir()


M = "sequences.json"
ANOTHER = "holds another sequence set"
# name: (damage, words in the readers' error, words in the build's error or None: the build
# succeeds and re-renders the set as it was)
CASES = {
    "not-utf8": (_edit(lambda d: b"\xff\xfe" + json.dumps(d).encode()),
                 (M, "cannot read the sequence manifest"), (M, "cannot read the sequence")),
    "truncated": (_edit(lambda d: json.dumps(d)[:70]), (M, "not valid JSON"),
                  (M, "not valid JSON")),
    "empty": (_edit(lambda d: ""), (M, "not valid JSON"), (M, "not valid JSON")),
    "list": (_edit(lambda d: "[]"), (M, "must be an object"), (M, "must be an object")),
    "format-missing": (_edit(lambda d: drop(d, "format")), (M, "not a jaxden sequence"),
                       (M, "not a jaxden sequence")),
    "config-list": (_edit(lambda d: d.__setitem__("config", [])),
                    (M, "'config' must be an object"), (M, "'config' must be an object")),
    "config-frames-text": (_edit(lambda d: d["config"].__setitem__("frames", "3")),
                           (M, "field 'config'", "frames"), (ANOTHER, "frames")),
    "config-unknown-key": (_edit(lambda d: d["config"].__setitem__("framez", 3)),
                           (M, "field 'config'", "framez"), (ANOTHER, "framez")),
    "config-frames-more": (_edit(lambda d: d["config"].__setitem__("frames", 4)),
                           (M, "lists 3 frames, the set's config gives 4"), (ANOTHER, "frames")),
    "sequences-list": (_edit(lambda d: d.__setitem__("sequences", [])),
                       (M, "'sequences' must be an object"), (M, "'sequences' must be an")),
    "sequences-missing": (_edit(lambda d: drop(d, "sequences")), (M, "'sequences' is missing"),
                          (M, "'sequences' is missing")),
    "record-text": (_edit(lambda d: d["sequences"].__setitem__(KEY, "x")),
                    (M, KEY, "expected an object"), (M, KEY, "expected an object")),
    "scene-number": (_edit(lambda d: d["sequences"][KEY].__setitem__("scene", 3)),
                     (M, "'scene' must be a string"), (M, "'scene' must be a string")),
    "scene-other": (_edit(lambda d: d["sequences"][KEY].__setitem__("scene", "veach-mis")),
                    (M, "'scene' must be 'cornell-box'"), (M, "'scene' must be 'cornell-box'")),
    "frames-missing": (_edit(lambda d: drop(d["sequences"][KEY], "frames")),
                       (M, "'frames' is missing"), (M, "'frames' is missing")),
    "frames-object": (_edit(lambda d: d["sequences"][KEY].__setitem__("frames", {})),
                      (M, "'frames' must be a list"), (M, "'frames' must be a list")),
    "frame-index-text": (_edit(lambda d: _frames(d)[1].__setitem__("frame", "1")),
                         (M, "frames[1]", "'frame' must be a whole number"),
                         (M, "'frame' must be a whole number")),
    "frame-index-bool": (_edit(lambda d: _frames(d)[0].__setitem__("frame", False)),
                         (M, "frames[0]", "'frame' must be a whole number"),
                         (M, "'frame' must be a whole number")),
    "frame-index-float": (_edit(lambda d: _frames(d)[1].__setitem__("frame", 1.0)),
                          (M, "'frame' must be a whole number"),
                          (M, "'frame' must be a whole number")),
    "frame-index-out-of-range": (_edit(lambda d: _frames(d)[2].__setitem__("frame", 7)),
                                 (M, "frames[2]", "'frame' must be 2"), (M, "'frame' must be 2")),
    "frame-index-negative": (_edit(lambda d: _frames(d)[0].__setitem__("frame", -1)),
                             (M, "'frame' must be 0"), (M, "'frame' must be 0")),
    "frames-swapped": (_edit(lambda d: _frames(d).reverse()), (M, "'frame' must be 0"),
                       (M, "'frame' must be 0")),
    "frame-extra": (_edit(lambda d: _frames(d).append(_frames(d)[0])),
                    (M, "lists 4 frames, the set's config gives 3"), (M, "lists 4 frames")),
    "files-missing": (_edit(lambda d: drop(_frames(d)[0], "files")), (M, "'files' is missing"),
                      (M, "'files' is missing")),
    "files-one": (_edit(lambda d: _frames(d)[1]["files"].pop()), (M, "must list 2 files"),
                  (M, "must list 2 files")),
    "file-text": (_edit(lambda d: _frames(d)[1]["files"].__setitem__(0, "f001.exr")),
                  (M, "files[0]", "expected an object"), (M, "expected an object")),
    "path-number": (_edit(lambda d: _file(d, 0, 0).__setitem__("path", 0)),
                    (M, "'path' must be a string"), (M, "'path' must be a string")),
    "path-missing": (_edit(lambda d: drop(_file(d, 0, 1), "path")), (M, "'path' is missing"),
                     (M, "'path' is missing")),
    "path-dotdot": (_edit(lambda d: _file(d, 0, 0).__setitem__("path", f"../{KEY}/f000.exr")),
                    (M, "leaves the sequence folder"), (M, "leaves the sequence folder")),
    "path-absolute": (_edit(lambda d: _file(d, 1, 1).__setitem__("path", "/etc/passwd")),
                      (M, "leaves the sequence folder"), (M, "leaves the sequence folder")),
    "path-empty": (_edit(lambda d: _file(d, 1, 0).__setitem__("path", "")),
                   (M, "leaves the sequence folder"), (M, "leaves the sequence folder")),
    "path-other-frame": (_edit(lambda d: _file(d, 0, 0).__setitem__("path", "f001.exr")),
                         (M, "'path' must be 'f000.exr'"), (M, "'path' must be 'f000.exr'")),
    "path-reference-as-input": (_edit(lambda d: _frames(d)[2]["files"].reverse()),
                                (M, "'path' must be 'f002.exr' (the input"),
                                (M, "'path' must be 'f002.exr'")),
    "sha-missing": (_edit(lambda d: drop(_file(d, 2, 0), "sha256")),
                    (M, "'sha256' is missing"), (M, "'sha256' is missing")),
    "sha-number": (_edit(lambda d: _file(d, 2, 0).__setitem__("sha256", 12)),
                   (M, "'sha256' must be a string"), (M, "'sha256' must be a string")),
    "sha-short": (_edit(lambda d: _file(d, 2, 0).__setitem__("sha256", "abc")),
                  (M, "'sha256' must be 64 hex digits"), (M, "'sha256' must be 64 hex")),
    "key-dotdot": (_edit(lambda d: _rename(d, f"../{KEY}")), (M, "not a folder inside"),
                   (M, "not a folder inside")),
    "key-absolute": (_edit(lambda d: _rename(d, "/tmp")), (M, "not a folder inside"),
                     (M, "not a folder inside")),
    "key-other": (_edit(lambda d: _rename(d, "s001-cornell-box")),
                  (M, "not one of the sequences"), (M, "not one of the sequences")),
    # An unfinished build: the readers refuse it, a build finishes it.
    "sequence-deleted": (_edit(lambda d: d["sequences"].clear()), (M, "is not built yet"),
                         None),
    "frame-dropped": (_edit(lambda d: _frames(d).pop()), (M, "lists 2 frames", "did not finish"),
                      None),
    "frames-empty": (_edit(lambda d: _frames(d).clear()), (M, "lists 0 frames"), None),
    # The frame files: the readers check them against the manifest; a build re-renders them.
    "exr-missing": (_exr("f001.exr", Path.unlink), ("f001.exr: missing",), None),
    "exr-truncated": (_exr("f002.ref.exr", _truncate),
                      ("f002.ref.exr: does not match its checksum",), None),
    "exr-other-frame": (_exr("f000.exr", lambda p: shutil.copy(p.with_name("f001.exr"), p)),
                        ("f000.exr: does not match its checksum",), None),
    "exr-folder": (_exr("f001.ref.exr", _into_folder), ("f001.ref.exr: not a regular file",),
                   "f001.ref.exr"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_broken_sequence_set_is_one_line(case, built, tmp_path, capsys):
    """The evaluation refuses the set in one line naming the file and the field; the build
    refuses it the same way, or (an unfinished set, a damaged frame) renders it again, byte
    for byte as built; a refusal changes nothing."""
    source, config, original = built
    folder = tmp_path / "set"
    shutil.copytree(source, folder)
    damage, reader_words, builder_words = CASES[case]
    damage(folder)
    before = snapshot(folder)
    error = evaluate(folder)
    assert error is not None, case
    for word in reader_words:
        assert word in error, (word, error)
    assert snapshot(folder) == before
    code, lines, _ = build(folder, config, capsys)
    if builder_words is None:
        assert code == 0 and lines == [], (code, lines)
        assert snapshot(folder) == original
    else:
        words = (builder_words,) if isinstance(builder_words, str) else builder_words
        assert_one_error_line(code, lines, *words)
        assert snapshot(folder) == before


def test_a_missing_or_wrong_folder_is_one_line(built, tmp_path, capsys):
    from jaxden.data.sequences import load_sequence

    (tmp_path / "empty").mkdir()
    (tmp_path / "file").write_text("x")
    for folder, words in ((tmp_path / "nothing", "does not exist"),
                          (tmp_path / "file", "is a file"),
                          (tmp_path / "empty", "has no sequences.json")):
        assert words in evaluate(folder)
    with pytest.raises(JaxdenError, match="no sequence 's009'"):
        load_sequence(built[0], "s009")


# --------------------------------------------------------------------------- jaxden sweep
PROGRESS = re.compile(r"^train \w+: +\d+%\|")  # tqdm's bar (the sweep has no --quiet)
SWEEP_CASES = ("not-utf8", "path-dotdot", "frame-index-text", "frame-dropped", "exr-truncated")


@pytest.mark.slow  # ~13 s: trains a 2-step model first; the table above covers the reader
def test_jaxden_sweep_on_a_broken_sequence_set_is_one_line(built, tmp_path, capsys):
    """`jaxden sweep` with ``[evaluate] sequences``: the intact set evaluates; with the run's
    result.json gone (the sweep redoes the run from its final checkpoint, no training), each
    broken set stops it in one line and changes nothing."""
    dataset = build_tiny_dataset(tmp_path / "tiny")
    source, _, original = built
    folder = tmp_path / "set"
    shutil.copytree(source, folder)
    base = write_train_config(tmp_path, dataset)
    sweep = tmp_path / "sweep.toml"
    sweep.write_text(f'base = "{base}"\n[axes]\nseed = [0]\n[evaluate]\n'
                     f'sequences = ["{folder}"]\n')
    workdir = tmp_path / "w"
    result = workdir / "seed=0" / "result.json"
    code, lines, _ = run_cli(["sweep", sweep, "--workdir", workdir], capsys)
    assert code == 0, lines
    assert json.loads(result.read_text())["evaluations"][f"seq:{folder}"]["count"] == 2
    assert snapshot(folder) == original
    for case in SWEEP_CASES:
        shutil.rmtree(folder)
        shutil.copytree(source, folder)
        result.unlink(missing_ok=True)
        damage, words, _ = CASES[case]
        damage(folder)
        before = snapshot(folder)
        code, lines, _ = run_cli(["sweep", sweep, "--workdir", workdir], capsys)
        lines = [line for line in lines if not PROGRESS.match(line)]  # the bars of the resume
        assert_one_error_line(code, lines, *words)
        assert snapshot(folder) == before, case
        assert not result.exists()


# ------------------------------------------------------------------ manifest mutations
JUNK = st.one_of(
    st.none(), st.booleans(), st.integers(-10**30, 10**30),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
    st.sampled_from(["../outside.exr", "/etc/passwd", "~/x.exr", "", ".", KEY, "f000.exr",
                     "f001.ref.exr", "cornell-box", "0" * 64, "random", "orbit"]),
    st.integers(-3, 5),
    st.lists(st.integers(-3, 40), max_size=5),
    st.dictionaries(st.text(max_size=4), st.integers(), max_size=2))


@pytest.fixture(scope="module")
def mutation_case(built, tmp_path_factory):
    """A private copy of the built set, its manifest text and every key path in it."""
    folder = tmp_path_factory.mktemp("mutated") / "set"
    shutil.copytree(built[0], folder)
    text = (folder / MANIFEST_NAME).read_text()
    return folder, text, list(json_paths(json.loads(text)))


def _mutated(text: str, paths, draw) -> str:
    data = json.loads(text)
    kind = draw(st.sampled_from(["set", "set", "set", "delete", "truncate", "escape",
                                 "rename", "unfinish"]))
    if kind == "unfinish":  # what an interrupted build leaves: the build finishes it
        del _frames(data)[draw(st.integers(0, 2)):]
        return json.dumps(data)
    if kind == "truncate":
        return text[: draw(st.integers(0, len(text) - 1))]
    if kind == "escape":  # a frame file that leaves the folder, or is another frame's file
        t, f = draw(st.integers(0, 2)), draw(st.integers(0, 1))
        entry = _file(data, t, f)
        entry["path"] = draw(st.sampled_from(
            [f"../set/{KEY}/{entry['path']}", "../../etc/passwd", "/etc/passwd",
             f"{KEY}/../../x.exr", _file(data, 2 - t, 1 - f)["path"], "~/x.exr",
             "./" + entry["path"]]))
        return json.dumps(data)
    if kind == "rename":
        _rename(data, draw(st.one_of(st.sampled_from(
            ["../" + KEY, "/tmp", "", ".", "..", f"{KEY}/..", "s001-cornell-box", KEY + "/"]),
            st.text(max_size=8))))
        return json.dumps(data)
    return set_or_delete(data, paths, draw, JUNK, delete=kind == "delete")


@settings(max_examples=100, deadline=None, derandomize=True, database=None,
          phases=[Phase.explicit, Phase.generate],  # each example is one mutation: no shrinking
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_mutated_sequence_manifests_evaluate_build_or_give_one_line(built, mutation_case,
                                                                    capsys, data):
    """The evaluation works or raises one jaxden error of one line, leaving the folder as it
    was; `jaxden dataset sequences` on the folder ends in 0 with the set as built (it
    finished or repaired it) or in 2 with one `jaxden: error:` line and the folder as it
    was."""
    _, config, original = built
    folder, text, paths = mutation_case
    mutated = _mutated(text, paths, data.draw)
    (folder / MANIFEST_NAME).write_text(mutated)
    try:
        before = snapshot(folder)
        # FLIP (NVIDIA's flip_evaluator, ~1 s per HDR call here) is left out of the
        # evaluations that succeed: reading the set is under test; the intact set's test
        # runs the full evaluation.
        with mock.patch("jaxden.metrics.flip", lambda *args: 0.0):
            evaluate(folder)
        assert snapshot(folder) == before
        code, lines, _ = build(folder, config, capsys)
        if code == 0:
            assert lines == []
            assert snapshot(folder) == original
        else:
            assert_one_error_line(code, lines)
            assert snapshot(folder) == before
    finally:
        (folder / MANIFEST_NAME).write_text(text)
