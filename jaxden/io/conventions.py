"""Channel conventions of other renderers: which EXR channels hold a Frame's colour, albedo,
normal, depth and variance, what the variance means, and where the sample count is written.

One table, :data:`CONVENTIONS`, used by :func:`jaxden.io.exr.read_frame` (``convention=``)
and the command line's ``--from``. Each field lists the channel-name sets the renderer is
known to write, most usual first; the first set present in a file is used. ``{layer}`` stands
for a render layer's name (Blender's view layer, ``ViewLayer`` by default): it is found from
the layer's colour pass, and must be named (``layer=``, ``--layer``) when a file holds
several. Explicit channel names (``channel_map``, ``--channels``) win over a convention.

A renderer that writes one file per output (Falcor) has a ``file_pattern``: the file named
on the command line is any one of a capture's files, and its siblings (same folder, prefix
and frame number) are read with it (:mod:`jaxden.io.siblings`); a sibling's channels are
named ``<output>.<channel>``, e.g. ``AccumulatePass.output.R``.

=========  ==================  =================================  ===========================
renderer   file layout         colour / albedo / normal / depth   variance
=========  ==================  =================================  ===========================
jaxden     one EXR             R,G,B / albedo.* / normal.* /      variance.*: of the mean
                               depth.Z
cycles     multilayer EXR      {layer}.Noisy Image.* (a denoised  none: jaxden merge
                               render), else Combined.* /
                               Denoising Albedo, Diffuse Color
                               or DiffCol / Denoising Normal or
                               Normal / Denoising Depth or
                               Depth.Z
pbrt-v4    one EXR (film       R,G,B / Albedo.* / Ns.* (camera    none read: Variance.* is
           "gbuffer")          space unless coordinatesystem      per sample, of the sensor's
                               "world") / P.Z (camera space)      XYZ, over hits only
mitsuba    one EXR (aov        R,G,B / albedo.* / sh_normal.* /   none: jaxden merge
           integrator)         depth.T
falcor     one EXR (PNG for    AccumulatePass.output or           none: jaxden merge
           8-bit outputs) per  PathTracer.color / PathTracer.
           render-graph        albedo or GBuffer diffuseOpacity
           output              / PathTracer.guideNormal or
                               GBuffer normW (world space) /
                               GBuffer linearZ
=========  ==================  =================================  ===========================

docs/renderers.md has the full table, with how to get a variance from each renderer.

A renderer that can write a denoised image beside the raw one (Cycles with Render Properties
> Sampling > Render > Denoise on: ``Combined`` is denoised, ``Noisy Image`` is the raw Monte
Carlo mean) reads the raw one as the colour; :attr:`Convention.denoised_colour` names the other,
which nothing merges into a variance (:func:`jaxden.io.exr.read_frame`'s ``refuse_denoised``).
A per-pixel sample-count pass (Cycles' ``Debug Sample Count``: each pixel's samples over the
most any pixel took) shows adaptive sampling, under which the header's count is not every
pixel's (:attr:`Convention.sample_fraction`). ``Convention.how_to`` says, in the renderer's
own terms, how to make it write a field or change a setting, for messages.

An albedo is a reflectance in [0, 1] to every denoiser (WSKP divides the colour by it and
multiplies the filtered irradiance back; OIDN clips it to [0, 1]), but Cycles' Denoising
Albedo also holds the light its camera paths see: on a pixel that sees a lamp it is the
Emission pass plus the surface's albedo (values up to the lamp's strength), where it sees
the sky the Environment pass, and light met through near-specular surfaces, weighted by
their colour (Cycles' ``film_write_emission_or_background_pass`` adds every emission or
background contribution to the Denoising Albedo while the path still gathers denoising
features). :attr:`Convention.albedo_includes_emission` names such albedo channels; they are
read clipped to [0, 1], as OIDN and Blender's own denoiser read them: a pixel that sees a
lamp gets albedo 1 (white), not the lamp's strength. Measured on two Cycles scenes with a lamp
in view (``experiments/results/renderers/cycles-emission.md``), the clip serves OIDN better
than the surfaces' own albedo (the Denoising Albedo minus the Emission pass) and WSKP-6 with
``:emission=separate`` as well; the raw values made WSKP-6 brighten the lamp.

Checked against files the renderers wrote: Blender 5.0.1 Cycles (``bpy`` from PyPI, multilayer
EXR with every pass a user may enable, denoised and adaptive renders among them:
``experiments/renderers/cycles_fixtures.py``, ``tests/data/cycles/``; the older pass names
``Emit`` and ``DiffCol`` from Blender's source, ``RE_PASSNAME_*``) and Mitsuba 3
(the ``aov`` integrator's film, AOVs named as below). pbrt-v4 from its source
(``src/pbrt/film.cpp``, ``GBufferFilm::AddSample`` and ``GetImage``: its channels, and
``Variance.*`` as a Welford estimate of the per-sample variance of the sensor's values (CIE
XYZ with the default ``cie1931`` sensor) over the samples that hit a surface, so not the
variance of the written R,G,B; ``src/pbrt/util/image.cpp``: the ``samplesPerPixel``
attribute). Falcor from its source (``Source/Mogwai/Extensions/Capture/FrameCapture.cpp``
and ``CaptureTrigger.cpp``: file names; ``Source/Falcor/Utils/Image/Bitmap.cpp`` with
FreeImage's EXR writer: channels R,G,B as half floats, PIZ-compressed, and PNG for 8-bit
outputs; the pass outputs in ``Source/RenderPasses/PathTracer``, ``GBuffer`` and
``AccumulatePass``).
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

#: The header attribute (``jaxden.written_by_jaxden``) of every file jaxden writes.
WRITTEN_BY_JAXDEN = "written_by_jaxden"


@dataclasses.dataclass(frozen=True)
class Convention:
    """One renderer's EXR layout (see the module docstring)."""

    name: str
    fields: Mapping[str, tuple[tuple[str, ...], ...]]
    variance: str  # one of VARIANCE_KINDS
    spp_attributes: tuple[str, ...] = ()  # header attributes holding the sample count
    layer_pass: str | None = None  # the colour pass that names a layer ("{layer}.Combined")
    note: str = ""
    #: One file per output: a regular expression of the file names with the groups
    #: ``prefix``, ``output``, ``frame``, ``ext`` and (optional) ``mask``
    #: (:mod:`jaxden.io.siblings`); None: one file holds the frame.
    file_pattern: str | None = None
    file_example: str = ""  # a file name the pattern matches, for messages
    #: Depth at or above this (+inf included) is a miss, read as jaxden's 0 (None: as stored).
    depth_miss: float | None = None
    #: Channels of the renderer's denoised image, when the raw one (``fields["color"][0]``)
    #: is beside them in a file: never merged into a variance.
    denoised_colour: tuple[str, ...] = ()
    #: A channel holding each pixel's sample count over the most any pixel took (adaptive
    #: sampling when below 1 somewhere); None: the renderer writes none.
    sample_fraction: str | None = None
    #: How to make the renderer write a field (keyed by field) or turn off a setting (keys
    #: "denoise", "adaptive", "file"), in its own terms, for messages.
    how_to: Mapping[str, str] = dataclasses.field(default_factory=dict)
    #: Albedo channel sets (among ``fields["albedo"]``) that hold the light the renderer's
    #: camera paths see besides the surfaces' reflectance (Blender's Denoising Albedo: the
    #: emission of the lamps it sees): read clipped to [0, 1] (module docstring).
    albedo_includes_emission: tuple[tuple[str, ...], ...] = ()


@dataclasses.dataclass(frozen=True)
class Reading:
    """What a convention makes of one file (:func:`resolve`).

    ``mapping``: field -> the file's channels for it (the fields the file has);
    ``spp``: the header's sample count (None: none there); ``variance``: one of
    :data:`VARIANCE_KINDS`; ``layer``: the render layer read (None: not layered);
    ``denoised``: the channels of a denoised image beside the raw colour (empty: none);
    ``sample_fraction``: the channel of a per-pixel sample-count pass (None: none)."""

    mapping: dict[str, tuple[str, ...]]
    spp: float | None
    variance: str
    layer: str | None = None
    denoised: tuple[str, ...] = ()
    sample_fraction: str | None = None


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
        layer_pass="Combined", depth_miss=1e10,  # the Z pass's misses
        fields={"color": (_rgb("{layer}.Noisy Image."), _rgb("{layer}.Combined.")),
                "albedo": (_rgb("{layer}.Denoising Albedo."), _rgb("{layer}.Diffuse Color."),
                           _rgb("{layer}.DiffCol.")),
                "normal": (_xyz("{layer}.Denoising Normal."), _xyz("{layer}.Normal.")),
                "depth": (("{layer}.Denoising Depth.Z",), ("{layer}.Depth.Z",)),
                "position": (_xyz("{layer}.Position."),),
                "emission": (_rgb("{layer}.Emission."), _rgb("{layer}.Emit."))},
        denoised_colour=_rgb("{layer}.Combined."),
        sample_fraction="{layer}.Debug Sample Count.X",
        albedo_includes_emission=(_rgb("{layer}.Denoising Albedo."),),
        how_to={
            "color": "enable View Layer Properties > Passes > Data > Combined",
            "albedo": "enable View Layer Properties > Passes > Data > Denoising Data (or "
                      "Passes > Light > Diffuse > Color)",
            "normal": "enable View Layer Properties > Passes > Data > Denoising Data (or "
                      "Passes > Data > Normal)",
            "depth": "enable View Layer Properties > Passes > Data > Denoising Data (or "
                     "Passes > Data > Z)",
            "position": "enable View Layer Properties > Passes > Data > Position",
            "emission": "enable View Layer Properties > Passes > Light > Emission",
            "denoise": "turn off Render Properties > Sampling > Render > Denoise",
            "adaptive": "turn off Render Properties > Sampling > Render > Noise Threshold "
                        "(adaptive sampling)",
            "file": "save a multilayer EXR: Output Properties > Output > Media Type: "
                    "Multi-Layer EXR (before Blender 5.0: File Format: OpenEXR MultiLayer)"},
        note="multilayer EXR, one part per pass; no variance: merge K renders (jaxden merge)"),
    "pbrt-v4": Convention(
        name="pbrt-v4", variance="none", spp_attributes=("samplesPerPixel",),
        fields={"color": (_rgb(""),), "albedo": (_rgb("Albedo."),),
                "normal": (_xyz("Ns."), _xyz("N.")), "depth": (("P.Z",),),
                "position": (_xyz("P."),)},
        note="film \"gbuffer\": Ns, P in camera space unless \"string coordinatesystem\" "
             "\"world\" (depth = P.Z of camera space); its Variance.R/G/B is the per-sample "
             "variance of the sensor's values (CIE XYZ by default) over the samples that hit "
             "a surface, not of R,G,B: merge K renders (jaxden merge), or read it anyway as "
             "the variance, named Variance.R,Variance.G,Variance.B and taken as a per-sample "
             "variance"),
    "mitsuba": Convention(
        name="mitsuba", variance="none",
        fields={"color": (_rgb(""),),
                "albedo": (_rgb("albedo."),),
                "normal": (_xyz("sh_normal."), _xyz("nn."), _xyz("normal.")),
                "depth": (("depth.T",), ("dd.T",), ("depth.Y",), ("dd.Y",))},
        note="aov integrator with aovs=\"albedo:albedo,sh_normal:sh_normal,depth:depth\"; "
             "no variance: merge K renders"),
    "falcor": Convention(
        name="falcor", variance="none",
        file_pattern=(r"^(?P<prefix>.*)\.(?P<output>[^.]+\.[^.]+)\.(?P<frame>[0-9]+)"
                      r"(?:\.(?P<mask>RGBA|R|G|B|A))?\.(?P<ext>exr|png)$"),
        file_example="Mogwai.AccumulatePass.output.256.exr",
        depth_miss=1e8,  # GBufferRT's kEnvMapDepth; +inf once stored as half
        fields={"color": (_rgb("AccumulatePass.output."), _rgb("PathTracer.color.")),
                "albedo": (_rgb("PathTracer.albedo."), _rgb("GBufferRT.diffuseOpacity."),
                           _rgb("GBufferRaster.diffuseOpacity.")),
                "normal": (_rgb("PathTracer.guideNormal."), _rgb("GBufferRT.normW."),
                           _rgb("GBufferRaster.normW."), _rgb("GBufferRT.guideNormalW."),
                           _rgb("GBufferRaster.guideNormalW.")),
                "depth": (("GBufferRT.linearZ.R",), ("GBufferRaster.linearZ.R",)),
                "position": (_rgb("GBufferRT.posW."), _rgb("GBufferRaster.posW."))},
        note="Mogwai frame capture, one file per marked output (<prefix>.<pass>.<output>."
             "<frame>.exr); world-space normals; no variance: capture K independent "
             "accumulations and merge them (jaxden merge --from falcor)"),
}


def _layers(convention: Convention, present: Iterable[str]) -> list[str]:
    """Layer names of a layered file: prefixes of ``{layer}.<colour pass>.R``."""
    pattern = re.compile(rf"^(.+)\.{re.escape(convention.layer_pass)}\.R$")
    return sorted({m.group(1) for name in present if (m := pattern.match(name))})


def resolve(name: str, present: Iterable[str], header: Mapping[str, Any], *,
            layer: str | None = None, where: str = "") -> Reading:
    """What convention ``name`` makes of the file whose channels are ``present`` and whose
    header is ``header``: a :class:`Reading` (its channel map, sample count, variance kind,
    layer, denoised channels and sample-count pass).

    Raises ExrError for an unknown convention (with a close match suggested), a layered
    file whose layer is ambiguous or missing (a single-layer file told how to save a
    layered one), and a header sample count that is no number.
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
                raise ExrError(prefix + _layer_problem(convention, layers, present))
            layer = layers[0]
        elif layer not in layers:
            raise ExrError(f"{prefix}no render layer {layer!r}; layers: "
                           f"{', '.join(layers) or 'none'}")

    def named(names):
        return tuple(n.replace("{layer}", layer or "") for n in names)

    mapping = {}
    for field, candidates in convention.fields.items():
        for names in map(named, candidates):
            if set(names) <= present:
                mapping[field] = names
                break
    denoised = named(convention.denoised_colour)
    if not (denoised and set(named(convention.fields["color"][0])) <= present
            and set(denoised) <= present):
        denoised = ()
    fraction = None
    if convention.sample_fraction is not None:
        fraction = named((convention.sample_fraction,))[0]
        fraction = fraction if fraction in present else None
    spp = None
    for key in convention.spp_attributes:
        value = header.get(key.replace("{layer}", layer or ""))
        if value is not None:
            spp = header_number(value, f"{prefix}header attribute {key}")
            break
    return Reading(mapping, spp, convention.variance, layer, denoised, fraction)


def _layer_problem(convention: Convention, layers: list[str], present: set[str]) -> str:
    """Why a layered file's layer cannot be chosen: several layers, no colour pass in a
    file of passes, or a single-layer file (plain channel names)."""
    colour = f"<layer>.{convention.layer_pass}.R"
    if layers:
        return (f"a {convention.name} file names its render layer in every channel "
                f"('{colour}'); layers found: {', '.join(layers)}; choose one with --layer")
    shown = ", ".join(sorted(present)[:8]) + (", ..." if len(present) > 8 else "")
    passes = sorted({n.rsplit(".", 1)[0] for n in present if n.count(".") >= 2})
    if passes:
        return (f"no '{colour}' channel among its passes ({', '.join(passes[:8])}): "
                + convention.how_to.get("color", f"write the {convention.layer_pass} pass"))
    return (f"a single-layer EXR (channels {shown or 'none'}), but a {convention.name} file "
            f"is a multilayer EXR with a part per pass ('{colour}', ...); "
            + convention.how_to.get("file", "save a multilayer EXR"))


def header_number(value: Any, what: str) -> float:
    """A header attribute's ``value`` as a float; ExrError "``what`` is not a number" if it
    is none (a string, a vector, ...)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ExrError(f"{what} is not a number: {value!r}") from None


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
