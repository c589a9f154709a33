"""The batch form of `jaxden denoise` and `jaxden progressive`: several input files, each
denoised and written in turn with one loaded (and, per frame size, once compiled) model, or
consecutive frames of one animation with a temporal model's history carried (``--sequence``).
A batch stopped part-way keeps the files it wrote (each written atomically); ``--skip-existing``
resumes it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxden.cli.options import emission_spec, emission_specs, stderr
from jaxden.errors import ConfigError


def denoisers_by_input(base, spec, inputs, args) -> list:
    """The denoiser each input runs: ``base`` (loaded from ``spec``), or ``base`` with the
    emission kept out of the filter where the file asks for it (:func:`emission_specs`,
    its note said once); one object each, so that compiled functions are shared."""
    from jaxden.denoise.registry import with_options

    decided = emission_specs(spec, inputs, args) if len(inputs) > 1 else [
        emission_spec(spec, inputs[0], args)]
    separated = None
    chosen = []
    for text in decided:
        if text == spec:
            chosen.append(base)
            continue
        if separated is None:
            separated = with_options(base, emission="separate")
        chosen.append(separated)
    return chosen


def input_sizes(inputs) -> list[tuple[int, int]]:
    """Each input's (width, height) from its header: every input is found readable before
    any work (an unreadable one is one error naming it)."""
    from jaxden.io.exr import read_header

    return [tuple(read_header(source)["size"]) for source in inputs]


def check_sequence(args, inputs, sizes, denoisers) -> None:
    """What a temporal denoiser's sequence needs, before any work: frames of one size, one
    denoiser for all, every frame run (no --skip-existing), whole frames (no --tile)."""
    name = args.model
    if args.skip_existing:
        raise ConfigError(f"--sequence with {name} carries its history from frame to frame, so "
                          f"every frame must run: --skip-existing cannot skip some; rerun the "
                          f"whole sequence, or drop --sequence to denoise each frame alone")
    if args.tile:
        raise ConfigError(f"--tile: {name} with --sequence carries its history over whole "
                          f"frames and cannot run in tiles; drop --tile, or drop --sequence to "
                          f"denoise each frame alone")
    for source, size in zip(inputs, sizes):
        if size != sizes[0]:
            raise ConfigError(f"--sequence: {source} is {size[0]}x{size[1]}, but the sequence's "
                              f"first frame {inputs[0]} is {sizes[0][0]}x{sizes[0][1]}; the "
                              f"frames of one sequence share their size")
    kinds = dict.fromkeys(denoiser.name for denoiser in denoisers)
    if len(kinds) > 1:
        raise ConfigError(f"--sequence: the frames do not agree on the emission ({' and '.join(kinds)}"
                          f"); one history needs one denoiser: add :emission=separate or "
                          f":emission=filter to --model")


def sequence_step(denoiser, frame, limit, source):
    """``step(state, frame) -> (image, state)`` of ``denoiser`` for a sequence of frames like
    ``frame``, compiled once a frame size; refused in one line when a whole frame's step with
    its history does not fit the memory limit (a history cannot be carried over tiles)."""
    import jax
    import numpy as np

    from jaxden.limits import format_bytes, memory_limit
    from jaxden.tiling import MemoryPlanError

    if not denoiser.differentiable:
        return denoiser.step
    step = jax.jit(denoiser.step)
    state = jax.eval_shape(lambda f: denoiser.step(None, f)[1], frame)
    try:
        stats = step.lower(state, frame).compile().memory_analysis()
    except Exception:  # noqa: BLE001 - a backend without the analysis: nothing to plan with
        return step
    if stats is None:
        return step
    limit = memory_limit() if limit is None else int(limit)
    frame_bytes = sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(frame))
    needed = int(stats.temp_size_in_bytes + stats.argument_size_in_bytes
                 + stats.output_size_in_bytes)
    if frame_bytes + needed > limit:
        height, width = np.shape(frame.color)[:2]
        raise MemoryPlanError(
            f"{source}: {denoiser.name} with --sequence carries its history over whole frames "
            f"and cannot run in tiles, but a {width}x{height} frame's step needs about "
            f"{format_bytes(frame_bytes + needed)}, more than the memory limit "
            f"{format_bytes(limit)}; raise --memory-limit (or JAXDEN_MEMORY_LIMIT), or drop "
            f"--sequence to denoise each frame alone, in tiles")
    return step


def run_jobs(jobs, work, *, skip_existing: bool, folders=(), sequence: bool = False):
    """Run ``work(source, *outputs, denoiser)`` for each job ``(source, outputs, denoiser)``
    in turn, one frame in memory at a time, with a progress line per file on stderr when
    there are several. ``skip_existing``: a job whose outputs all exist is skipped.
    ``folders``: the output folders to make before the first write. An error after some files
    were written says how many and how to go on; an interruption says so in one line and
    returns None. Returns ``(written, skipped)``."""
    import contextlib
    import time

    from jaxden.errors import JaxdenError

    total, written, skipped = len(jobs), 0, 0
    several = total > 1
    resume = ("rerun the whole sequence (its history needs every frame)" if sequence
              else "rerun the same command with --skip-existing to go on")
    for index, (source, outputs, denoiser) in enumerate(jobs, 1):
        given = [path for path in outputs if path is not None]
        if skip_existing and all(path.exists() for path in given):
            skipped += 1
            if several:
                stderr(f"jaxden: [{index}/{total}] {source}: {given[0]} exists, skipped "
                       f"(--skip-existing)")
            continue
        made = [new for folder in folders for new in missing_folders(folder)]
        for folder in folders:
            Path(folder).mkdir(parents=True, exist_ok=True)
        folders = ()
        start = time.perf_counter()
        try:
            work(source, *outputs, denoiser)
        except BaseException as error:
            for folder in made if not written else ():  # nothing written: no folder left
                with contextlib.suppress(OSError):
                    folder.rmdir()
            if isinstance(error, KeyboardInterrupt) and several:
                stderr(f"jaxden: interrupted at {source}; {written} of {total} files were "
                       f"written (each whole): {resume}")
                return None
            if isinstance(error, JaxdenError) and several and written:
                text = (f"{error} ({written} of {total} files were written before it: "
                        f"{resume})")
                error.args = (text,)
            raise
        made = ()
        written += 1
        if several:
            stderr(f"jaxden: [{index}/{total}] {source} -> {given[0]} "
                   f"({time.perf_counter() - start:.1f} s)")
    return written, skipped


def missing_folders(folder) -> list[Path]:
    """``folder`` and those of its parents that do not exist, deepest first."""
    missing, folder = [], Path(folder).absolute()
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    return missing


def batch_summary(done, folder, what: str) -> str:
    written, skipped = done
    text = f"wrote {written} file{'s' * (written != 1)} into {folder} ({what})"
    return text + (f"; skipped {skipped} that exist (--skip-existing)" if skipped else "")


def add_skip_existing_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--skip-existing", action="store_true",
                        help="leave an input whose output exists alone (resume an interrupted "
                             "batch; not with --sequence of a temporal denoiser)")

