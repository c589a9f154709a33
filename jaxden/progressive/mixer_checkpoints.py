"""Mixer checkpoints: the meta record (:func:`mixer_meta`), released weights
(:func:`save_mixer`) and loading any mixer spec (:func:`load_mixer`: a training run, a
.msgpack file, shipped weights, the closed form)."""

from __future__ import annotations

import jax

from jaxden.errors import ConfigError
from jaxden.progressive.mixer_config import (
    CLOSED_FORM_SPEC,
    MixerConfig,
    closed_form_mixer,
    mixer_layout,
    upgrade_mixer_config,
)
from jaxden.progressive.network import mixer_init

#: The ``kind`` and ``model`` of a mixer checkpoint's meta record.
MIXER_KIND = "mixer"
MIXER_MODEL = "mixer"


def mixer_meta(config: MixerConfig) -> dict:
    """The meta record of a mixer's checkpoint: what it is, its config and its layout."""
    from jaxden.config import config_to_dict

    return {
        "kind": MIXER_KIND,
        "model": MIXER_MODEL,
        "model_config": config_to_dict(config),
        "layout": mixer_layout(config),
    }


def save_mixer(path, params, config: MixerConfig, **extra_meta) -> None:
    """Write released mixer weights: ``path`` (.msgpack) and its .json meta record (atomic).

    ``extra_meta``: anything worth recording (training steps, dataset, measured metrics).
    """
    from jaxden.checkpoint import save_weights

    save_weights(path, params, {**extra_meta, **mixer_meta(config)})


def load_mixer(spec, *, expect_features: tuple[str, ...] | None = None):
    """``(params, config)`` of a trained mixer.

    ``spec``: a training workdir or checkpoint folder of ``jaxden train`` with ``model =
    "mixer"``, a released ``.msgpack`` file (with its .json), the name of weights shipped in
    ``jaxden/weights/<name>.msgpack``, or ``closed-form[:KEY=VALUE,...]`` for the mixer
    without weights (:func:`~jaxden.progressive.mixer_config.closed_form_mixer`; params
    ``{}``). ``expect_features``: the input layout the caller needs. A record written before
    the SURE settings were one table loads the same
    (:func:`~jaxden.progressive.mixer_config.upgrade_mixer_config`).

    Raises CheckpointError naming the difference when the checkpoint is not a mixer (e.g. a
    denoiser checkpoint), its config is not a valid :class:`MixerConfig`, its recorded input
    layout differs from what this jaxden builds for that config, its features differ from
    ``expect_features``, or a parameter's shape does not fit the config.
    """
    from pathlib import Path

    from jaxden.checkpoint import load_trained_params, read_checkpoint_meta
    from jaxden.config import config_diff, load_config
    from jaxden.errors import CheckpointError

    if isinstance(spec, str) and spec.partition(":")[0] == CLOSED_FORM_SPEC:
        return closed_form_mixer(spec)
    from jaxden.paths import resolve_weights

    path = resolve_weights(spec) or Path(spec)
    if not path.exists():
        raise CheckpointError(
            f"mixer {spec}: no such checkpoint folder or weights file (train one with "
            f"`jaxden train` and a config with model = \"mixer\")"
        )
    meta = read_checkpoint_meta(path)
    if meta.get("kind") != MIXER_KIND:
        raise CheckpointError(
            f"{path}: holds a {meta.get('kind', 'unknown')!r} checkpoint (model "
            f"{meta.get('model')!r}), not a mixer; a denoiser goes to --denoiser"
        )
    try:
        config = load_config(upgrade_mixer_config(meta.get("model_config", {})), MixerConfig)
    except ConfigError as error:
        raise CheckpointError(
            f"{path}: its model_config is not a valid mixer config: {error}"
        ) from None
    layout = mixer_layout(config)
    stored = meta.get("layout")
    if stored is not None:
        differences = config_diff(stored, layout)
        if differences:
            raise CheckpointError(
                f"{path}: the recorded mixer input layout differs from the one this jaxden "
                f"builds for its config (stored -> built): {'; '.join(differences)}"
            )
    if expect_features is not None and tuple(expect_features) != tuple(config.features):
        raise CheckpointError(
            f"{path}: the mixer was trained on features {list(config.features)}, expected "
            f"{list(expect_features)}"
        )
    # Shapes only: the loader checks names and shapes against it and fills in the values.
    target = jax.eval_shape(lambda: mixer_init(jax.random.PRNGKey(0), config))
    expect = {"kind": MIXER_KIND, "model": MIXER_MODEL}
    params, _ = load_trained_params(path, target, expect=expect)
    return params, config
