"""Commands with ``--json`` print one JSON document alone on stdout (``json.loads(stdout)``
reads it); their tables and progress go to stderr. Checked at the file-descriptor level, so
what a library prints from C (Mitsuba, XLA) counts too."""

from __future__ import annotations

import argparse
import json

import pytest

from jaxden import bench
from jaxden.cli import build_parser, main

#: The commands that take --json, each tested below.
JSON_COMMANDS = {"bench"}


def commands_with(parser: argparse.ArgumentParser, flag: str, prefix: str = "") -> set[str]:
    """The (sub)commands of ``parser`` that accept ``flag``, as space-joined names."""
    found = set()
    for action in parser._actions:
        if flag in action.option_strings and prefix:
            found.add(prefix)
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found |= commands_with(sub, flag, f"{prefix} {name}".strip())
    return found


def test_every_command_with_json_is_tested_here():
    assert commands_with(build_parser(), "--json") == JSON_COMMANDS


def test_bench_json_is_alone_on_stdout(monkeypatch, capfd):
    """The cheapest benchmark (render, at 16 x 16 and 2 spp) through the CLI."""
    from jaxden.bench import render

    monkeypatch.setattr(render, "QUICK", ((16, 16), 2, 1))
    capfd.readouterr()
    assert main(["bench", "render", "--quick", "--json"]) == 0
    out, err = capfd.readouterr()
    result = json.loads(out)
    assert result["bench"] == "render" and result["size"] == "16x16" and result["ratio"] > 0
    assert "benchmark render (quick)" in err and "ratio" in err  # the table, on stderr


@pytest.fixture
def chatty(monkeypatch):
    """A benchmark that prints while it runs, as a benchmark's progress would."""
    monkeypatch.setattr(bench, "_REGISTRY", dict(bench._REGISTRY))

    @bench.register("chatty")
    def chatty(quick: bool) -> dict:
        print("chatty: warming up")
        return {"ratio": 0.5, "peer_s": 1.25}


def test_what_a_benchmark_prints_goes_to_stderr_with_json(chatty, capfd):
    capfd.readouterr()
    assert main(["bench", "chatty", "--json"]) == 0
    out, err = capfd.readouterr()
    assert json.loads(out) == {"bench": "chatty", "peer_s": 1.25, "ratio": 0.5}
    assert "chatty: warming up" in err and "peer_s" in err
    # Without --json, the table (and the benchmark's own lines) are the output.
    assert main(["bench", "chatty"]) == 0
    out, err = capfd.readouterr()
    assert "chatty: warming up" in out and "ratio" in out and "{" not in out
