"""Nearest target points of the batched windowed ICP on an OpenCL device (issue #18).

:class:`CellNearest` is a drop-in for :class:`slipmap.core.icp_cells._Matcher` (the slow,
obvious reference is a fresh ``cKDTree`` query, which the numpy matcher is tested against):
the same pairs (up to exact ties), the same cache of four candidate targets per source point,
but the cache test, the grid search, the gate and the cell's box are one kernel pass over the
moved points (``nearest.cl``) instead of a dozen numpy passes and a tree query. For rigid
cells :meth:`CellNearest.step` also moves the points and computes their residual rows there.
The target normals are computed on the device too (:meth:`GridTargets.normals`), on first
use, into the host's :class:`slipmap.core.icp._NormalCache`.

Why a kernel and not numpy/scipy: at 0.3-0.5 million source points per iteration the numpy
matcher spends about 0.6 microseconds per point and iteration in passes over the points
(gathers, masks, the tree query of the points that moved), two thirds of the batched ICP's
time; a compiled pass does the same work in one read of each point. The same kernels run
on the CPU through Numba (:mod:`slipmap.core.icp_numba`, ``backend="numba"``), where no
OpenCL driver is installed.

Targets are bucketed by the columns of a 2D grid (:mod:`slipmap.core.target_grid`, see
``nearest.cl``); coordinates are centred on the targets' mean before they reach the device.
"""

from __future__ import annotations

import logging
import math
import warnings
from pathlib import Path

import numpy as np

from ..target_grid import PairsFromNearest, target_grid
from .backend import _runtime

log = logging.getLogger(__name__)

KERNEL_FILE = Path(__file__).parent / "nearest.cl"
CANDIDATES = 4  # KC of nearest.cl: the cached nearest targets per source point
MAX_NORMAL_K = 64  # KMAX of nearest.cl: larger neighbourhoods stay on the host


class _Program:
    """The compiled ``nearest.cl`` of the process's runtime: its kernels and their
    work-group sizes."""

    _cache: dict = {}

    @classmethod
    def get(cls, rt) -> dict:
        key = (id(rt), rt.pid)
        if key not in cls._cache:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # a non-empty build log is a CompilerWarning
                prog = rt.cl.Program(rt.ctx, KERNEL_FILE.read_text(encoding="utf-8")).build()
            i8, f8, i4 = np.int64, np.float64, np.int32
            # tp, colstart, nx, ny, x0, y0, h
            grid = [None, None, i8, i8, f8, f8, f8]
            # tp, colstart, perm, nx, ny, x0, y0, h, centres, boxes, use_boxes, gate2
            match = grid[:2] + [None] + grid[2:] + [None, None, i4, f8]
            kernels = {}
            for name, dtypes in (
                ("cell_nearest", match + [None, None, None, i8] + [None] * 5),
                ("cell_match", match + [None, None, None, i8] + [None] * 8),
                ("cell_residuals", [None] * 5 + [i8] + [None] * 9),
                ("target_normals", grid + [None, None, i8, i4, None, None]),
            ):
                k = rt.cl.Kernel(prog, name)
                k.set_scalar_arg_dtypes(dtypes)
                info = rt.cl.kernel_work_group_info.WORK_GROUP_SIZE
                most = int(k.get_work_group_info(info, rt.device))
                local = 64
                while local > max(1, most):
                    local //= 2
                kernels[name] = (k, local)
            cls._cache[key] = kernels
        return cls._cache[key]


class GridTargets:
    """Target points bucketed by (x, y) grid columns on the device, built once per epoch.

    Parameters
    ----------
    before : (M, 3) float64
        Target (epoch 1) points, metres (map coordinates).
    """

    MAX_NORMAL_K = MAX_NORMAL_K

    def __init__(self, before: np.ndarray) -> None:
        self.rt = _runtime()
        self.kernels = _Program.get(self.rt)
        self.M = len(before)
        if self.M >= np.iinfo(np.int32).max:
            raise ValueError("more than 2**31 target points")
        g = target_grid(before)
        self.offset, self.h, self.nx, self.ny, self.lo = g.offset, g.h, g.nx, g.ny, g.lo
        self.perm = g.perm.astype(np.int32)
        self.points = g.points
        self.buf_points = self.rt.to_device(self.points)
        self.buf_colstart = self.rt.to_device(g.colstart.astype(np.int32))
        self.buf_perm = self.rt.to_device(self.perm)
        self.buf_iperm = self.rt.to_device(g.iperm.astype(np.int32))
        log.debug(
            "OpenCL target grid: %d x %d columns of %.3f m for %d points",
            self.nx, self.ny, self.h, self.M,
        )  # fmt: skip

    def matcher(self, before, normals, gate, boxes, centres, n_points) -> CellNearest:
        """The batched ICP's matcher over these targets (:class:`CellNearest`)."""
        return CellNearest(before, self, normals, gate, boxes, centres, n_points)

    def run(self, name: str, n: int, *args) -> None:
        """Enqueue kernel ``name`` over ``n`` work-items (rounded up to whole work groups;
        the kernels bound-check)."""
        kernel, local = self.kernels[name]
        kernel(self.rt.queue, (-(-int(n) // local) * local,), (local,), *args)

    def normals(self, ids: np.ndarray, k: int):
        """Normals of targets ``ids`` (J,) from their ``k`` nearest targets: (J, 3) unit
        normals (z >= 0) and a (J,) mask of the neighbourhoods whose two smallest eigenvalues
        nearly coincide (to be recomputed with ``eigh``: :func:`slipmap.core.icp._pca_normals`).
        """
        ids = np.ascontiguousarray(ids, dtype=np.int64)
        n = len(ids)
        out = np.empty((n, 3))
        hard = np.empty(n, dtype=np.int32)
        if n == 0:
            return out, hard.astype(bool)
        rt = self.rt
        bo, bh = rt.empty(out.nbytes), rt.empty(hard.nbytes)
        self.run(
            "target_normals", n,
            self.buf_points, self.buf_colstart, self.nx, self.ny, self.lo[0], self.lo[1],
            self.h, self.buf_iperm, rt.to_device(ids), n, int(k), bo, bh,
        )  # fmt: skip
        rt.read(out, bo)
        rt.read(hard, bh)
        return out, hard.astype(bool)


class CellNearest(PairsFromNearest):
    """:class:`slipmap.core.icp_cells._Matcher` with the matching on an OpenCL device.

    Same constructor arguments plus ``grid`` (:class:`GridTargets` of ``before``); same
    call: ``(q (P', 3) centred per cell, seg (P',), gi (P',)) -> ok, target (J, 3) centred,
    normals (J, 3), target ids (J,)``.
    """

    def __init__(self, before, grid: GridTargets, normals, gate, boxes, centres, n_points):
        self.before, self.grid, self.normals = before, grid, normals
        rt = self.rt = grid.rt
        self.centres = np.asarray(centres, dtype=np.float64)
        off = grid.offset
        self.buf_centres = rt.to_device(self.centres - off)
        self.use_boxes = boxes is not None
        bx = np.zeros((max(len(self.centres), 1), 4))
        if boxes is not None:
            bx = np.asarray(boxes, dtype=np.float64) - off[[0, 0, 1, 1]]
        self.buf_boxes = rt.to_device(bx)
        self.gate2 = float(gate) ** 2 if math.isfinite(gate) else math.inf
        n = max(int(n_points), 1)
        mf = rt.cl.mem_flags
        self.buf_last = rt.cl.Buffer(
            rt.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.full((n, 3), np.nan)
        )
        neg = np.full(n, -1.0)
        self.buf_m1 = rt.cl.Buffer(rt.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=neg)
        self.buf_mc = rt.cl.Buffer(rt.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=neg)
        self.buf_cand = rt.cl.Buffer(
            rt.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.full(CANDIDATES * n, -1, np.int32)
        )

    # ------------------------------------------------------------- the fused rigid step
    def load_sources(self, src: np.ndarray, seg: np.ndarray) -> None:
        """Put the cells' source points (P, 3) (centred per cell) and their cells (P,) on the
        device for :meth:`step`."""
        rt = self.rt
        self.buf_src = rt.to_device(np.ascontiguousarray(src, dtype=np.float64))
        self.buf_seg = rt.to_device(np.asarray(seg, dtype=np.int32))
        self.buf_normals = None  # the normals array on the device (see step)

    def step(self, lin: np.ndarray, t: np.ndarray, pm: np.ndarray):
        """One rigid iteration's rows for the source points ``pm`` (P',): each moved by its
        cell's ``lin`` (K, 3, 3) and ``t`` (K, 3), paired, and its point-to-plane residual.

        Returns ``ok`` (P',) bool (a pair with a normal) and, for those, the residuals ``v``,
        the Jacobian rows ``A`` (J, 6) = ``(q x n, n)`` and ``q . q`` (the same as
        :func:`slipmap.core.icp_cells.fit_cells` computes on the host).
        """
        rt, g = self.rt, self.grid
        n = len(pm)
        out = np.empty(n, dtype=np.int32)
        if n == 0:
            return np.zeros(0, bool), np.zeros(0), np.zeros((0, 6)), np.zeros(0)
        b_pm = rt.to_device(np.asarray(pm, dtype=np.int32))
        b_lin = rt.to_device(np.ascontiguousarray(lin, dtype=np.float64).reshape(-1, 9))
        b_t = rt.to_device(np.ascontiguousarray(t, dtype=np.float64).reshape(-1, 3))
        b_out, b_sorted = rt.empty(out.nbytes), rt.empty(out.nbytes)
        g.run(
            "cell_match", n,
            g.buf_points, g.buf_colstart, g.buf_perm, g.nx, g.ny, g.lo[0], g.lo[1], g.h,
            self.buf_centres, self.buf_boxes, int(self.use_boxes), self.gate2,
            self.buf_src, self.buf_seg, b_pm, n, b_lin, b_t,
            self.buf_last, self.buf_m1, self.buf_mc, self.buf_cand, b_out, b_sorted,
        )  # fmt: skip
        rt.read(out, b_out)
        # the normals of new targets (into the host array), on the device again when any
        if self.normals.ensure(out[out >= 0]) or self.buf_normals is None:
            self.buf_normals = rt.to_device(self.normals.normals)
        ok = np.empty(n, dtype=np.int32)
        v, A, qq = np.empty(n), np.empty((n, 6)), np.empty(n)
        b_ok, b_v, b_A, b_qq = (rt.empty(a.nbytes) for a in (ok, v, A, qq))
        g.run(
            "cell_residuals", n,
            g.buf_points, self.buf_centres, self.buf_src, self.buf_seg, b_pm, n, b_lin, b_t,
            self.buf_normals, b_out, b_sorted, b_ok, b_v, b_A, b_qq,
        )  # fmt: skip
        for arr, buf in ((ok, b_ok), (v, b_v), (A, b_A), (qq, b_qq)):
            rt.read(arr, buf)
        okb = ok.astype(bool)
        return okb, v[okb], A[okb], qq[okb]

    def nearest(self, q: np.ndarray, seg: np.ndarray, gi: np.ndarray) -> np.ndarray:
        """(P',) original index of each moved point's nearest usable target, -1: none (beyond
        the gate or outside the cell's box)."""
        n = len(q)
        out = np.empty(n, dtype=np.int32)
        if n == 0:
            return out.astype(np.int64)
        rt, g = self.rt, self.grid
        bq = rt.to_device(np.ascontiguousarray(q, dtype=np.float64))
        bs = rt.to_device(np.asarray(seg, dtype=np.int32))
        bg = rt.to_device(np.asarray(gi, dtype=np.int32))
        bo = rt.empty(out.nbytes)
        g.run(
            "cell_nearest", n,
            g.buf_points, g.buf_colstart, g.buf_perm, g.nx, g.ny, g.lo[0], g.lo[1], g.h,
            self.buf_centres, self.buf_boxes, int(self.use_boxes), self.gate2,
            bq, bs, bg, n,
            self.buf_last, self.buf_m1, self.buf_mc, self.buf_cand, bo,
        )  # fmt: skip
        rt.read(out, bo)
        return out.astype(np.int64)
