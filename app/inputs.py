"""Reading and selecting a job's inputs, once for every face.

Shared option rows (:func:`cloud_option`, :func:`crs_option`, :func:`selection_options`,
:func:`out_dir_option`) and the readers that go with them: :func:`read_cloud`,
:func:`read_epoch_pair`, :func:`select_points`. Errors name the option (so the face can
say ``BEFORE``, "Before epoch" or the view) and which epoch.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Optional, Sequence, Tuple

import numpy as np

from ..core.errors import SlipMapError
from .options import Option, OptionError

log = logging.getLogger("slipmap.app")

LAS_FILTER = "LAS/LAZ (*.las *.laz *.LAS *.LAZ)"


# --------------------------------------------------------------------------- option rows


def cloud_option(key: str, help: str, label: str, *, cli: Optional[str] = None, **kw) -> Option:
    """A required LAS/LAZ input (a positional on the CLI named ``key`` unless ``cli``)."""
    return Option(
        key,
        "path",
        help,
        label=label,
        required=True,
        role="input",
        cli=cli if cli is not None else key,
        qgis=kw.pop("qgis", key.upper()),
        pdal=kw.pop("pdal", None),  # PDAL gives the points of its view instead
        file_filter=LAS_FILTER,
        **kw,
    )


def out_dir_option(help: str = "output folder (created when missing)") -> Option:
    """The CLI's ``--out`` folder; QGIS and PDAL name their outputs one by one instead."""
    return Option(
        "out",
        "path",
        help,
        label="Output folder",
        required=True,
        role="output",
        qgis=None,
        pdal=None,
        metavar="DIR",
    )


def crs_option(help: str = "") -> Option:
    return Option(
        "crs",
        "crs",
        help
        or "CRS of the input when the file lacks one or declares a wrong one (e.g. "
        "EPSG:32611): it replaces the file's CRS (nothing is reprojected) and the outputs "
        "carry it",
        label="CRS of the input (when the file has none or a wrong one)",
        advanced=True,
        pdal=None,  # PDAL's readers have override_srs
        metavar="CRS",
        unset_text="the file's",
    )


def selection_options(*, ground_default: bool) -> Tuple[Option, Option]:
    """``classes`` and ``exclude_classes``; with ``ground_default`` ground (class 2) is left out
    when the file is classified and neither is given (the planar method removes ground)."""
    excl_help = (
        "drop these ASPRS classes (default: 2, ground, when the file is classified and no "
        "classes are given; 'none' keeps every class)"
        if ground_default
        else "drop these ASPRS classes (default: none)"
    )
    return (
        Option(
            "classes",
            "ints",
            "keep only these ASPRS classes (e.g. 6 for buildings)",
            label="Keep only these classes (e.g. 6)",
            nargs="+",
            group="point selection",
            metavar="C",
            minimum=0,
            maximum=255,
            unset_text="all",
            pdal=None,  # PDAL pipelines select with filters.expression / filters.range
        ),
        Option(
            "exclude_classes",
            "ints",
            excl_help,
            label="Leave out these classes",
            nargs="+",
            group="point selection",
            metavar="C",
            minimum=0,
            maximum=255,
            unset_text="2 (ground)" if ground_default else "none",
            pdal=None,
        ),
    )


# --------------------------------------------------------------------------- reading


def as_crs(value):
    """A ``pyproj.CRS`` of an option's value (None stays None)."""
    if value is None:
        return None
    from ..core.io.crs import parse_crs

    return parse_crs(value)


def read_cloud(path, *, key: str = "input", crs=None, what: str = ""):
    """One LAS/LAZ cloud; empty files refused; ``crs`` replaces the file's CRS.

    Raises
    ------
    OptionError
        Naming ``key`` for a missing, unreadable or empty file.
    """
    from ..core.io.las import read_las

    crs = as_crs(crs)
    label = f"{what} " if what else ""
    try:  # a CRS the user gave replaces the file's, unparsed: no warning about the file's
        cloud = read_las(path, crs=crs)
    except OptionError:
        raise
    except SlipMapError as exc:
        raise OptionError(key, f"{label}{exc}") from exc
    if len(cloud) == 0:
        raise OptionError(key, f"{label}{path}: the file has no points; give a non-empty file")
    if crs is not None:
        _refuse_geographic_on_metres(cloud, crs, label)
        cloud.crs = crs
    return cloud


def _refuse_geographic_on_metres(cloud, crs, label: str = "") -> None:
    """A geographic CRS given for coordinates that cannot be degrees (|x| > 180 or |y| > 90)
    is refused: the points are surely in a projected CRS (metres)."""
    if not getattr(crs, "is_geographic", False) or len(cloud) == 0:
        return
    xyz = cloud.xyz
    x_max = float(np.max(np.abs(xyz[:, 0])))
    y_max = float(np.max(np.abs(xyz[:, 1])))
    if x_max > 180.0 or y_max > 90.0:
        raise OptionError(
            "crs",
            f"{crs.name} is a geographic CRS (degrees) but {label}{cloud.source} has "
            f"coordinates up to |x| = {x_max:.6g}, |y| = {y_max:.6g}, which are not degrees; "
            "give the projected CRS the coordinates are in (e.g. a UTM zone, EPSG:326xx)",
        )


@dataclass
class EpochPair:
    """Both epochs: clouds, the after epoch's points in the before epoch's CRS, and the CRS."""

    before: Any
    after: Any
    after_xyz: np.ndarray
    crs: Any


def read_epoch_pair(
    before, after, *, crs=None, keys: Tuple[str, str] = ("before", "after")
) -> EpochPair:
    """Both epochs, the second reprojected to the first's CRS when they differ.

    The same file as both epochs is refused. ``crs`` replaces both files' CRS (nothing is
    reprojected). A pair without any CRS is read as it is, with a warning (outputs then carry
    no CRS and cannot be placed on a map).
    """
    from ..core.io.crs import reproject_points, same_crs
    from .outputs import refuse_same_inputs

    refuse_same_inputs([(keys[0], before), (keys[1], after)])
    crs = as_crs(crs)
    first = read_cloud(before, key=keys[0], crs=crs, what="before epoch")
    second = read_cloud(after, key=keys[1], crs=crs, what="after epoch")
    xyz2 = second.xyz
    if crs is None:
        if first.crs is not None and second.crs is not None:
            if not same_crs(first.crs, second.crs):
                log.info(
                    "reprojecting %s from %s to %s",
                    second.source,
                    second.crs.name,
                    first.crs.name,
                )
                xyz2 = reproject_points(second.xyz, second.crs, first.crs)
        elif (first.crs is None) != (second.crs is None):
            log.warning("only one epoch declares a CRS; both are taken to be in the same CRS")
        else:
            log.warning(
                "neither epoch declares a CRS: outputs will carry none; give the CRS option "
                "to place them on a map"
            )
    out_crs = first.crs if first.crs is not None else second.crs
    return EpochPair(first, second, xyz2, out_crs)


def select_points(
    cloud,
    *,
    classes: Optional[Sequence[int]] = None,
    exclude_classes: Optional[Sequence[int]] = None,
    ground_default: bool = False,
    what: str = "",
    keys: Tuple[str, str] = ("classes", "exclude_classes"),
) -> np.ndarray:
    """Indices ``(K,)`` of the points kept by the class options.

    ``exclude_classes=()`` keeps every class. With ``ground_default`` and neither option given,
    ground (class 2) is left out of a classified cloud.

    Raises
    ------
    OptionError
        A class option on a cloud without Classification, or no point left.
    """
    n = len(cloud)
    cls = cloud.attributes.get("Classification")
    label = f"{what} ({cloud.source})" if what else str(cloud.source or "input")
    if cls is None:
        for key, value in zip(keys, (classes, exclude_classes)):
            if value:
                raise OptionError(
                    key, f"{label} has no Classification dimension; leave this option out"
                )
        return np.arange(n)
    cls = np.asarray(cls)
    keep = np.ones(n, dtype=bool)
    if classes:
        keep &= np.isin(cls, np.asarray(classes))
    if exclude_classes is not None:
        if len(exclude_classes):
            keep &= ~np.isin(cls, np.asarray(exclude_classes))
    elif ground_default and not classes and np.any(cls == 2):
        keep &= cls != 2
        log.info(
            "%s: leaving out ground (class 2); set the classes to exclude (none keeps every "
            "class) to change",
            label,
        )
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        present = ", ".join(str(int(c)) for c in np.unique(cls)[:20])
        key = keys[0] if classes else keys[1]
        raise OptionError(
            key,
            f"no point of {label} is left by the class selection (its classes: "
            f"{present}); choose other classes",
        )
    return idx
