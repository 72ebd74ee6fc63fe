"""Target points bucketed by the columns of a 2-D (x, y) grid (issues #18, #29).

The layout the compiled matchers search (:mod:`slipmap.core.icp_numba` on the CPU,
:mod:`slipmap.core.opencl.nearest` on an OpenCL device): the epoch-1 points centred on their
mean and sorted by grid column, ``colstart[c] .. colstart[c + 1]`` the targets of column
``c = row * nx + col``. Pure numpy; built once per epoch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

PER_COLUMN = 2.0  # targets per grid column on average (measured: 2 beats 1, 4 and 8)
MAX_COLUMN_FACTOR = 4  # at most this many columns per target


@dataclass(frozen=True)
class TargetGrid:
    """Targets sorted by grid column.

    Attributes
    ----------
    offset : (3,) float64
        Mean of the targets (metres); every coordinate below is relative to it.
    lo : (2,) float64
        (x, y) of the grid's lower-left corner, metres.
    h : float
        Column size, metres.
    nx, ny : int
        Columns along x and y.
    points : (M, 3) float64
        The centred targets in column order.
    perm : (M,) int64
        Original index of each sorted target.
    iperm : (M,) int64
        Sorted index of each original target.
    colstart : (nx * ny + 1,) int64
        First sorted target of each column (and the end).
    """

    offset: np.ndarray
    lo: np.ndarray
    h: float
    nx: int
    ny: int
    points: np.ndarray
    perm: np.ndarray
    iperm: np.ndarray
    colstart: np.ndarray


def _columns(c, lo, ext, h):
    nx = int(ext[0] // h) + 1
    ny = int(ext[1] // h) + 1
    ix = np.clip(((c[:, 0] - lo[0]) // h).astype(np.int64), 0, nx - 1)
    iy = np.clip(((c[:, 1] - lo[1]) // h).astype(np.int64), 0, ny - 1)
    return iy * nx + ix, nx, ny


def target_grid(before: np.ndarray) -> TargetGrid:
    """Bucket the targets ``before`` (M, 3) (metres, map coordinates) by grid columns.

    About ``PER_COLUMN`` targets per column over the bounding box, the column size halved
    while the occupied columns are crowded (uneven coverage), never more than
    ``MAX_COLUMN_FACTOR`` columns per target.
    """
    b = np.asarray(before, dtype=np.float64)
    m = len(b)
    offset = b.mean(axis=0) if m else np.zeros(3)
    c = b - offset
    lo = c[:, :2].min(axis=0) if m else np.zeros(2)
    ext = np.maximum((c[:, :2].max(axis=0) - lo) if m else np.ones(2), 1e-9)
    h = max(math.sqrt(ext[0] * ext[1] * PER_COLUMN / max(m, 1)), 1e-6)
    for _ in range(6):
        col, nx, ny = _columns(c, lo, ext, h)
        occupied = np.count_nonzero(np.bincount(col, minlength=nx * ny)) if m else 1
        if m / max(occupied, 1) <= 8 * PER_COLUMN:
            break
        h2 = h / 2
        if (ext[0] / h2 + 1) * (ext[1] / h2 + 1) > MAX_COLUMN_FACTOR * m + 1024:
            break
        h = h2
    order = np.argsort(col, kind="stable")
    iperm = np.empty(m, dtype=np.int64)
    iperm[order] = np.arange(m, dtype=np.int64)
    return TargetGrid(
        offset=offset,
        lo=lo,
        h=float(h),
        nx=nx,
        ny=ny,
        points=np.ascontiguousarray(c[order]),
        perm=order.astype(np.int64),
        iperm=iperm,
        colstart=np.searchsorted(col[order], np.arange(nx * ny + 1)).astype(np.int64),
    )


class PairsFromNearest:
    """The batched ICP's matcher call shared by the compiled matchers (Numba on the CPU,
    OpenCL): ``matcher(q, seg, gi) -> (ok, target - cell centre, normal, target id)`` from
    the subclass's ``nearest(q, seg, gi)`` (-1: none within the gate), ``normals(ids)``,
    ``before`` and ``centres``; targets whose normal is undefined are dropped."""

    def __call__(self, q: np.ndarray, seg: np.ndarray, gi: np.ndarray):
        j = self.nearest(q, seg, gi)
        ok = j >= 0
        jj = j[ok]
        nrm = self.normals(jj)
        fin = np.isfinite(nrm).all(axis=1)
        if not fin.all():
            ok[np.flatnonzero(ok)[~fin]] = False
            jj, nrm = jj[fin], nrm[fin]
        return ok, self.before[jj] - self.centres[seg[ok]], nrm, jj
