"""Horizontal strain fields from a gridded displacement field (the study's strain maps).

From the horizontal displacement ``(u, v) = (dx, dy)`` of a :class:`GriddedField` the
displacement-gradient tensor

    L = [[du/dx, du/dy],
         [dv/dx, dv/dy]]

is estimated by finite differences that respect gaps (cells without a vector):

- along a row (x, east): central difference ``(u[c+1] - u[c-1]) / (2 sx)`` where both
  neighbours have a vector, one-sided ``(u[c+1] - u[c]) / sx`` or ``(u[c] - u[c-1]) / sx``
  where only one has, NaN where neither has;
- along a column (y, north): the same, but rows run south, so
  ``d/dy = (u[r-1] - u[r+1]) / (2 sy)`` (north neighbour minus south neighbour);
- a cell without a vector itself gets NaN everywhere (no strain is made up in a gap).

From L, infinitesimal (small-strain) quantities, all dimensionless except angles:

- ``exx = du/dx``, ``eyy = dv/dy``, ``exy = (du/dy + dv/dx) / 2`` (tensor shear strain);
- rotation ``omega = (dv/dx - du/dy) / 2`` (radians, counter-clockwise positive);
- principal strains ``e1 >= e2 = (exx + eyy)/2 +- sqrt(((exx - eyy)/2)**2 + exy**2)``
  (extension positive);
- ``e1_azimuth_deg``: azimuth of the e1 axis, degrees clockwise from north in [0, 180);
  the e1 axis makes ``theta = atan2(2 exy, exx - eyy) / 2`` counter-clockwise with +x, so
  azimuth = ``(90 - degrees(theta)) mod 180``; NaN where the strain is isotropic
  (``e1 == e2`` to rounding: every direction is principal);
- ``max_shear = (e1 - e2) / 2``: the maximum **tensor** shear strain (the radius of Mohr's
  circle). The maximum engineering shear strain is twice this, ``e1 - e2``;
- ``dilatation = exx + eyy`` (areal strain).

The vertical displacement is not used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputDataError
from .fields import GriddedField

__all__ = [
    "StrainField",
    "displacement_gradient",
    "displacement_gradient_reference",
    "strain_field",
    "strain_from_gradient",
]

_ISOTROPIC_RTOL = 1e-12  # e1 - e2 below this fraction of the tensor's size: no azimuth


@dataclass(frozen=True, eq=False)
class StrainField:
    """Horizontal infinitesimal strain on the grid of a displacement field.

    All arrays are (n_rows, n_cols) float64 on the grid of the source field (row 0 =
    north); NaN where the gradient could not be estimated. Strains are dimensionless
    (m/m, extension positive).

    Attributes
    ----------
    origin_xy, spacing_m : tuple of float
        Grid geometry, as :class:`~slipmap.core.fields.GriddedField` (metres).
    dudx, dudy, dvdx, dvdy : numpy.ndarray
        Displacement-gradient components (``u`` east, ``v`` north).
    exx, eyy, exy : numpy.ndarray
        Strain tensor components (``exy`` is tensor shear, half the engineering shear).
    rotation_rad : numpy.ndarray
        Rigid rotation ``(dv/dx - du/dy) / 2``, radians, counter-clockwise positive.
    e1, e2 : numpy.ndarray
        Principal strains, ``e1 >= e2``.
    e1_azimuth_deg : numpy.ndarray
        Azimuth of the e1 axis, degrees clockwise from north in [0, 180); NaN where
        isotropic.
    max_shear : numpy.ndarray
        Maximum tensor shear strain ``(e1 - e2) / 2`` (engineering: twice this).
    dilatation : numpy.ndarray
        ``exx + eyy``.
    """

    origin_xy: tuple[float, float]
    spacing_m: tuple[float, float]
    dudx: np.ndarray
    dudy: np.ndarray
    dvdx: np.ndarray
    dvdy: np.ndarray
    exx: np.ndarray
    eyy: np.ndarray
    exy: np.ndarray
    rotation_rad: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    e1_azimuth_deg: np.ndarray
    max_shear: np.ndarray
    dilatation: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)``."""
        return (int(self.exx.shape[0]), int(self.exx.shape[1]))

    @property
    def valid(self) -> np.ndarray:
        """(n_rows, n_cols) bool: the full gradient is known at the cell."""
        return np.isfinite(self.exx) & np.isfinite(self.eyy) & np.isfinite(self.exy)

    def bands(self) -> dict[str, np.ndarray]:
        """Strain products in band order for a multi-band GeoTIFF.

        Returns
        -------
        dict
            Insertion-ordered ``name -> (n_rows, n_cols) float64``: ``exx``, ``eyy``,
            ``exy``, ``rotation_rad``, ``e1``, ``e2``, ``e1_azimuth_deg``, ``max_shear``,
            ``dilatation``.
        """
        names = (
            "exx",
            "eyy",
            "exy",
            "rotation_rad",
            "e1",
            "e2",
            "e1_azimuth_deg",
            "max_shear",
            "dilatation",
        )
        return {name: getattr(self, name) for name in names}


# --------------------------------------------------------------------------- gradient


def _check_field(field: GriddedField) -> np.ndarray:
    """Validity mask of a field fit for strain; raises on unusable input."""
    if not isinstance(field, GriddedField):
        raise InputDataError(f"strain needs a GriddedField, got {type(field).__name__}.")
    sx, sy = field.spacing_m
    if not (sx > 0 and sy > 0):  # GriddedField already refuses this; kept for safety
        raise InputDataError(f"The field's spacing_m must be > 0, got {field.spacing_m!r}.")
    n_rows, n_cols = field.shape
    if n_rows < 2 or n_cols < 2:
        raise InputDataError(
            f"Strain needs a field of at least 2 x 2 cells, got {n_rows} x {n_cols}; use a "
            "smaller cell size or a larger area."
        )
    valid = field.valid
    if not np.any(valid):
        raise InputDataError("The displacement field has no vector (all dx/dy are NaN); no strain.")
    return valid


def _diff_axis(a: np.ndarray, ok: np.ndarray, step: float, axis: int) -> np.ndarray:
    """Gap-aware derivative of ``a`` along ``axis`` towards increasing index, per ``step``."""
    a = np.moveaxis(a, axis, 0)
    ok = np.moveaxis(ok, axis, 0)
    n = a.shape[0]
    prev_ok = np.zeros_like(ok)
    next_ok = np.zeros_like(ok)
    prev_ok[1:] = ok[:-1]
    next_ok[:-1] = ok[1:]
    prev = np.full_like(a, np.nan)
    nxt = np.full_like(a, np.nan)
    if n > 1:
        prev[1:] = a[:-1]
        nxt[:-1] = a[1:]
    central = ok & prev_ok & next_ok
    forward = ok & next_ok & ~prev_ok
    backward = ok & prev_ok & ~next_ok
    out = np.full_like(a, np.nan)
    out[central] = (nxt[central] - prev[central]) / (2.0 * step)
    out[forward] = (nxt[forward] - a[forward]) / step
    out[backward] = (a[backward] - prev[backward]) / step
    return np.moveaxis(out, 0, axis)


def displacement_gradient(
    field: GriddedField,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gap-aware finite-difference displacement gradient of a gridded field (vectorised).

    Parameters
    ----------
    field : GriddedField
        At least 2 x 2 cells with at least one vector.

    Returns
    -------
    tuple of numpy.ndarray
        ``(dudx, dudy, dvdx, dvdy)``, each (n_rows, n_cols) float64 (m/m); NaN where the
        cell has no vector or no neighbour with one along that axis.
    """
    valid = _check_field(field)
    sx, sy = field.spacing_m
    u = np.where(valid, field.dx, np.nan)
    v = np.where(valid, field.dy, np.nan)
    # along rows (axis 1) x increases; along columns (axis 0) y decreases
    dudx = _diff_axis(u, valid, sx, axis=1)
    dvdx = _diff_axis(v, valid, sx, axis=1)
    dudy = -_diff_axis(u, valid, sy, axis=0)
    dvdy = -_diff_axis(v, valid, sy, axis=0)
    return dudx, dudy, dvdx, dvdy


def displacement_gradient_reference(
    field: GriddedField,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slow per-cell reference of :func:`displacement_gradient` (for tests)."""
    valid = _check_field(field)
    sx, sy = field.spacing_m
    n_rows, n_cols = field.shape
    out = [np.full((n_rows, n_cols), np.nan) for _ in range(4)]
    for r in range(n_rows):
        for c in range(n_cols):
            if not valid[r, c]:
                continue
            for k, comp in enumerate((field.dx, field.dy)):
                # x: east neighbour is c + 1, west is c - 1
                east = c + 1 < n_cols and valid[r, c + 1]
                west = c - 1 >= 0 and valid[r, c - 1]
                if east and west:
                    gx = (comp[r, c + 1] - comp[r, c - 1]) / (2 * sx)
                elif east:
                    gx = (comp[r, c + 1] - comp[r, c]) / sx
                elif west:
                    gx = (comp[r, c] - comp[r, c - 1]) / sx
                else:
                    gx = np.nan
                # y: north neighbour is r - 1 (y + sy), south is r + 1
                north = r - 1 >= 0 and valid[r - 1, c]
                south = r + 1 < n_rows and valid[r + 1, c]
                if north and south:
                    gy = (comp[r - 1, c] - comp[r + 1, c]) / (2 * sy)
                elif north:
                    gy = (comp[r - 1, c] - comp[r, c]) / sy
                elif south:
                    gy = (comp[r, c] - comp[r + 1, c]) / sy
                else:
                    gy = np.nan
                out[2 * k][r, c] = gx  # dudx or dvdx
                out[2 * k + 1][r, c] = gy  # dudy or dvdy
    dudx, dudy, dvdx, dvdy = out
    return dudx, dudy, dvdx, dvdy


# --------------------------------------------------------------------------- strain


def strain_from_gradient(
    dudx: np.ndarray, dudy: np.ndarray, dvdx: np.ndarray, dvdy: np.ndarray
) -> dict[str, np.ndarray]:
    """Infinitesimal strain quantities from displacement-gradient components.

    Parameters
    ----------
    dudx, dudy, dvdx, dvdy : numpy.ndarray
        Same-shape arrays (m/m); ``u`` east, ``v`` north.

    Returns
    -------
    dict
        ``exx``, ``eyy``, ``exy``, ``rotation_rad``, ``e1``, ``e2``, ``e1_azimuth_deg``,
        ``max_shear`` (tensor shear), ``dilatation``; arrays of the input shape.
    """
    dudx, dudy, dvdx, dvdy = (np.asarray(a, dtype=np.float64) for a in (dudx, dudy, dvdx, dvdy))
    exx = dudx.copy()
    eyy = dvdy.copy()
    exy = 0.5 * (dudy + dvdx)
    rot = 0.5 * (dvdx - dudy)
    mean = 0.5 * (exx + eyy)
    half = 0.5 * (exx - eyy)
    radius = np.hypot(half, exy)
    e1 = mean + radius
    e2 = mean - radius
    theta = 0.5 * np.arctan2(2.0 * exy, exx - eyy)  # CCW from +x, in (-90, 90] degrees
    az = np.mod(90.0 - np.degrees(theta), 180.0)
    az = np.where(az >= 180.0, 0.0, az)  # mod can round up to exactly 180
    scale = np.abs(exx) + np.abs(eyy) + np.abs(exy)
    with np.errstate(invalid="ignore"):
        isotropic = radius <= _ISOTROPIC_RTOL * scale
    az = np.where(isotropic, np.nan, az)
    return {
        "exx": exx,
        "eyy": eyy,
        "exy": exy,
        "rotation_rad": rot,
        "e1": e1,
        "e2": e2,
        "e1_azimuth_deg": az,
        "max_shear": radius,  # (e1 - e2) / 2
        "dilatation": exx + eyy,
    }


def strain_field(field: GriddedField) -> StrainField:
    """Horizontal infinitesimal strain of a gridded displacement field.

    Parameters
    ----------
    field : GriddedField
        Displacement field, at least 2 x 2 cells with at least one vector; ``dz`` is
        ignored.

    Returns
    -------
    StrainField
        On the field's grid; NaN at cells without a vector or without a neighbour with a
        vector along x or along y.

    Raises
    ------
    InputDataError
        Fewer than 2 x 2 cells, no vector at all, or no cell with neighbours along both axes
        (isolated vectors: no gradient can be estimated anywhere).

    Notes
    -----
    Finite differences: central where both neighbours have a vector, one-sided where only
    one has (first order: exact for linear fields, error ``O(spacing)`` for curved ones). See
    the module docstring for the formulas and sign conventions.
    """
    dudx, dudy, dvdx, dvdy = displacement_gradient(field)
    parts = strain_from_gradient(dudx, dudy, dvdx, dvdy)
    if not np.any(
        np.isfinite(parts["exx"]) & np.isfinite(parts["eyy"]) & np.isfinite(parts["exy"])
    ):
        raise InputDataError(
            "No cell of the displacement field has a neighbouring vector along both x and y, so no "
            "strain can be estimated; use a larger cell size or fill the gaps."
        )
    return StrainField(
        origin_xy=field.origin_xy,
        spacing_m=field.spacing_m,
        dudx=dudx,
        dudy=dudy,
        dvdx=dvdx,
        dvdy=dvdy,
        **parts,
    )
