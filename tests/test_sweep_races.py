"""Sweeps that cannot race or run away: shared data (a SURE cache) is prepared once before the
runs start and the runs only read it; run names stay inside --workdir; huge sweeps need
--allow-large. (Runs on two Ray or local workers at once: tests/test_ray.py.)"""

from __future__ import annotations

from pathlib import Path

import pytest

from jaxden.cli import main
from jaxden.config import load_config
from jaxden.data.builder import build_dataset
from jaxden.data.config import DatasetConfig
from jaxden.errors import ConfigError
from jaxden.fileio import folder_lock
from jaxden.render.synthetic import synthetic_render
from jaxden.sweep import MAX_RUNS, run_sweep
from jaxden.train import loop

ROOT = Path(__file__).resolve().parent.parent
TINY_MIXER = ROOT / "experiments" / "configs" / "mixer-tiny.toml"


def write_sweep(folder: Path, body: str) -> Path:
    path = folder / "sweep.toml"
    path.write_text(f'base = "{TINY_MIXER}"\n' + body)
    return path


@pytest.mark.parametrize("name", ["..", ".", "", "summary.md"])
def test_a_run_name_outside_the_workdir_is_refused_before_anything_runs(tmp_path, capsys,
                                                                        name):
    sweep = write_sweep(tmp_path, f'mode = "zip"\n[axes]\nname = ["ok", "{name}"]\n'
                                  "seed = [0, 1]\n")
    workdir = tmp_path / "w" / "sweep"
    for extra in ([], ["--dry-run"]):
        assert main(["sweep", str(sweep), "--workdir", str(workdir), *extra]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"folder name {name!r}" in err[0], err
        assert "not a folder inside --workdir" in err[0]
    assert not (tmp_path / "w").exists()


def test_a_sweep_states_its_size_and_refuses_a_huge_one(tmp_path, capsys):
    values = ", ".join(str(v) for v in range(15))
    sweep = write_sweep(tmp_path, f"[axes]\nseed = [{values}]\n\"optim.steps\" = [{values}]\n")
    workdir = tmp_path / "w"
    assert main(["sweep", str(sweep), "--workdir", str(workdir)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"has 225 runs, more than {MAX_RUNS}" in err[0], err
    assert "--allow-large" in err[0] and not workdir.exists()
    # --allow-large passes that check (the configs are then checked: steps = 0 is invalid).
    with pytest.raises(ConfigError, match="optim.steps"):
        run_sweep(sweep, workdir, allow_large=True, progress=False)
    # --dry-run makes the same checks: the size, then (with --allow-large) the configs.
    capsys.readouterr()
    assert main(["sweep", str(sweep), "--workdir", str(workdir), "--dry-run"]) == 2
    assert f"has 225 runs, more than {MAX_RUNS}" in capsys.readouterr().err
    assert main(["sweep", str(sweep), "--workdir", str(workdir), "--dry-run",
                 "--allow-large"]) == 2
    assert "optim.steps" in capsys.readouterr().err and not workdir.exists()


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("races") / "tiny"
    config = load_config(ROOT / "experiments" / "configs" / "dataset-tiny.toml", DatasetConfig)
    build_dataset(config, out, executor="serial", render_fn=synthetic_render, progress=False)
    return out


def test_runs_only_read_the_sure_cache_prepared_before_them(tmp_path, tiny_dataset,
                                                             monkeypatch, capsys):
    """The runs of a sweep share one SURE cache. It is built once, by the sweep, before any
    run starts; then the runs only read it: they succeed while its build lock is held (what
    a second writer would hold), where the runs of issue 23 failed with 'another SURE cache
    build is writing into .../derived/oidn'."""
    from jaxden.progressive.cache import CACHE_MANIFEST, LOCK_NAME

    calls = []
    real = loop.prepare_shared_data
    monkeypatch.setattr(loop, "prepare_shared_data",
                        lambda config, **kw: (calls.append(config.seed), real(config, **kw))[1])
    overrides = (f'overrides = ["data.dataset={tiny_dataset}", "optim.steps=2", '
                 '"eval_every=2", "checkpoint_every=2", "eval_batches=1", '
                 '"model_config.width=8"]\n')
    sweep = write_sweep(tmp_path, overrides + "[axes]\nseed = [0, 1]\n")
    cache = tiny_dataset / "derived" / "oidn"
    assert not cache.exists()
    # A first sweep (one run) builds the cache before its run starts.
    (tmp_path / "first").mkdir()
    first = write_sweep(tmp_path / "first", overrides + "[axes]\nseed = [7]\n")
    run_sweep(first, tmp_path / "first-sweep", progress=False)
    assert (cache / CACHE_MANIFEST).is_file()
    assert calls == [7]
    # With the cache complete and its lock held by another writer, both runs still train.
    calls.clear()
    with folder_lock(cache, LOCK_NAME, "SURE cache build"):
        results = run_sweep(sweep, tmp_path / "sweep", progress=True)
    assert [r["run"] for r in results] == ["seed=0", "seed=1"]
    assert calls == [0]  # prepared once for the two runs that share it
    out = capsys.readouterr().out
    assert "sweep " in out and ": 2 run(s) of" in out  # the sweep states its size
