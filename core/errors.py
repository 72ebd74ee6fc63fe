"""SlipMap's exception hierarchy.

Every error SlipMap raises on purpose is a :class:`SlipMapError`; its message names the
parameter or file at fault and says what to do. Adapters (CLI, PDAL, QGIS) turn these into
their own error types with the same message.
"""

from __future__ import annotations


class SlipMapError(Exception):
    """Base class of all SlipMap errors."""


class InvalidParameterError(SlipMapError, ValueError):
    """An option has a value that cannot work (e.g. a negative cell size)."""


class InputDataError(SlipMapError, ValueError):
    """The data cannot be processed (empty, NaN coordinates, all points identical, ...)."""


class SlipMapFileError(SlipMapError, OSError):
    """A file is missing, unreadable, corrupt, or an output cannot be written."""


class DependencyError(SlipMapError, ImportError):
    """An optional package is missing; the message gives the install command."""


class CancelledError(SlipMapError):
    """The user cancelled a long run (raised from a progress callback)."""


class NoResultWarning(UserWarning):
    """A run finished but found nothing (e.g. no planes); outputs are empty, not missing."""
