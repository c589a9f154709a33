"""TOML <-> frozen dataclass configs: loading, errors, overrides, round trips."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path
from typing import Literal

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from jaxden.config import (
    config_diff,
    config_to_dict,
    dump_config,
    load_config,
    parse_override,
    save_config,
)
from jaxden.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class Optimizer:
    rate: float = 0.1
    kind: Literal["adam", "sgd", "lamb"] = "adam"


@dataclasses.dataclass(frozen=True)
class Part:
    name: str
    weight: float = 1.0


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str  # required
    steps: int = 10
    flag: bool = False
    sizes: tuple[int, ...] = (1, 2)
    pair: tuple[int, str] = (1, "a")
    names: list[str] = dataclasses.field(default_factory=list)
    limit: int | None = None
    scale: float | None = 2.0
    path: Path = Path("out")
    table: dict[str, int] = dataclasses.field(default_factory=dict)
    parts: tuple[Part, ...] = ()
    optimizer: Optimizer = Optimizer()

    def __post_init__(self) -> None:
        if self.steps < 0:
            raise ConfigError(f"steps must be >= 0, got {self.steps}")


GOOD = """\
name = "run"
steps = 20
sizes = [3, 4, 5]

[optimizer]
rate = 1
kind = "sgd"
"""


def write(tmp_path: Path, text: str, name: str = "exp.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_loads_file_with_nested_table_and_converts_int_to_float(tmp_path):
    config = load_config(write(tmp_path, GOOD), Experiment)
    expected = Experiment(name="run", steps=20, sizes=(3, 4, 5), optimizer=Optimizer(1.0, "sgd"))
    assert config == expected
    assert isinstance(config.optimizer.rate, float)
    assert isinstance(config.sizes, tuple)


def test_unknown_key_names_key_file_line_suggestion_and_allowed_keys(tmp_path):
    path = write(tmp_path, 'name = "run"\n\nstesp = 3\n')
    with pytest.raises(ConfigError) as info:
        load_config(path, Experiment)
    message = str(info.value)
    assert "'stesp'" in message and str(path) in message and "line 3" in message
    assert "did you mean 'steps'?" in message
    assert "Allowed keys: flag, limit, name, names, optimizer" in message


def test_unknown_key_in_nested_table_names_the_table(tmp_path):
    path = write(tmp_path, GOOD + "momentum = 0.9\n")
    with pytest.raises(ConfigError, match=r"unknown key 'momentum' in table \[optimizer\]") as info:
        load_config(path, Experiment)
    assert "line 8" in str(info.value) and "Allowed keys: kind, rate" in str(info.value)


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ('name = "r"\nsteps = "ten"', r"key 'steps': expected int, found 'ten' \(str\)"),
        ('name = "r"\nsteps = 2.5', r"key 'steps': expected int, found 2.5 \(float\)"),
        ('name = "r"\nsteps = true', r"key 'steps': expected int, found True \(bool\)"),
        ('name = "r"\nflag = 1', r"key 'flag': expected bool"),
        ('name = "r"\nsizes = [1, "x"]', r"key 'sizes.1': expected int, found 'x'"),
        ('name = "r"\nsizes = 3', r"key 'sizes': expected an array of int, found 3"),
        ('name = "r"\npair = [1]', r"key 'pair': expected an array of 2 \(int, str\)"),
        ('name = "r"\nlimit = "many"', r"key 'limit': expected int, found 'many'.*or none"),
        ('name = "r"\noptimizer = 3', r"key 'optimizer': expected a table \(Optimizer\)"),
        ('name = "r"\ntable = {a = "b"}', r"key 'table.a': expected int"),
        ("name = 5", r"key 'name': expected str, found 5 \(int\)"),
    ],
)
def test_wrong_type_names_key_expected_type_and_found_value(tmp_path, text, pattern):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=pattern) as info:
        load_config(path, Experiment)
    assert str(path) in str(info.value)


def test_bad_literal_lists_choices_and_suggests(tmp_path):
    path = write(tmp_path, 'name = "r"\n[optimizer]\nkind = "adma"\n')
    with pytest.raises(ConfigError) as info:
        load_config(path, Experiment)
    message = str(info.value)
    assert "key 'optimizer.kind'" in message and "line 3" in message
    assert "one of 'adam', 'sgd', 'lamb'" in message and "did you mean 'adam'?" in message


def test_missing_required_key(tmp_path):
    with pytest.raises(ConfigError, match=r"missing required key 'name' at the top level"):
        load_config(write(tmp_path, "steps = 1\n"), Experiment)
    with pytest.raises(ConfigError, match=r"missing required key 'name' in table \[parts.0\]"):
        load_config({"name": "x", "parts": [{"weight": 2.0}]}, Experiment)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(ConfigError, match=r"config file .*nope.toml does not exist"):
        load_config(tmp_path / "nope.toml", Experiment)
    with pytest.raises(ConfigError, match="is a folder"):
        load_config(tmp_path, Experiment)


@pytest.mark.parametrize(
    "text", ['name = "run"\nsteps = 3\nsizes = [1, 2\n', 'name = "run"\n\nsteps = = 3\n']
)
def test_invalid_toml_names_file_and_line(tmp_path, text):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=r"invalid TOML") as info:
        load_config(path, Experiment)
    assert str(path) in str(info.value) and "line 3" in str(info.value)


def test_validation_error_from_post_init_names_file(tmp_path):
    path = write(tmp_path, 'name = "r"\nsteps = -1\n')
    with pytest.raises(ConfigError, match=r"exp.toml.*steps must be >= 0, got -1"):
        load_config(path, Experiment)


def test_overrides_are_parsed_as_toml_with_string_fallback(tmp_path):
    config = load_config(
        write(tmp_path, GOOD),
        Experiment,
        [
            "steps=5",
            "optimizer.rate=0.5",
            "optimizer.kind=lamb",  # not TOML: taken as the string
            "sizes=[7, 8]",
            "limit=3",
            "scale=none",
            "name=hello world",
            "table.x=1",
            'path="a/b"',
        ],
    )
    assert config.steps == 5 and config.optimizer == Optimizer(0.5, "lamb")
    assert config.sizes == (7, 8) and config.limit == 3 and config.scale is None
    assert config.name == "hello world" and config.table == {"x": 1} and config.path == Path("a/b")


def test_parse_override_values():
    assert parse_override("a.b=3") == (("a", "b"), 3)
    assert parse_override("a = true") == (("a",), True)
    assert parse_override('a="3"') == (("a",), "3")
    assert parse_override("a=x=y") == (("a",), "x=y")
    assert parse_override("a=2024-01-01") == (("a",), "2024-01-01")
    assert parse_override("a={b = 1}") == (("a",), {"b": 1})
    with pytest.raises(ConfigError, match="must have the form key=value"):
        parse_override("steps")
    with pytest.raises(ConfigError, match="empty key"):
        parse_override("=3")
    with pytest.raises(ConfigError, match="empty key"):
        parse_override("a..b=3")


def test_override_errors_name_the_override(tmp_path):
    path = write(tmp_path, GOOD)
    with pytest.raises(ConfigError) as info:
        load_config(path, Experiment, ["optimizer.rat=1"])
    message = str(info.value)
    assert "override 'optimizer.rat=1'" in message and str(path) in message
    assert "did you mean 'rate'?" in message
    with pytest.raises(ConfigError, match=r"override 'steps=many'.*expected int, found 'many'"):
        load_config(path, Experiment, ["steps=many"])
    with pytest.raises(ConfigError, match=r"override 'steps.x=1': 'steps' is not a table"):
        load_config(path, Experiment, ["steps.x=1"])


def test_load_from_dict_and_from_config_object():
    base = load_config({"name": "a", "optimizer": {"kind": "sgd"}}, Experiment)
    assert base.optimizer.kind == "sgd"
    changed = load_config(base, Experiment, ["steps=3"])
    assert changed == dataclasses.replace(base, steps=3)
    with pytest.raises(ConfigError, match="config dict: unknown key 'bogus'"):
        load_config({"name": "a", "bogus": 1}, Experiment)
    with pytest.raises(ConfigError, match="takes a TOML file path"):
        load_config(3, Experiment)


ODD = Experiment(
    name='quote " backslash \\ newline \n tab \t unicode é ☃ controls \x00 \x1f \x7f',
    steps=-0 + 7,
    flag=True,
    sizes=(),
    pair=(-3, "key with = sign"),
    names=["a", "b c"],
    limit=None,
    scale=None,  # default is 2.0: written as "none"
    path=Path("some dir/file.txt"),
    table={"plain": 1, "needs quotes": 2, "dotted.key": 3},
    parts=(Part("p1"), Part("p2", 1e-5)),
    optimizer=Optimizer(1e300, "lamb"),
)


def test_dump_round_trip_with_odd_values(tmp_path):
    text = dump_config(ODD, header="made by a test\nsecond line")
    assert text.startswith("# made by a test\n# second line\n")
    assert load_config(tomllib.loads(text), Experiment) == ODD
    save_config(ODD, tmp_path / "odd.toml")
    assert load_config(tmp_path / "odd.toml", Experiment) == ODD
    assert [p.name for p in tmp_path.iterdir()] == ["odd.toml"]  # no temporary left


def test_dump_writes_tables_after_keys():
    text = dump_config(Experiment(name="x"))
    lines = text.splitlines()
    assert lines[0] == 'name = "x"'
    assert lines.index("[table]") < lines.index("[optimizer]")
    assert "limit" not in text  # None with default None is omitted


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    name=st.text(),
    steps=st.integers(min_value=-(2**53), max_value=2**53),
    rate=st.floats(allow_nan=False, allow_infinity=False),
    sizes=st.lists(st.integers(min_value=-(10**6), max_value=10**6), max_size=5),
    limit=st.none() | st.integers(min_value=0, max_value=100),
    table=st.dictionaries(st.text(min_size=1, max_size=8), st.integers(-5, 5), max_size=3),
)
@example(name="\x7f", steps=0, rate=0.0, sizes=[], limit=None, table={"\x7f\x00": 1, "0\n": 2})
def test_round_trip_property(name, steps, rate, sizes, limit, table):
    config = Experiment(
        name=name,
        steps=abs(steps),
        sizes=tuple(sizes),
        limit=limit,
        table=table,
        optimizer=Optimizer(rate=rate),
    )
    assert load_config(tomllib.loads(dump_config(config)), Experiment) == config


def test_config_to_dict_and_diff():
    a = config_to_dict(Experiment(name="a"))
    assert a["optimizer"] == {"rate": 0.1, "kind": "adam"} and a["path"] == "out"
    b = config_to_dict(Experiment(name="a", optimizer=Optimizer(kind="sgd"), sizes=(1,)))
    assert config_diff(a, b) == ['optimizer.kind: "adam" -> "sgd"', "sizes: [1, 2] -> [1]"]
    assert config_diff(a, a) == []


def test_non_finite_and_huge_numbers_are_refused():
    """Config numbers are finite and at most 2^53 in size, whatever the source: a NaN or inf
    float and a 2^60 int name their key (a dump of such a value does not load back)."""
    text = dump_config(Experiment(name="n", optimizer=Optimizer(rate=math.nan)))
    with pytest.raises(ConfigError, match="key 'optimizer.rate': expected a finite number"):
        load_config(tomllib.loads(text), Experiment)
    for override, key in (("optimizer.rate=inf", "optimizer.rate"), ("steps=1152921504606846976", "steps")):
        with pytest.raises(ConfigError, match=f"key '{key}'"):
            load_config({"name": "x"}, Experiment, [override])


def test_declared_ranges_are_checked_for_every_source(tmp_path):
    """`bounded` fields: TOML, overrides and compact CLI specs meet the same check."""
    from jaxden.progressive.mixer import closed_form_mixer
    from jaxden.train.config import load_train_config

    base = tmp_path / "t.toml"
    base.write_text('model = "wskp"\n[optim]\ngrad_clip_norm = -1.0\n')
    with pytest.raises(ConfigError, match=r"grad_clip_norm: -1.0 is outside the valid range \(0, "):
        load_train_config(base)
    base.write_text('model = "wskp"\n')
    for override in ("optim.grad_clip_norm=0", "seed=-1", "optim.learning_rate=0",
                     "data.batch_size=0", "optim.warmup_fraction=1.5"):
        field = override.split("=")[0].split(".")[-1]
        with pytest.raises(ConfigError, match=field):
            load_train_config(base, [override])
    with pytest.raises(ConfigError, match=r"closed_form_sigma: 1000000000.0 is outside .*pixels"):
        closed_form_mixer("closed-form:sigma=1e9")
    assert load_train_config(base, ["optim.grad_clip_norm=1.5"]).optim.grad_clip_norm == 1.5


EXPERIMENT_CONFIGS = sorted((Path(__file__).parent.parent / "experiments" / "configs").glob("*.toml"))


@pytest.mark.parametrize("path", EXPERIMENT_CONFIGS, ids=lambda p: p.name)
def test_every_shipped_experiment_config_loads(path):
    """Each committed config parses with its schema, model tables included (a wrong or stale key
    in a config that a README command runs would otherwise only fail hours into a job)."""
    from jaxden.config import load_config

    if path.name.startswith("dataset-"):
        from jaxden.data.config import load_dataset_config

        assert load_dataset_config(path).spp
        return
    if path.name.startswith("sequences-"):
        from jaxden.data.sequences import load_sequence_config

        assert load_sequence_config(path).frames >= 2
        return
    from jaxden.train.config import load_train_config
    from jaxden.train.tasks import get_trainable

    config = load_train_config(path)
    load_config(dict(config.model_config), get_trainable(config.model).config_cls)
