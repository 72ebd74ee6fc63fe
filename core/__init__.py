"""SlipMap's science: numpy/scipy functions on (N, 3) float64 point arrays.

Nothing here imports QGIS, PDAL or the file-format layer ``core.io``.
"""

from .errors import (
    CancelledError,
    DependencyError,
    InputDataError,
    InvalidParameterError,
    SlipMapError,
    SlipMapFileError,
)

__all__ = [
    "CancelledError",
    "DependencyError",
    "InputDataError",
    "InvalidParameterError",
    "SlipMapError",
    "SlipMapFileError",
]
