"""Pieces that several test modules share: a tiny KP training config, the tiny Mitsuba-free
dataset, a small tmpfs, running ``jaxden`` in process and reading its error line, the
subprocess environment, snapshots and Hypothesis mutations of JSON files, reading a run's
checkpoints and metrics log, and loading a script of experiments/ by its file.

A plain module, not a conftest: pytest puts tests/ on sys.path (there is no __init__.py), so
a test module imports it as ``helpers``. Fixtures stay in the test modules (pytest does not
collect them from here); they call these functions. jaxden is imported inside the functions,
so importing this module imports no JAX.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import pytest
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parent.parent
#: XLA_FLAGS of test subprocesses: LLVM at -O0 like the suite (tests/conftest.py: compiles
#: dominate), and no device count (the command under test chooses it).
FAST_COMPILE = "--xla_backend_optimization_level=0"


# ------------------------------------------------------------------ tiny training config
_TRAIN_TOML = """
model = "kp"
seed = 1
log_every = {log_every}
eval_every = {eval_every}
eval_batches = {eval_batches}
checkpoint_every = {checkpoint_every}
{keep}[model_config]
num_layers = 1
width = 8
kernel_size = 3
[data]
dataset = "{dataset}"
crop_size = 16
batch_size = {batch_size}
[optim]
steps = {steps}
learning_rate = 1e-3
"""


def train_toml(dataset, *, steps: int = 2, log_every: int = 1, eval_every: int = 2,
               eval_batches: int = 1, checkpoint_every: int = 2,
               keep_checkpoints: int | None = None, batch_size: int = 2) -> str:
    """The TOML of a tiny KP model (one layer of width 8, 16-pixel crops) trained on
    ``dataset``; ``keep_checkpoints`` None leaves the key out (the config's default)."""
    keep = "" if keep_checkpoints is None else f"keep_checkpoints = {keep_checkpoints}\n"
    return _TRAIN_TOML.format(dataset=dataset, steps=steps, log_every=log_every,
                              eval_every=eval_every, eval_batches=eval_batches,
                              checkpoint_every=checkpoint_every, keep=keep,
                              batch_size=batch_size)


def write_train_config(folder: Path, dataset, **options) -> Path:
    """``folder/train.toml`` with :func:`train_toml` (``options`` are its keywords)."""
    path = folder / "train.toml"
    path.write_text(train_toml(dataset, **options))
    return path


# ------------------------------------------------------------------------ tiny dataset
def build_tiny_dataset(out: Path, overrides: Sequence[str] = ()) -> Path:
    """Build experiments/configs/dataset-tiny.toml (with ``overrides``) into ``out`` without
    Mitsuba (``synthetic_render``), serially; returns ``out``."""
    from jaxden.config import load_config
    from jaxden.data.builder import build_dataset
    from jaxden.data.config import DatasetConfig
    from jaxden.render.synthetic import synthetic_render

    config = load_config(ROOT / "experiments" / "configs" / "dataset-tiny.toml", DatasetConfig,
                         overrides)
    build_dataset(config, out, executor="serial", render_fn=synthetic_render, progress=False)
    return out


# ------------------------------------------------------------------ experiment scripts
def load_script(name: str):
    """The script experiments/NAME.py as a module, loaded from its file (no sys.path entry:
    the scripts are clients of the package and import no other script)."""
    import importlib.util
    import sys

    key = f"experiments_{name}"
    if key not in sys.modules:
        spec = importlib.util.spec_from_file_location(key, ROOT / "experiments" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[key] = module  # before running it: dataclasses look their module up
        spec.loader.exec_module(module)
    return sys.modules[key]


# ---------------------------------------------------------------------------- full disk
@contextmanager
def small_tmpfs(folder: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` (mount's ``size=``, e.g. "64k", "4m") mounted on the new folder
    ``folder`` (root only; the test is skipped otherwise), unmounted afterwards."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("needs root to mount a small tmpfs")
    folder.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=False)


def fill_disk(path: Path) -> Path:
    """Write zeros into the file ``path`` until its disk is full; returns ``path``."""
    with open(path, "wb", buffering=0) as handle:
        try:
            while True:
                handle.write(b"\0" * 4096)
        except OSError:
            pass
    return path


# ------------------------------------------------------------ jaxden and its error line
def run_cli(argv, capsys) -> tuple[int, list[str], str]:
    """Exit status, the non-empty stderr lines and stdout of ``jaxden ARGV`` in process (a
    traceback is an exception that fails the test)."""
    from jaxden import cli

    capsys.readouterr()
    try:
        code = cli.main([str(a) for a in argv])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, [line for line in err.splitlines() if line.strip()], out


def assert_one_error_line(code, lines, *words):
    """Exit status 2 and one stderr line ``jaxden: error: ...`` holding every one of
    ``words``."""
    assert code == 2, (code, lines)
    assert len(lines) == 1 and lines[0].startswith("jaxden: error: "), lines
    for word in words:
        assert word in lines[0], (word, lines[0])


def cli_env(cache: Path, **extra: str) -> dict[str, str]:
    """The environment of a ``jaxden`` subprocess: this one's, JAX on one CPU device, XLA at
    -O0 and the compilation cache in ``cache`` (one per module: each program compiles once),
    then ``extra``."""
    return {**os.environ, "JAXDEN_CACHE_DIR": str(cache), "JAX_PLATFORMS": "cpu",
            "JAXDEN_CPU_DEVICES": "1", "XLA_FLAGS": FAST_COMPILE, **extra}


# ------------------------------------------------------------------------- files
def hooked_env(folder: Path, hook: str) -> dict[str, str]:
    """Write the fault-injecting ``hook`` script to ``folder/hook.py``; the subprocess env for
    it and for ``jaxden`` (this checkout's package, one XLA cache per test module)."""
    (folder / "hook.py").write_text(hook)
    path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    return cli_env(folder / "cache", PYTHONPATH=path)


def run_jaxden(folder: Path, env: dict, argv, *, hook_var: str = "", hook_value: str | None = None,
               **options) -> subprocess.CompletedProcess:
    """``jaxden ARGV`` in a subprocess; with ``hook_value``, through ``folder/hook.py`` with
    ``hook_var`` set to it (the hook decides where to act)."""
    import sys

    if hook_value:
        command = [sys.executable, str(folder / "hook.py"), *map(str, argv)]
        env = {**env, hook_var: hook_value}
    else:
        command = [sys.executable, "-m", "jaxden.cli", *map(str, argv)]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=300,
                          preexec_fn=sigint_default,
                          check=False, **options)


def snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every path under ``folder`` (relative) with its bytes (None for folders)."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(folder.rglob("*"))}


def json_paths(tree, prefix=()):
    """Every key path of a JSON tree (the first two entries of each list)."""
    children = (tree.items() if isinstance(tree, dict)
                else enumerate(tree[:2]) if isinstance(tree, list) else ())
    for key, value in children:
        yield prefix + (key,)
        yield from json_paths(value, prefix + (key,))


def set_or_delete(data, paths, draw, junk, *, delete: bool) -> str:
    """The JSON text of ``data`` (a parsed JSON tree) after deleting one key path drawn from
    ``paths`` (as :func:`json_paths` lists them), or setting it to a value drawn from ``junk``
    (a Hypothesis strategy); ``draw`` is Hypothesis's ``data.draw``."""
    path = draw(st.sampled_from(paths))
    node = data
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = draw(junk)
    return json.dumps(data)


def drop(tree: dict, key) -> None:
    """``del tree[key]`` as a call (for the lambdas of the damage tables)."""
    del tree[key]


# ------------------------------------------------------------------------ a run's files
def checkpoint_steps(workdir: Path) -> list[int]:
    """The steps of the checkpoints in a run folder, in order."""
    return sorted(int(p.name) for p in workdir.iterdir() if p.name.isdigit())


def metrics_records(workdir: Path) -> list[dict]:
    """The entries of a run's metrics.jsonl."""
    return [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]


def restore_last_checkpoint(workdir: Path):
    """(state, meta) of the last checkpoint of a run folder."""
    from jaxden.checkpoint import Checkpointer

    checkpointer = Checkpointer(workdir, create=False)
    try:
        return checkpointer.restore()
    finally:
        checkpointer.close()


# --------------------------------------------------- a stopped command and what it left
def files(folder: Path) -> dict[str, tuple[bytes, int]]:
    """Every file under ``folder``: (bytes, mtime_ns), by relative path."""
    return {str(p.relative_to(folder)): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def assert_no_partial_files(folder: Path) -> None:
    """No temporary file or orbax temporary folder; every JSON and JSONL file reads whole, and
    so does every EXR."""
    from jaxden.fileio import read_json, read_jsonl
    from jaxden.io.exr import read_frame

    leftovers = [p for p in folder.rglob("*") if ".tmp" in p.name or "orbax-checkpoint-tmp"
                 in p.name]
    assert not leftovers, leftovers
    for path in folder.rglob("*.json"):
        if path.parent.name not in ("meta",):
            read_json(path, "a json file", kind=(dict, list))
    for path in folder.rglob("metrics.jsonl"):
        assert read_jsonl(path, "the metrics log")[1] is False, path  # no cut last line
    for path in folder.rglob("*.exr"):
        read_frame(path)


def write_sweep(folder: Path, target: Path) -> Path:
    """``target/sweep.toml``: two runs, 'a' and 'b', of the same config
    (``folder/train.toml``): b must end exactly where a ends."""
    path = target / "sweep.toml"
    path.write_text(f'base = "{folder / "train.toml"}"\nmode = "zip"\n[axes]\n'
                    'name = ["a", "b"]\n')
    return path


def logged_steps(workdir: Path) -> tuple[list[int], list[int]]:
    """The steps of the loss entries and of the validation entries of metrics.jsonl."""
    records = metrics_records(workdir)
    return ([r["step"] for r in records if "loss" in r],
            [r["step"] for r in records if "val_loss" in r])


def assert_same_state(a: Path, b: Path) -> None:
    """The last checkpoints of the run folders ``a`` and ``b`` hold the same step and (to
    float32 round-off) the same parameters and optimizer state."""
    import jax
    import numpy as np

    x, y = restore_last_checkpoint(a)[0], restore_last_checkpoint(b)[0]
    assert int(x["step"]) == int(y["step"])
    for left, right in zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)):
        np.testing.assert_allclose(np.asarray(left), np.asarray(right), rtol=1e-6, atol=1e-7)


def sigint_default() -> None:
    """``preexec_fn`` of commands that a test interrupts: SIGINT at its default, as under a
    terminal (a disposition of SIG_IGN would be inherited from the test process, where some
    library may have left it, and Python then never raises KeyboardInterrupt). Runs between
    fork and exec: one system call, no import (``signal`` is imported with this module)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
