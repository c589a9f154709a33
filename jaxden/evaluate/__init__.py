"""Evaluation on held-out data: evaluators by name, one shape, writing results.

The floor above :mod:`jaxden.denoise`, :mod:`jaxden.sure`, :mod:`jaxden.progressive` and
:mod:`jaxden.data` (it imports them; they never import it). Each evaluator
(:class:`~jaxden.evaluate.evaluator.Evaluator`) measures one thing on a rendered test set and
is built from its options by name, by ``jaxden evaluate NAME`` and by a sweep's
``[evaluate]`` table alike, neither of which branches on the name:

- ``pd`` (:mod:`~jaxden.evaluate.pd`): progressive denoising against MC, the denoiser and the
  oracles, per spp (the paper's Table 3 / Fig. 10);
- ``oracle`` (:mod:`~jaxden.evaluate.oracle`): the 8 x 8-tile oracle and its alphas
  cross-fitted on an independent render;
- ``sure`` (:mod:`~jaxden.evaluate.sure`): SURE against the noise-corrected true MSE;
- ``sure-buffers`` (:mod:`~jaxden.evaluate.sure_buffers`): Stein SURE against sub-buffer SURE
  on fresh renders;
- ``denoise``, ``sequences`` (:mod:`~jaxden.evaluate.denoise`): a denoiser's PSNR, SSIM,
  relMSE, FLIP and noise-corrected RMSE per crop, or per frame with temporal accumulation.

An evaluator of a user's own is one more :class:`~jaxden.evaluate.evaluator.Evaluator`
passed to :func:`~jaxden.evaluate.registry.register_evaluator` in a plugin module
(:mod:`jaxden.plugins`): ``jaxden evaluate NAME --plugin FILE`` runs it (one flag per field of
its options dataclass) and, with ``sweep_options``, a sweep's ``[evaluate]`` table too.

A result is OUT.json (summary, rows, provenance: :mod:`jaxden.provenance`) and OUT.md (its
tables); "report" names only the HTML page of :mod:`jaxden.report`.
"""

from jaxden.evaluate.denoise import (
    DENOISE_METRICS,
    DenoiseOptions,
    SequencesOptions,
    evaluate_denoiser,
    evaluate_sequences,
    image_errors,
)
from jaxden.evaluate.evaluator import (
    Evaluator,
    dataset_provenance,
    evaluation_provenance,
    write_evaluation,
)
from jaxden.evaluate.oracle import (
    ORACLE_BLOCK,
    OracleOptions,
    oracle_alpha,
    oracle_mix,
    true_error,
)
from jaxden.evaluate.pd import (
    PD_METHODS,
    PD_METRICS,
    PDOptions,
    evaluate_progressive,
    markdown_progressive,
    noise_margin,
    resolve_mixer,
    result_is_current,
    summarize_progressive,
)
from jaxden.evaluate.registry import (
    EVALUATORS,
    evaluate_run,
    get_evaluator,
    make_options,
    register_evaluator,
)
from jaxden.evaluate.shared import denoiser_label, weights_identity
from jaxden.evaluate.sure import (
    SureOptions,
    markdown_sure,
    median_crop_checks,
    ratio_interval,
    summarize_sure,
    sure_accuracy,
)
from jaxden.evaluate.sure_buffers import (
    BUFFER_SEED_BASE,
    SureBuffersOptions,
    sure_accuracy_buffers,
)

__all__ = [
    "BUFFER_SEED_BASE",
    "DENOISE_METRICS",
    "EVALUATORS",
    "ORACLE_BLOCK",
    "PD_METHODS",
    "PD_METRICS",
    "DenoiseOptions",
    "Evaluator",
    "OracleOptions",
    "PDOptions",
    "SequencesOptions",
    "SureBuffersOptions",
    "SureOptions",
    "dataset_provenance",
    "denoiser_label",
    "evaluate_denoiser",
    "evaluate_progressive",
    "evaluate_run",
    "evaluate_sequences",
    "evaluation_provenance",
    "get_evaluator",
    "image_errors",
    "make_options",
    "markdown_progressive",
    "markdown_sure",
    "median_crop_checks",
    "noise_margin",
    "oracle_alpha",
    "oracle_mix",
    "ratio_interval",
    "register_evaluator",
    "resolve_mixer",
    "result_is_current",
    "summarize_progressive",
    "summarize_sure",
    "sure_accuracy",
    "sure_accuracy_buffers",
    "true_error",
    "weights_identity",
    "write_evaluation",
]
