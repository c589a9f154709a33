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
  against the true image when the reference is an independent render), and ``rmse``.

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


def _denoiser(spec):
    from jaxden.denoise.registry import Denoiser, load_denoiser

    return spec if isinstance(spec, Denoiser) else load_denoiser(spec)


def evaluate_denoiser(dataset_dir, denoiser, *, split: str = "test", spp=(1,),
                      include_input: bool = True) -> list[dict[str, Any]]:
    """One row per (crop, spp) of ``split`` (``all``: every crop): the denoiser's errors
    (``den_<metric>``) and, with ``include_input``, the noisy input's (``mc_<metric>``).

    ``denoiser``: a :class:`jaxden.denoise.Denoiser` or a spec for ``load_denoiser`` (a
    registered black box such as ``oidn``, a shipped name, a run folder).
    """
    model = _denoiser(denoiser)
    rows = []
    for crop, reference, inputs in iter_crops(dataset_dir, split, tuple(spp), min_spp=1):
        for level, frame in inputs:
            row: dict[str, Any] = {"crop": crop.id, "scene": crop.scene, "spp": level}
            row |= {f"den_{k}": v for k, v in image_errors(model(frame), reference).items()}
            if include_input:
                row |= {f"mc_{k}": v for k, v in image_errors(frame.color, reference).items()}
            rows.append(row)
    return rows


def evaluate_sequences(sequence_dir, denoiser, *, temporal=None,
                       skip_frames: int = 1) -> list[dict[str, Any]]:
    """One row per frame of every sequence of a set built by ``jaxden dataset sequences``:
    errors of the denoiser on the frame alone (``den_*``) and on the temporally accumulated
    input (``tdn_*``: :func:`jaxden.denoise.temporal.accumulate` with ``temporal``, a
    :class:`~jaxden.denoise.temporal.TemporalConfig`), and of the two inputs (``mc_*``,
    ``acc_*``). The first ``skip_frames`` frames (no history yet) are left out of the rows.
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
        history = None
        for t, (frame, reference) in enumerate(zip(frames, references)):
            if history is None:
                history, accumulated = start_history(frame), np.asarray(frame.color)
            else:
                accumulated, history = step(history, frame)
            if t < skip_frames:
                continue
            acc_frame = frame.replace(color=np.asarray(accumulated, np.float32))
            row: dict[str, Any] = {"sequence": key, "frame": t}
            for prefix, image in (("mc", frame.color), ("den", model(frame)),
                                  ("acc", acc_frame.color), ("tdn", model(acc_frame))):
                row |= {f"{prefix}_{k}": v for k, v in image_errors(image, reference).items()}
            rows.append(row)
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Means over rows of every numeric ``<prefix>_<metric>`` column (PSNR: the mean of the
    per-image dB, as the paper averages; ``rmse_nc``: the root of the mean ``mse_nc``)."""
    keys = [k for k in rows[0] if isinstance(rows[0][k], float)] if rows else []
    out = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    for key in [k for k in keys if k.endswith("_mse_nc")]:
        out[key.replace("_mse_nc", "_rmse_nc")] = math.sqrt(max(out[key], 0.0))
    out["count"] = len(rows)
    return out


def markdown(summaries: dict[str, dict[str, float]], prefixes=("den",)) -> str:
    """A table with one row per named summary: PSNR, SSIM, relMSE, FLIP, RMSE (noise-corr.)."""
    columns = [("psnr", "PSNR (dB)", "{:.2f}"), ("ssim", "SSIM", "{:.4f}"),
               ("relmse", "relMSE", "{:.4f}"), ("flip", "FLIP", "{:.4f}"),
               ("rmse_nc", "RMSE (noise-corrected)", "{:.4f}")]
    lines = ["| method | " + " | ".join(c[1] for c in columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for name, summary in summaries.items():
        for prefix in prefixes:
            label = name if len(prefixes) == 1 else f"{name} ({prefix})"
            cells = [fmt.format(summary[f"{prefix}_{key}"]) if f"{prefix}_{key}" in summary
                     else "" for key, _, fmt in columns]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
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
SWEEP_METRICS = (("psnr", "PSNR"), ("ssim", "SSIM"), ("relmse", "relMSE"), ("flip", "FLIP"))


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
                "spp (the WSKP paper's Tables 1/6)",
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
        {_label(provenance): fields["summary"]}, prefixes=("mc", "den", "acc", "tdn")),
    provenance=lambda options: {**_weights(options), "skip_frames": options.skip_frames},
    dataset=sequence_provenance,
    sweep_options=lambda run_dir, table: SequencesOptions(denoiser=str(run_dir)),
    sweep_check=check_sequence_set,
    sweep_key="seq",
    sweep_columns=_sweep_columns({"den": "", "tdn": "temporal"}),
)
