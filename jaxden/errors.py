"""User-facing errors.

Every error a user can cause (bad file, bad config, bad scene, bad checkpoint) is raised as a
subclass of :class:`JaxdenError` with a message naming the file, field or option, what was
found and what was expected. The CLI prints these as one line and exits non-zero; anything else
is a bug and keeps its traceback.
"""


class JaxdenError(Exception):
    """Base class of all errors caused by user input."""


class FrameError(JaxdenError, ValueError):
    """A Frame (or raw arrays meant for one) is malformed: shape, channel, value."""


class ExrError(JaxdenError, OSError):
    """An EXR file is missing, unreadable, truncated, or lacks required channels."""


class SceneError(JaxdenError, ValueError):
    """A scene name, scene file or render parameter is invalid."""


class ConfigError(JaxdenError, ValueError):
    """A configuration file or override is invalid (unknown key, wrong type, bad value)."""


class DatasetError(JaxdenError, ValueError):
    """A dataset directory or manifest is inconsistent."""


class OutputError(JaxdenError, OSError):
    """An output file or folder cannot be written there (a folder in the way, no permission,
    a missing parent folder, two outputs on the same path)."""


class CheckpointError(JaxdenError, ValueError):
    """A checkpoint is missing, corrupt, or belongs to another model or config."""
