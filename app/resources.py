"""Memory checks before large allocations, so a too-fine grid is a clear error, not exit 1."""

from __future__ import annotations

import math
import os
from typing import Callable, Optional, Tuple

import numpy as np

from .options import OptionError

#: share of the available memory one array may take
_SHARE = 0.5


def available_bytes() -> Optional[int]:
    """Memory available to this process now (bytes), None where it cannot be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return None


def check_grid_memory(
    key: str, n_cells: float, *, bytes_per_cell: float, what: str = "grid"
) -> None:
    """Refuse a grid whose working arrays would not fit in memory.

    Parameters
    ----------
    key
        The option that sets the grid's resolution (named in the message).
    n_cells
        Number of cells of the grid.
    bytes_per_cell
        Working memory per cell of the job (all its arrays together), bytes.

    Raises
    ------
    OptionError
        When ``n_cells * bytes_per_cell`` exceeds half the memory available now.
    """
    need = float(n_cells) * float(bytes_per_cell)
    avail = available_bytes()
    if avail is None or need <= _SHARE * avail:
        return
    raise OptionError(
        key,
        f"the {what} would have {n_cells:.3g} cells and need {need / 2**30:.1f} GiB, more than "
        f"the {_SHARE * avail / 2**30:.1f} GiB this machine can give it; choose a coarser value "
        "or crop the input",
    )


# --------------------------------------------------------------------------- budgets
#: most processing tiles (or blocks of a grid) one run may cut its data into: beyond it the
#: bookkeeping of empty or near-empty tiles outweighs the work (a 0.001 m tile over a 40 m
#: cloud gave ~370 000 tiles and ran for hours); 50 000 tiles of 100 m cover 500 km²
MAX_TILES = 50_000
#: a grid whose data fill less than this share of its extent (a stray point far from the
#: rest) is refused when it is large (over :data:`SPARSE_MIN_CELLS` cells)
SPARSE_SHARE = 0.01
SPARSE_MIN_CELLS = 1_000_000


def _nice_up(v: float) -> float:
    """The smallest of 1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k at or above ``v``."""
    if not (v > 0 and math.isfinite(v)):
        return v
    e = math.floor(math.log10(v))
    for m in (1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0):
        if m * 10.0**e >= v * (1 - 1e-12):
            return float(f"{m * 10.0**e:.6g}")
    return 10.0 ** (e + 1)  # pragma: no cover


def smallest_fitting(count: Callable[[float], float], size: float, budget: float) -> float:
    """The smallest round size (1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8 x 10^k) at or above ``size``
    for which ``count(size) <= budget`` (``count`` decreasing with the size)."""
    s = _nice_up(size)
    for _ in range(400):
        if count(s) <= budget:
            return s
        s = _nice_up(s * 1.0001)
    return s  # pragma: no cover - 400 steps cover 40 decades


def box_counts(lo: np.ndarray, hi: np.ndarray, size: float) -> np.ndarray:
    """Number of ``size`` squares (aligned to multiples of ``size``) each box (lo (n, 2), hi
    (n, 2)) meets."""
    lo, hi = np.asarray(lo, float)[:, :2], np.asarray(hi, float)[:, :2]
    n = np.floor(hi / size) - np.floor(lo / size) + 1
    return n[:, 0] * n[:, 1]


def check_tile_budget(
    key: str,
    count: Callable[[float], float],
    size: float,
    *,
    what: str = "tiles",
    budget: int = MAX_TILES,
    unit: str = "m",
) -> None:
    """Refuse a ``size`` (the option ``key``) that cuts the data into more than ``budget``
    pieces (``count(size)``, computed from the inputs' headers), naming the smallest that fits.

    Raises
    ------
    OptionError
        ``key``, with the count and the smallest size that fits.
    """
    n = count(size)
    if n <= budget:
        return
    best = smallest_fitting(count, size, budget)
    raise OptionError(
        key,
        f"= {size:g} {unit} cuts the data into {n:.3g} {what}, more than the {budget} one run "
        f"may take; choose {best:g} {unit} or more (the smallest that fits), or crop the input",
    )


def outlying_boxes(lo: np.ndarray, hi: np.ndarray, *, factor: float = 20.0) -> np.ndarray:
    """Indices of the boxes that lie far from all others, or are far larger than the others
    (a file holding one stray point: its header box spans the gap).

    A box is *far* when the gap to its nearest neighbouring box exceeds ``factor`` times the
    median box size, *large* when its size exceeds ``factor`` times the median (x and y, from
    the files' headers; three boxes at least, else none is named).
    """
    lo, hi = np.asarray(lo, float)[:, :2], np.asarray(hi, float)[:, :2]
    n = len(lo)
    if n < 3:
        return np.zeros(0, dtype=np.int64)
    size = np.max(hi - lo, axis=1)
    typical = max(float(np.median(size)), 1e-3)
    large = size > factor * typical
    # gap between boxes i and j: the larger of the x and y gaps (0 when they meet); rows in
    # chunks so that 10 000 files take 10 000 x 256 numbers at a time
    nearest = np.empty(n)
    for s in range(0, n, 256):
        e = min(n, s + 256)
        gx = np.maximum(lo[s:e, None, 0] - hi[None, :, 0], lo[None, :, 0] - hi[s:e, None, 0])
        gy = np.maximum(lo[s:e, None, 1] - hi[None, :, 1], lo[None, :, 1] - hi[s:e, None, 1])
        gap = np.maximum(0.0, np.maximum(gx, gy))
        gap[np.arange(e - s), np.arange(s, e)] = np.inf
        nearest[s:e] = gap.min(axis=1)
    far = nearest > factor * typical
    return np.flatnonzero(large | far)


def stray_points(xy: np.ndarray, *, share: float = 1e-4) -> Tuple[np.ndarray, np.ndarray, int]:
    """A robust extent of points: ``(lo (2,), hi (2,), n_outside)``, the box of the points
    between the ``share`` and ``1 - share`` quantiles grown by a tenth of its size (and one
    metre), and how many points lie outside it."""
    xy = np.asarray(xy, float)[:, :2]
    if len(xy) == 0:
        return np.zeros(2), np.zeros(2), 0
    q_lo = np.quantile(xy, share, axis=0)
    q_hi = np.quantile(xy, 1.0 - share, axis=0)
    pad = 0.1 * (q_hi - q_lo) + 1.0
    lo, hi = q_lo - pad, q_hi + pad
    out = np.any((xy < lo) | (xy > hi), axis=1)
    return lo, hi, int(out.sum())


def check_sparse_grid(
    key: str,
    n_cells: float,
    robust_cells: float,
    *,
    where: str,
    what: str = "grid",
) -> None:
    """Refuse a large grid whose extent is made by a few points far from the rest.

    ``n_cells``: cells of the grid over the data's whole extent; ``robust_cells``: over the
    extent without the stray points (``where`` says which they are and where they lie).
    """
    if n_cells < SPARSE_MIN_CELLS or robust_cells > SPARSE_SHARE * n_cells:
        return
    raise OptionError(
        key,
        f"the {what} would span {n_cells:.3g} cells of which the data fill {robust_cells:.3g}: "
        f"{where}; remove the stray points (e.g. PDAL filters.outlier or filters.crop) or "
        "crop the input to the study area",
    )


def point_tile_count(xys, size: float) -> int:
    """Distinct ``size`` squares (aligned to multiples of ``size``) that hold at least one of
    the points (``xys``: arrays (N, >=2), metres)."""
    keys = np.concatenate([np.floor(np.asarray(p, float)[:, :2] / size) for p in xys])
    if not len(keys):
        return 0
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(span[0]) * float(span[1]) < 2.0**62:
        return int(np.unique(keys[:, 0].astype(np.int64) * int(span[1]) + keys[:, 1]).size)
    return int(np.unique(keys, axis=0).shape[0])


def check_point_tiles(key: str, xys, size: float, *, budget: int = MAX_TILES) -> None:
    """:func:`check_tile_budget` for points in memory: the tiles holding points."""
    check_tile_budget(key, lambda s: point_tile_count(xys, s), float(size), budget=budget)
