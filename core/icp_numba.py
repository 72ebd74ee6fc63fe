"""Compiled CPU kernels of the batched windowed ICP (issue #29), through Numba.

:class:`NumbaTargets` and :class:`CellNearestCPU` are the CPU twins of
:class:`slipmap.core.opencl.nearest.GridTargets` and ``CellNearest``: the same kernels
(``core/opencl/nearest.cl`` line for line, compiled by Numba instead of an OpenCL driver), the
same target grid (:mod:`slipmap.core.target_grid`), the same interface to
:func:`slipmap.core.icp_cells.fit_cells`. Per iteration one pass over the moved source
points finds each one's nearest target (the four-candidate cache of the numpy
:class:`~slipmap.core.icp_cells._Matcher`, the exact four nearest by a search of grid columns
when a point has moved beyond it, the gate and the cell's box), and for rigid cells a second
pass gives the point-to-plane residual rows; the target normals come from the grid too.

Why compiled code and not numpy: at a few hundred thousand source points the numpy matcher
makes a dozen passes over the points per iteration and queries the KD-tree again for every
point that left its cached candidates, about 1 microsecond per point and iteration, twice
Open3D's per-cell ICP on the same points (docs/benchmarks.md). Numba is a well-kept compiler
for exactly this (numpy arrays, loops), pip- and conda-installable in QGIS's Python; it is an
optional dependency (``pip install 'slipmap[fast]'``): without it ``backend="auto"`` falls
back to the numpy matcher, which stays the reference the kernels are tested against.

The kernels release the GIL (``nogil``) and large passes are split over the CPU's cores by
a thread pool (not Numba's own ``parallel`` threading layer, whose default is not safe for
calls from several threads at once, as Dask's threaded scheduler makes). Compiled code is
cached on disk (``cache=True``): the first run on a machine compiles for a few seconds.
"""

from __future__ import annotations

import logging
import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import numpy as np

from .target_grid import PairsFromNearest, target_grid

log = logging.getLogger(__name__)

try:  # optional: the numpy matcher is the fallback
    import numba

    _IMPORT_ERROR: Optional[str] = None
except ImportError as exc:  # pragma: no cover - depends on the environment
    numba = None
    _IMPORT_ERROR = f"Numba cannot be imported ({exc})"

CANDIDATES = 4  # the cached nearest targets per source point (as the numpy matcher)
MAX_NORMAL_K = 64  # larger normal neighbourhoods stay with the host's KD-tree
PARALLEL_MIN = 40_000  # smaller passes run on the calling thread
NORMALS_PARALLEL_MIN = 4_000  # the same for target normals (a k-neighbour search each)
_CHUNKS_PER_CORE = 4
INSTALL_HINT = "install Numba: `pip install numba` (or `pip install 'slipmap[fast]'`)"


def unavailable() -> Optional[str]:
    """None when the compiled kernels can be used, else one line saying why not."""
    return _IMPORT_ERROR


def _jit(fn):
    return numba.njit(cache=True, nogil=True)(fn) if numba is not None else fn


# ----------------------------------------------------------------------------- kernels
# Line for line nearest.cl (see there for the search's bounds), and a column whose (x, y)
# rectangle is farther than the kk-th best so far is skipped; tp are the sorted centred
# targets, colstart the columns' first targets; sorted target indices, -1: none.


@_jit
def _grid_knn(tp, colstart, nx, ny, x0, y0, h, x, y, z, kk, d, j):  # pragma: no cover
    for m in range(kk):
        d[m] = np.inf
        j[m] = -1
    fx = (x - x0) / h
    fy = (y - y0) / h
    cxf = min(max(math.floor(fx), -1.0e9), 1.0e9)
    cyf = min(max(math.floor(fy), -1.0e9), 1.0e9)
    cx = int(cxf)
    cy = int(cyf)
    e = max(min(min(fx - cxf, cxf + 1.0 - fx), min(fy - cyf, cyf + 1.0 - fy)), 0.0) * h
    dxo = -cx if cx < 0 else (cx - nx + 1 if cx >= nx else 0)
    dyo = -cy if cy < 0 else (cy - ny + 1 if cy >= ny else 0)
    r0 = max(dxo, dyo)
    rmax = r0 + max(nx, ny)
    for r in range(r0, rmax + 1):
        if r > 0:
            lb = ((r - 1) * h + e) * (1.0 - 1.0e-12)
            if lb > 0.0 and lb * lb > d[kk - 1]:
                break
        ylo = max(cy - r, 0)
        yhi = min(cy + r, ny - 1)
        for yy in range(ylo, yhi + 1):
            edge = yy == cy - r or yy == cy + r
            if edge:
                xlo = max(cx - r, 0)
                xhi = min(cx + r, nx - 1)
                step = 1
            else:
                xlo = cx - r
                xhi = cx + r
                step = 1 if r == 0 else 2 * r
            # the column's (x, y) rectangle lower-bounds its targets' distances
            ey = max(y0 + yy * h - y, y - (y0 + (yy + 1) * h), 0.0)
            xx = xlo
            while xx <= xhi:
                ex = max(x0 + xx * h - x, x - (x0 + (xx + 1) * h), 0.0)
                if 0 <= xx < nx and (ex * ex + ey * ey) * (1.0 - 1.0e-12) <= d[kk - 1]:
                    c = yy * nx + xx
                    for k in range(colstart[c], colstart[c + 1]):
                        dx = tp[k, 0] - x
                        dy = tp[k, 1] - y
                        dz = tp[k, 2] - z
                        dk = dx * dx + dy * dy + dz * dz
                        if dk < d[kk - 1] or (dk == d[kk - 1] and k < j[kk - 1]):
                            m = kk - 1
                            while m > 0 and (dk < d[m - 1] or (dk == d[m - 1] and k < j[m - 1])):
                                d[m] = d[m - 1]
                                j[m] = j[m - 1]
                                m -= 1
                            d[m] = dk
                            j[m] = k
                xx += step


@_jit
def _dist2(tp, k, x, y, z):  # pragma: no cover
    dx = tp[k, 0] - x
    dy = tp[k, 1] - y
    dz = tp[k, 2] - z
    return dx * dx + dy * dy + dz * dz


@_jit
def _match_point(
    tp, colstart, nx, ny, x0, y0, h, boxes, use_boxes, gate2, c, g, x, y, z,
    last, m1, mc, cand, d, jj,
):  # fmt: skip  # pragma: no cover
    kc = cand.shape[1]
    mx = x - last[g, 0]
    my = y - last[g, 1]
    mz = z - last[g, 2]
    move2 = mx * mx + my * my + mz * mz
    a1 = m1[g]
    ac = mc[g]
    if a1 > 0.0 and move2 < a1 * a1:
        j = cand[g, 0]
    elif ac > 0.0 and move2 < ac * ac:
        j = -1
        best = np.inf
        for m in range(kc):
            k = cand[g, m]
            if k < 0:
                continue
            dk = _dist2(tp, k, x, y, z)
            if dk < best or (dk == best and k < j):
                best = dk
                j = k
    else:
        _grid_knn(tp, colstart, nx, ny, x0, y0, h, x, y, z, kc, d, jj)
        last[g, 0] = x
        last[g, 1] = y
        last[g, 2] = z
        for m in range(kc):
            cand[g, m] = jj[m]
        if math.isfinite(d[0]):
            d0 = math.sqrt(d[0])
            m1[g] = 0.5 * (math.sqrt(d[1]) - d0)
            mc[g] = 0.5 * (math.sqrt(d[kc - 1]) - d0)
        else:
            m1[g] = -1.0
            mc[g] = -1.0
        j = jj[0]
    if j >= 0 and not (_dist2(tp, j, x, y, z) <= gate2):
        j = -1
    if j >= 0 and use_boxes:
        tx = tp[j, 0]
        ty = tp[j, 1]
        if not (
            tx >= boxes[c, 0] and tx <= boxes[c, 1] and ty >= boxes[c, 2] and ty <= boxes[c, 3]
        ):
            j = -1
    return j


@_jit
def _cell_match(
    tp, colstart, perm, nx, ny, x0, y0, h, centres, boxes, use_boxes, gate2,
    src, seg, pm, lin, t, last, m1, mc, cand, out, out_sorted, i0, i1,
):  # fmt: skip  # pragma: no cover
    """Pairs of the source points pm[i0:i1], each moved by its cell's (lin, t)."""
    kc = cand.shape[1]
    d = np.empty(kc)
    jj = np.empty(kc, dtype=np.int64)
    for i in range(i0, i1):
        g = pm[i]
        c = seg[g]
        sx, sy, sz = src[g, 0], src[g, 1], src[g, 2]
        qx = lin[c, 0, 0] * sx + lin[c, 0, 1] * sy + lin[c, 0, 2] * sz + t[c, 0]
        qy = lin[c, 1, 0] * sx + lin[c, 1, 1] * sy + lin[c, 1, 2] * sz + t[c, 1]
        qz = lin[c, 2, 0] * sx + lin[c, 2, 1] * sy + lin[c, 2, 2] * sz + t[c, 2]
        j = _match_point(
            tp, colstart, nx, ny, x0, y0, h, boxes, use_boxes, gate2, c, g,
            qx + centres[c, 0], qy + centres[c, 1], qz + centres[c, 2],
            last, m1, mc, cand, d, jj,
        )  # fmt: skip
        out[i] = perm[j] if j >= 0 else -1
        out_sorted[i] = j


@_jit
def _cell_nearest(
    tp, colstart, perm, nx, ny, x0, y0, h, centres, boxes, use_boxes, gate2,
    q, seg, gi, last, m1, mc, cand, out, i0, i1,
):  # fmt: skip  # pragma: no cover
    """Pairs of the moved points q[i0:i1] (centred on their cells seg, cache slots gi)."""
    kc = cand.shape[1]
    d = np.empty(kc)
    jj = np.empty(kc, dtype=np.int64)
    for i in range(i0, i1):
        c = seg[i]
        j = _match_point(
            tp, colstart, nx, ny, x0, y0, h, boxes, use_boxes, gate2, c, gi[i],
            q[i, 0] + centres[c, 0], q[i, 1] + centres[c, 1], q[i, 2] + centres[c, 2],
            last, m1, mc, cand, d, jj,
        )  # fmt: skip
        out[i] = perm[j] if j >= 0 else -1


@_jit
def _cell_residuals(
    tp, centres, src, seg, pm, lin, t, normals, out, out_sorted, ok, v, A, qq, i0, i1,
):  # fmt: skip  # pragma: no cover
    """Rigid point-to-plane rows of the pairs of _cell_match: residual, (q x n, n), q . q."""
    for i in range(i0, i1):
        j = out[i]
        ok[i] = False
        if j < 0:
            continue
        nx = normals[j, 0]
        ny = normals[j, 1]
        nz = normals[j, 2]
        if not (math.isfinite(nx) and math.isfinite(ny) and math.isfinite(nz)):
            continue
        js = out_sorted[i]
        g = pm[i]
        c = seg[g]
        sx, sy, sz = src[g, 0], src[g, 1], src[g, 2]
        q0 = lin[c, 0, 0] * sx + lin[c, 0, 1] * sy + lin[c, 0, 2] * sz + t[c, 0]
        q1 = lin[c, 1, 0] * sx + lin[c, 1, 1] * sy + lin[c, 1, 2] * sz + t[c, 1]
        q2 = lin[c, 2, 0] * sx + lin[c, 2, 1] * sy + lin[c, 2, 2] * sz + t[c, 2]
        dx = q0 - (tp[js, 0] - centres[c, 0])
        dy = q1 - (tp[js, 1] - centres[c, 1])
        dz = q2 - (tp[js, 2] - centres[c, 2])
        ok[i] = True
        v[i] = nx * dx + ny * dy + nz * dz
        A[i, 0] = q1 * nz - q2 * ny
        A[i, 1] = q2 * nx - q0 * nz
        A[i, 2] = q0 * ny - q1 * nx
        A[i, 3] = nx
        A[i, 4] = ny
        A[i, 5] = nz
        qq[i] = q0 * q0 + q1 * q1 + q2 * q2


@_jit
def _target_normals(
    tp, colstart, nx, ny, x0, y0, h, iperm, ids, kk, out, hard, i0, i1
):  # pragma: no cover
    """Normals of targets ids[i0:i1] from their kk nearest (nearest.cl target_normals: the
    closed form of slipmap.core.icp._pca_normals; hard: left to eigh on the host)."""
    d = np.empty(kk)
    jj = np.empty(kk, dtype=np.int64)
    for i in range(i0, i1):
        s = iperm[ids[i]]
        _grid_knn(tp, colstart, nx, ny, x0, y0, h, tp[s, 0], tp[s, 1], tp[s, 2], kk, d, jj)
        mx = 0.0
        my = 0.0
        mz = 0.0
        for m in range(kk):
            mx += tp[jj[m], 0]
            my += tp[jj[m], 1]
            mz += tp[jj[m], 2]
        mx /= kk
        my /= kk
        mz /= kk
        a00 = a11 = a22 = a01 = a02 = a12 = 0.0
        for m in range(kk):
            ux = tp[jj[m], 0] - mx
            uy = tp[jj[m], 1] - my
            uz = tp[jj[m], 2] - mz
            a00 += ux * ux
            a11 += uy * uy
            a22 += uz * uz
            a01 += ux * uy
            a02 += ux * uz
            a12 += uy * uz
        q = (a00 + a11 + a22) / 3.0
        b00 = a00 - q
        b11 = a11 - q
        b22 = a22 - q
        p = math.sqrt(
            (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0
        )
        det = (
            b00 * (b11 * b22 - a12 * a12)
            - a01 * (a01 * b22 - a12 * a02)
            + a02 * (a01 * a12 - b11 * a02)
        )
        pp = p if p > 0.0 else 1.0
        r = min(max(det / (2.0 * pp * pp * pp), -1.0), 1.0)
        phi = math.acos(r) / 3.0
        e2 = q + 2.0 * p * math.cos(phi)
        e0 = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
        e1 = 3.0 * q - e2 - e0
        r00, r01, r02 = a00 - e0, a01, a02
        r10, r11, r12 = a01, a11 - e0, a12
        r20, r21, r22 = a02, a12, a22 - e0
        # the largest of the three cross products of two rows of C - e0 I
        cx = r01 * r12 - r02 * r11
        cy = r02 * r10 - r00 * r12
        cz = r00 * r11 - r01 * r10
        nn = cx * cx + cy * cy + cz * cz
        bx = r01 * r22 - r02 * r21
        by = r02 * r20 - r00 * r22
        bz = r00 * r21 - r01 * r20
        vv = bx * bx + by * by + bz * bz
        if vv > nn:
            cx, cy, cz, nn = bx, by, bz, vv
        bx = r11 * r22 - r12 * r21
        by = r12 * r20 - r10 * r22
        bz = r10 * r21 - r11 * r20
        vv = bx * bx + by * by + bz * bz
        if vv > nn:
            cx, cy, cz, nn = bx, by, bz, vv
        norm = math.sqrt(max(nn, 1e-300))
        sgn = -1.0 if cz < 0.0 else 1.0
        out[i, 0] = sgn * cx / norm
        out[i, 1] = sgn * cy / norm
        out[i, 2] = sgn * cz / norm
        scale = max(e2, 1e-300)
        hard[i] = not ((e1 - e0 > 1e-3 * scale) and (e1 > 1e-6 * scale))


@_jit
def _normal_equations6(A, w, v, seg, N, b):  # pragma: no cover
    """N[c] = sum w a a', b[c] = -sum w a v of 6-parameter rows A (J, 6), segments sorted:
    the 27 sums of a segment in registers."""
    n = A.shape[0]
    i = 0
    while i < n:
        c = seg[i]
        s00 = s01 = s02 = s03 = s04 = s05 = 0.0
        s11 = s12 = s13 = s14 = s15 = 0.0
        s22 = s23 = s24 = s25 = 0.0
        s33 = s34 = s35 = 0.0
        s44 = s45 = 0.0
        s55 = 0.0
        t0 = t1 = t2 = t3 = t4 = t5 = 0.0
        while i < n and seg[i] == c:
            wi = w[i]
            a0, a1, a2, a3, a4, a5 = A[i, 0], A[i, 1], A[i, 2], A[i, 3], A[i, 4], A[i, 5]
            w0, w1, w2, w3, w4, w5 = wi * a0, wi * a1, wi * a2, wi * a3, wi * a4, wi * a5
            s00 += w0 * a0
            s01 += w0 * a1
            s02 += w0 * a2
            s03 += w0 * a3
            s04 += w0 * a4
            s05 += w0 * a5
            s11 += w1 * a1
            s12 += w1 * a2
            s13 += w1 * a3
            s14 += w1 * a4
            s15 += w1 * a5
            s22 += w2 * a2
            s23 += w2 * a3
            s24 += w2 * a4
            s25 += w2 * a5
            s33 += w3 * a3
            s34 += w3 * a4
            s35 += w3 * a5
            s44 += w4 * a4
            s45 += w4 * a5
            s55 += w5 * a5
            vi = v[i]
            t0 += w0 * vi
            t1 += w1 * vi
            t2 += w2 * vi
            t3 += w3 * vi
            t4 += w4 * vi
            t5 += w5 * vi
            i += 1
        up = (
            (s00, s01, s02, s03, s04, s05), (s01, s11, s12, s13, s14, s15),
            (s02, s12, s22, s23, s24, s25), (s03, s13, s23, s33, s34, s35),
            (s04, s14, s24, s34, s44, s45), (s05, s15, s25, s35, s45, s55),
        )  # fmt: skip
        for r in range(6):
            for q in range(6):
                N[c, r, q] = up[r][q]
        b[c, 0] = -t0
        b[c, 1] = -t1
        b[c, 2] = -t2
        b[c, 3] = -t3
        b[c, 4] = -t4
        b[c, 5] = -t5


def normal_matrices(A: np.ndarray, w: np.ndarray, v: np.ndarray, seg: np.ndarray, k: int):
    """Compiled :func:`slipmap.core.icp_cells._normal_matrices` for rigid rows (P = 6; other
    models go to that numpy reference, which this is tested equal to, to rounding):
    ``N_k = sum w a a'`` (K, 6, 6) and ``b_k = -sum w a v`` (K, 6) over the rows (J, 6) of
    each segment of the sorted ``seg`` (J,), in one pass."""
    if A.shape[1] != 6:
        from .icp_cells import _normal_matrices

        return _normal_matrices(A, w, v, seg, k)
    N = np.zeros((k, 6, 6))
    b = np.zeros((k, 6))
    _normal_equations6(
        np.ascontiguousarray(A, dtype=np.float64), np.ascontiguousarray(w, dtype=np.float64),
        np.ascontiguousarray(v, dtype=np.float64), np.ascontiguousarray(seg, dtype=np.int64),
        N, b,
    )  # fmt: skip
    return N, b


# ----------------------------------------------------------------------------- host side
_POOL: Optional[ThreadPoolExecutor] = None
_POOL_PID = 0


def _cores() -> int:
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not Linux
        return max(os.cpu_count() or 1, 1)


def _run(kernel, n: int, *args, parallel_min: int = PARALLEL_MIN) -> None:
    """``kernel(*args, i0, i1)`` over ``0 .. n``: in one call below ``parallel_min`` items,
    else in chunks on a thread pool, a few per core so that a core slowed by other work
    holds up little (the kernels release the GIL and write disjoint rows)."""
    global _POOL, _POOL_PID
    workers = _cores()
    if n < parallel_min or workers == 1:
        kernel(*args, 0, n)
        return
    if _POOL is None or _POOL_PID != os.getpid():  # a forked child has none of its threads
        _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="slipmap-icp")
        _POOL_PID = os.getpid()
    bounds = np.linspace(0, n, _CHUNKS_PER_CORE * workers + 1).astype(np.int64)
    futures = [_POOL.submit(kernel, *args, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
    for f in futures:
        f.result()


class NumbaTargets:
    """The target points in grid columns for the compiled CPU kernels (built once per epoch).

    Parameters
    ----------
    before : (M, 3) float64
        Target (epoch 1) points, metres (map coordinates).

    Raises
    ------
    slipmap.core.errors.DependencyError
        Numba cannot be imported.
    """

    MAX_NORMAL_K = MAX_NORMAL_K

    def __init__(self, before: np.ndarray) -> None:
        if numba is None:
            from .errors import DependencyError

            raise DependencyError(
                f"backend 'numba': {_IMPORT_ERROR}; {INSTALL_HINT}, or choose backend 'auto' "
                "(numpy where Numba is missing)"
            )
        g = target_grid(before)
        self.M = len(before)
        self.offset, self.h, self.nx, self.ny, self.lo = g.offset, g.h, g.nx, g.ny, g.lo
        self.points, self.perm, self.iperm, self.colstart = g.points, g.perm, g.iperm, g.colstart
        log.debug("CPU target grid: %d x %d columns of %.3f m for %d points",
                  self.nx, self.ny, self.h, self.M)  # fmt: skip

    def _grid_args(self):
        return (self.points, self.colstart, self.nx, self.ny, self.lo[0], self.lo[1], self.h)

    def normals(self, ids: np.ndarray, k: int):
        """Normals of targets ``ids`` (J,) from their ``k`` nearest targets: (J, 3) unit
        normals (z >= 0) and a (J,) mask of the neighbourhoods whose two smallest eigenvalues
        nearly coincide (to be recomputed with ``eigh``: :func:`slipmap.core.icp._pca_normals`).
        """
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        n = len(ids)
        out = np.empty((n, 3))
        hard = np.zeros(n, dtype=np.bool_)
        if n:
            _run(
                _target_normals, n, *self._grid_args(), self.iperm, ids, int(k), out, hard,
                parallel_min=NORMALS_PARALLEL_MIN,
            )  # fmt: skip
        return out, hard

    def matcher(self, before, normals, gate, boxes, centres, n_points) -> CellNearestCPU:
        """The batched ICP's matcher over these targets (:class:`CellNearestCPU`)."""
        return CellNearestCPU(before, self, normals, gate, boxes, centres, n_points)


class CellNearestCPU(PairsFromNearest):
    """:class:`slipmap.core.icp_cells._Matcher` with the matching compiled (the same
    constructor arguments plus ``grid``, the same call, and the fused rigid :meth:`step` of
    :class:`slipmap.core.opencl.nearest.CellNearest`)."""

    def __init__(self, before, grid: NumbaTargets, normals, gate, boxes, centres, n_points):
        self.before, self.grid, self.normals = before, grid, normals
        off = grid.offset
        self.centres = np.asarray(centres, dtype=np.float64)
        self.centres_c = np.ascontiguousarray(self.centres - off)
        self.use_boxes = boxes is not None
        bx = np.zeros((max(len(self.centres), 1), 4))
        if boxes is not None:
            bx = np.asarray(boxes, dtype=np.float64) - off[[0, 0, 1, 1]]
        self.boxes = np.ascontiguousarray(bx)
        self.gate2 = float(gate) ** 2 if math.isfinite(gate) else math.inf
        n = max(int(n_points), 1)
        self.last = np.full((n, 3), np.nan)
        self.m1 = np.full(n, -1.0)
        self.mc = np.full(n, -1.0)
        self.cand = np.full((n, CANDIDATES), -1, dtype=np.int64)

    normal_matrices = staticmethod(normal_matrices)

    def _match_args(self):
        g = self.grid
        return (
            g.points, g.colstart, g.perm, g.nx, g.ny, g.lo[0], g.lo[1], g.h,
            self.centres_c, self.boxes, self.use_boxes, self.gate2,
        )  # fmt: skip

    def _cache(self):
        return (self.last, self.m1, self.mc, self.cand)

    def load_sources(self, src: np.ndarray, seg: np.ndarray) -> None:
        """The cells' source points (P, 3) (centred per cell) and their cells (P,)."""
        self.src = np.ascontiguousarray(src, dtype=np.float64)
        self.seg = np.ascontiguousarray(seg, dtype=np.int64)

    def step(self, lin: np.ndarray, t: np.ndarray, pm: np.ndarray):
        """One rigid iteration's rows for the source points ``pm`` (P',): each moved by its
        cell's ``lin`` (K, 3, 3) and ``t`` (K, 3), paired, and its point-to-plane residual.

        Returns ``ok`` (P',) bool (a pair with a normal) and, for those, the residuals ``v``,
        the Jacobian rows ``A`` (J, 6) = ``(q x n, n)`` and ``q . q``.
        """
        n = len(pm)
        if n == 0:
            return np.zeros(0, bool), np.zeros(0), np.zeros((0, 6)), np.zeros(0)
        pm = np.ascontiguousarray(pm, dtype=np.int64)
        lin = np.ascontiguousarray(lin, dtype=np.float64)
        t = np.ascontiguousarray(t, dtype=np.float64)
        out = np.empty(n, dtype=np.int64)
        out_sorted = np.empty(n, dtype=np.int64)
        _run(
            _cell_match, n, *self._match_args(), self.src, self.seg, pm, lin, t,
            *self._cache(), out, out_sorted,
        )  # fmt: skip
        self.normals.ensure(out[out >= 0])
        ok = np.empty(n, dtype=np.bool_)
        v, A, qq = np.empty(n), np.empty((n, 6)), np.empty(n)
        _run(
            _cell_residuals, n, self.grid.points, self.centres_c, self.src, self.seg, pm, lin,
            t, self.normals.normals, out, out_sorted, ok, v, A, qq,
        )  # fmt: skip
        if ok.all():
            return ok, v, A, qq
        return ok, v[ok], A[ok], qq[ok]

    def nearest(self, q: np.ndarray, seg: np.ndarray, gi: np.ndarray) -> np.ndarray:
        """(P',) original index of each moved point's nearest usable target, -1: none (beyond
        the gate or outside the cell's box)."""
        n = len(q)
        out = np.empty(n, dtype=np.int64)
        if n:
            _run(
                _cell_nearest, n, *self._match_args(),
                np.ascontiguousarray(q, dtype=np.float64),
                np.ascontiguousarray(seg, dtype=np.int64),
                np.ascontiguousarray(gi, dtype=np.int64), *self._cache(), out,
            )  # fmt: skip
        return out
