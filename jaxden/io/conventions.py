"""Channel conventions of other renderers: which EXR channels hold a Frame's colour, albedo,
normal, depth and variance, what the variance means, and where the sample count is written.

One table, :data:`CONVENTIONS`, used by :func:`jaxden.io.exr.read_frame` (``convention=``)
and the command line's ``--from``. Each field lists the channel-name sets the renderer is
known to write, most usual first; the first set present in a file is used. ``{layer}`` stands
for a render layer's name (Blender's view layer, ``ViewLayer`` by default): it is found from
the layer's colour pass, and must be named (``layer=``, ``--layer``) when a file holds
several. Explicit channel names (``channel_map``, ``--channels``) win over a convention.

Checked against files the renderers wrote: Blender 5.0 Cycles (``bpy`` from PyPI, multilayer
EXR with the Denoising Data passes; ``experiments/renderers/cycles_render.py``) and Mitsuba 3
(the ``aov`` integrator's film, AOVs named as below). pbrt-v4 from its ``GBufferFilm``
source (``src/pbrt/film.cpp``: channels, variance per sample from a Welford estimator;
``src/pbrt/util/image.cpp``: the ``samplesPerPixel`` attribute).
"""

from __future__ import annotations

import dataclasses
import difflib
import re
from collections.abc import Iterable, Mapping
from typing import Any

from jaxden.errors import ExrError

#: What a file's variance channels hold: the variance of the pixel mean (what jaxden uses),
#: the per-sample variance (divided by the sample count on reading), or none written.
VARIANCE_KINDS = ("mean", "sample", "none")


@dataclasses.dataclass(frozen=True)
class Convention:
    """One renderer's EXR layout (see the module docstring)."""

    name: str
    fields: Mapping[str, tuple[tuple[str, ...], ...]]
    variance: str  # one of VARIANCE_KINDS
    spp_attributes: tuple[str, ...] = ()  # header attributes holding the sample count
    layer_pass: str | None = None  # the colour pass that names a layer ("{layer}.Combined")
    note: str = ""


def _xyz(prefix: str) -> tuple[str, str, str]:
    return tuple(f"{prefix}{c}" for c in "XYZ")


def _rgb(prefix: str) -> tuple[str, str, str]:
    return tuple(f"{prefix}{c}" for c in "RGB")


CONVENTIONS: dict[str, Convention] = {
    "jaxden": Convention(
        name="jaxden", variance="mean", spp_attributes=("spp",),
        fields={"color": (_rgb(""),), "variance": (_rgb("variance."),),
                "albedo": (_rgb("albedo."),), "normal": (_xyz("normal."),),
                "depth": (("depth.Z",),), "position": (_xyz("position."),),
                "motion": (("motion.X", "motion.Y"),),
                "covariance": (("covariance.RG", "covariance.GB", "covariance.BR"),),
                "emission": (_rgb("emission."),)},
        note="jaxden render and jaxden merge: variance of the mean, jaxden.spp"),
    "cycles": Convention(
        name="cycles", variance="none", spp_attributes=("cycles.{layer}.samples",),
        layer_pass="Combined",
        fields={"color": (_rgb("{layer}.Combined."),),
                "albedo": (_rgb("{layer}.Denoising Albedo."), _rgb("{layer}.DiffCol.")),
                "normal": (_xyz("{layer}.Denoising Normal."), _xyz("{layer}.Normal.")),
                "depth": (("{layer}.Denoising Depth.Z",), ("{layer}.Depth.Z",)),
                "position": (_xyz("{layer}.Position."),),
                "emission": (_rgb("{layer}.Emit."),)},
        note="multilayer EXR, one part per pass; no variance: merge K renders (jaxden merge)"),
    "pbrt-v4": Convention(
        name="pbrt-v4", variance="sample", spp_attributes=("samplesPerPixel",),
        fields={"color": (_rgb(""),), "variance": (_rgb("Variance."),),
                "albedo": (_rgb("Albedo."),),
                "normal": (("Nsx", "Nsy", "Nsz"), _xyz("Ns."), ("Nx", "Ny", "Nz"), _xyz("N.")),
                "depth": (("Pz",), ("P.Z",)),
                "position": (("Px", "Py", "Pz"), _xyz("P."))},
        note="film \"gbuffer\": shading normal, camera-space position (depth = Pz), "
             "per-sample variance"),
    "mitsuba": Convention(
        name="mitsuba", variance="none",
        fields={"color": (_rgb(""),),
                "albedo": (_rgb("albedo."),),
                "normal": (_xyz("sh_normal."), _xyz("nn."), _xyz("normal.")),
                "depth": (("depth.T",), ("dd.T",), ("depth.Y",), ("dd.Y",))},
        note="aov integrator with aovs=\"albedo:albedo,sh_normal:sh_normal,depth:depth\"; "
             "no variance: merge K renders"),
}


def _layers(convention: Convention, present: Iterable[str]) -> list[str]:
    """Layer names of a layered file: prefixes of ``{layer}.<colour pass>.R``."""
    pattern = re.compile(rf"^(.+)\.{re.escape(convention.layer_pass)}\.R$")
    return sorted({m.group(1) for name in present if (m := pattern.match(name))})


def resolve(name: str, present: Iterable[str], header: Mapping[str, Any], *,
            layer: str | None = None, where: str = "") -> tuple[dict, float | None, str]:
    """The channel map, sample count (None: not in the header) and variance kind that
    convention ``name`` gives the file whose channels are ``present``.

    Raises ExrError for an unknown convention (with a close match suggested), a layered
    file whose layer is ambiguous or missing, and a header sample count that is no number.
    """
    convention = CONVENTIONS.get(name)
    if convention is None:
        close = difflib.get_close_matches(name.lower(), list(CONVENTIONS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ExrError(f"unknown renderer convention {name!r}{hint}; known: "
                       f"{', '.join(CONVENTIONS)}")
    present = set(present)
    prefix = f"{where}: " if where else ""
    if convention.layer_pass is not None:
        layers = _layers(convention, present)
        if layer is None:
            if len(layers) != 1:
                found = ", ".join(layers) if layers else "none"
                raise ExrError(
                    f"{prefix}a {name} file names its render layer in every channel "
                    f"('<layer>.{convention.layer_pass}.R'); layers found: {found}"
                    + ("; choose one with --layer" if layers else ""))
            layer = layers[0]
        elif layer not in layers:
            raise ExrError(f"{prefix}no render layer {layer!r}; layers: "
                           f"{', '.join(layers) or 'none'}")
    mapping = {}
    for field, candidates in convention.fields.items():
        for names in candidates:
            names = tuple(n.replace("{layer}", layer or "") for n in names)
            if set(names) <= present:
                mapping[field] = names
                break
    spp = None
    for key in convention.spp_attributes:
        value = header.get(key.replace("{layer}", layer or ""))
        if value is not None:
            try:
                spp = float(value)
            except (TypeError, ValueError):
                raise ExrError(f"{prefix}header attribute {key} is not a number: "
                               f"{value!r}") from None
            break
    return mapping, spp, convention.variance


def case_hints(missing: Iterable[str], present: Iterable[str]) -> str:
    """"; did you mean ..." for missing channel names that a present one matches under another
    case or closely (empty when none does)."""
    present = sorted(set(present))
    lowered = {name.lower(): name for name in present}
    hints = []
    for name in missing:
        match = lowered.get(name.lower())
        if match is None:
            close = difflib.get_close_matches(name, present, n=1, cutoff=0.8)
            match = close[0] if close else None
        if match is not None:
            hints.append(f"{match!r} for {name!r}")
    return f"; did you mean {', '.join(hints)}?" if hints else ""
