"""Where data and runs live: ``$JAXDEN_HOME`` (default ``~/jaxden-work``), outside any checkout,
and the expansion of ``~`` and ``$VARIABLE`` in paths that configs and overrides give."""

from __future__ import annotations

import os
import re
from pathlib import Path

#: The folder that holds datasets and runs when paths say ``$JAXDEN_HOME`` (outside the checkout).
DEFAULT_HOME = "~/jaxden-work"
_VARIABLE = re.compile(r"\$(?:\{(\w+)\}|(\w+))")


def jaxden_home() -> Path:
    """``$JAXDEN_HOME``, or ``~/jaxden-work`` when it is not set: where data and runs live."""
    return Path(os.environ.get("JAXDEN_HOME") or DEFAULT_HOME).expanduser()


def expand_path(text: str) -> str:
    """A path from a config with ``~`` and ``$VARIABLE`` / ``${VARIABLE}`` expanded
    (``$JAXDEN_HOME`` defaults to :func:`jaxden_home`); unknown variables stay as written, so
    the missing folder's error shows them."""
    if not text or ("$" not in text and not text.startswith("~")):
        return text

    def value(match: re.Match) -> str:
        name = match.group(1) or match.group(2)
        if name == "JAXDEN_HOME":
            return str(jaxden_home())
        return os.environ.get(name, match.group(0))

    return os.path.expanduser(_VARIABLE.sub(value, text))


def portable(text: str) -> str:
    """``text`` with this machine's :func:`jaxden_home` written as ``$JAXDEN_HOME``: commands
    and paths recorded in results and model cards then work on any machine."""
    home = str(jaxden_home())
    return text.replace(home, "$JAXDEN_HOME") if home not in ("", "/") else text


# ------------------------------------------------------------------------- shipped weights
#: The weights shipped in the package, each ``NAME.msgpack`` beside its model card
#: ``NAME.json`` (denoisers and mixers alike).
WEIGHTS_DIR = Path(__file__).parent / "weights"


def shipped_weights_file(name: str) -> Path | None:
    """``jaxden/weights/NAME.msgpack`` when ``name`` ships (weights and card), else None."""
    if not isinstance(name, str) or not name or "/" in name or os.sep in name:
        return None
    path = WEIGHTS_DIR / f"{name}.msgpack"
    return path if path.is_file() and path.with_suffix(".json").is_file() else None


def shipped_weights_names() -> list[str]:
    """The names of every model shipped in ``jaxden/weights`` (denoisers and mixers)."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.msgpack")
                  if p.with_suffix(".json").is_file())


def resolve_weights(spec) -> Path | None:
    """The one lookup of a weights spec: an existing file or folder (a ``.msgpack`` file, a
    checkpoint or training folder) as it is, else a shipped name's file, else None."""
    path = Path(spec)
    if path.exists():
        return path
    return shipped_weights_file(spec) if isinstance(spec, str) else None
