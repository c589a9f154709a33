"""Stock against fine-tuned: two ``jaxden evaluate denoise`` reports of one held-out set side by
side, per spp level, with the gain crop by crop.

    python experiments/finetune_gain.py --stock experiments/results/oidn/oidn-finetune-stock.json \
        --tuned experiments/results/oidn/oidn-finetune-tuned.json \
        --title "OIDN fine-tuned on jaxden renders" --out experiments/results/oidn/oidn-finetune

Both reports must score the same crops at the same spp levels of the same dataset build (its
manifest digest); anything else is refused, naming the report. Per spp: the crop means of
PSNR, SSIM (tone-mapped), relMSE and FLIP (linear HDR) for each model, the mean PSNR gain and
how many crops gain; then the same over every spp level together. When both reports score lamp
pixels (data whose frames carry the emission, with emitters in view: ``jaxden evaluate
denoise``'s lamp entries), also each model's relMSE over the lamp pixels and its lamp mean over
the reference's, pooled over the lamp pixels of the level's crops.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
METRICS = (("psnr", "PSNR (dB)", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"),
           ("relmse", "relMSE", "{:.4f}"), ("flip", "FLIP", "{:.4f}"))
#: Pooled over the lamp pixels (jaxden.evaluate.denoise.pool_lamps), when both reports have them.
LAMP_METRICS = (("lamp_relmse", "relMSE on lamps", "{:.4f}"),
                ("lamp_ratio", "lamp mean / reference", "{:.3f}"))


class ReportError(ValueError):
    """A report that cannot be compared (another dataset, other crops, no rows)."""


def load(path: Path) -> dict:
    try:
        report = json.loads(Path(path).read_text())
    except (OSError, ValueError) as error:
        raise ReportError(f"{path}: not a readable evaluate-denoise report ({error})") from None
    if not isinstance(report, dict) or not report.get("rows"):
        raise ReportError(f"{path}: has no rows (not an `jaxden evaluate denoise` report)")
    return report


def _cells(report: dict) -> dict[tuple[str, int], dict]:
    return {(row["crop"], int(row["spp"])): row for row in report["rows"]}


def compare(stock: dict, tuned: dict, stock_name: str = "stock",
            tuned_name: str = "tuned") -> dict:
    """Per spp (and "all"): crop means of each metric for both reports, the mean PSNR gain and
    the crops that gain. Raises ReportError for reports of different data or crops."""
    digests = [r.get("provenance", {}).get("dataset", {}).get("manifest_sha256")
               for r in (stock, tuned)]
    if digests[0] != digests[1]:
        raise ReportError(f"{tuned_name}: scores another dataset build than {stock_name} "
                          f"(manifest {digests[1]} against {digests[0]})")
    a, b = _cells(stock), _cells(tuned)
    if set(a) != set(b):
        only = sorted(set(a) ^ set(b))[:3]
        raise ReportError(f"{tuned_name}: other crops or spp levels than {stock_name} "
                          f"(e.g. {only})")
    from jaxden.evaluate.denoise import pool_lamps

    levels = sorted({spp for _, spp in a})
    out: dict = {}
    for level in [*levels, "all"]:
        keys = sorted(k for k in a if level == "all" or k[1] == level)
        entry: dict = {"crops": len(keys)}
        for metric, _, _ in METRICS:
            entry[f"stock_{metric}"] = sum(a[k][f"den_{metric}"] for k in keys) / len(keys)
            entry[f"tuned_{metric}"] = sum(b[k][f"den_{metric}"] for k in keys) / len(keys)
        lamps = [pool_lamps([cells[k] for k in keys]) for cells in (a, b)]
        if all(lamps):
            entry["lamp_pixels"] = lamps[0]["lamp_pixels"]
            for metric, _, _ in LAMP_METRICS:
                for name, pooled in zip(("stock", "tuned"), lamps):
                    if f"den_{metric}" in pooled:
                        entry[f"{name}_{metric}"] = pooled[f"den_{metric}"]
        gains = [b[k]["den_psnr"] - a[k]["den_psnr"] for k in keys]
        entry["psnr_gain"] = sum(gains) / len(gains)
        entry["crops_gaining"] = sum(g > 0 for g in gains)
        entry["worst_psnr_gain"] = min(gains)
        entry["best_psnr_gain"] = max(gains)
        out[str(level)] = entry
    return out


def markdown(table: dict, title: str, stock: dict, tuned: dict) -> str:
    lamps = any("lamp_pixels" in entry for entry in table.values())
    lines = [f"# {title}", "",
             f"Stock: `{stock['provenance'].get('denoiser', {}).get('spec', '?')}`; fine-tuned: "
             f"`{tuned['provenance'].get('denoiser', {}).get('spec', '?')}`; data: "
             f"`{stock['provenance'].get('dataset', {}).get('dir', '?')}` (split "
             f"`{stock['provenance'].get('dataset', {}).get('split', '?')}`). Crop means; PSNR "
             f"and SSIM tone-mapped, relMSE and FLIP linear HDR."
             + (" Lamps: the pixels whose reference sees an emitter directly, pooled over the "
                "crops (linear HDR)." if lamps else ""), ""]
    lamp_metrics = LAMP_METRICS if lamps else ()

    def pairs(metrics) -> str:
        return "".join(f" | {label}: stock | fine-tuned" for _, label, _ in metrics)

    lines += ["| spp | crops" + pairs(METRICS) + " | PSNR gain (dB): mean | worst crop | "
              "best crop | crops gaining" + pairs(lamp_metrics)
              + (" | lamp pixels" if lamps else "") + " |",
              "|---" * (2 + 2 * len(METRICS) + 4 + (2 * len(lamp_metrics) + 1) * lamps) + "|"]
    for level, entry in table.items():
        cells = [level, str(entry["crops"])]
        for metric, _, form in METRICS:
            cells += [form.format(entry[f"stock_{metric}"]), form.format(entry[f"tuned_{metric}"])]
        cells += [f"{entry['psnr_gain']:+.2f}", f"{entry['worst_psnr_gain']:+.2f}",
                  f"{entry['best_psnr_gain']:+.2f}", f"{entry['crops_gaining']} of {entry['crops']}"]
        for metric, _, form in lamp_metrics:  # a level whose crops see no lamp: empty cells
            cells += [form.format(entry[f"{name}_{metric}"]) if f"{name}_{metric}" in entry
                      else "" for name in ("stock", "tuned")]
        if lamps:
            cells.append(str(entry.get("lamp_pixels", 0)))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stock", type=Path, required=True, help="the stock model's report .json")
    parser.add_argument("--tuned", type=Path, required=True, help="the fine-tuned model's .json")
    parser.add_argument("--title", default="Stock against fine-tuned")
    parser.add_argument("--out", type=Path, required=True, help="output path without suffix")
    args = parser.parse_args(argv)
    try:
        stock, tuned = load(args.stock), load(args.tuned)
        table = compare(stock, tuned, str(args.stock), str(args.tuned))
    except ReportError as error:
        print(f"finetune_gain: error: {error}", file=sys.stderr)
        return 2
    from jaxden.provenance import result_provenance, run_identity, write_result

    identity = run_identity(argv)
    result = {"provenance": result_provenance(identity, stock=str(args.stock),
                                              tuned=str(args.tuned)),
              "per_spp": table}
    write_result(args.out, result, markdown(table, args.title, stock, tuned))
    return 0


if __name__ == "__main__":
    sys.exit(main())
