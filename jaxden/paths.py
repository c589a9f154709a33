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
