"""Measuring denoisers on held-out data: the WSKP paper's Tables 1/6 on jaxden's datasets (the
``denoise`` and ``sequences`` evaluators).

:func:`evaluate_denoiser` denoises every input of a dataset split at the chosen spp and scores
it against the crop's independent reference; :func:`evaluate_sequences` does the same per frame
of camera-path sequences, once frame by frame and once after temporal accumulation (the WSKP
paper's preprocessing: :mod:`jaxden.denoise.temporal`). Metrics, as the paper reports them plus
the HDR ones jaxden uses elsewhere (:mod:`jaxden.metrics`):

- ``psnr``, ``ssim``: on tone-mapped images (clip to [0, 1], gamma 2.2), as the paper;
- ``relmse``, ``flip``: on linear HDR radiance (FLIP in HDR mode);
- ``mse_nc``: MSE minus the reference's own variance of the mean (unbiased for the MSE
  against the true image when the reference is an independent render), and ``rmse``;
- on the lamp pixels, when the dataset's frames carry the emission (``Frame.emission``) and
  some crop of the split sees an emitter: ``lamp_relmse`` (the mean per-pixel relMSE over
  them), ``lamp_ratio`` (the mean of the image over them divided by the reference's: 1 when
  the emitters keep their brightness) and their count ``lamp_pixels``, pooled over the split
  (:func:`lamp_mask`, :func:`pool_lamps`). A lamp pixel is one whose *reference* sees an
  emitter directly (its emission > 0 in any channel): the reference's emission is the mean
  over its many samples, so the set is the same for every input level and denoiser, where a
  1-spp input's emission sees a lamp's edge or not by chance.

References here are finite-spp renders (jaxden's datasets keep them cheap): PSNR and SSIM
against a noisy reference are biased low, by more the better the denoiser; ``mse_nc`` is the
unbiased comparison. Every row names its crop, scene and spp so tables can be regrouped.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from jaxden.data.crops import iter_crops
from jaxden.evaluate.evaluator import Evaluator
from jaxden.evaluate.shared import denoiser_label

DENOISE_METRICS = ("psnr", "ssim", "relmse", "flip", "rmse", "mse_nc")
#: A row's lamp-pixel entries per image (``<prefix>_<name>``), beside its ``lamp_pixels`` and
#: ``ref_lamp_mean``: pooled over rows by :func:`pool_lamps`, never averaged row by row.
LAMP_METRICS = ("lamp_relmse", "lamp_mean")


def image_errors(image, reference) -> dict[str, float]:
    """The :data:`DENOISE_METRICS` of one (H, W, 3) linear image against a reference Frame."""
    from jaxden import metrics

    image = np.asarray(image, np.float32)
    truth = np.asarray(reference.color, np.float32)
    out = {
        "psnr": float(metrics.psnr(image, truth)),
        "ssim": float(metrics.ssim(image, truth)),
        "relmse": float(metrics.relmse(image, truth)),
        "flip": float(metrics.flip(image, truth, "HDR")),
        "rmse": float(metrics.rmse(image, truth)),
    }
    if reference.variance is not None:
        out["mse_nc"] = float(metrics.noise_corrected_mse(image, truth, reference.variance))
    else:
        out["mse_nc"] = float(metrics.mse(image, truth))
    return out


def lamp_mask(reference) -> np.ndarray | None:
    """(H, W) bool: the lamp pixels of a crop, those whose reference Frame's emission is > 0
    in any channel (an emitter seen directly); None when the reference carries no emission."""
    if reference.emission is None:
        return None
    return np.any(np.asarray(reference.emission, np.float32) > 0, axis=-1)


def lamp_errors(image, reference, mask) -> dict[str, float | None]:
    """The :data:`LAMP_METRICS` of one (H, W, 3) linear image on the ``mask`` pixels (from
    :func:`lamp_mask`) against a reference Frame: ``lamp_relmse``, the mean over those pixels
    of each pixel's relMSE (:func:`jaxden.metrics.relmse` of its 3 channels), and
    ``lamp_mean``, the image's mean over those pixels and channels; None when none."""
    from jaxden import metrics

    if not mask.any():
        return dict.fromkeys(LAMP_METRICS)
    image = np.asarray(image, np.float32)
    truth = np.asarray(reference.color, np.float32)
    # each pixel as a 1 x 1 image: relMSE keeps its one definition (metrics.py)
    per_pixel = np.asarray(metrics.relmse(image[..., None, None, :], truth[..., None, None, :]))
    return {"lamp_relmse": float(per_pixel[mask].mean()), "lamp_mean": float(image[mask].mean())}


def _lamp_entries(reference, mask, images: dict) -> dict[str, Any]:
    """A row's lamp entries: ``lamp_pixels``, ``ref_lamp_mean`` and the
    :func:`lamp_errors` of each ``{prefix: image}``; none when ``mask`` is None."""
    if mask is None:
        return {}
    count = int(mask.sum())
    truth = np.asarray(reference.color, np.float32)
    row: dict[str, Any] = {"lamp_pixels": count,
                           "ref_lamp_mean": float(truth[mask].mean()) if count else None}
    for prefix, image in images.items():
        row |= {f"{prefix}_{k}": v for k, v in lamp_errors(image, reference, mask).items()}
    return row


def _denoiser(spec):
    from jaxden.denoise.registry import Denoiser, load_denoiser

    return spec if isinstance(spec, Denoiser) else load_denoiser(spec)


def evaluate_denoiser(dataset_dir, denoiser, *, split: str = "test", spp=(1,),
                      include_input: bool = True) -> list[dict[str, Any]]:
    """One row per (crop, spp) of ``split`` (``all``: every crop): the denoiser's errors
    (``den_<metric>``) and, with ``include_input``, the noisy input's (``mc_<metric>``).
    When the references carry the emission, also the crop's lamp pixels: ``lamp_pixels``,
    the reference's mean over them ``ref_lamp_mean`` and each image's
    ``<prefix>_lamp_relmse`` and ``<prefix>_lamp_mean`` (:func:`lamp_errors`; None, as the
    mean, when the crop has none).

    ``denoiser``: a :class:`jaxden.denoise.Denoiser` or a spec for ``load_denoiser`` (a
    registered black box such as ``oidn``, a shipped name, a run folder).
    """
    model = _denoiser(denoiser)
    rows = []
    for crop, reference, inputs in iter_crops(dataset_dir, split, tuple(spp), min_spp=1):
        mask = lamp_mask(reference)
        for level, frame in inputs:
            images = {"den": model(frame)} | ({"mc": frame.color} if include_input else {})
            row: dict[str, Any] = {"crop": crop.id, "scene": crop.scene, "spp": level}
            for prefix, image in images.items():
                row |= {f"{prefix}_{k}": v for k, v in image_errors(image, reference).items()}
            row |= _lamp_entries(reference, mask, images)
            rows.append(row)
    return rows


def evaluate_sequences(sequence_dir, denoiser, *, temporal=None,
                       skip_frames: int = 1) -> list[dict[str, Any]]:
    """One row per frame of every sequence of a set built by ``jaxden dataset sequences``:
    errors of the denoiser on the frame alone (``den_*``) and on the temporally accumulated
    input (``tdn_*``: :func:`jaxden.denoise.temporal.accumulate` with ``temporal``, a
    :class:`~jaxden.denoise.temporal.TemporalConfig`), and of the two inputs (``mc_*``,
    ``acc_*``); a temporal denoiser (SVGF, BMFR: :attr:`Denoiser.temporal`) also with its own
    history over the raw frames (``seq_*``: :meth:`Denoiser.step` from the sequence's first
    frame). The first ``skip_frames`` frames (no history yet) are left out of the rows.
    """
    import jax

    from jaxden.data.sequences import load_sequence, read_manifest
    from jaxden.denoise.temporal import TemporalConfig, accumulate, start_history

    model = _denoiser(denoiser)
    temporal = temporal or TemporalConfig()
    step = jax.jit(lambda history, frame: accumulate(history, frame, temporal))
    rows = []
    for key in read_manifest(sequence_dir)["sequences"]:
        frames, references = load_sequence(sequence_dir, key)
        history, state = None, None
        for t, (frame, reference) in enumerate(zip(frames, references)):
            own = None
            if model.temporal:
                own, state = model.step(state, frame)
            if history is None:
                history, accumulated = start_history(frame), np.asarray(frame.color)
            else:
                accumulated, history = step(history, frame)
            if t < skip_frames:
                continue
            acc_frame = frame.replace(color=np.asarray(accumulated, np.float32))
            row: dict[str, Any] = {"sequence": key, "frame": t}
            for prefix, image in (("mc", frame.color), ("den", model(frame)),
                                  ("acc", acc_frame.color), ("tdn", model(acc_frame)),
                                  *((("seq", own),) if own is not None else ())):
                row |= {f"{prefix}_{k}": v for k, v in image_errors(image, reference).items()}
            rows.append(row)
    return rows


def _is_lamp_entry(key: str) -> bool:
    return key in ("lamp_pixels", "ref_lamp_mean") or key.endswith(
        tuple(f"_{name}" for name in LAMP_METRICS))


def pool_lamps(rows: list[dict[str, Any]]) -> dict[str, float | int]:
    """The rows' lamp entries (:func:`evaluate_denoiser`) pooled over every lamp pixel they
    score: ``lamp_pixels`` (their number, summed over rows: a crop scored at two spp levels
    counts twice), ``ref_lamp_mean`` and per prefix ``<prefix>_lamp_relmse`` (the mean
    per-pixel relMSE), ``<prefix>_lamp_mean`` and ``<prefix>_lamp_ratio`` (its mean over the
    reference's). Empty when no row has a lamp pixel (or the rows have no lamp entries)."""
    lit = [r for r in rows if r.get("lamp_pixels")]
    if not lit:
        return {}
    count = sum(r["lamp_pixels"] for r in lit)

    def pooled(key: str) -> float:
        return sum(r[key] * r["lamp_pixels"] for r in lit) / count

    out: dict[str, float | int] = {"lamp_pixels": count, "ref_lamp_mean": pooled("ref_lamp_mean")}
    prefixes = [k[: -len("_lamp_relmse")] for k in lit[0] if k.endswith("_lamp_relmse")]
    for prefix in prefixes:
        out[f"{prefix}_lamp_relmse"] = pooled(f"{prefix}_lamp_relmse")
        out[f"{prefix}_lamp_mean"] = pooled(f"{prefix}_lamp_mean")
        if out["ref_lamp_mean"] > 0:
            out[f"{prefix}_lamp_ratio"] = out[f"{prefix}_lamp_mean"] / out["ref_lamp_mean"]
    return out


def summarize(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Means over rows of every numeric ``<prefix>_<metric>`` column (PSNR: the mean of the
    per-image dB, as the paper averages; ``rmse_nc``: the root of the mean ``mse_nc``), then
    ``count``, then the lamp entries pooled over the rows' lamp pixels when there are any
    (:func:`pool_lamps`)."""
    keys = ([k for k in rows[0] if isinstance(rows[0][k], float) and not _is_lamp_entry(k)]
            if rows else [])
    out = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    for key in [k for k in keys if k.endswith("_mse_nc")]:
        out[key.replace("_mse_nc", "_rmse_nc")] = math.sqrt(max(out[key], 0.0))
    out["count"] = len(rows)
    return out | pool_lamps(rows)


#: The lamp columns of :func:`markdown`: (summary key, label, format, prefixed by the image).
LAMP_COLUMNS = (("lamp_relmse", "relMSE (lamps)", "{:.4f}", True),
                ("lamp_ratio", "lamp mean / reference", "{:.3f}", True),
                ("lamp_pixels", "lamp pixels", "{:d}", False))


def markdown(summaries: dict[str, dict[str, float]], prefixes=("den",)) -> str:
    """A table with one row per named summary: PSNR, SSIM, relMSE, FLIP, RMSE (noise-corr.),
    and, when a summary has lamp pixels (:func:`pool_lamps`), the :data:`LAMP_COLUMNS` with a
    line under the table saying what they measure."""
    columns = [("psnr", "PSNR (dB)", "{:.2f}", True), ("ssim", "SSIM", "{:.4f}", True),
               ("relmse", "relMSE", "{:.4f}", True), ("flip", "FLIP", "{:.4f}", True),
               ("rmse_nc", "RMSE (noise-corrected)", "{:.4f}", True)]
    lamps = any(s.get("lamp_pixels") for s in summaries.values())
    if lamps:
        columns += LAMP_COLUMNS
    lines = ["| method | " + " | ".join(c[1] for c in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for name, summary in summaries.items():
        for prefix in prefixes:
            label = name if len(prefixes) == 1 else f"{name} ({prefix})"
            keys = [(f"{prefix}_{key}" if prefixed else key, fmt)
                    for key, _, fmt, prefixed in columns]
            cells = [fmt.format(summary[key]) if key in summary else "" for key, fmt in keys]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    if lamps:
        lines += ["", ("Lamp pixels: those whose reference sees an emitter directly (its "
                       "emission > 0), pooled over the split's crops and spp levels; relMSE "
                       "(lamps) is their mean per-pixel relMSE, lamp mean / reference the mean "
                       "radiance over them against the reference's (linear HDR).")]
    return "\n".join(lines)


def dataset_label(path) -> str:
    return Path(str(path)).name


# ---------------------------------------------------------------------------- the evaluators
@dataclasses.dataclass(frozen=True)
class DenoiseOptions:
    """``denoiser``: a spec (``oidn``, a shipped name, a run folder); ``spp``: the input spp
    levels scored; ``include_input``: score the noisy input too (``mc_*``)."""

    denoiser: str = "oidn"
    split: str = "test"
    spp: tuple[int, ...] = (1,)
    include_input: bool = True


@dataclasses.dataclass(frozen=True)
class SequencesOptions:
    """``denoiser``: a spec; ``skip_frames``: leading frames of each sequence left out (no
    history yet); temporal accumulation with the default TemporalConfig."""

    denoiser: str = "oidn"
    skip_frames: int = 1


def sequence_provenance(data, split: str | None) -> dict:
    """The ``dataset`` entry of a result measured on a sequence set (checked)."""
    from jaxden.data.sequences import MANIFEST_NAME, read_manifest
    from jaxden.provenance import dataset_identity

    manifest = read_manifest(data)
    return dataset_identity(data, Path(data) / MANIFEST_NAME, manifest.get("config"), split)


def _label(provenance: dict) -> str:
    return denoiser_label(provenance["denoiser"]["spec"])


def _weights(options) -> dict:
    from jaxden.evaluate.shared import weights_identity

    return {"denoiser": weights_identity(options.denoiser)}


def _summary(rows, provenance) -> dict:
    return {"summary": summarize(rows)}


#: The metrics a sweep's summary shows, by their column labels.
#: A metric missing from a summary (the lamp relMSE of data without emitters) has no column.
SWEEP_METRICS = (("psnr", "PSNR"), ("ssim", "SSIM"), ("relmse", "relMSE"), ("flip", "FLIP"),
                 ("lamp_relmse", "lamp relMSE"))


def _sweep_columns(prefixes: dict[str, str]):
    """``sweep_columns`` showing the :data:`SWEEP_METRICS` of each summary prefix, labelled
    by ``prefixes[prefix]`` ("" for the plain label)."""
    def columns(summary: dict) -> dict[str, float]:
        return {" ".join(filter(None, (title, shown))): summary[f"{prefix}_{metric}"]
                for prefix, title in prefixes.items() for metric, shown in SWEEP_METRICS
                if f"{prefix}_{metric}" in summary}

    return columns


def check_sequence_set(data, table: dict) -> None:
    """The ``sweep_check`` of a sequence set: its manifest is there, readable and says the
    build finished (:func:`jaxden.data.sequences.read_manifest`'s DatasetError if not)."""
    from jaxden.data.sequences import read_manifest

    read_manifest(data)


DENOISE = Evaluator(
    name="denoise",
    description="PSNR, SSIM, relMSE, FLIP and noise-corrected RMSE of a denoiser per crop and "
                "spp (the WSKP paper's Tables 1/6), and relMSE on the lamp pixels when the "
                "frames carry the emission",
    options=DenoiseOptions,
    run=lambda data, options, progress=False: evaluate_denoiser(
        data, options.denoiser, split=options.split, spp=options.spp,
        include_input=options.include_input),
    summarize=_summary,
    table=lambda fields, rows, provenance: markdown(
        {_label(provenance): fields["summary"]},
        prefixes=("den", "mc") if provenance.get("include_input", True) else ("den",)),
    provenance=lambda options: {**_weights(options), "spp": list(options.spp),
                                "include_input": options.include_input},
    sweep_options=lambda run_dir, table: DenoiseOptions(
        denoiser=str(run_dir), split=table["split"], spp=tuple(table["denoise_spp"])),
    sweep_settings=(("split", str, "test"), ("denoise_spp", tuple[int, ...], (1,))),
    sweep_key="den",
    sweep_columns=_sweep_columns({"den": ""}),
)

SEQUENCES = Evaluator(
    name="sequences",
    description="the same per frame of camera-path sequences, frame by frame and after "
                "temporal accumulation",
    options=SequencesOptions,
    run=lambda data, options, progress=False: evaluate_sequences(
        data, options.denoiser, skip_frames=options.skip_frames),
    summarize=_summary,
    table=lambda fields, rows, provenance: markdown(
        {_label(provenance): fields["summary"]},
        prefixes=("mc", "den", "acc", "tdn",
                  *(("seq",) if "seq_rmse" in fields["summary"] else ()))),
    provenance=lambda options: {**_weights(options), "skip_frames": options.skip_frames},
    dataset=sequence_provenance,
    sweep_options=lambda run_dir, table: SequencesOptions(denoiser=str(run_dir)),
    sweep_check=check_sequence_set,
    sweep_key="seq",
    sweep_columns=_sweep_columns({"den": "", "tdn": "temporal", "seq": "own history"}),
)
