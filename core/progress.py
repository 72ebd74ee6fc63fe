"""One progress-callback type for every long loop in SlipMap.

A callback is ``callback(fraction, message)`` with ``fraction`` in [0, 1]. It returns nothing;
to cancel, it raises :class:`~slipmap.core.errors.CancelledError` (the QGIS adapter does this
when ``feedback.isCanceled()``). The CLI maps it to a progress bar.
"""

from __future__ import annotations

from typing import Callable, Optional

ProgressCallback = Callable[[float, str], None]


def report(callback: Optional[ProgressCallback], fraction: float, message: str = "") -> None:
    """Call ``callback`` if given, clamping ``fraction`` to [0, 1]."""
    if callback is not None:
        callback(min(1.0, max(0.0, float(fraction))), message)


def scaled(
    callback: Optional[ProgressCallback], start: float, stop: float
) -> Optional[ProgressCallback]:
    """A callback that maps [0, 1] of a sub-task onto [start, stop] of ``callback``."""
    if callback is None:
        return None

    def sub(fraction: float, message: str = "") -> None:
        callback(start + (stop - start) * min(1.0, max(0.0, fraction)), message)

    return sub
