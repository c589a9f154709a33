"""Every number in README.md, in its results table and in its prose, equals the JSON file in
experiments/results/ it comes from, at the README's rounding.

The results table under "## Results" is parsed: HEADLINE maps each row (its "result" and "data"
cells) to the JSON values its "value" cell quotes, in order, and the row's "file" cell must name
exactly those files. Only numbers with a decimal point are quotes there: labels such as
"WSKP-6", "3..13" or "32..4096" are not.

The prose (everything outside tables and fenced code blocks, whitespace collapsed) is scanned for
decimal numbers (also glued to a letter, as in "x0.883") and percentages ("13 %"). Each must lie
inside one of the PROSE phrases, which map a short quoted phrase to the JSON values of the
numbers in it, in order, or inside one of the NOT_QUOTES phrases (numbers that are not
measurements). A number edited in the README, a row or number added without a source here, a
phrase reworded, or a JSON file regenerated with other values fails.
"""

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
RESULTS = ROOT / "experiments" / "results"
#: A quoted number in a table cell: a decimal number standing alone.
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?![\w.])")
#: A number in prose that must have a source: a percentage, or any decimal number (also after a
#: letter, "x0.883"), but not a part of a version or a range ("0.1.0", "2..1024").
PROSE_NUMBER = re.compile(r"(?<![\d.])\d+(?:\.\d+)?(?= ?%)|(?<![\d.])\d+\.\d+(?!\.?\d)")


def _key(*path):
    def get(data):
        for part in path:
            data = data[part]
        return data
    get.path = "/".join(path)
    return get


def _percent_over_one(get):
    """(value - 1) in percent: a ratio of 1.133 quoted as "13 %"."""
    def percent(data):
        return (get(data) - 1.0) * 100.0
    percent.path = f"({get.path} - 1) x 100"
    return percent


def _worst_crop_over_mc(report: dict) -> float:
    """PD / MC RMSE at the top spp of the worst crop of a PD report."""
    return max(crop["pd_over_mc_rmse_at_max_spp"]
               for crop in report["summary"]["per_crop"].values())


_worst_crop_over_mc.path = "max over summary/per_crop/*/pd_over_mc_rmse_at_max_spp"


def _pd(file: str, ratio: str, *metrics: str):
    """summary/headline/RATIO/METRIC of a PD report, for each metric."""
    return [(file, _key("summary", "headline", ratio, metric)) for metric in metrics]


def _rt(label: str, metric: str):
    """The mean over seeds of ``metric`` of ``label`` at 1 spp (rt-table1.json's and
    rt-comparisons.json's ``per_frame``)."""
    def get(data):
        return data["per_frame"][label][metric][0]
    get.path = f"per_frame/{label}/{metric}[0]"
    return get


OIDN_HIGH = "pd-oidn-test-high-shipped.json"
OIDN_TEST = "pd-oidn-test-shipped.json"

#: The results table: (result cell, data cell) -> [(file, value getter), ...] in the order the
#: value cell quotes them.
HEADLINE = {
    ("PD(OIDN) / OIDN with the shipped `oidn-pd`: RMSE, relMSE, FLIP",
     "test-high: 8 held-out crops, 32..4096 spp"):
        _pd(OIDN_HIGH, "pd_over_denoiser", "rmse", "relmse", "flip"),
    ("the same", "test: the same crops, 2..1024 spp"):
        _pd(OIDN_TEST, "pd_over_denoiser", "rmse", "relmse", "flip"),
    ("PD(OIDN) / MC, RMSE at 4096 spp: crop mean; worst crop", "test-high"):
        _pd(OIDN_HIGH, "pd_over_mc_at_max_spp", "rmse") + [(OIDN_HIGH, _worst_crop_over_mc)],
    ("PD(OIDN in JAX) / OIDN, `oidn-pd` fed one Rademacher jvp probe: RMSE, relMSE, FLIP",
     "test-high"):
        _pd("pd-oidnjax-k1rad-test-high.json", "pd_over_denoiser", "rmse", "relmse", "flip"),
    ("8 x 8-tile oracle / OIDN (a bound, not a method): RMSE, relMSE", "test-high"):
        _pd(OIDN_HIGH, "oracle_over_denoiser", "rmse", "relmse"),
    ("PD(WSKP-6) / WSKP-6 with the shipped `wskp-6-pd`: RMSE, relMSE, FLIP",
     "pd-test-high: 8 held-out crops, 32..4096 spp"):
        _pd("pd-wskp6-test-high.json", "pd_over_denoiser", "rmse", "relmse", "flip"),
    ("the same, without the error guard", "a held-out 256 x 256 frame, 2..4096 spp"):
        _pd("pd-wskp6-sequence.json", "pd_over_denoiser", "rmse", "relmse", "flip"),
    ("PSNR (dB) at 1 spp: WSKP-6; WSKP-3; KP 13 x 13; NBGD; MR-KP (each 2 seeds); OIDN 2",
     "rt-test: 24 held-out crops"): [
        ("rt-comparisons.json", _rt("WSKP-6, trained here (runs: 2)", "psnr")),
        ("rt-comparisons.json", _rt("WSKP-3, trained here (runs: 2)", "psnr")),
        ("rt-comparisons.json", _rt("KP (13x13), trained here (runs: 2)", "psnr")),
        ("rt-comparisons.json", _rt("NBGD, trained here (runs: 2)", "psnr")),
        ("rt-comparisons.json", _rt("MR-KP, trained here (runs: 2)", "psnr")),
        ("rt-comparisons.json", _rt("OIDN 2 (pretrained, 'high')", "psnr"))],
    ("inference time, 1280 x 720: WSKP-6 / KP; WSKP-6 / OIDN", "one frame"): [
        ("bench-denoisers.json", _key("wskp6_over_kp")),
        ("bench-denoisers.json", _key("wskp6_over_oidn"))],
    ("inference time, 1280 x 720, over WSKP-6's in the same run: SVGF; BMFR; NBGD; MR-KP; "
     "the Deep Combiner over OIDN in JAX; NFOR", "one frame"): [
        ("bench-denoisers.json", _key("svgf_over_wskp6")),
        ("bench-denoisers.json", _key("bmfr_over_wskp6")),
        ("bench-denoisers.json", _key("nbgd_over_wskp6")),
        ("bench-denoisers.json", _key("mrkp_over_wskp6")),
        ("bench-denoisers.json", _key("dc_over_wskp6")),
        ("bench-denoisers.json", _key("nfor_over_wskp6"))],
    ("inference time, 1280 x 720, over OIDN's in the same run: StatMC; its Moon-CI test; NJS "
     "over OIDN in JAX (two half buffers)", "one frame"): [
        ("bench-denoisers.json", lambda d: d["statmc_s"] / d["oidn_s"]),
        ("bench-denoisers.json", lambda d: d["statmc_moon_s"] / d["oidn_s"]),
        ("bench-denoisers.json", lambda d: d["njs_s"] / d["oidn_s"])],
    ("offline, 64 spp, whole frames: RMSE of NFOR, OIDN, PD(OIDN) / MC's (scene means)",
     "8 held-out 256 x 256 frames (lamps, glints)"): [
        ("offline-nfor.json", lambda d: d["means"]["NFOR"]["rmse"] / d["means"]["MC"]["rmse"]),
        ("offline-nfor.json", lambda d: d["means"]["OIDN"]["rmse"] / d["means"]["MC"]["rmse"]),
        ("offline-nfor.json",
         lambda d: d["means"]["PD(OIDN)"]["rmse"] / d["means"]["MC"]["rmse"])],
    ("consistent denoisers, RMSE over MC's at 4096 spp, worst frame: PD(OIDN); PD(DC s0); "
     "StatMC; its Moon-CI test; NJS(OIDN) s0",
     "stress: 8 frames (small lamps, glints, caustics)"): [
        ("consistent-table.json",
         _key("sets", "stress-stats", "rmse", "top_spp_over_mc", label, "worst"))
        for label in ("PD(OIDN)", "PD(DC s0)", "StatMC", "StatMC (Moon CI)", "NJS(OIDN) s0")],
    ("OIDN in JAX (Intel's weights) / pyoidn, 1280 x 720", "one frame"): [
        ("bench-denoisers.json", _key("oidnjax_over_oidn"))],
    ("SURE by `jax.jvp` (one probe) / one WSKP-6 forward, 1280 x 720", "one frame"): [
        ("bench-sure.json", _key("jvp_k1_over_forward"))],
    ("PD(WSKP-6) / one WSKP-6 forward; PD(OIDN) / one OIDN call, 1280 x 720", "one frame"): [
        ("bench-progressive.json", _key("pd_wskp6_over_wskp6")),
        ("bench-progressive.json", _key("pd_over_oidn"))],
    ("PD(OIDN in JAX), SURE by `jax.jvp`: 1 Rademacher probe (its default); 4 normal probes / "
     "one pyoidn call, 1280 x 720", "the same run"): [
        ("bench-progressive.json", _key("pd_oidnjax_over_oidn")),
        ("bench-progressive.json", _key("pd_oidnjax_k4_over_oidn"))],
    ("PSNR (dB), stock OIDN -> OIDN fine-tuned on jaxden renders at 2-8 spp: at 2 spp; at 64 spp",
     "test-chain: 8 held-out crops"): [
        ("oidn-finetune.json", _key("per_spp", "2", "stock_psnr")),
        ("oidn-finetune.json", _key("per_spp", "2", "tuned_psnr")),
        ("oidn-finetune.json", _key("per_spp", "64", "stock_psnr")),
        ("oidn-finetune.json", _key("per_spp", "64", "tuned_psnr"))],
    ("box-sum kernel decoder / unfold decoder, 6 kernels 3..13: memory, time", "1280 x 720"): [
        ("bench-decoder.json", _key("memory_ratio")),
        ("bench-decoder.json", _key("time_ratio"))],
    ("peak memory (GB) of `jaxden progressive`, 7680 x 4320: PD(OIDN); PD(WSKP-6)",
     "one frame, the whole command"): [
        ("bench-frames-progressive.json", _key("pd_oidn_7680x4320_gb")),
        ("bench-frames-progressive.json", _key("pd_wskp6_7680x4320_gb"))],
    ("time per megapixel, 7680 x 4320 / 1920 x 1080: PD(OIDN); PD(WSKP-6)", "the same run"): [
        ("bench-frames-progressive.json", _key("pd_oidn_time_per_mp_7680x4320_over_1920x1080")),
        ("bench-frames-progressive.json",
         _key("pd_wskp6_time_per_mp_7680x4320_over_1920x1080"))],
    ("peak memory (GB) of `jaxden denoise`, 7680 x 4320: OIDN; WSKP-6; OIDN-JAX",
     "one frame, the whole command"): [
        ("bench-frames-denoisers.json", _key("oidn_7680x4320_gb")),
        ("bench-frames-denoisers.json", _key("wskp6_7680x4320_gb")),
        ("bench-frames-denoisers.json", _key("oidnjax_7680x4320_gb"))],
}

#: README prose: a phrase (as in the README, whitespace collapsed; its numbers stand for any
#: number) -> [(file, value getter), ...] for the numbers in it, in order.
PROSE = {
    "a fine-tuned WSKP-6 (23.05 -> 26.24 dB PSNR on held-out Cycles views at 1 spp)": [
        ("cycles-wskp6-stock.json", _key("summary", "den_psnr")),
        ("cycles-wskp6-finetuned.json", _key("summary", "den_psnr"))],
    "raises its RMSE by 4 % and its relMSE by 13 % on average over 2..1024 spp": [
        ("oidn-no-features.json",
         _percent_over_one(_key("summary", "mean_over_spp", "none", "rmse"))),
        ("oidn-no-features.json",
         _percent_over_one(_key("summary", "mean_over_spp", "none", "relmse")))],
    "bring OIDN's RMSE to 0.934 of that with the legacy ones on average over 2..1024 spp and to "
    "0.826 at 1024 spp": [
        ("oidn-aux-features.json",
         _key("summary", "mean_over_spp", "specular-chain:1024:clean", "rmse")),
        ("oidn-aux-features.json",
         _key("summary", "per_spp", "1024", "ratio", "specular-chain:1024:clean", "rmse"))],
}

#: Prose numbers that are not measurements: phrase -> why.
NOT_QUOTES = {
    "Python >= 3.11": "the Python version the package supports",
}


def result_file(name: str) -> Path:
    """experiments/results/NAME, or the one file of that name in a subfolder of it (results are
    grouped by family)."""
    if (RESULTS / name).is_file():
        return RESULTS / name
    found = sorted(RESULTS.rglob(name))
    assert len(found) == 1, f"experiments/results: {len(found)} files named {name}"
    return found[0]


def _collapse(text: str) -> str:
    return " ".join(text.split())


def _phrase_pattern(phrase: str) -> re.Pattern:
    """``phrase`` as a pattern in which each of its numbers matches any number (a group), so
    that an edited number is reported with its value rather than as a missing phrase."""
    parts, last = [], 0
    for match in PROSE_NUMBER.finditer(phrase):
        parts += [re.escape(phrase[last:match.start()]), r"(\d+(?:\.\d+)?)"]
        last = match.end()
    return re.compile("".join(parts) + re.escape(phrase[last:]))


def prose(text: str | None = None) -> str:
    """README.md without its tables and fenced code blocks, whitespace collapsed."""
    lines, fenced = [], False
    for line in (README.read_text() if text is None else text).splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced and not line.lstrip().startswith("|"):
            lines.append(line)
    return _collapse("\n".join(lines))


def tables_under(heading: str, text: str | None = None) -> list[list[dict]]:
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


def quotes(text: str | None = None) -> tuple[list[tuple[str, list[str], list]], list[str]]:
    """([(where, [README numbers], [(file, getter), ...]), ...], [problems found on the way]):
    every quoting row of the results table and every sourced prose phrase; rows, phrases and
    prose numbers without a source are problems."""
    out, problems = [], []
    (table,) = tables_under("## Results", text)
    seen = set()
    for row in table:
        key = (row["result"], row["data"])
        if key not in HEADLINE:
            problems.append(f"results table row without a source: {key}")
            continue
        seen.add(key)
        sources = HEADLINE[key]
        named = set(re.findall(r"`([^`]+\.json)`", row["file"]))
        if named != {file for file, _ in sources}:
            problems.append(f"results table row {key}: file cell names {sorted(named)}, "
                            f"its numbers come from {sorted({f for f, _ in sources})}")
        out.append((f"results table / {row['result']} / {row['data']}",
                    DECIMAL.findall(row["value"]), sources))
    problems += [f"results table row missing: {key}" for key in HEADLINE if key not in seen]

    body = prose(text)
    covered = []
    for phrase, sources in PROSE.items():
        matches = list(_phrase_pattern(phrase).finditer(body))
        if len(matches) != 1:
            problems.append(f"prose phrase found {len(matches)} times (expected once): {phrase!r}")
            continue
        covered.append(matches[0].span())
        out.append((f"prose / {phrase!r}", list(matches[0].groups()), sources))
    for phrase in NOT_QUOTES:
        covered += [m.span() for m in re.finditer(re.escape(phrase), body)]
    for match in PROSE_NUMBER.finditer(body):
        if not any(start <= match.start() and match.end() <= end for start, end in covered):
            context = body[max(0, match.start() - 60):match.end() + 20]
            problems.append(f"prose number {match.group()!r} without a source (add its phrase "
                            f"to PROSE): ...{context}...")
    return out, problems


def check(text: str | None = None) -> list[str]:
    """Every mismatch between a README number and its JSON value, as a message."""
    found, problems = quotes(text)
    cache = {}
    for where, numbers, sources in found:
        if len(numbers) != len(sources):
            problems.append(f"{where}: {len(numbers)} numbers {numbers}, {len(sources)} sources")
            continue
        for number, (file, get) in zip(numbers, sources):
            if file not in cache:
                cache[file] = json.loads(result_file(file).read_text())
            value = get(cache[file])
            decimals = len(number.split(".")[1]) if "." in number else 0
            if f"{value:.{decimals}f}" != number:
                problems.append(f"{where}: README says {number}, "
                                f"{result_file(file).relative_to(ROOT).as_posix()} "
                                f"{get.path} = {value:.6g} ({value:.{decimals}f})")
    return problems


def test_readme_numbers_match_their_json():
    assert check() == []


def test_an_edited_table_number_is_caught():
    text = README.read_text()
    edited = text.replace("| 0.866, 0.908, 0.891 |", "| 0.866, 0.909, 0.891 |", 1)
    assert edited != text
    problems = check(edited)
    assert len(problems) == 1 and "README says 0.909" in problems[0]
    assert "pd-oidn-test-high-shipped.json" in problems[0]


def test_an_edited_prose_number_is_caught():
    text = README.read_text()
    edited = text.replace("to 0.826 at 1024 spp", "to 0.816 at 1024 spp", 1)
    assert edited != text
    problems = check(edited)
    assert len(problems) == 1 and "README says 0.816" in problems[0]
    assert "oidn-aux-features.json" in problems[0]
    edited = text.replace("relMSE by 13 %", "relMSE by 12 %", 1)
    assert edited != text
    problems = check(edited)
    assert len(problems) == 1 and "README says 12" in problems[0]


def test_a_reworded_prose_phrase_is_caught():
    text = README.read_text()
    edited = text.replace("raises its RMSE by 4 %", "raises the RMSE by 4 %", 1)
    assert edited != text
    problems = check(edited)
    assert any("found 0 times" in p for p in problems)
    assert any("'4' without a source" in p for p in problems)


@pytest.mark.parametrize("sentence", ["It is 1.5x faster than a plain render.",
                                      "OIDN's error falls by x0.883 with them.",
                                      "SURE is within 3 % of the true error."])
def test_a_prose_number_without_a_source_is_caught(sentence):
    text = README.read_text()
    edited = text.replace("It is safe to run again.", f"It is safe to run again. {sentence}", 1)
    assert edited != text
    problems = check(edited)
    assert len(problems) == 1 and "without a source" in problems[0]


def _edit_row(text: str, result: str, column: int, change) -> str:
    """README text with cell ``column`` of the results row whose result cell is ``result``
    passed through ``change`` (the row found by its label, so new values do not break it)."""
    lines = text.splitlines(keepends=True)
    for i, line in enumerate(lines):
        cells = line.split(" | ")
        if line.startswith(f"| {result} |"):
            cells[column] = change(cells[column])
            lines[i] = " | ".join(cells)
            return "".join(lines)
    raise AssertionError(f"no results row {result!r}")


DECODER_ROW = "box-sum kernel decoder / unfold decoder, 6 kernels 3..13: memory, time"
SURE_ROW = "SURE by `jax.jvp` (one probe) / one WSKP-6 forward, 1280 x 720"


def test_a_table_number_without_a_source_is_caught():
    text = README.read_text()
    edited = _edit_row(text, DECODER_ROW, 2, lambda value: value + ", 0.5")
    assert edited != text
    assert any("3 numbers" in p for p in check(edited))


def test_a_table_row_naming_another_file_is_caught():
    text = README.read_text()
    edited = _edit_row(text, SURE_ROW, 3, lambda file: file.replace("bench-sure.json",
                                                                    "bench-sure-h100.json"))
    assert edited != text
    assert any("file cell names" in p for p in check(edited))


def test_every_cited_json_exists():
    found, _ = quotes()
    files = {file for _, _, sources in found for file, _ in sources}
    assert files and all(result_file(file).is_file() for file in files)


@pytest.mark.parametrize("text,numbers", [("WSKP-6 0.37, WSKP-3 0.23", ["0.37", "0.23"]),
                                          ("0.9999 (4096)", ["0.9999"]),
                                          ("6 kernels 3..13, 1280x720", [])])
def test_only_decimal_numbers_are_quotes(text, numbers):
    assert DECIMAL.findall(text) == numbers


@pytest.mark.parametrize("text,numbers", [("by 4 % and 13% and 2.5 %", ["4", "13", "2.5"]),
                                          ("x0.883 and 0.742x", ["0.883", "0.742"]),
                                          ("jaxden 0.1.0, 2..1024 spp, 1280x720, 64 spp", [])])
def test_prose_numbers(text, numbers):
    assert PROSE_NUMBER.findall(text) == numbers
