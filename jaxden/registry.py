"""The one shape of jaxden's registries: a name -> entry table that knows who filled each name.

Every registry (denoisers, trainable models, mixers, losses, evaluators) is a
:class:`Registry`. jaxden's own entries and a user's plugin (:mod:`jaxden.plugins`) fill it
the same way, through :meth:`Registry.add`. A name taken by one module cannot be taken by
another: a plugin that names its denoiser ``wskp-6`` is refused in one line, since results,
caches and checkpoints are keyed by name and two meanings of one name would mix them. The same
module may register a name again (a module imported twice, a notebook re-running a cell): the
new entry replaces the old one.

A leaf module: it imports nothing of jaxden's but :mod:`jaxden.errors`.
"""

from __future__ import annotations

import sys
from typing import Any, TypeVar

from jaxden.errors import ConfigError

T = TypeVar("T")
_REGISTER_PLUMBING = True

#: The package whose modules are jaxden's own (an owner under it is a built-in).
BUILT_IN_PACKAGE = "jaxden"


class PluginClashError(ConfigError):
    """A plugin names an entry that a built-in or another plugin already took."""


#: A module that sets this global to True only relays registrations (a ``register``
#: function): the owner of an entry is the first module up the stack that does not.
PLUMBING_FLAG = "_REGISTER_PLUMBING"


def caller_module(depth: int = 2) -> str:
    """``__name__`` of the module registering an entry: the first frame from ``depth`` up
    whose module is not registry plumbing (:data:`PLUMBING_FLAG`) nor importlib's."""
    frame = sys._getframe(depth)
    while frame is not None:
        names = frame.f_globals
        name = names.get("__name__", "?")
        if not names.get(PLUMBING_FLAG) and not name.startswith("importlib"):
            return name
        frame = frame.f_back
    return "?"


def is_built_in(module: str) -> bool:
    """Whether ``module`` is one of jaxden's own modules."""
    return module == BUILT_IN_PACKAGE or module.startswith(BUILT_IN_PACKAGE + ".")


class Registry(dict):
    """``{name: entry}`` with the module that registered each name (``owner``).

    ``what`` names the kind of entry in messages ("denoiser", "evaluator", ...). Reading is
    a plain dict's; writing goes through :meth:`add`.
    """

    def __init__(self, what: str) -> None:
        super().__init__()
        self.what = what
        self.owners: dict[str, str] = {}

    def add(self, name: str, entry: T, owner: str | None = None) -> T:
        """Register ``entry`` as ``name``; ``owner``: the registering module (default: the
        caller's). A name another module holds is a :class:`PluginClashError` naming both."""
        if not isinstance(name, str) or not name or any(c.isspace() for c in name) or \
                ":" in name:
            raise ConfigError(f"{self.what} name must be a non-empty string without spaces "
                              f"or ':', got {name!r}")
        owner = owner or caller_module()
        held_by = self.owners.get(name)
        if held_by is not None and held_by != owner:
            raise PluginClashError(self.clash_message(name, owner, held_by))
        self[name] = entry
        self.owners[name] = owner
        return entry

    def clash_message(self, name: str, owner: str, held_by: str, what: str | None = None) -> str:
        """One line: ``owner``'s ``what`` (default: this registry's kind) called ``name``
        clashes with this registry's entry that ``held_by`` registered."""
        holder = (f"jaxden's built-in {self.what}" if is_built_in(held_by)
                  else f"the {self.what} of module '{held_by}'")
        return (f"{what or self.what} name {name!r} from module '{owner}' clashes with "
                f"{holder} {name!r}; register it under another name")

    def find(self, name: str) -> Any:
        """The entry ``name``; when it is missing, the plugins that ``JAXDEN_PLUGINS`` and
        the installed entry points name are imported first (:func:`jaxden.plugins.
        load_ambient`), so a spawned worker resolves them too. None if still missing."""
        if name not in self:
            from jaxden.plugins import load_ambient

            load_ambient()
        return self.get(name)

    def owner(self, name: str) -> str | None:
        """The module that registered ``name`` (None: not registered)."""
        return self.owners.get(name)

    def from_plugins(self) -> dict[str, Any]:
        """The entries that outside modules registered."""
        return {name: self[name] for name, owner in self.owners.items()
                if not is_built_in(owner) and name in self}


def check_free(name: str, what: str, owner: str, *others: Registry) -> None:
    """PluginClashError when ``name`` is taken in any of ``others`` by another module (names
    shared across registries: a trainable model may not shadow a denoiser)."""
    for registry in others:
        held_by = registry.owner(name)
        if held_by is not None and held_by != owner:
            raise PluginClashError(registry.clash_message(name, owner, held_by, what))
