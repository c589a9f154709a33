"""`jaxden dataset import`: another renderer's EXRs (one folder per view) -> a jaxden dataset
that the loader, `dataset verify` and training read as a built one.

Sources are tiny synthetic frames written by jaxden.io.exr (seeded) and the committed Blender
Cycles fixtures (tests/data/cycles: two 16-spp renders of one view, seeds 1 and 2)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_error_line, run_cli

from jaxden.data import importer
from jaxden.data.importer import import_dataset
from jaxden.data.layout import load_manifest
from jaxden.data.loader import DatasetLoader
from jaxden.data.merge import merge_renders
from jaxden.data.verify import verify_dataset
from jaxden.errors import DatasetError
from jaxden.frame import Frame
from jaxden.io.exr import read_frame, read_header, write_channels, write_frame

CYCLES = Path(__file__).parent / "data" / "cycles"
FEATURES = ("color", "albedo", "normal", "depth")
SIZE = (24, 20)  # (width, height)


def synthetic(rng, spp, *, variance, size=SIZE, position=False) -> Frame:
    """A random frame of ``size`` (W, H) with the dataset features, ``spp`` in its header."""
    width, height = size
    normal = rng.standard_normal((height, width, 3))
    fields = {"color": rng.gamma(2.0, 0.5, (height, width, 3)),
              "albedo": rng.uniform(0.0, 1.0, (height, width, 3)),
              "normal": normal / np.linalg.norm(normal, axis=-1, keepdims=True),
              "depth": rng.uniform(1.0, 5.0, (height, width, 1))}
    if variance:
        fields["variance"] = rng.uniform(0.0, 0.1, (height, width, 3))
    if position:
        fields["position"] = rng.uniform(-1.0, 1.0, (height, width, 3))
    return Frame(**{k: v.astype(np.float32) for k, v in fields.items()}, spp=np.float32(spp))


def make_source(root: Path, views=("v0", "v1"), seed=0) -> Path:
    """Per view: spp1.exr (one render), spp2/b0..b1.exr (two 1-spp buffers), reference.exr
    (64 spp with its variance)."""
    rng = np.random.default_rng(seed)
    for view in views:
        (root / view / "spp2").mkdir(parents=True)
        write_frame(root / view / "spp1.exr", synthetic(rng, 1, variance=False))
        for k in range(2):
            write_frame(root / view / "spp2" / f"b{k}.exr", synthetic(rng, 1, variance=False))
        write_frame(root / view / "reference.exr", synthetic(rng, 64, variance=True))
    return root


def crop_of(frame: Frame, window) -> Frame:
    top, left, height, width = window
    return frame.crop(top, left, height, width)


def test_import_gives_the_loader_the_source_crops(tmp_path):
    """The loader's batches (no augmentation, the stored crop size) are the source files'
    crops at the manifest's windows: the 1-spp input as written, the 2-spp input equal to
    merge_renders of its buffers (colour, variance, features), the reference; the held-out
    view is the test split and `dataset verify` passes. The covariance is left out: the
    single-file references carry none."""
    src = make_source(tmp_path / "src")
    out = tmp_path / "data"
    manifest = import_dataset(src, out, crop_size=16, crops_per_view=2, held_out=("v1",),
                              progress=False)
    assert verify_dataset(out).ok
    assert manifest.config["spp"] == [1, 2] and manifest.config["reference_spp"] == 64
    assert manifest.config["size"] == list(SIZE)
    assert {c.scene: c.split for c in manifest.crops} == {"v0": "train", "v1": "test"}
    windows = {c.id: c.window for c in manifest.crops}
    view_of = {c.id: c.scene for c in manifest.crops}
    items = manifest.item_by_id()
    for split in ("train", "test"):
        for spp, features in ((1, FEATURES), (2, FEATURES + ("variance",))):
            loader = DatasetLoader(out, split, batch_size=2, crop_size=16, spp=[spp],
                                   features=features, augment=False, shuffle=False)
            batches = list(loader.epoch(0))
            assert sum(len(b.items) for b in batches) == 2  # 2 crops of the view
            for batch in batches:
                assert batch.input.color.shape == (2, 16, 16, 3)
                assert batch.input.depth.shape == (2, 16, 16, 1)
                for row, item_id in enumerate(batch.items):
                    crop = items[item_id].crop
                    view = src / view_of[crop]
                    if spp == 1:
                        source = read_frame(view / "spp1.exr")
                    else:
                        source = merge_renders([read_frame(view / "spp2" / f"b{k}.exr")
                                                for k in range(2)])
                    expected = crop_of(source, windows[crop])
                    for field in features:
                        np.testing.assert_array_equal(getattr(batch.input, field)[row],
                                                      getattr(expected, field), err_msg=field)
                    reference = crop_of(read_frame(view / "reference.exr"), windows[crop])
                    np.testing.assert_array_equal(batch.reference.color[row], reference.color)
    two = read_header(out / next(i.path for i in manifest.items if i.spp == 2))
    assert float(two["variance_dof"]) == 1.0 and float(two["spp"]) == 2.0
    assert "covariance.RG" not in two["channels"]


def test_cycles_buffers_import_as_jaxden_merge_merges_them(tmp_path, capsys):
    """Through the CLI with --from cycles: a level of two real Cycles renders (16 spp each)
    becomes a 32-spp input whose colour, variance and features are merge_renders' of the two
    files read by the Cycles convention, at the crop's window."""
    src = tmp_path / "src"
    for folder in ("spp32", "reference"):
        (src / "cyc" / folder).mkdir(parents=True)
        for k, seed in enumerate((1, 2)):
            shutil.copy(CYCLES / f"spheres-16spp-seed{seed}.exr",
                        src / "cyc" / folder / f"b{k}.exr")
    (src / "cyc" / "notes.txt").write_text("files other than .exr are ignored")
    out = tmp_path / "data"
    code, errors, printed = run_cli(["dataset", "import", src, "--from", "cycles", "--crop", 16,
                                     "--crops-per-view", 1, "--quiet", "--out", out], capsys)
    assert code == 0 and errors == [], errors
    assert "1 views x 1 crops of 16 pixels" in printed
    manifest = load_manifest(out)
    (crop,) = manifest.crops
    merged = merge_renders([read_frame(src / "cyc" / "spp32" / f"b{k}.exr", convention="cycles")
                            for k in range(2)])
    item = next(i for i in manifest.items if i.kind == "input")
    written = read_frame(out / item.path)
    assert item.spp == 32 and float(written.spp) == 32.0
    for field in ("color", "variance", "covariance", "albedo", "normal", "depth"):
        np.testing.assert_array_equal(getattr(written, field),
                                      getattr(crop_of(merged, crop.window), field), err_msg=field)
    assert manifest.extra["import"]["convention"] == "cycles"
    assert run_cli(["dataset", "verify", out], capsys)[0] == 0


def _no_reference(src):
    (src / "v1" / "reference.exr").unlink()
    return "v1", "no reference"


def _mixed_size(src):
    write_frame(src / "v1" / "spp1.exr", synthetic(np.random.default_rng(1), 1, variance=False,
                                                   size=(20, 20)))
    return "v1/spp1.exr", "20x20 pixels"


def _other_scene_size(src):
    write_frame(src / "v0" / "spp2" / "b1.exr", synthetic(np.random.default_rng(1), 1,
                                                          variance=False, size=(24, 16)))
    return "v0/spp2/b1.exr", "24x16 pixels"


def _other_scene_fields(src):
    write_frame(src / "v0" / "spp2" / "b1.exr", synthetic(np.random.default_rng(1), 1,
                                                          variance=False, position=True))
    return "v0/spp2/b1.exr", "position"


def _nan(src):
    from jaxden.frame import CHANNELS

    frame = read_frame(src / "v0" / "spp2" / "b0.exr")
    color = np.array(frame.color)
    color[3, 4, 1] = np.nan
    channels = {name: (color if field == "color" else np.asarray(getattr(frame, field)))[..., i]
                for field in FEATURES for i, name in enumerate(CHANNELS[field])}
    write_channels(src / "v0" / "spp2" / "b0.exr", channels, attributes={"spp": 1},
                   allow_nonfinite=True)
    return "v0/spp2/b0.exr", "non-finite"


def _one_seed(src):
    shutil.copy(src / "v0" / "spp2" / "b0.exr", src / "v0" / "spp2" / "b1.exr")
    return "v0/spp2/b1.exr", "same image"


def _no_colour(src):
    frame = read_frame(src / "v1" / "spp1.exr")
    write_channels(src / "v1" / "spp1.exr",
                   {f"albedo.{c}": np.asarray(frame.albedo)[..., i] for i, c in enumerate("RGB")},
                   attributes={"spp": 1})
    return "v1/spp1.exr", "color"


def _unknown_layout(src):
    shutil.copy(src / "v0" / "spp1.exr", src / "v0" / "render0001.exr")
    return "v0/render0001.exr", "not part of the import layout"


def _no_variance(src):
    write_frame(src / "v0" / "spp4.exr", synthetic(np.random.default_rng(2), 4, variance=False))
    write_frame(src / "v1" / "spp4.exr", synthetic(np.random.default_rng(3), 4, variance=False))
    return "v0/spp4.exr", "needs the variance of its mean"


def _levels_differ(src):
    shutil.rmtree(src / "v1" / "spp2")
    return "v1", "the same levels"


BAD_SOURCES = {"no-reference": _no_reference, "mixed-size": _mixed_size,
               "other-scene-size": _other_scene_size, "other-scene-fields": _other_scene_fields,
               "nan": _nan, "one-seed": _one_seed, "no-colour": _no_colour,
               "unknown-layout": _unknown_layout, "no-variance": _no_variance,
               "levels-differ": _levels_differ}


@pytest.mark.parametrize("case", list(BAD_SOURCES))
def test_bad_source_is_one_line_naming_the_file_and_writes_nothing(tmp_path, capsys, case):
    src = make_source(tmp_path / "src")
    where, words = BAD_SOURCES[case](src)
    out = tmp_path / "data"
    code, errors, _ = run_cli(["dataset", "import", src, "--crop", 16, "--quiet", "--out", out],
                              capsys)
    assert_one_error_line(code, errors, str(src / where), words)
    assert not out.exists()


def test_options_are_checked_before_anything_is_written(tmp_path):
    """Unknown or doubly assigned views, a crop larger than the views, a renderer that writes
    one file per output, an output folder inside the source: one error each, no folder."""
    src = make_source(tmp_path / "src")
    out = tmp_path / "a"
    with pytest.raises(DatasetError, match=r"^held_out: v7 is not a view .*v0, v1"):
        import_dataset(src, out, crop_size=16, held_out=("v7",), progress=False)
    with pytest.raises(DatasetError, match=r"^held_out and val both name v1"):
        import_dataset(src, out, crop_size=16, held_out=("v1",), val=("v1",), progress=False)
    with pytest.raises(DatasetError, match=r"^crop_size=21: must be in 1\.\.20"):
        import_dataset(src, out, crop_size=21, progress=False)
    with pytest.raises(DatasetError, match=r"^convention=falcor: .*one file per output.* with "
                                           r"convention left out"):
        import_dataset(src, out, crop_size=16, convention="falcor", progress=False)
    with pytest.raises(DatasetError, match=r"^out_dir=.*: inside the source folder"):
        import_dataset(src, src / "data", crop_size=16, progress=False)
    with pytest.raises(DatasetError, match=r"^channel_map: albedo=a,b: expected 3 channel "
                                           r"name\(s\) for albedo"):
        import_dataset(src, out, crop_size=16, channel_map={"albedo": ("a", "b")},
                       progress=False)
    with pytest.raises(DatasetError, match=r"^channel_map: colour=R,G,B: expected one of color"):
        import_dataset(src, out, crop_size=16, channel_map={"colour": ("R", "G", "B")},
                       progress=False)
    assert not out.exists() and not (src / "data").exists()


@pytest.mark.parametrize("flags, words", [
    (["--held-out", "v7"], "--held-out: v7 is not a view"),
    (["--held-out", "v1", "--val", "v1"], "--held-out and --val both name v1"),
    (["--crop", "21"], "--crop 21: must be in 1..20"),
    (["--from", "falcor"], "with --from left out"),
])
def test_the_cli_names_its_flags_where_the_library_names_parameters(tmp_path, capsys, flags,
                                                                      words):
    src = make_source(tmp_path / "src")
    out = tmp_path / "data"
    code, errors, _ = run_cli(["dataset", "import", src, "--crop", 16, "--quiet", "--out", out,
                               *flags], capsys)
    assert_one_error_line(code, errors, words)
    assert "held_out" not in errors[0] and "crop_size" not in errors[0]
    assert not out.exists()


def test_an_argument_error_pickles_with_its_message():
    import pickle

    from jaxden.data.importer import ImportArgumentError

    error = ImportArgumentError(lambda name: f"{name('crop_size', 21)}: too big")
    assert str(error) == "crop_size=21: too big"
    assert error.naming({"crop_size": "--crop"}) == "--crop 21: too big"
    assert str(pickle.loads(pickle.dumps(error))) == "crop_size=21: too big"


def test_interrupted_import_resumes_and_a_finished_one_is_not_redone(tmp_path, monkeypatch):
    """Stopped after 3 of 12 files, the rerun writes only the other 9 (without decoding the
    source again up front) and ends byte-identical to an uninterrupted import; a third run
    reads no source at all; a changed source file is then refused."""
    src = make_source(tmp_path / "src")
    options = {"crop_size": 16, "crops_per_view": 2, "progress": False}
    clean = import_dataset(src, tmp_path / "clean", **options)
    original = importer.ImportedRenders.__call__
    calls, checks = [], []

    def stop_at_fourth(self, *args, **kwargs):
        calls.append(kwargs["seed"])
        if len(calls) == 4:
            raise KeyboardInterrupt
        return original(self, *args, **kwargs)

    monkeypatch.setattr(importer.ImportedRenders, "__call__", stop_at_fourth)
    out = tmp_path / "data"
    with pytest.raises(KeyboardInterrupt):
        import_dataset(src, out, **options)
    written = [i for i in clean.items if (out / i.path).is_file()]
    assert len(written) == 3 and not load_manifest(out).complete

    def counted(self, *args, **kwargs):
        calls.append(kwargs["seed"])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(importer.ImportedRenders, "__call__", counted)
    validate = importer._validate
    monkeypatch.setattr(importer, "_validate", lambda *a: checks.append(a) or validate(*a))
    calls.clear()
    manifest = import_dataset(src, out, **options)
    assert len(calls) == 9 and checks == []
    assert [(i.id, i.sha256) for i in manifest.items] == [(i.id, i.sha256) for i in clean.items]
    assert verify_dataset(out).ok
    calls.clear()
    import_dataset(src, out, **options)
    assert calls == [] and checks == []
    write_frame(src / "v0" / "spp1.exr", synthetic(np.random.default_rng(9), 1, variance=False))
    with pytest.raises(DatasetError, match=r"other source files"):
        import_dataset(src, out, **options)
