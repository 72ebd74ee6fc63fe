"""What every job returns, and the progress/cancel protocol the faces map onto."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Dict, List

from ..core.errors import CancelledError
from ..core.progress import ProgressCallback, scaled

log = logging.getLogger("slipmap.app")

#: ``progress(fraction 0..1, message)``; raises :class:`CancelledError` to stop the run
Progress = ProgressCallback


@dataclass(frozen=True)
class JobResult:
    """The outcome of one job run.

    Attributes
    ----------
    summary
        JSON-safe payload (what ``<job>.json`` holds; QGIS outputs and PDAL metadata read it).
    lines
        Human summary, one line each, units included (console, QGIS log, PDAL headline).
    files
        ``{output key: final path}`` of the files written.
    data
        The core result object(s), for faces that show more (QGIS layers); not serialised.
    """

    summary: Dict[str, Any]
    lines: List[str] = field(default_factory=list)
    files: Dict[str, Path] = field(default_factory=dict)
    data: Any = None


class Timer:
    """``with Timer() as t: ...; t.seconds``"""

    def __enter__(self):
        self._t0 = time.perf_counter()
        self.seconds = 0.0
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self._t0


__all__ = ["JobResult", "Progress", "scaled", "Timer", "CancelledError"]


NO_MATPLOTLIB = "matplotlib is not installed: no PNG figures (pip install matplotlib)"


def matplotlib_available() -> bool:
    """Whether matplotlib can be imported (the figures and the report's plots need it; it is
    optional). Says nothing: a job warns (:func:`plotting`) once it is past its checks."""
    import importlib.util

    return importlib.util.find_spec("matplotlib") is not None


def plotting():
    """:mod:`slipmap.app.report` (figures, HTML report), or None with one warning when
    matplotlib is missing."""
    if not matplotlib_available():
        log.warning(NO_MATPLOTLIB)
        return None
    from . import report

    return report
