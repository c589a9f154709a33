"""docs/your-denoiser.md runs as written: its files (code blocks whose first line is
``# file: NAME``) are written into an empty folder outside the package, and its command blocks
run there in order, with jaxden's virtual environment first on PATH, nothing of the clone on
PYTHONPATH and $JAXDEN_HOME in the folder. A command that fails fails the test with its
output."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "your-denoiser.md"
BLOCK = re.compile(r"```(\w+)\n(.*?)```", re.S)


def page_blocks() -> list[tuple[str, str]]:
    """``(kind, text)`` of the page's code blocks in order: kind ``file:NAME`` for a file,
    ``bash`` for commands."""
    out = []
    for language, text in BLOCK.findall(PAGE.read_text()):
        first = text.splitlines()[0] if text.strip() else ""
        if first.startswith("# file: "):
            out.append((f"file:{first.removeprefix('# file: ').strip()}", text))
        elif language == "bash":
            out.append(("bash", text))
    return out


def test_the_page_names_its_files_and_commands():
    kinds = [kind for kind, _ in page_blocks()]
    assert "file:my_filter.py" in kinds and "file:test_my_filter.py" in kinds
    commands = "\n".join(text for kind, text in page_blocks() if kind == "bash")
    for command in ("jaxden sure", "jaxden progressive", "jaxden train", "jaxden evaluate denoise",
                    "jaxden evaluate pd", "jaxden sweep", "--executor local", "pytest",
                    "jaxden evaluate my-rmse"):
        assert command in commands, command


@pytest.mark.slow  # renders, two trainings, a mixer with its SURE cache, a sweep: ~2 min
def test_the_page_runs_as_written(tmp_path):
    work = tmp_path / "my-research"
    work.mkdir()
    env = {key: value for key, value in os.environ.items()
           if key not in ("PYTHONPATH", "JAXDEN_PLUGINS", "XLA_FLAGS")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["JAXDEN_HOME"] = str(tmp_path / "home")
    env["JAXDEN_CACHE_DIR"] = str(tmp_path / "compile-cache")
    for kind, text in page_blocks():
        if kind.startswith("file:"):
            (work / kind.removeprefix("file:")).write_text(text)
            continue
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", text], cwd=work, env=env,
                              capture_output=True, text=True, timeout=900, check=False)
        assert done.returncode == 0, (text, done.stdout[-3000:], done.stderr[-3000:])
        assert "Traceback" not in done.stderr, (text, done.stderr[-3000:])
    for output in ("frame.sure.exr", "frame.pd-closed.exr", "frame.pd-shipped.exr",
                   "frame.pd-trained.exr", "results/kernelnet.json", "results/pd-guided-blur.json",
                   "results/my-rmse.json"):
        assert (work / output).is_file(), output
    runs = sorted(p.parent.name for p in
                  (tmp_path / "home" / "runs" / "sweep-kernelnet").glob("*/result.json"))
    assert runs == ["seed=0", "seed=1"]
