"""Dataset config, plan, resumable builder and verifier (with the Mitsuba-free synthetic
renderer; one end-to-end build with the real renderer)."""

from __future__ import annotations

import dataclasses
import fcntl
import json
from pathlib import Path

import numpy as np
import pytest

from jaxden.config import load_config
from jaxden.data import (
    DatasetConfig,
    ProceduralConfig,
    SplitConfig,
    build_dataset,
    load_dataset_config,
    load_manifest,
    plan_dataset,
    verify_dataset,
)
from jaxden.data.layout import LOCK_NAME, sha256_file
from jaxden.errors import ConfigError, DatasetError
from jaxden.executor import ExecutorError, make_executor
from jaxden.render.synthetic import synthetic_render

CONFIGS = Path(__file__).resolve().parents[1] / "experiments" / "configs"

SMALL = DatasetConfig(
    name="small",
    scenes=("alpha", "beta"),
    procedural=ProceduralConfig(count=1, seed=7),
    size=(40, 30),
    crop_size=8,
    crops_per_scene=2,
    spp=(2, 4, 16),
    reference_spp=256,
    seed=3,
    splits=SplitConfig(train=0.5, val=0.5, test=0.0),
)
ITEMS = 3 * 2 * 4  # scenes x crops x (3 spp levels + reference)


class CountingRender:
    """The synthetic renderer, counting calls; raises after ``crash_after`` calls (a crash in
    the middle of a build). Used with the serial executor (state stays in this process)."""

    def __init__(self, crash_after: int | None = None) -> None:
        self.calls = 0
        self.crash_after = crash_after

    def __call__(self, scene, spp, seed=0, size=None, *, crop=None):
        if self.crash_after is not None and self.calls >= self.crash_after:
            raise RuntimeError("simulated crash")
        self.calls += 1
        return synthetic_render(scene, spp, seed, size, crop=crop)


def build(directory, render=None, config=SMALL, **kwargs):
    render = render or CountingRender()
    manifest = build_dataset(
        config, directory, executor="serial", render_fn=render, progress=False, **kwargs
    )
    return manifest, render


def file_states(directory: Path) -> dict[str, tuple[int, str]]:
    return {
        str(p.relative_to(directory)): (p.stat().st_mtime_ns, sha256_file(p))
        for p in directory.rglob("*.exr")
    }


# ----------------------------------------------------------------------------- config
def test_shipped_configs_load():
    tiny = load_dataset_config(CONFIGS / "dataset-tiny.toml")
    default = load_dataset_config(CONFIGS / "dataset-default.toml")
    assert tiny.crop_size <= min(tiny.size) and len(plan_dataset(tiny).items) <= 40
    assert default.crop_size == 128 and default.reference_spp >= max(default.spp)
    from jaxden.data.builder import check_scenes

    check_scenes(tiny.scene_ids())  # raises SceneError for a scene the renderer lacks
    check_scenes(default.scene_ids())


@pytest.mark.parametrize(
    ("changes", "pattern"),
    [
        ({"spp": (0, 4)}, r"spp: every sample count must be > 0"),
        ({"spp": (4, 4)}, r"distinct"),
        ({"spp": ()}, r"at least one"),
        ({"reference_spp": 8}, r"reference_spp \(8\) must be >= the largest input spp \(16\)"),
        ({"crop_size": 31}, r"crop_size 31 does not fit in the film size 40x30"),
        ({"crops_per_scene": 0}, r"crops_per_scene must be > 0"),
        ({"scenes": (), "procedural": ProceduralConfig(0, 0)}, r"no scenes"),
        ({"scenes": ("a", "a")}, r"a appear\(s\) twice"),
        ({"scenes": ("procedural:7",)}, r"procedural:7 appear\(s\) twice"),
        ({"scenes": ("procedural:x",)}, r"'procedural:SEED'"),
        ({"splits": SplitConfig(val_scenes=("zeta",))}, r"splits.val_scenes: zeta is not one"),
        ({"aux": "next-hit"}, r"aux must be one of first-hit, specular-chain, got 'next-hit'"),
        ({"feature_spp": 0}, r"feature_spp must be > 0, got 0"),
    ],
)
def test_dataset_config_rejects_bad_values(changes, pattern):
    with pytest.raises(ConfigError, match=pattern):
        dataclasses.replace(SMALL, **changes)


def test_split_config_rejects_bad_fractions():
    with pytest.raises(ConfigError, match=r"sum to 1, got 0.5 \+ 0.6 \+ 0.0 = 1.1"):
        SplitConfig(train=0.5, val=0.6)
    with pytest.raises(ConfigError, match=r"splits.val must be a fraction in \[0, 1\], got -0.5"):
        SplitConfig(train=1.5 - 1.0, val=-0.5)
    with pytest.raises(ConfigError, match=r"in both"):
        SplitConfig(val_scenes=("a",), test_scenes=("a",))


def test_dataset_config_from_toml_names_file(tmp_path):
    path = tmp_path / "d.toml"
    path.write_text('scenes = ["a"]\nsize = [64, 64]\ncrop_size = 128\n')
    with pytest.raises(ConfigError, match=r"d.toml.*crop_size 128 does not fit"):
        load_dataset_config(path)
    config = load_dataset_config(path, ["crop_size=32", "splits.by=crop"])
    assert config.crop_size == 32 and config.splits.by == "crop"


# ----------------------------------------------------------------------------- plan
def test_plan_is_deterministic_and_well_formed():
    first, second = plan_dataset(SMALL), plan_dataset(SMALL)
    assert first.to_json()["items"] == second.to_json()["items"]
    assert first.crops == second.crops
    assert len(first.items) == ITEMS and len(first.crops) == 6
    seeds = [item.seed for item in first.items]
    assert len(set(seeds)) == len(seeds)  # every render has its own seed
    paths = [item.path for item in first.items]
    assert len(set(paths)) == len(paths)
    width, height = SMALL.size
    for crop in first.crops:
        top, left, h, w = crop.window
        assert (h, w) == (8, 8) and 0 <= top <= height - h and 0 <= left <= width - w
        items = first.items_of(crop.id)
        assert sorted(i.spp for i in items if i.kind == "input") == [2, 4, 16]
        assert [i.spp for i in items if i.kind == "reference"] == [256]
    assert [s["id"] for s in first.scenes] == ["alpha", "beta", "procedural:7"]


def test_plan_seeds_follow_scene_identity_not_order():
    a = plan_dataset(SMALL)
    b = plan_dataset(dataclasses.replace(SMALL, scenes=("beta", "alpha")))
    seeds_a = {(c.scene, c.crop_index, i.spp): i.seed for c in a.crops for i in a.items_of(c.id)}
    seeds_b = {(c.scene, c.crop_index, i.spp): i.seed for c in b.crops for i in b.items_of(c.id)}
    assert seeds_a == seeds_b
    windows_a = {(c.scene, c.crop_index): c.window for c in a.crops}
    assert windows_a == {(c.scene, c.crop_index): c.window for c in b.crops}
    c = plan_dataset(dataclasses.replace(SMALL, seed=4))
    assert {i.seed for i in c.items}.isdisjoint({i.seed for i in a.items})


def test_splits_by_scene_fractions_and_explicit_lists():
    config = dataclasses.replace(
        SMALL,
        scenes=tuple(f"s{i}" for i in range(10)),
        procedural=ProceduralConfig(),
        crops_per_scene=1,
        splits=SplitConfig(train=0.7, val=0.2, test=0.1),
    )
    manifest = plan_dataset(config)
    assert manifest.split_counts() == {"train": 7, "val": 2, "test": 1}
    for scene in manifest.scenes:  # every crop of a scene is in the scene's split
        assert {c.split for c in manifest.crops if c.scene == scene["id"]} == {scene["split"]}
    explicit = plan_dataset(
        dataclasses.replace(
            config,
            splits=SplitConfig(
                train=1.0, val=0.0, test=0.0, val_scenes=("s3",), test_scenes=("s5", "s6")
            ),
        )
    )
    assert {s["id"]: s["split"] for s in explicit.scenes if s["split"] != "train"} == {
        "s3": "val",
        "s5": "test",
        "s6": "test",
    }


def test_small_split_gets_at_least_one_scene_and_by_crop_divides_crops():
    config = dataclasses.replace(
        SMALL, splits=SplitConfig(train=0.95, val=0.05), procedural=ProceduralConfig()
    )
    # 2 scenes x 2 crops: the 5 % validation split still gets one scene (2 crops).
    assert plan_dataset(config).split_counts() == {"train": 2, "val": 2, "test": 0}
    by_crop = plan_dataset(
        dataclasses.replace(config, crops_per_scene=10, splits=SplitConfig(0.8, 0.2, 0.0, "crop"))
    )
    assert by_crop.split_counts() == {"train": 16, "val": 4, "test": 0}


# ----------------------------------------------------------------------------- build
def test_build_writes_every_item_with_checksums_and_headers(tmp_path):
    from jaxden.io.exr import read_frame, read_header

    manifest, render = build(tmp_path / "d")
    assert render.calls == ITEMS and manifest.complete
    stored = load_manifest(tmp_path / "d")
    assert stored.complete and stored.config == manifest.config
    crops = stored.crop_by_id()
    for item in stored.items:
        path = tmp_path / "d" / item.path
        assert sha256_file(path) == item.sha256 and path.stat().st_size == item.bytes
        header = read_header(path)
        assert (header["item"], header["seed"], header["spp"]) == (item.id, item.seed, item.spp)
        crop = crops[item.crop]
        expected = synthetic_render(crop.scene, item.spp, item.seed, SMALL.size, crop=crop.window)
        frame = read_frame(path, require=("color", "albedo", "normal", "depth"))
        np.testing.assert_array_equal(frame.color, expected.color)
        np.testing.assert_array_equal(frame.position, expected.position)
        assert (frame.variance is None) == (item.spp == 1)
    manifest_json = json.loads((tmp_path / "d" / "manifest.json").read_text())
    assert manifest_json["complete"] and manifest_json["items_done"] == ITEMS
    assert load_dataset_config(tmp_path / "d" / "dataset.toml") == SMALL
    assert verify_dataset(tmp_path / "d").ok


def test_resume_after_crash_keeps_finished_items(tmp_path):
    directory = tmp_path / "d"
    with pytest.raises(RuntimeError, match="simulated crash"):
        build(directory, CountingRender(crash_after=7))
    partial = load_manifest(directory)
    assert sum(item.done for item in partial.items) == 7 and not partial.complete
    before = file_states(directory)
    assert len(before) == 7
    report = verify_dataset(directory)
    assert len(report.problems) == ITEMS - 7
    assert all("not built yet" in p.message for p in report.problems)

    manifest, render = build(directory)
    assert render.calls == ITEMS - 7 and manifest.complete
    after = file_states(directory)
    assert len(after) == ITEMS
    assert {k: after[k] for k in before} == before  # finished files untouched (mtime, bytes)
    assert verify_dataset(directory).ok
    # A third run has nothing to do.
    _, render = build(directory)
    assert render.calls == 0


def test_resume_recovers_files_finished_after_last_manifest_save(tmp_path):
    directory = tmp_path / "d"
    build(directory)
    data = json.loads((directory / "manifest.json").read_text())
    for item in data["items"][:5]:  # as if killed after writing these, before saving
        item["sha256"] = item["bytes"] = None
    (directory / "manifest.json").write_text(json.dumps(data))
    before = file_states(directory)
    leftover = directory / Path(data["items"][0]["path"]).parent / ".spp00002.exr.x1y2.tmp.exr"
    leftover.write_bytes(b"half-written")
    manifest, render = build(directory)
    assert render.calls == 0 and manifest.complete
    assert not leftover.exists() and file_states(directory) == before
    assert verify_dataset(directory).ok


def test_corrupt_and_missing_items_are_reported_and_rebuilt(tmp_path):
    directory = tmp_path / "d"
    manifest, _ = build(directory)
    corrupt = directory / manifest.items[3].path
    data = bytearray(corrupt.read_bytes())
    data[len(data) // 2] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    truncated = directory / manifest.items[5].path
    truncated.write_bytes(truncated.read_bytes()[:100])
    missing = directory / manifest.items[8].path
    missing.unlink()
    (directory / "stray.txt").write_text("x")

    report = verify_dataset(directory)
    assert not report.ok
    found = {p.path: p.message for p in report.problems}
    assert set(found) == {str(corrupt), str(truncated), str(missing)}
    assert "SHA-256" in found[str(corrupt)] and "size" in found[str(truncated)]
    assert found[str(missing)] == "missing"
    assert any("stray.txt" in w for w in report.warnings)
    assert str(corrupt) in str(report) and "3 problem(s)" in report.summary()

    _, render = build(directory)
    assert render.calls == 3
    assert verify_dataset(directory).ok


def test_verify_detects_a_valid_exr_of_another_item(tmp_path):
    directory = tmp_path / "d"
    manifest, _ = build(directory)
    first, second = manifest.items[1], manifest.items[2]
    (directory / second.path).write_bytes((directory / first.path).read_bytes())
    data = json.loads((directory / "manifest.json").read_text())
    data["items"][2]["sha256"], data["items"][2]["bytes"] = first.sha256, first.bytes
    (directory / "manifest.json").write_text(json.dumps(data))
    problems = [str(p) for p in verify_dataset(directory).problems]
    assert any(f"jaxden.item is '{first.id}', expected '{second.id}'" in p for p in problems)
    assert any("jaxden.spp" in p for p in problems)
    assert verify_dataset(directory, read=False, checksums=False).problems  # header check alone


def test_different_config_or_renderer_in_same_folder_is_an_error(tmp_path):
    directory = tmp_path / "d"
    build(directory)
    other = dataclasses.replace(SMALL, spp=(2, 8, 16), crop_size=6)
    with pytest.raises(DatasetError) as info:
        build(directory, config=other)
    message = str(info.value)
    assert "different config" in message and str(directory) in message
    assert "spp: [2, 4, 16] -> [2, 8, 16]" in message and "crop_size: 8 -> 6" in message
    with pytest.raises(DatasetError, match="renderer .*CountingRender, not .*synthetic_render"):
        build_dataset(
            SMALL, directory, executor="serial", render_fn=synthetic_render, progress=False
        )


def test_dataset_of_an_older_jaxden_without_aux_resumes(tmp_path):
    # Datasets written before `aux` existed store no such key: they were first-hit, and must
    # resume under today's config (default first-hit) but not under another aux.
    directory = tmp_path / "d"
    build(directory)
    path = directory / "manifest.json"
    stored = json.loads(path.read_text())
    del stored["config"]["aux"], stored["config"]["feature_spp"]
    path.write_text(json.dumps(stored))
    _, render = build(directory)
    assert render.calls == 0
    other = dataclasses.replace(SMALL, aux="specular-chain")
    with pytest.raises(DatasetError, match='aux: "first-hit" -> "specular-chain"'):
        build(directory, render=AuxRender(), config=other)


def test_finishing_a_build_of_files_without_the_colour_covariance_is_refused(tmp_path):
    # The core renderer writes the covariance beside the variance; files of an older jaxden
    # have none, and a build that finished them would mix the two (SURE from the covariance
    # silently per-channel on some items). The synthetic renderer stands for the older one.
    from jaxden.data.verify import check_covariance_recorded

    old, _ = build(tmp_path / "old")
    with pytest.raises(DatasetError, match=r"old: 24 of its 24 finished files \(.*\.exr, \.\.\.\) "
                                           r"have the variance but no colour covariance"):
        check_covariance_recorded(tmp_path / "old", old.items)

    def with_covariance(scene, spp, seed=0, size=None, *, crop=None):
        frame = synthetic_render(scene, spp, seed, size, crop=crop)
        if frame.variance is None:
            return frame
        return frame.replace(covariance=np.zeros_like(frame.variance))

    new, _ = build(tmp_path / "new", render=with_covariance)
    check_covariance_recorded(tmp_path / "new", new.items)  # every file has it: no error


class AuxRender(CountingRender):
    """CountingRender that takes (and records) the aux mode."""

    def __call__(self, scene, spp, seed=0, size=None, *, crop=None, aux="first-hit",
                 feature_spp=16):
        self.aux, self.feature_spp = aux, feature_spp
        return super().__call__(scene, spp, seed, size, crop=crop)


def test_feature_options_reach_the_renderer_and_a_renderer_without_them_is_refused(tmp_path):
    config = dataclasses.replace(SMALL, aux="specular-chain", feature_spp=256)
    _, render = build(tmp_path / "a", render=AuxRender(), config=config)
    assert (render.aux, render.feature_spp, render.calls) == ("specular-chain", 256, ITEMS)
    with pytest.raises(DatasetError, match="aux = 'specular-chain', feature_spp = 256 needs a "
                                           "renderer that takes `aux=`, `feature_spp=`"):
        build(tmp_path / "b", config=config)
    assert not (tmp_path / "b").exists()


def test_refeature_refuses_incomplete_or_foreign_sources(tmp_path):
    from jaxden.data.refeature import refeature_dataset

    with pytest.raises(RuntimeError, match="simulated crash"):
        build(tmp_path / "part", render=CountingRender(crash_after=3))
    with pytest.raises(DatasetError, match="not complete"):
        refeature_dataset(tmp_path / "part", tmp_path / "x", ["feature_spp=64"])
    build(tmp_path / "synthetic")
    with pytest.raises(DatasetError, match="built by .*CountingRender; refeature needs"):
        refeature_dataset(tmp_path / "synthetic", tmp_path / "x", ["feature_spp=64"])
    assert not (tmp_path / "x").exists()


def test_refuses_foreign_folder_and_concurrent_build(tmp_path):
    (tmp_path / "foreign").mkdir()
    (tmp_path / "foreign" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty .*notes.txt"):
        build(tmp_path / "foreign")
    directory = tmp_path / "d"
    directory.mkdir()
    with open(directory / LOCK_NAME, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(DatasetError, match="another build"):
            build(directory)


def test_bad_render_output_is_a_clear_error(tmp_path):
    def wrong_size(scene, spp, seed=0, size=None, *, crop=None):
        frame = synthetic_render(scene, spp, seed, size, crop=crop)
        return frame.crop(0, 0, 4, 4)

    with pytest.raises(DatasetError, match=r"colour of shape \(4, 4, 3\), expected .*\(8, 8, 3\)"):
        build(tmp_path / "a", wrong_size)

    def no_albedo(scene, spp, seed=0, size=None, *, crop=None):
        return synthetic_render(scene, spp, seed, size, crop=crop).replace(albedo=None)

    with pytest.raises(DatasetError, match="without albedo"):
        build(tmp_path / "b", no_albedo)


def test_process_pool_build_matches_serial_build(tmp_path):
    config = dataclasses.replace(SMALL, crops_per_scene=1)
    common = {"render_fn": synthetic_render, "progress": False}
    serial = build_dataset(config, tmp_path / "s", executor="serial", **common)
    pooled = build_dataset(config, tmp_path / "p", executor="local", workers=2, **common)
    assert [i.sha256 for i in serial.items] == [i.sha256 for i in pooled.items]


def test_executor_kinds():
    with make_executor("serial") as pool:
        assert sorted(pool.map_unordered(abs, [-3, 1, -2])) == [1, 2, 3]
    with pytest.raises(ExecutorError, match="unknown executor 'threads'"):
        make_executor("threads")
    try:
        import ray  # noqa: F401
    except ImportError:
        with pytest.raises(ExecutorError, match=r"pip install 'jaxden\[ray\]'"):
            make_executor("ray")


def test_local_executor_propagates_task_errors():
    with make_executor("local", workers=1) as pool:
        with pytest.raises(ValueError, match="math domain error"):
            list(pool.map_unordered(_sqrt, [4.0, -1.0, 9.0]))
        assert sorted(pool.map_unordered(_sqrt, [4.0, 9.0])) == [2.0, 3.0]  # pool still usable


def _sqrt(x: float) -> float:
    import math

    return math.sqrt(x)


ORPHAN_SCRIPT = """
import sys, time
from pathlib import Path

def task(path):
    import os
    Path(path).write_text(str(os.getpid()))
    time.sleep(120)

if __name__ == "__main__":
    from jaxden.executor import make_executor
    with make_executor("local", workers=1) as pool:
        list(pool.map_unordered(task, [sys.argv[1]]))
"""


def test_local_workers_exit_when_their_parent_is_killed(tmp_path):
    """A build killed with SIGKILL (or `kill PID` of the parent alone) must not leave its
    worker rendering on unseen: a rerun would render the same items twice at once."""
    import os
    import signal
    import subprocess
    import sys
    import time

    script, pid_file = tmp_path / "parent.py", tmp_path / "worker.pid"
    script.write_text(ORPHAN_SCRIPT)
    parent = subprocess.Popen([sys.executable, str(script), str(pid_file)])
    try:
        deadline = time.monotonic() + 60
        while not (pid_file.exists() and pid_file.read_text()):
            assert time.monotonic() < deadline and parent.poll() is None, "worker never started"
            time.sleep(0.1)
        worker = int(pid_file.read_text())
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        deadline = time.monotonic() + 10  # the watcher polls every PARENT_POLL_SECONDS = 1
        while Path(f"/proc/{worker}").exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        alive = Path(f"/proc/{worker}").exists()
        if alive:
            os.kill(worker, signal.SIGKILL)
        assert not alive, "the worker outlived its parent by more than 10 s"
    finally:
        if parent.poll() is None:
            parent.kill()


def test_synthetic_render_variance_matches_noise():
    """The synthetic renderer's variance channel estimates the variance of the mean: over many
    seeds, the empirical variance of the colour equals the mean variance estimate (tolerance:
    4 standard errors of a variance estimate from 400 samples, ~28 %, pooled over 64 pixels
    and 3 channels gives a few %)."""
    frames = [synthetic_render("x", 8, seed, (16, 16), crop=(4, 4, 8, 8)) for seed in range(400)]
    colors = np.stack([f.color for f in frames])
    estimates = np.stack([f.variance for f in frames])
    ratio = colors.var(axis=0, ddof=1).mean() / estimates.mean()
    assert abs(ratio - 1.0) < 0.05
    assert load_config({"scenes": ["x"]}, DatasetConfig).scene_ids() == ["x"]


# ----------------------------------------------------------------------------- real renderer
# Mitsuba is a required dependency (pyproject.toml) and jaxden.render is part of the package:
# these tests run everywhere, with no skip guard (one that imported jaxden's own modules could
# never fire, and a missing renderer must fail, not skip).


def test_tiny_config_end_to_end_with_mitsuba(tmp_path):
    """The shipped tiny config with the real renderer (8 renders, 10-20 s, mostly Mitsuba's
    kernel compilation): build, verify, load a batch."""
    from jaxden.data import DatasetLoader

    config = load_dataset_config(CONFIGS / "dataset-tiny.toml")
    directory = tmp_path / "tiny"
    manifest = build_dataset(config, directory, executor="serial", progress=False)
    assert manifest.complete and len(manifest.items) == len(plan_dataset(config).items)
    report = verify_dataset(directory)
    assert report.ok, str(report)
    loader = DatasetLoader(directory, "train", batch_size=2, seed=0)
    batch = next(iter(loader))
    assert batch.input.color.shape == (2, config.crop_size, config.crop_size, 3)
    assert np.isfinite(batch.reference.color).all() and (batch.input.variance >= 0).all()


def test_micro_build_with_mitsuba_stores_exactly_render_frame(tmp_path):
    """Two real renders (one crop, 2 spp + an 8 spp reference): the stored item equals
    render_frame called with the item's recorded scene, seed and crop."""
    from jaxden.io.exr import read_frame
    from jaxden.render.core import render_frame

    config = DatasetConfig(
        name="micro",
        scenes=("cornell-box",),
        size=(32, 24),
        crop_size=8,
        crops_per_scene=1,
        spp=(2,),
        reference_spp=8,
        splits=SplitConfig(train=1.0, val=0.0),
    )
    manifest = build_dataset(config, tmp_path / "m", executor="serial", progress=False)
    assert verify_dataset(tmp_path / "m").ok
    crop = manifest.crops[0]
    for item in manifest.items[1:]:  # the 2-spp input (the reference works the same way)
        direct = render_frame(  # the dataset defaults are the legacy features
            crop.scene, item.spp, seed=item.seed, size=config.size, crop=crop.window,
            aux="first-hit", feature_spp=16,
        )
        stored = read_frame(tmp_path / "m" / item.path, require=("color", "variance"))
        np.testing.assert_array_equal(stored.color, direct.color)
        np.testing.assert_array_equal(stored.variance, direct.variance)
        np.testing.assert_array_equal(stored.normal, direct.normal)


def test_micro_build_with_specular_chain_features(tmp_path):
    """aux = "specular-chain" reaches render_frame: the stored albedo is the chain's, which
    differs from the first-hit albedo on glossy-glass (smooth glass and metal)."""
    from jaxden.io.exr import read_frame
    from jaxden.render.core import render_frame

    config = DatasetConfig(name="chain", scenes=("glossy-glass",), size=(40, 40), crop_size=40,
                           crops_per_scene=1, spp=(2,), reference_spp=4, aux="specular-chain",
                           splits=SplitConfig(train=1.0, val=0.0))
    manifest = build_dataset(config, tmp_path / "m", executor="serial", progress=False)
    crop, item = manifest.crops[0], manifest.items[1]
    stored = read_frame(tmp_path / "m" / item.path)
    kwargs = {"seed": item.seed, "size": config.size, "crop": crop.window}
    chain = render_frame(crop.scene, item.spp, aux="specular-chain", feature_spp=16, **kwargs)
    first = render_frame(crop.scene, item.spp, aux="first-hit", feature_spp=16, **kwargs)
    np.testing.assert_array_equal(stored.albedo, chain.albedo)
    np.testing.assert_array_equal(stored.color, first.color)
    assert np.abs(stored.albedo - first.albedo).max() > 0.1


def test_refeature_equals_a_full_build_of_the_new_config(tmp_path):
    """`refeature` keeps the colour and re-renders the features: item for item, the result
    equals a full build of the new config, and differs from the source only in features."""
    from jaxden.data.refeature import refeature_dataset
    from jaxden.io.exr import read_frame

    source = DatasetConfig(name="src", scenes=("glossy-glass",), size=(40, 40), crop_size=24,
                           crops_per_scene=1, spp=(2, 32), reference_spp=64,
                           splits=SplitConfig(train=1.0, val=0.0))
    build_dataset(source, tmp_path / "a", executor="serial", progress=False)
    refeatured = refeature_dataset(tmp_path / "a", tmp_path / "b",
                                   ["aux=specular-chain", "feature_spp=64", "name=b"],
                                   executor="serial", progress=False)
    assert verify_dataset(tmp_path / "b").ok
    assert refeatured.renderer.endswith("ColourFrom")
    fresh = dataclasses.replace(source, name="b", aux="specular-chain", feature_spp=64)
    build_dataset(fresh, tmp_path / "c", executor="serial", progress=False)
    changed = 0
    for item in refeatured.items:
        a, b, c = (read_frame(tmp_path / d / item.path) for d in "abc")
        for name in ("color", "variance", "albedo", "normal", "depth", "position"):
            np.testing.assert_array_equal(getattr(b, name), getattr(c, name), err_msg=name)
        np.testing.assert_array_equal(b.color, a.color)
        np.testing.assert_array_equal(b.variance, a.variance)
        changed += np.abs(b.albedo - a.albedo).max() > 0.05
    assert changed == len(refeatured.items)
    # Resuming a finished refeature renders nothing; colour-changing overrides are refused.
    refeature_dataset(tmp_path / "a", tmp_path / "b",
                      ["aux=specular-chain", "feature_spp=64", "name=b"], executor="serial",
                      progress=False)
    with pytest.raises(DatasetError, match="refeature can change only aux, feature_spp, name; "
                                           "spp would change the colour renders"):
        refeature_dataset(tmp_path / "a", tmp_path / "d", ["spp=[2,16]"], progress=False)
    with pytest.raises(DatasetError, match="must not be"):
        refeature_dataset(tmp_path / "a", tmp_path / "a", ["feature_spp=32"], progress=False)
    assert not (tmp_path / "d").exists()


def test_unknown_scene_is_rejected_before_rendering(tmp_path):
    from jaxden.errors import SceneError

    config = dataclasses.replace(SMALL, scenes=("cornell-bx",), procedural=ProceduralConfig())
    with pytest.raises(SceneError, match="unknown scene 'cornell-bx'; did you mean 'cornell-box'"):
        build_dataset(config, tmp_path / "x", executor="serial", progress=False)
    assert not (tmp_path / "x" / "manifest.json").exists()
    missing_xml = dataclasses.replace(config, scenes=(str(tmp_path / "none.xml"),))
    with pytest.raises(SceneError, match="none.xml does not exist"):
        build_dataset(missing_xml, tmp_path / "y", executor="serial", progress=False)


KILL_SCRIPT = """
import sys, time
from pathlib import Path
from jaxden.data import build_dataset, DatasetConfig, ProceduralConfig, SplitConfig
from jaxden.render.synthetic import synthetic_render

block_at, marker = int(sys.argv[2]), Path(sys.argv[3])
calls = 0

def blocking_render(scene, spp, seed=0, size=None, *, crop=None):
    # Render call number block_at (0-based) announces itself and never returns: the block_at
    # items before it are written (each file is written before the next render starts).
    global calls
    if calls == block_at:
        marker.write_text(str(calls))
        while True:
            time.sleep(60)
    calls += 1
    return synthetic_render(scene, spp, seed, size, crop=crop)

config = DatasetConfig(scenes=("a", "b"), size=(24, 24), crop_size=8, crops_per_scene=3,
                       spp=(2, 4), reference_spp=8, splits=SplitConfig(train=1.0, val=0.0))
build_dataset(config, sys.argv[1], executor="serial", render_fn=blocking_render, progress=False)
print("DONE")
"""


def test_killed_build_resumes(tmp_path):
    """SIGKILL a real build process mid-way, rerun it: every item ends up built and verified,
    and the files finished before the kill are untouched. The kill is deterministic: the
    process is killed while its 8th render call blocks, after exactly 7 items (two crops of 3
    items and one item of the third crop, not yet in the manifest) are on disk."""
    import signal
    import subprocess
    import sys
    import time

    directory = tmp_path / "killed"
    script = tmp_path / "build.py"
    script.write_text(KILL_SCRIPT)
    marker = tmp_path / "blocked"
    process = subprocess.Popen([sys.executable, str(script), str(directory), "7", str(marker)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not marker.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    blocked = marker.exists()
    process.send_signal(signal.SIGKILL)
    out, err = process.communicate()
    assert blocked, f"the build never reached its 8th render call:\n{out}\n{err[-3000:]}"
    assert process.returncode == -signal.SIGKILL
    before = file_states(directory)
    assert len(before) == 7, sorted(before)
    assert not [p for p in before if Path(p).name.startswith(".")]  # the kill hit no write
    result = subprocess.run(
        [sys.executable, str(script), str(directory), "-1", str(marker)], capture_output=True,
        text=True, timeout=240, check=False,
    )
    assert result.returncode == 0 and "DONE" in result.stdout, result.stderr
    after = file_states(directory)
    assert len(after) == 18 and {k: after[k] for k in before} == before
    assert verify_dataset(directory).ok


def test_config_may_change_while_nothing_is_built(tmp_path):
    with pytest.raises(RuntimeError, match="simulated crash"):
        build(tmp_path / "d", CountingRender(crash_after=0))
    changed = dataclasses.replace(SMALL, crop_size=6)
    manifest, render = build(tmp_path / "d", config=changed)
    assert manifest.complete and render.calls == ITEMS and manifest.config["crop_size"] == 6
    assert load_dataset_config(tmp_path / "d" / "dataset.toml") == changed


def test_progress_bar_counts_samples(tmp_path, capsys):
    config = dataclasses.replace(SMALL, crops_per_scene=1)
    build_dataset(config, tmp_path / "d", executor="serial", render_fn=synthetic_render)
    err = capsys.readouterr().err
    total = 3 * (2 + 4 + 16 + 256) * 8 * 8  # scenes x spp x pixels
    assert "build small" in err and "100%" in err and f"{total / 1000:.1f}k" in err


def test_verify_refuses_manifest_paths_outside_the_dataset(tmp_path):
    directory = tmp_path / "d"
    manifest, _ = build(directory)
    outside = tmp_path / "outside.exr"
    outside.write_bytes((directory / manifest.items[1].path).read_bytes())
    data = json.loads((directory / "manifest.json").read_text())
    data["items"][1]["path"] = "../outside.exr"
    (directory / "manifest.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="'../outside.exr', which leaves the dataset folder"):
        verify_dataset(directory)


def test_a_replica_has_the_same_crops_and_independent_renders():
    import dataclasses

    from jaxden.data.config import DatasetConfig
    from jaxden.data.layout import plan_dataset

    config = DatasetConfig(name="r", scenes=("cornell-box",), size=(32, 32), crop_size=8,
                           crops_per_scene=3, spp=(4, 8), reference_spp=8, seed=2)
    first = plan_dataset(config)
    again = plan_dataset(dataclasses.replace(config, replica=0))
    second = plan_dataset(dataclasses.replace(config, replica=1))
    third = plan_dataset(dataclasses.replace(config, replica=2))
    assert [i.seed for i in again.items] == [i.seed for i in first.items]
    assert [c.window for c in second.crops] == [c.window for c in first.crops]
    assert [c.split for c in second.crops] == [c.split for c in first.crops]
    assert [i.path for i in second.items] == [i.path for i in first.items]
    seeds = [i.seed for plan in (first, second, third) for i in plan.items]
    assert len(set(seeds)) == len(seeds)
