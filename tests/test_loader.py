"""DatasetLoader: batches, determinism, epochs, and dihedral augmentation (incl. motion)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from jaxden.data import (
    DatasetConfig,
    DatasetLoader,
    ProceduralConfig,
    SplitConfig,
    build_dataset,
    dihedral,
    dihedral_frame,
    dihedral_motion,
)
from jaxden.errors import DatasetError
from jaxden.frame import Frame
from jaxden.render.synthetic import synthetic_render

CONFIG = DatasetConfig(
    name="loader",
    scenes=("alpha", "beta", "gamma"),
    procedural=ProceduralConfig(),
    size=(48, 40),
    crop_size=12,
    crops_per_scene=2,
    spp=(1, 2, 8),
    reference_spp=64,
    seed=11,
    splits=SplitConfig(train=2 / 3, val=1 / 3, test=0.0),
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    directory = tmp_path_factory.mktemp("loader") / "d"
    build_dataset(CONFIG, directory, executor="serial", render_fn=synthetic_render, progress=False)
    return directory


def batches(loader, epoch):
    return list(loader.epoch(epoch))


def assert_batches_equal(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.items == y.items
        for name in x.input.features():
            np.testing.assert_array_equal(getattr(x.input, name), getattr(y.input, name))
        np.testing.assert_array_equal(x.reference.color, y.reference.color)


# ----------------------------------------------------------------------------- dihedral
def reference_transform(image: np.ndarray, index: int) -> np.ndarray:
    """Slow reference: element ``index`` of D4 by explicit pixel coordinates.

    With x = column, y = row, a counter-clockwise quarter turn (as displayed) of an image of
    width W sends (x, y) to (y, W - 1 - x); the flip sends (x, y) to (W' - 1 - x, y).
    """
    out = image
    for _ in range(index % 4):
        height, width = out.shape[:2]
        turned = np.empty((width, height) + out.shape[2:], out.dtype)
        for y in range(height):
            for x in range(width):
                turned[width - 1 - x, y] = out[y, x]
        out = turned
    if index >= 4:
        height, width = out.shape[:2]
        flipped = np.empty_like(out)
        for y in range(height):
            for x in range(width):
                flipped[y, width - 1 - x] = out[y, x]
        out = flipped
    return out


@pytest.mark.parametrize("index", range(8))
def test_dihedral_matches_pixel_reference_and_numpy(index):
    image = np.random.default_rng(index).random((5, 7, 3)).astype(np.float32)
    out = dihedral(image, index)
    np.testing.assert_array_equal(out, reference_transform(image, index))
    numpy_form = np.rot90(image, index % 4)
    if index >= 4:
        numpy_form = np.fliplr(numpy_form)
    np.testing.assert_array_equal(out, numpy_form)
    batched = np.stack([image, image * 2])
    np.testing.assert_array_equal(dihedral(batched, index)[1], out * 2)


def test_dihedral_is_the_group_d4():
    image = np.arange(4 * 4).reshape(4, 4, 1)
    images = [dihedral(image, i) for i in range(8)]
    keys = {im.tobytes() for im in images}
    assert len(keys) == 8  # eight distinct symmetries
    for a, b in itertools.product(range(8), repeat=2):  # closed under composition
        assert dihedral(dihedral(image, a), b).tobytes() in keys
    with pytest.raises(ValueError, match="0..7"):
        dihedral(image, 8)


@pytest.mark.parametrize("index", range(8))
def test_motion_vectors_stay_consistent_under_every_symmetry(index):
    """A current frame whose pixels show the previous frame at xy + motion: after transforming
    both frames and the motion field, the same relation must hold pixel by pixel."""
    rng = np.random.default_rng(100 + index)
    height, width = 6, 9
    previous = rng.permutation(height * width).reshape(height, width, 1).astype(np.float32)
    ys, xs = np.mgrid[0:height, 0:width]
    target_x = rng.integers(0, width, size=(height, width))
    target_y = rng.integers(0, height, size=(height, width))
    motion = np.stack([target_x - xs, target_y - ys], axis=-1).astype(np.float32)
    current = previous[target_y, target_x]

    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    frame = Frame(color=np.repeat(current, 3, -1), motion=motion, normal=normal)
    moved = dihedral_frame(frame, index)
    previous_t = dihedral(previous, index)[..., 0]
    m = moved.motion
    h2, w2 = m.shape[:2]
    ys2, xs2 = np.mgrid[0:h2, 0:w2]
    px = (xs2 + m[..., 0]).astype(int)
    py = (ys2 + m[..., 1]).astype(int)
    assert px.min() >= 0 and py.min() >= 0 and px.max() < w2 and py.max() < h2
    np.testing.assert_array_equal(moved.color[..., 0], previous_t[py, px])
    # World-space normals move with their pixels but keep their components.
    np.testing.assert_array_equal(moved.normal, dihedral(normal, index))
    if index != 0:  # motion components do change (else the test above would be vacuous)
        assert not np.array_equal(m, dihedral(motion, index))
    np.testing.assert_array_equal(dihedral_motion(motion, 0), motion)


# ----------------------------------------------------------------------------- loader
def test_batches_have_shapes_spp_and_aligned_reference(dataset):
    loader = DatasetLoader(dataset, "train", batch_size=4, crop_size=8, seed=0, spp=[2, 8])
    assert loader.spp_levels == (2, 8) and len(loader) == len(loader.samples) // 4
    batch = next(iter(loader))
    assert batch.input.color.shape == (4, 8, 8, 3) and batch.input.color.dtype == np.float32
    assert batch.input.depth.shape == (4, 8, 8, 1) and batch.input.spp.shape == (4,)
    assert set(batch.input.spp.tolist()) <= {2.0, 8.0}
    assert batch.reference.features() == ("color", "variance")
    assert (batch.reference.spp == 64).all()
    # Input and reference cover the same film pixels with the same symmetry: compare against
    # the clean synthetic image of that window, recovered from the draws.
    loader_all = DatasetLoader(
        dataset, "train", batch_size=4, crop_size=8, seed=0, spp=[2, 8],
        features=("color", "position"), reference_features=("color", "position"),
    )
    batch = next(iter(loader_all))
    np.testing.assert_array_equal(batch.input.position, batch.reference.position)


def test_batches_equal_manual_crop_and_symmetry(dataset):
    from jaxden.io.exr import read_frame

    loader = DatasetLoader(
        dataset, "val", batch_size=3, crop_size=7, seed=5, features=("color", "albedo")
    )
    draws = loader.plan_epoch(2)
    batch = next(loader.epoch(2))
    for b, (index, top, left, symmetry) in enumerate(draws[:3]):
        item, reference = loader.samples[index]
        stored = read_frame(dataset / item.path)
        expected = stored.color[top : top + 7, left : left + 7]
        expected = reference_transform(expected, symmetry)
        np.testing.assert_array_equal(batch.input.color[b], expected)
        ref = read_frame(dataset / reference.path).color[top : top + 7, left : left + 7]
        np.testing.assert_array_equal(batch.reference.color[b], reference_transform(ref, symmetry))
        assert batch.items[b] == item.id and batch.input.spp[b] == item.spp


def test_same_seed_same_batches_and_epochs_differ(dataset):
    make = lambda seed, cache: DatasetLoader(  # noqa: E731
        dataset, "train", batch_size=3, crop_size=6, seed=seed, spp=[2, 8], cache=cache
    )
    first, second = make(1, True), make(1, False)
    assert_batches_equal(batches(first, 0), batches(second, 0))
    assert_batches_equal(batches(first, 3), batches(second, 3))
    assert [b.items for b in batches(first, 0)] != [b.items for b in batches(first, 1)]
    other = make(2, True)
    assert [b.items for b in batches(first, 0)] != [b.items for b in batches(other, 0)]
    # Iterating the loader walks through epochs 0, 1, ...
    assert_batches_equal(list(iter(second)), batches(first, 0))
    assert_batches_equal(list(iter(second)), batches(first, 1))


def test_read_of_part_of_a_batch_gives_its_rows(dataset):
    """What each process of a multi-process run reads: ``read`` of some of a batch's draws
    gives exactly those rows of the epoch's batch (same crops, symmetries and order)."""
    loader = DatasetLoader(dataset, "train", batch_size=4, crop_size=6, seed=5, spp=[2, 8],
                           drop_last=False)
    plan = list(loader.batch_draws(2))
    assert [len(d) for d in plan[:-1]] == [4] * (len(plan) - 1) and plan[-1]
    for draws, batch in zip(plan, batches(loader, 2), strict=True):
        for rows in (slice(0, 2), slice(2, None)):
            part = loader.read(draws[rows])
            assert part.items == batch.items[rows]
            for name in batch.input.features():
                np.testing.assert_array_equal(getattr(part.input, name),
                                              getattr(batch.input, name)[rows])
            np.testing.assert_array_equal(part.reference.color, batch.reference.color[rows])


def test_epoch_visits_every_sample_once_and_uses_all_symmetries(dataset):
    loader = DatasetLoader(
        dataset, "all", batch_size=5, crop_size=10, seed=3, spp=[2, 8], drop_last=False
    )
    assert len(loader.samples) == 6 * 2 and len(loader) == 3
    ids = [i for batch in loader.epoch(0) for i in batch.items]
    assert sorted(ids) == sorted(item.id for item, _ in loader.samples)
    symmetries = [s for e in range(10) for (_, _, _, s) in loader.plan_epoch(e)]
    assert set(symmetries) == set(range(8))
    plain = DatasetLoader(
        dataset, "all", batch_size=4, seed=3, spp=[2], augment=False, shuffle=False
    )
    assert all(s == 0 for (_, _, _, s) in plain.plan_epoch(0))
    assert [i for (i, _, _, _) in plain.plan_epoch(0)] == list(range(len(plain.samples)))


def test_splits_are_disjoint(dataset):
    train = DatasetLoader(dataset, "train", batch_size=1, spp=[2])
    val = DatasetLoader(dataset, "val", batch_size=1, spp=[2])
    train_crops = {item.crop for item, _ in train.samples}
    val_crops = {item.crop for item, _ in val.samples}
    assert train_crops and val_crops and not train_crops & val_crops
    with pytest.raises(DatasetError, match="split 'test' .* has no samples"):
        DatasetLoader(dataset, "test", batch_size=1, spp=[2])
    with pytest.raises(DatasetError, match="unknown split 'training'"):
        DatasetLoader(dataset, "training", batch_size=1)


def test_loader_errors(dataset, tmp_path):
    with pytest.raises(DatasetError, match=r"spp level\(s\) \[3\] are not in"):
        DatasetLoader(dataset, "train", spp=[3])
    with pytest.raises(DatasetError, match="crop_size 13 must be in 1..12"):
        DatasetLoader(dataset, "train", crop_size=13)
    with pytest.raises(DatasetError, match="spp levels include 1"):
        DatasetLoader(dataset, "train", batch_size=1)
    with pytest.raises(DatasetError, match="unknown feature"):
        DatasetLoader(dataset, "train", spp=[2], features=("color", "colour"))
    with pytest.raises(DatasetError, match="fewer than batch_size 100"):
        DatasetLoader(dataset, "train", spp=[2], batch_size=100)
    loader = DatasetLoader(dataset, "train", spp=[2], batch_size=1, features=("color", "motion"))
    with pytest.raises(DatasetError, match="missing feature.*motion"):
        next(iter(loader))
    with pytest.raises(DatasetError, match="does not exist"):
        DatasetLoader(tmp_path / "nothing", "train")


def test_incomplete_dataset_is_refused(tmp_path):
    class Crash:
        calls = 0

        def __call__(self, scene, spp, seed=0, size=None, *, crop=None):
            Crash.calls += 1
            if Crash.calls > 3:
                raise RuntimeError("stop")
            return synthetic_render(scene, spp, seed, size, crop=crop)

    with pytest.raises(RuntimeError):
        build_dataset(CONFIG, tmp_path / "d", executor="serial", render_fn=Crash(), progress=False)
    with pytest.raises(DatasetError, match=r"incomplete \(3 of 24 files built\)"):
        DatasetLoader(tmp_path / "d", "train")


# ------------------------------------------------------------------------- Noise2Noise
def test_target_spp_pairs_each_input_with_its_own_crops_independent_render(dataset):
    """With target_spp = 8 the target of each 1- and 2-spp input is the 8-spp input of the same
    crop (read back from its EXR), at the same sub-crop and symmetry; never the reference."""
    from jaxden.data.layout import load_manifest
    from jaxden.io.exr import read_frame

    loader = DatasetLoader(dataset, "train", batch_size=2, crop_size=12, seed=3, augment=False,
                           shuffle=False, target_spp=8, features=("color", "albedo"))
    assert loader.spp_levels == (1, 2)
    manifest = load_manifest(dataset)
    by_id = {item.id: item for item in manifest.items}
    for batch in loader.epoch(0):
        for row, item_id in enumerate(batch.items):
            item = by_id[item_id]
            siblings = manifest.items_of(item.crop)
            target = next(i for i in siblings if i.kind == "input" and i.spp == 8)
            reference = next(i for i in siblings if i.kind == "reference")
            expected = read_frame(dataset / target.path).color
            np.testing.assert_array_equal(batch.reference.color[row], expected)
            assert not np.array_equal(expected, read_frame(dataset / reference.path).color)
            assert batch.reference.spp[row] == 8 and item.spp in (1, 2)


def test_target_spp_is_refused_when_missing_or_also_an_input(dataset):
    with pytest.raises(DatasetError, match="target_spp 4 is not an input spp level"):
        DatasetLoader(dataset, "train", batch_size=2, target_spp=4, features=("color",))
    with pytest.raises(DatasetError, match="also an input level"):
        DatasetLoader(dataset, "train", batch_size=2, spp=[1, 8], target_spp=8,
                      features=("color",))
