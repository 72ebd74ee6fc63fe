"""Checks of the optional Python packages the algorithms need inside QGIS's Python."""

from __future__ import annotations

import importlib.util
import os
import sys

#: the optional Python packages SlipMap's algorithms need inside QGIS's Python (scipy comes
#: with QGIS, except a Debian QGIS installed with --no-install-recommends)
PACKAGES = ("laspy", "lazrs", "scipy")
#: what each algorithm needs (``slipmap:<id>`` -> packages); strain reads a table or GeoTIFF
NEEDS = {"strain": ("scipy",)}
DEFAULT_NEEDS = PACKAGES
#: package -> (Debian package, conda-forge package); None: not packaged (pip)
_DEBIAN = {
    "scipy": "python3-scipy",
    "numba": "python3-numba",
    "threadpoolctl": "python3-threadpoolctl",
}
_CONDA = {"lazrs": "lazrs-python"}
#: optional packages that make an algorithm faster, never needed to run it (package -> what
#: it speeds up); a missing one is said in the run's log with its install command
SPEEDUPS = {
    "numba": "the windowed ICP's compiled CPU kernels (the point pairs several times faster "
    "where no OpenCL device is available)",
    "threadpoolctl": "the windowed ICP and its spline field (one BLAS thread for their many "
    "small matrix operations, where OpenBLAS's idle threads would hold the cores)",
}


def needs(algorithm_id: str = "") -> tuple:
    """The packages algorithm ``algorithm_id`` (``"piv"``; empty: any) needs."""
    return NEEDS.get(algorithm_id, DEFAULT_NEEDS)


def missing_packages(names=None) -> list:
    """Names of the packages (default: all of :data:`PACKAGES`) that cannot be imported."""
    return [name for name in (names or PACKAGES) if not _importable(name)]


def _importable(name: str) -> bool:
    """Whether ``import name`` can find the package (without importing it: scipy is slow)."""
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):  # a finder refuses it, or a broken entry in sys.modules
        return False


def platform_kind() -> str:
    """Where this QGIS runs, for the install command: ``conda``, ``osgeo4w`` (Windows),
    ``macos`` (qgis.org's QGIS.app), ``debian`` (a Linux distribution's QGIS) or ``linux``."""
    prefix = sys.base_prefix or sys.prefix
    if os.path.isdir(os.path.join(sys.prefix, "conda-meta")) or os.environ.get("CONDA_PREFIX"):
        return "conda"
    if sys.platform.startswith("win"):
        return "osgeo4w"
    if sys.platform == "darwin":
        return "macos"
    if os.path.exists("/etc/debian_version") or prefix == "/usr":
        return "debian"
    return "linux"


def _externally_managed() -> bool:
    """Whether pip refuses to install here without --break-system-packages (PEP 668)."""
    import sysconfig

    return os.path.exists(os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED"))


def _macos_python() -> str:
    """The Python inside the running QGIS.app (QGIS-LTR.app, ...), else qgis.org's path."""
    for path in (sys.executable, sys.prefix):
        if ".app/" in path:
            return path.split(".app/")[0] + ".app/Contents/MacOS/bin/python3"
    return "/Applications/QGIS.app/Contents/MacOS/bin/python3"


def _quoted(path: str) -> str:
    return f'"{path}"' if " " in path else path


def install_command(missing, kind: str = "") -> str:
    """ONE shell command that installs ``missing`` into the Python QGIS runs, as printed for
    platform ``kind`` (default: this one, :func:`platform_kind`).

    Debian 12/13 (and Ubuntu 23.04+) mark their Python "externally managed" (PEP 668): pip
    then needs ``--user --break-system-packages`` (it writes only under ~/.local, which QGIS
    reads, and leaves the system's packages alone); scipy comes from apt (python3-scipy), and
    pip itself from python3-pip where it is missing. There is no ``python`` on Debian: the
    command names ``python3``.
    """
    kind = kind or platform_kind()
    missing = list(missing)
    if kind == "conda":
        return "conda install -c conda-forge " + " ".join(_CONDA.get(m, m) for m in missing)
    if kind == "osgeo4w":
        return "python -m pip install " + " ".join(missing)
    if kind == "macos":
        return f"{_quoted(_macos_python())} -m pip install " + " ".join(missing)
    apt = [_DEBIAN[m] for m in missing if m in _DEBIAN] if kind == "debian" else []
    pip = [m for m in missing if m not in _DEBIAN or kind != "debian"]
    if pip and kind == "debian" and not _importable("pip"):
        apt.insert(0, "python3-pip")
    parts = []
    if apt:
        parts.append("sudo apt install " + " ".join(apt))
    if pip:
        flags = "--user --break-system-packages" if _externally_managed() else "--user"
        parts.append(f"python3 -m pip install {flags} " + " ".join(pip))
    return " && ".join(parts)


#: where to run the command, per platform (plain text: no "<...>", see INSTALL_HINT)
_WHERE = {
    "conda": "in the conda environment QGIS runs from",
    "osgeo4w": "in the OSGeo4W Shell (Start menu)",
    "macos": "in a Terminal",
    "debian": "in a terminal",
    "linux": "in a terminal",
}
#: the command for every platform, for the docs and the Plugin Manager (``about``)
PLATFORM_COMMANDS = (
    (
        "Debian 12/13 or Ubuntu, in a terminal",
        "python3 -m pip install --user --break-system-packages laspy lazrs",
    ),
    ("Windows, in the OSGeo4W Shell", "python -m pip install laspy lazrs"),
    (
        "macOS, in a Terminal",
        "/Applications/QGIS.app/Contents/MacOS/bin/python3 -m pip install laspy lazrs",
    ),
    ("conda, in QGIS's environment", "conda install -c conda-forge laspy lazrs-python"),
)


def missing_message(missing, kind: str = "") -> str:
    """What is missing and the one command that installs it here, as one plain-text line
    (no "<...>": QGIS shows it in rich-text tooltips and message boxes). The command ends the
    text, with nothing after it, so that it can be copied as it is."""
    kind = kind or platform_kind()
    s = "s" if len(missing) > 1 else ""
    return (
        f"SlipMap needs the Python package{s} {', '.join(missing)}, missing in the Python that "
        f"QGIS runs. Run this command {_WHERE[kind]}, then restart QGIS: "
        f"{install_command(missing, kind)}"
    )


#: what to run where laspy/lazrs are missing, every platform (docs, metadata ``about``); the
#: commands are separated by " -- " so that none ends with a full stop
INSTALL_HINT = (
    "It needs the Python packages laspy and lazrs in the Python that QGIS runs; install them "
    "with the command for your platform and restart QGIS -- "
    + " -- ".join(f"{where}: {command}" for where, command in PLATFORM_COMMANDS)
)


def speedup_message(name: str, kind: str = "") -> str:
    """One plain-text line for the run's log where the optional package ``name`` (a key of
    :data:`SPEEDUPS`) is missing, with its install command at the end; empty where it is
    installed."""
    if _importable(name):
        return ""
    return (
        f"Optional: the Python package {name} is not installed; it would speed up "
        f"{SPEEDUPS[name]}. Run this command {_WHERE[kind or platform_kind()]}, then restart "
        f"QGIS: {install_command([name], kind)}"
    )


def can_execute(algorithm_id: str = ""):
    """``(True, "")`` or ``(False, what is missing and the command)`` for ``canExecute()``
    of algorithm ``algorithm_id`` (its :func:`needs`)."""
    missing = missing_packages(needs(algorithm_id))
    if missing:
        return False, missing_message(missing)
    return True, ""


# --------------------------------------------------------------------------- QGIS API versions
# QGIS 3.38/3.40 deprecated API that SlipMap used since 3.22; these helpers call the new API where
# it exists and the old one elsewhere, so no DeprecationWarning shows on 3.40 and 3.22 still runs
# (QGIS 4 / Qt 6 removes the deprecated API: docs/qgis.md, "QGIS 4 / Qt 6").

#: field type names for :func:`make_field`, as QMetaType/QVariant type numbers (equal in Qt 5)
FIELD_TYPES = {"bool": 1, "int": 2, "longlong": 4, "double": 6, "string": 10}


def _qgis_version_int() -> int:
    from qgis.core import Qgis

    return int(Qgis.QGIS_VERSION_INT)


def make_field(name: str, kind):
    """A ``QgsField`` of type ``kind`` without the constructor deprecated in QGIS 3.38.

    ``kind`` is a name of :data:`FIELD_TYPES` ('double', 'int', 'longlong', 'string', 'bool')
    or a Qt type value (``QVariant.Double`` or ``QMetaType.Type.Double``). QGIS >= 3.38 is
    given a ``QMetaType.Type`` (the QVariant.Type constructor is deprecated there and gone in
    QGIS 4); older QGIS a ``QVariant.Type``.
    """
    from qgis.core import QgsField

    code = FIELD_TYPES[kind.lower()] if isinstance(kind, str) else int(getattr(kind, "value", kind))
    if _qgis_version_int() >= 33800:
        from qgis.PyQt.QtCore import QMetaType

        return QgsField(name, QMetaType.Type(code))
    from qgis.PyQt.QtCore import QVariant

    return QgsField(name, QVariant.Type(code))


def renderer_band(renderer) -> int:
    """The input band of a raster renderer (``inputBand()`` since QGIS 3.38, else ``band()``)."""
    if hasattr(renderer, "inputBand"):
        return int(renderer.inputBand())
    return int(renderer.band())


def set_renderer_band(renderer, band: int) -> None:
    """Set a raster renderer's input band (``setInputBand`` since QGIS 3.38, else ``setBand``)."""
    if hasattr(renderer, "setInputBand"):
        renderer.setInputBand(int(band))
    else:
        renderer.setBand(int(band))


def band_statistics(provider, band: int, stats=("Min", "Max")):
    """``provider.bandStatistics(band, …)`` holding at least the statistics named in ``stats``.

    ``stats`` holds ``QgsRasterBandStats`` names: 'Min', 'Max', 'Range', 'Sum', 'Mean',
    'StdDev', 'SumOfSquares', 'All'. QGIS 3.40 deprecates the call with int flags, and its
    Python binding takes that overload whenever ``stats`` is passed at all (also for
    ``Qgis.RasterBandStatistic`` flags), so from 3.40 on every statistic is computed (the
    default, one pass over the band) and the requested ones are among them.
    """
    if _qgis_version_int() >= 34000:
        return provider.bandStatistics(int(band))
    from qgis.core import QgsRasterBandStats

    flags = 0
    for name in stats:
        flags |= int(getattr(QgsRasterBandStats, name))
    return provider.bandStatistics(int(band), flags)


# --------------------------------------------------------------------------- pyproj in QThreads
#: PROJ contexts of pyproj kept alive for the QGIS worker threads they belong to
_PROJ_CONTEXTS = []


def keep_proj_context():
    """Keep the calling thread's pyproj context alive for the thread's next use.

    pyproj 3.7.0 to 3.7.2 (Debian 13's is 3.7.1) keeps one PROJ context per thread: a pointer
    in the thread's C-level storage, destroyed with the Python ``threading.local`` that holds
    its manager. A Processing run from the dialog runs in a thread of QGIS's pool, which Python
    did not create: when the run ends, its temporary Python thread state (and the local) goes,
    the context is destroyed, the pointer stays, and the next run on that pooled thread uses
    the freed context: QGIS 3.40 crashes (signal 11 in ``proj_create``) on the second run of
    any algorithm that reads a CRS (pyproj issue #1509, fixed upstream by PR #1539). Holding
    a reference to the manager keeps the context valid: one context per pool thread, kept
    for the session. Older pyproj (no per-thread contexts) and fixed ones need nothing and
    this does nothing harmful there. Call it at the end of the work in the thread.
    """
    try:
        from pyproj._context import get_context_manager
    except ImportError:  # pyproj < 3.7: one global handling, nothing to keep
        return
    try:
        manager = get_context_manager()
    except Exception:  # noqa: BLE001 - a missing manager is not worth failing a run for
        return
    if manager is not None and all(m is not manager for m in _PROJ_CONTEXTS):
        _PROJ_CONTEXTS.append(manager)
