"""Every number in README.md's results tables equals the JSON file in experiments/results/ it
comes from, at the README's rounding.

The README's markdown tables are parsed; SOURCES maps each table row to the JSON values its
numbers quote, in the order they appear in the cell. Only numbers with a decimal point are
quotes: labels such as "WSKP-6", "3..13" or "(4096)" are not. A number edited in the README, a
row or number added without a source here, or a JSON file regenerated with other values fails.
"""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
RESULTS = ROOT / "experiments" / "results"
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?![\w.])")


def _worst_crop_over_mc(report: dict) -> float:
    """PD / MC RMSE at the top spp of the worst crop of a pd_report.py report."""
    return max(crop["pd_over_mc_rmse_at_max_spp"]
               for crop in report["summary"]["per_crop"].values())


def _key(*path):
    def get(data):
        for part in path:
            data = data[part]
        return data
    get.path = "/".join(path)
    return get


def _pd(name: str, column: str, base: str = "oidn"):
    """The headline ratios of experiments/results/pd-BASE-NAME.json quoted in one column."""
    file = f"pd-{base}-{name}.json"
    headline = ("summary", "headline")
    if column == "oracle":
        return [(file, _key(*headline, "oracle_over_denoiser", "rmse")),
                (file, _key(*headline, "oracle_over_denoiser", "relmse"))]
    if column == "top spp":
        worst = _worst_crop_over_mc
        worst.path = "max over summary/per_crop/*/pd_over_mc_rmse_at_max_spp"
        return [(file, _key(*headline, "pd_over_mc_at_max_spp", "rmse")), (file, worst)]
    return [(file, _key(*headline, "pd_over_denoiser", column))]


# Benchmarks: first cell of the row -> {column: [(file, value getter), ...]}
BENCHMARKS = {
    "`jaxden bench decoder`": {"result": [("bench-decoder.json", _key("memory_ratio")),
                                          ("bench-decoder.json", _key("time_ratio"))]},
    "`jaxden bench denoisers`": {"result": [
        ("bench-denoisers.json", _key("wskp6_over_oidn")),
        ("bench-denoisers.json", _key("wskp3_over_oidn")),
        ("bench-denoisers.json", _key("kp_over_oidn")),
        ("bench-denoisers.json", _key("unet_over_oidn")),
        ("bench-denoisers.json", _key("wskp6_over_kp")),
        ("bench-denoisers.json", _key("wskp6_network_over_kp"))]},
    "`jaxden bench sharding`": {"result": [("bench-sharding.json", _key("unet_ratio")),
                                           ("bench-sharding.json", _key("wskp_ratio"))]},
    "`jaxden bench sure`": {"result": [
        ("bench-sure.json", _key("jvp_k1_over_forward")),
        ("bench-sure.json", _key("jvp_over_fd_k4")),
        ("bench-sure-h100.json", _key("jvp_k1_over_forward")),
        ("bench-sure-h100.json", _key("jvp_over_fd_k4"))]},
    "`jaxden bench progressive`": {"result": [
        ("bench-progressive.json", _key("pd_over_oidn")),
        ("bench-progressive.json", _key("pd_single_over_oidn")),
        ("bench-progressive.json", _key("mixer_over_oidn")),
        ("bench-progressive.json", _key("tstat_over_oidn")),
        ("bench-progressive.json", _key("closed_form_over_oidn")),
        ("bench-progressive.json", _key("pd_wskp6_over_wskp6")),
        ("bench-progressive.json", _key("pd_wskp6_closed_form_k1_over_wskp6"))]},
    "`docs/scaling_bench.py`": {"result": [("scaling-ray-local.json", _key("ray_over_local"))]},
    "`jaxden bench render`": {"result": [
        ("bench-render.json", _key("ratio")),
        ("bench-render.json", _key("ratio_legacy_features"))]},
}

# Progressive denoising: (set, start of the mixer cell) -> report name; the set is carried down
# from the row that names it.
PD_ROWS = {
    ("test-high", "**shipped `oidn-pd`**"): "test-high-shipped",
    ("test-high", "the same weights on the plain closed form"): "test-high-shipped-stops-none",
    ("test-high", "`--mixer closed-form:stops=1`"): "test-high-closed-form-stops1",
    ("test-high", "`--mixer closed-form`"): "test-high-closed-form",
    ("test-high", "oracle (8 x 8 tiles)"): "test-high-shipped",
    ("test", "**shipped `oidn-pd`**"): "test-shipped",
    ("test", "the same weights on the plain closed form"): "test-shipped-stops-none",
    ("test", "`--mixer closed-form:stops=1`"): "test-closed-form-stops1",
    ("test", "`--mixer closed-form`"): "test-closed-form",
    ("test", "oracle (8 x 8 tiles)"): "test-shipped",
}


#: PD over WSKP-6: first cell of the row (the set) -> report name (pd-wskp6-NAME.json).
PD_WSKP6_ROWS = {"progressive sequence": "sequence", "pd-test-high": "test-high",
                 "out of distribution": "ood-first-hit"}

#: The real-time tables: README section -> the file their rows quote (rows by method label).
RT_FILE = "rt-table1.json"


def _rt(section: str, label: str, metric: str, index: int):
    """Entry ``index`` (0 mean, 1 standard deviation) of ``section/label/metric`` in RT_FILE."""
    def get(data):
        return data[section][label][metric][index]
    get.path = f"{section}/{label}/{metric}[{index}]"
    return get


def tables_under(heading: str, text: str | None = None) -> list[dict]:
    """The markdown tables of README.md under ``heading`` (up to the next heading of any level),
    as lists of {column name: cell} rows."""
    lines = (README.read_text() if text is None else text).splitlines()
    start = lines.index(heading)
    tables, current, header = [], None, None
    for line in lines[start + 1:]:
        if line.startswith("#"):
            break
        if not line.startswith("|"):
            current = header = None
            continue
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if header is None:
            header, current = cells, []
            tables.append(current)
        elif set("".join(cells)) <= set("-: "):
            continue
        else:
            current.append(dict(zip(header, cells)))
    return tables


def quotes(text: str | None = None) -> list[tuple[str, str, list]]:
    """(where, README cell, [(file, getter), ...]) for every quoting cell of the results
    tables; a row without a source is an error here."""
    out = []
    (bench,) = tables_under("### Benchmarks", text)
    assert {row["benchmark"] for row in bench} == set(BENCHMARKS), "benchmark rows changed"
    for row in bench:
        for column, sources in BENCHMARKS[row["benchmark"]].items():
            out.append((f"{row['benchmark']} / {column}", row[column], sources))
    (pd,) = tables_under("### Progressive denoising of OIDN", text)
    columns = list(pd[0])
    rmse, relmse, flip, top = columns[2:6]
    current_set, seen = None, set()
    for row in pd:
        if row["set"]:
            current_set = row["set"].split(",")[0]
        key = next((k for k in PD_ROWS if k[0] == current_set and row["mixer"].startswith(k[1])),
                   None)
        assert key is not None, f"PD table row without a source: {current_set} / {row['mixer']}"
        seen.add(key)
        name = PD_ROWS[key]
        if key[1].startswith("oracle"):
            out.append((f"{current_set} / oracle", f"{row[rmse]} {row[relmse]}",
                        _pd(name, "oracle")))
            assert not DECIMAL.findall(row[flip] + row[top]), "oracle FLIP / top-spp: no source"
            continue
        for column, source in ((rmse, "rmse"), (relmse, "relmse"), (flip, "flip"),
                               (top, "top spp")):
            out.append((f"{current_set} / {row['mixer']} / {column}", row[column],
                        _pd(name, source)))
    assert seen == set(PD_ROWS), f"PD table rows missing: {set(PD_ROWS) - seen}"
    (wskp6,) = tables_under("### Progressive denoising of WSKP-6", text)
    columns = list(wskp6[0])
    assert {row[columns[0]].split(" (")[0] for row in wskp6} == set(PD_WSKP6_ROWS), \
        "PD(WSKP-6) table rows changed"
    for row in wskp6:
        name = PD_WSKP6_ROWS[row[columns[0]].split(" (")[0]]
        for column, source in zip(columns[1:5], ("rmse", "relmse", "flip", "top spp")):
            out.append((f"PD(WSKP-6) / {name} / {column}", row[column],
                        _pd(name, source, base="wskp6")))
    per_frame, temporal = tables_under("### Weight-sharing kernel prediction", text)
    metrics = {"PSNR (dB)": "psnr", "SSIM": "ssim", "relMSE": "relmse", "FLIP": "flip"}
    for section, rows in (("per_frame", per_frame), ("temporal", temporal)):
        for row in rows:
            for column, metric in metrics.items():
                cell = row[column]
                sources = [(RT_FILE, _rt(section, row["method"], metric, 0))]
                if "±" in cell:
                    sources.append((RT_FILE, _rt(section, row["method"], metric, 1)))
                out.append((f"real-time / {row['method']} / {column}", cell, sources))
    return out


def check(text: str | None = None) -> list[str]:
    """Every mismatch between a README quote and its JSON value, as a message."""
    problems, cache = [], {}
    for where, cell, sources in quotes(text):
        numbers = DECIMAL.findall(cell)
        if len(numbers) != len(sources):
            problems.append(f"{where}: {len(numbers)} numbers in {cell!r}, "
                            f"{len(sources)} sources")
            continue
        for number, (file, get) in zip(numbers, sources):
            if file not in cache:
                cache[file] = json.loads((RESULTS / file).read_text())
            value = get(cache[file])
            decimals = len(number.split(".")[1])
            if f"{value:.{decimals}f}" != number:
                problems.append(f"{where}: README says {number}, experiments/results/{file} "
                                f"{get.path} = {value:.6g} ({value:.{decimals}f})")
    return problems


def test_readme_numbers_match_their_json():
    assert check() == []


def test_an_edited_readme_number_is_caught():
    text = README.read_text()
    edited = text.replace("| 0.866 | 0.908 | 0.891 |", "| 0.866 | 0.909 | 0.891 |", 1)
    assert edited != text
    problems = check(edited)
    assert len(problems) == 1 and "README says 0.909" in problems[0]
    assert "pd-oidn-test-high-shipped.json" in problems[0]


def test_a_number_without_a_source_is_caught():
    text = README.read_text()
    edited = text.replace("memory 0.046, time 0.034", "memory 0.046, time 0.034, peak 0.5", 1)
    assert edited != text
    assert any("3 numbers" in p for p in check(edited))


def test_every_cited_json_exists():
    files = {file for _, _, sources in quotes() for file, _ in sources}
    assert files and all((RESULTS / file).is_file() for file in files)


@pytest.mark.parametrize("text,numbers", [("WSKP-6 0.37, WSKP-3 0.23", ["0.37", "0.23"]),
                                          ("0.9999 (4096)", ["0.9999"]),
                                          ("6 kernels 3..13, 1280x720", [])])
def test_only_decimal_numbers_are_quotes(text, numbers):
    assert DECIMAL.findall(text) == numbers
