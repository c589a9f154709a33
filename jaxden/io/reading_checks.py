"""What a renderer's file says about itself, checked while :func:`jaxden.io.exr.read_frame`
reads it: a denoised colour (Cycles' Denoise), adaptive sampling (a sample-count pass that
differs between pixels), an albedo that carries light (Cycles' Denoising Albedo) or lies above
1, a renderer's miss depth, and the one-line message for passes a file lacks, in the
renderer's own terms (:mod:`jaxden.io.conventions`)."""

from __future__ import annotations

import sys

import numpy as np

from jaxden.errors import ExrError
from jaxden.io.conventions import WRITTEN_BY_JAXDEN


def check_denoised(path, header, mapping, reading, convention, refuse, on_note) -> None:
    """Refuse (``refuse``) or note a denoised colour: a renderer's denoised pass named by
    ``channel_map`` while its raw pass is beside it, or an image jaxden's denoisers wrote."""
    from jaxden.io.conventions import CONVENTIONS

    if header.get(WRITTEN_BY_JAXDEN) and header.get("denoiser") is not None and refuse:
        raise ExrError(f"{path}: an image denoised by {header['denoiser']} (written by jaxden "
                       f"denoise or progressive): its spread over renders is no variance; "
                       f"merge the renders themselves")
    if reading is None or not reading.denoised:
        return
    rule = CONVENTIONS[convention]
    raw = rule.fields["color"][0][0].rsplit(".", 1)[0].replace("{layer}", reading.layer or "")
    denoised = reading.denoised[0].rsplit(".", 1)[0]
    colour = tuple(mapping["color"])
    if colour == reading.denoised:
        if refuse:
            raise ExrError(
                f"{path}: the colour named ({denoised}) is the renderer's denoised image (the "
                f"file has the raw one, {raw}, beside it): its spread over renders is no "
                f"variance; drop --channels color to read {raw}, or "
                f"{rule.how_to.get('denoise', 'turn the denoiser off')} and render again")
        if on_note is not None:
            on_note(f"the colour is {denoised}, the renderer's denoised image, as named; "
                    f"the raw one is {raw}")
    elif on_note is not None and colour == reading.mapping["color"]:
        on_note(f"a denoised render: the colour read is its raw Monte Carlo mean, {raw}, not "
                f"the denoised {denoised}")


def adaptive_sampling(path, header, fraction, convention, spp, spp_override, on_note):
    """The header without its sample count when the sample-count pass ``fraction`` (each
    pixel's samples over the most any pixel took) shows that pixels took different counts
    (adaptive sampling); an ExrError when a count was given for such a render."""
    from jaxden.io.conventions import CONVENTIONS

    short = np.asarray(fraction) < np.float32(1 - 1e-6)
    if not short.any():
        return header
    share = float(short.mean())
    said = header.get("spp")
    setting = CONVENTIONS[convention].how_to.get("adaptive", "turn off adaptive sampling")
    if spp is not None and not spp_override:
        raise ExrError(
            f"{path}: rendered with adaptive sampling: its sample-count pass says {share:.0%} "
            f"of the pixels took fewer samples than the most, so no one count ({spp:g}) holds "
            f"for every pixel; {setting} and render again")
    if on_note is not None:  # the same words for every file, so that a caller can group them
        on_note("rendered with adaptive sampling (its sample-count pass differs between "
                "pixels): no one sample count holds for every pixel, so the header's"
                + ("" if said is None else f" {float(said):g}") + " is not used")
    return {key: value for key, value in header.items() if key != "spp"}


#: Above this an albedo is no reflectance (float rounding of a white surface stays below).
ALBEDO_LIMIT = 1.001
_warned: set[str] = set()  # warnings printed in this process (a dataset's files repeat them)


def warn_once(path, line: str, key: str) -> None:
    """One ``jaxden: warning:`` line on stderr the first time this process meets ``key``."""
    if key in _warned:
        return
    _warned.add(key)
    print(f"jaxden: warning: {path}: {line}", file=sys.stderr, flush=True)


def read_albedo(path, all_channels, mapping, convention, layer) -> np.ndarray:
    """The albedo field, (H, W, 3), a reflectance in [0, 1]. Channels that a convention's
    renderer adds the light its camera paths see to (Cycles' Denoising Albedo:
    :attr:`~jaxden.io.conventions.Convention.albedo_includes_emission`) are read clipped to
    [0, 1], as OIDN reads them (a lamp pixel is white). Any other albedo above 1
    (:data:`ALBEDO_LIMIT`) is kept, with one warning line on stderr (once per process)."""
    from jaxden.io.conventions import CONVENTIONS

    names = tuple(mapping["albedo"])
    albedo = np.stack([all_channels[c] for c in names], axis=-1)
    rule = CONVENTIONS.get(convention) if convention is not None else None
    if rule is not None and names in {tuple(n.replace("{layer}", layer or "") for n in c)
                                      for c in rule.albedo_includes_emission}:
        return np.clip(albedo, 0.0, 1.0)
    over = albedo > ALBEDO_LIMIT
    if over.any():
        warn_once(path, f"the albedo is above 1 on {int(over.any(axis=-1).sum())} pixel(s) "
                         f"(up to {float(albedo.max()):.4g}), but an albedo is a reflectance "
                         f"in [0, 1]: WSKP divides the colour by it, which brightens or darkens "
                         f"those pixels, and OIDN clips it at 1. Blender's Denoising Albedo "
                         f"holds the emission of the lamps it sees: read Cycles renders with "
                         f"--from cycles (merge them again), which clips it",
                   key="albedo above 1")
    return albedo


def depth_misses(depth, names, convention, layer):
    """A convention's miss depth (and +inf) as jaxden's 0, where ``names`` are its own depth
    channels (Cycles' Z pass: 1e10; Falcor's linearZ: 1e8, +inf once stored as half)."""
    from jaxden.io.conventions import CONVENTIONS

    rule = CONVENTIONS[convention]
    own = {tuple(n.replace("{layer}", layer or "") for n in candidate)
           for candidate in rule.fields.get("depth", ())}
    if rule.depth_miss is None or tuple(names) not in own:
        return depth
    return np.where(np.isposinf(depth) | (depth >= rule.depth_miss), np.float32(0),
                    depth).astype(np.float32)


def missing_message(path, fields, mapping, present, convention, layer=None) -> str:
    """One line: the missing fields, the channels each needs (or a convention's candidates
    and how to make the renderer write them), a case-insensitive or close match where there
    is one, and the channels the file has."""
    from jaxden.frame import FIELD_HINTS
    from jaxden.io.conventions import CONVENTIONS, case_hints

    details, wanted = [], []
    for field in fields:
        if field in mapping:
            names = [c for c in mapping[field] if c not in present]
            hint = f": {FIELD_HINTS[field]}" if field in FIELD_HINTS else ""
            details.append(f"{field} needs {', '.join(names)}{hint}")
            wanted += names
        else:
            rule = CONVENTIONS[convention]
            candidates = [tuple(n.replace("{layer}", layer or "<layer>") for n in names)
                          for names in rule.fields.get(field, ())]
            options = " or ".join(",".join(names) for names in candidates)
            how = f": {rule.how_to[field]}" if field in rule.how_to else ""
            details.append(f"{field}: a {convention} file has "
                           + (f"it as {options}{how}" if candidates else
                              f"no such channels ({rule.note})"))
            wanted += [name for names in candidates for name in names]
    return (f"{path}: missing feature(s) {', '.join(fields)} ({'; '.join(details)})"
            f"{case_hints(wanted, present)}; the file has channels "
            f"{', '.join(sorted(present))}")
