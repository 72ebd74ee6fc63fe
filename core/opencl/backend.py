"""PyOpenCL implementation of the segmentation kernels (same interface as ``NumpyKernels``).

The kernels live in ``planes.cl`` (package data). One OpenCL context, queue and compiled
program are made lazily per process and cached: a GPU with double precision when a platform
offers one, else a CPU device (e.g. PoCL). ``SLIPMAP_OPENCL_DEVICE`` (a case-insensitive
substring of the device name) picks a device explicitly.

Results match :class:`slipmap.core.planes.NumpyKernels`: Morton keys bit for bit; node
centroids and covariances bit for bit too (the kernel reproduces numpy's pairwise summation
order), and the eigen-decomposition is numpy's own (``np.linalg.eigh`` on the host), so
eigenvalues and normals are identical; point-to-plane distances may differ by an ulp (numpy's
einsum order depends on its SIMD path), so a ``within`` flag can only differ for a point
whose distance equals the threshold to ~1e-16 relative; component labels exactly (the
smallest node index of every component is unique).
"""

from __future__ import annotations

import logging
import os
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from ..errors import DependencyError, InvalidParameterError

log = logging.getLogger(__name__)

DEVICE_ENV = "SLIPMAP_OPENCL_DEVICE"
KERNEL_FILE = Path(__file__).parent / "planes.cl"
_INSTALL_HINT = (
    "install PyOpenCL and an OpenCL driver: `pip install pyopencl` (or "
    "`pip install 'slipmap[opencl]'`) plus a driver such as `pip install "
    "pocl-binary-distribution` (CPU) or your GPU vendor's OpenCL runtime; on Debian/Ubuntu "
    "`apt install python3-pyopencl pocl-opencl-icd`"
)
_GROUP = 256  # global sizes are rounded up to a multiple of this; kernels bound-check
_INT32_MAX = np.iinfo(np.int32).max

_lock = threading.RLock()
_state: Optional[_Runtime] = None


class _Runtime:
    """Context, queue, program and kernels of one process."""

    def __init__(self, cl: Any, device: Any) -> None:
        self.cl = cl
        self.pid = os.getpid()
        self.device = device
        self.ctx = cl.Context([device])
        self.queue = cl.CommandQueue(self.ctx)
        source = KERNEL_FILE.read_text(encoding="utf-8")
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            # a non-empty build log is reported by pyopencl as a CompilerWarning
            warnings.simplefilter("ignore")
            self.program = cl.Program(self.ctx, source).build()
        log.debug("OpenCL program built in %.2f s", time.perf_counter() - t0)
        i8, f8, i4 = np.int64, np.float64, np.int32
        self._local: Dict[int, int] = {}
        self.k_encode = self._kernel("morton_encode", [None, f8, f8, f8, f8, f8, None, i8])
        self.k_moments = self._kernel("node_moments", [None, None, None, i8, None, None])
        self.k_within = self._kernel(
            "node_within", [None, None, None, i8, None, None, f8, None, None]
        )
        self.k_hook = self._kernel("cc_hook", [None, None, None, i4, None, None])
        self.k_jump = self._kernel("cc_jump", [None, i4, None])
        self.host_memory = bool(device.type & cl.device_type.CPU)
        # largest single buffer, in bytes (point coordinates are the largest)
        self.max_alloc = int(device.max_mem_alloc_size)

    def _kernel(self, name: str, dtypes: list) -> Any:
        k = self.cl.Kernel(self.program, name)
        k.set_scalar_arg_dtypes(dtypes)
        # An explicit work-group size: left to the driver, PoCL 6 (Debian 13) takes up to 4096
        # work-items per group, whose private stacks (node_moments keeps ~4 KB each) overflow
        # its thread stack (SIGSEGV). _GROUP, or the largest power of two the kernel allows.
        most = int(
            k.get_work_group_info(self.cl.kernel_work_group_info.WORK_GROUP_SIZE, self.device)
        )
        local = _GROUP
        while local > max(1, most):
            local //= 2
        self._local[id(k)] = local
        return k

    # buffers -----------------------------------------------------------------
    def to_device(self, arr: np.ndarray) -> Any:
        mf = self.cl.mem_flags
        arr = np.ascontiguousarray(arr)
        if arr.nbytes == 0:
            return self.cl.Buffer(self.ctx, mf.READ_ONLY, 8)
        # a CPU device reads host memory in place (no copy); the buffer keeps ``arr`` alive
        flag = mf.USE_HOST_PTR if self.host_memory else mf.COPY_HOST_PTR
        return self.cl.Buffer(self.ctx, mf.READ_ONLY | flag, hostbuf=arr)

    def empty(self, nbytes: int) -> Any:
        return self.cl.Buffer(self.ctx, self.cl.mem_flags.READ_WRITE, max(int(nbytes), 8))

    def run(self, kernel: Any, n: int, *args: Any) -> None:
        size = -(-int(n) // _GROUP) * _GROUP
        kernel(self.queue, (size,), (self._local[id(kernel)],), *args)

    def read(self, out: np.ndarray, buf: Any) -> np.ndarray:
        if out.nbytes:
            self.cl.enqueue_copy(self.queue, out, buf)
        return out


def _import_pyopencl() -> Any:
    try:
        import pyopencl as cl
    except ImportError as exc:
        raise DependencyError(
            f"the OpenCL backend needs PyOpenCL ({exc}); {_INSTALL_HINT}; or use backend='numpy'"
        ) from exc
    return cl


def _has_fp64(device: Any) -> bool:
    try:
        return "cl_khr_fp64" in str(device.extensions).split()
    except Exception:  # noqa: BLE001 - a device that cannot be queried is unusable
        return False


def _choose_device(cl: Any) -> Any:
    try:
        platforms = cl.get_platforms()
    except Exception as exc:  # noqa: BLE001 - pyopencl raises LogicError/RuntimeError here
        raise DependencyError(f"no OpenCL platform found ({exc}); {_INSTALL_HINT}") from exc
    devices = []
    for plat in platforms:
        try:
            devices.extend(plat.get_devices())
        except Exception as exc:  # noqa: BLE001 - a platform without devices
            log.debug("OpenCL platform %r: no devices (%s)", plat.name, exc)
    if not devices:
        raise DependencyError(f"no OpenCL device found; {_INSTALL_HINT}")
    names = [f"{d.name.strip()} ({d.platform.name.strip()})" for d in devices]
    wanted = os.environ.get(DEVICE_ENV, "").strip()
    if wanted:
        devices = [d for d in devices if wanted.lower() in d.name.lower()]
        if not devices:
            raise DependencyError(
                f"no OpenCL device name contains {DEVICE_ENV}={wanted!r}; devices: "
                + ", ".join(names)
            )
    usable = [d for d in devices if _has_fp64(d)]
    if not usable:
        raise DependencyError(
            "no OpenCL device supports double precision (cl_khr_fp64), which the kernels "
            "need; devices: " + ", ".join(names) + f"; {_INSTALL_HINT}"
        )
    gpus = [d for d in usable if d.type & cl.device_type.GPU]
    return (gpus or usable)[0]


def _runtime() -> _Runtime:
    """The process's OpenCL runtime, made on first use (again after a fork)."""
    global _state
    with _lock:
        if _state is not None and _state.pid == os.getpid():
            return _state
        cl = _import_pyopencl()
        device = _choose_device(cl)
        try:
            state = _Runtime(cl, device)
        except Exception as exc:  # noqa: BLE001 - driver/compiler failures
            raise DependencyError(
                f"OpenCL device {device.name.strip()!r} could not build the SlipMap kernels "
                f"({exc}); set {DEVICE_ENV} to pick another device, or use backend='numpy'"
            ) from exc
        log.info("OpenCL backend on %s (%s)", device.name.strip(), device.platform.name.strip())
        _state = state
        return state


# The probe's child: start the OpenCL runtime as the backend does (platforms, devices, a
# context and a double-precision program on the first fp64 device); prints the device name.
_PROBE_CHILD = r"""
import pyopencl as cl
devices = [d for p in cl.get_platforms() for d in p.get_devices()]
usable = [d for d in devices if "cl_khr_fp64" in str(d.extensions).split()]
if not usable:
    raise SystemExit("no OpenCL device with double precision (cl_khr_fp64)")
ctx = cl.Context([usable[0]])
cl.CommandQueue(ctx)
src = "__kernel void k(__global double *a) { a[get_global_id(0)] *= 2.0; }"
cl.Program(ctx, "#pragma OPENCL EXTENSION cl_khr_fp64 : enable\n" + src).build()
print(usable[0].name.strip())
"""
_probe_result: Dict[float, Optional[str]] = {}


def _no_driver_registered() -> Optional[str]:
    """On Linux, where the OpenCL ICD loader finds drivers only through ``*.icd`` files
    (``OCL_ICD_VENDORS`` or else ``OPENCL_VENDOR_PATH`` and ``/etc/OpenCL/vendors``, and the
    environment's ``etc/OpenCL/vendors`` that pip and conda drivers use), one line saying
    that none is registered, without starting a child process (the probe costs a second
    where PyOpenCL is installed without a driver); else None (probe). Other systems: None."""
    import importlib.util
    import sys

    if not sys.platform.startswith("linux"):
        return None
    if os.environ.get("OCL_ICD_FILENAMES"):
        return None
    if os.environ.get("OCL_ICD_VENDORS"):  # instead of the default folder
        places = [os.environ["OCL_ICD_VENDORS"]]
    else:
        places = [os.environ.get("OPENCL_VENDOR_PATH"), "/etc/OpenCL/vendors"]
    places.append(os.path.join(sys.prefix, "etc", "OpenCL", "vendors"))
    for place in filter(None, places):
        if os.path.isfile(place):
            return None
        try:
            if any(name.endswith(".icd") for name in os.listdir(place)):
                return None
        except OSError:
            continue
    try:  # pip's PoCL wheel registers itself from its package
        if importlib.util.find_spec("pocl_binary_distribution") is not None:
            return None
    except (ImportError, ValueError):  # pragma: no cover
        return None
    return "no OpenCL driver is registered (no *.icd file in the ICD loader's folders)"


def probe_runtime(*, timeout_s: float = 300.0) -> Optional[str]:
    """Whether the OpenCL runtime can start, tried in a child process.

    Some OpenCL drivers abort the whole process instead of raising: PoCL in a root without
    ``/sys`` (hwloc finds no CPU topology, then "Not enough memory to run on this device"
    and SIGABRT). No ``try`` catches that, so the runtime is started once in a child with the
    same interpreter, which takes the abort. The answer is cached for the process.

    Parameters
    ----------
    timeout_s : float
        Seconds the child may take (a first PoCL kernel build can take several).

    Returns
    -------
    str or None
        None when the runtime starts; otherwise one line saying why not (missing PyOpenCL,
        no device, the signal or exit status and the driver's last message).
    """
    import signal
    import subprocess
    import sys

    if timeout_s in _probe_result:
        return _probe_result[timeout_s]
    reason: Optional[str] = _no_driver_registered()
    if reason is not None:
        _probe_result[timeout_s] = reason
        return reason
    try:
        import pyopencl  # noqa: F401 - only whether it imports
    except ImportError as exc:
        reason = f"PyOpenCL cannot be imported ({exc})"
    else:
        try:
            run = subprocess.run(
                [sys.executable, "-c", _PROBE_CHILD],
                capture_output=True,
                text=True,
                timeout=timeout_s,
                check=False,
            )
        except subprocess.TimeoutExpired:
            reason = f"starting the OpenCL runtime took more than {timeout_s:g} s"
        else:
            if run.returncode == 0:
                reason = None
                log.debug("OpenCL probe: %s starts", run.stdout.strip())
            else:
                lines = [ln.strip() for ln in (run.stderr + run.stdout).splitlines()]
                last = "; ".join([ln for ln in lines if ln][-2:]) or "no message"
                if run.returncode < 0:
                    try:
                        how = signal.Signals(-run.returncode).name
                    except ValueError:
                        how = f"signal {-run.returncode}"
                    how = f"the OpenCL driver killed the process ({how})"
                else:
                    how = f"the OpenCL runtime did not start (exit {run.returncode})"
                reason = f"{how}: {last}"
    _probe_result[timeout_s] = reason
    return reason


def _grouped(
    sub: np.ndarray, starts: np.ndarray, counts: np.ndarray
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contiguous float64 points and int64 node ranges; the nodes must partition the points
    in order, as the numpy kernels assume (checked: a wrong range would read past a buffer)."""
    sub = np.ascontiguousarray(sub, dtype=np.float64).reshape(-1, 3)
    starts = np.ascontiguousarray(starts, dtype=np.int64).reshape(-1)
    counts = np.ascontiguousarray(counts, dtype=np.int64).reshape(-1)
    ends = np.cumsum(counts)
    if (
        counts.shape != starts.shape
        or (counts.size and (ends[-1] != sub.shape[0] or np.any(counts < 0)))
        or not np.array_equal(starts, ends - counts)
    ):
        raise InvalidParameterError(
            "starts/counts must partition the points in order "
            "(starts == cumsum(counts) - counts, counts.sum() == len(sub))"
        )
    return sub, starts, counts


def _chunks(starts: np.ndarray, counts: np.ndarray, max_alloc: int) -> List[Tuple[int, ...]]:
    """Runs of whole nodes ``(a, b, first point, end point)`` whose points fit one buffer."""
    ends = starts + counts
    limit = max(1, int(max_alloc) // 24)
    out = []
    a, m = 0, starts.size
    while a < m:
        b = max(a + 1, int(np.searchsorted(ends, starts[a] + limit, side="right")))
        out.append((a, b, int(starts[a]), int(ends[b - 1])))
        a = b
    return out


class OpenCLKernels:
    """The per-node kernels on an OpenCL device (see :class:`~slipmap.core.planes.NumpyKernels`).

    Raises
    ------
    DependencyError
        PyOpenCL is missing, no OpenCL device (with double precision) exists, or the kernels
        do not build.
    """

    name = "opencl"

    def __init__(self, fallback: Any = None) -> None:
        self._rt = _runtime()
        #: the numpy reference kernels, for the rare cases the device cannot take (given by
        #: ``core.planes.get_kernels``, so this module does not import ``core.planes``)
        self.fallback = fallback

    @property
    def device_name(self) -> str:
        return str(self._rt.device.name).strip()

    # ------------------------------------------------------------------ encode
    def encode(self, pts: np.ndarray, lo: np.ndarray, scale: float, cells: int) -> np.ndarray:
        """Morton keys, bit-identical to :func:`slipmap.core.octree.quantise_encode`."""
        pts = np.ascontiguousarray(pts, dtype=np.float64)
        n = pts.shape[0]
        keys = np.empty(n, dtype=np.uint64)
        if n == 0:
            return keys
        rt = self._rt
        lo = np.asarray(lo, dtype=np.float64)
        top = float(cells - 1)
        chunk = max(1, min(n, rt.max_alloc // 24))
        with _lock:
            for a in range(0, n, chunk):
                b = min(n, a + chunk)
                d_pts = rt.to_device(pts[a:b])
                d_keys = rt.empty(8 * (b - a))
                rt.run(
                    rt.k_encode, b - a, d_pts, lo[0], lo[1], lo[2], float(scale), top, d_keys,
                    b - a,
                )  # fmt: skip
                rt.read(keys[a:b], d_keys)
        return keys

    # ---------------------------------------------------------------- node_fit
    def node_fit(
        self, sub: np.ndarray, starts: np.ndarray, counts: np.ndarray, threshold: float
    ) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Plane fit and planarity count of every node (see ``NumpyKernels.node_fit``).

        The nodes must partition ``sub`` in order (``starts == cumsum(counts) - counts``), as
        the numpy version assumes.
        """
        sub, starts, counts = _grouped(sub, starts, counts)
        n, m = sub.shape[0], starts.size
        mean = np.empty((m, 3))
        cov6 = np.empty((m, 6))
        n_within = np.zeros(m, dtype=np.int64)
        within = np.zeros(n, dtype=np.bool_)
        if m == 0:
            z = np.empty((0, 3))
            return z, z.copy(), z.copy(), n_within, within
        rt = self._rt
        chunks = []
        with _lock:
            for a, b, base, stop in _chunks(starts, counts, rt.max_alloc):
                mc = b - a
                d_pts = rt.to_device(sub[base:stop])
                d_starts = rt.to_device(starts[a:b] - base)
                d_counts = rt.to_device(counts[a:b])
                d_mean = rt.empty(24 * mc)
                d_cov = rt.empty(48 * mc)
                rt.run(rt.k_moments, mc, d_pts, d_starts, d_counts, mc, d_mean, d_cov)
                rt.read(mean[a:b], d_mean)
                rt.read(cov6[a:b], d_cov)
                chunks.append((a, b, base, stop, d_pts, d_starts, d_counts, d_mean))
        cov = np.empty((m, 3, 3))
        for c, (i, j) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
            cov[:, i, j] = cov6[:, c]
            cov[:, j, i] = cov6[:, c]
        evals, evecs = np.linalg.eigh(cov)
        normal = np.ascontiguousarray(evecs[:, :, 0])
        with _lock:
            for a, b, base, stop, d_pts, d_starts, d_counts, d_mean in chunks:
                d_normal = rt.to_device(normal[a:b])
                self._within(
                    d_pts, d_starts, d_counts, d_mean, d_normal, threshold,
                    within[base:stop], n_within[a:b],
                )  # fmt: skip
        return mean, evals, normal, n_within, within

    # ------------------------------------------------------------- plane_within
    def plane_within(
        self,
        sub: np.ndarray,
        starts: np.ndarray,
        counts: np.ndarray,
        origin: np.ndarray,
        normal: np.ndarray,
        threshold: float,
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Points within ``threshold`` of given node planes (see ``NumpyKernels.plane_within``).

        Returns ``n_within`` (M,) int64 and ``within`` (n,) bool.
        """
        sub, starts, counts = _grouped(sub, starts, counts)
        origin = np.ascontiguousarray(origin, dtype=np.float64).reshape(-1, 3)
        normal = np.ascontiguousarray(normal, dtype=np.float64).reshape(-1, 3)
        n, m = sub.shape[0], starts.size
        if origin.shape[0] != m or normal.shape[0] != m:
            raise InvalidParameterError(
                f"plane_within: origin and normal need {m} rows (one per node), got "
                f"{origin.shape[0]} and {normal.shape[0]}"
            )
        n_within = np.zeros(m, dtype=np.int64)
        within = np.zeros(n, dtype=np.bool_)
        if m == 0:
            return n_within, within
        rt = self._rt
        with _lock:
            for a, b, base, stop in _chunks(starts, counts, rt.max_alloc):
                self._within(
                    rt.to_device(sub[base:stop]), rt.to_device(starts[a:b] - base),
                    rt.to_device(counts[a:b]), rt.to_device(origin[a:b]),
                    rt.to_device(normal[a:b]), threshold, within[base:stop], n_within[a:b],
                )  # fmt: skip
        return n_within, within

    def _within(
        self,
        d_pts: Any,
        d_starts: Any,
        d_counts: Any,
        d_origin: Any,
        d_normal: Any,
        threshold: float,
        within: np.ndarray,
        n_within: np.ndarray,
    ) -> None:
        """Run ``node_within`` on one chunk; fills the views ``within`` and ``n_within``."""
        rt = self._rt
        mc = n_within.size
        d_flags = rt.empty(within.size)
        d_nw = rt.empty(8 * mc)
        rt.run(
            rt.k_within, mc, d_pts, d_starts, d_counts, mc, d_origin, d_normal,
            float(threshold), d_flags, d_nw,
        )  # fmt: skip
        rt.read(within.view(np.uint8), d_flags)
        rt.read(n_within, d_nw)

    # -------------------------------------------------------- propagate_labels
    def propagate_labels(
        self, indptr: np.ndarray, indices: np.ndarray, nodes: np.ndarray, n: int
    ) -> np.ndarray:
        """Connected-component labels: the smallest node index of each node's component.

        Min-label propagation with hooking and pointer jumping on the device, repeated until
        a pass changes no label (see ``NumpyKernels.propagate_labels`` for the arguments).
        """
        n = int(n)
        lab = np.arange(n, dtype=np.int64)
        nodes = np.asarray(nodes)
        if n == 0 or nodes.size == 0:
            return lab
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        indices = np.asarray(indices)
        k = nodes.size
        if indptr.shape != (k + 1,) or indptr[0] != 0 or indptr[-1] != indices.size:
            raise InvalidParameterError(
                f"propagate_labels: indptr must have len(nodes) + 1 = {k + 1} entries from 0 "
                f"to len(indices) = {indices.size}"
            )
        for name, arr in (("nodes", nodes), ("indices", indices)):
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise InvalidParameterError(f"propagate_labels: {name} must lie in [0, {n})")
        if n > _INT32_MAX:  # 32-bit labels for atomic_min; never reached by real clouds
            if self.fallback is None:
                raise InvalidParameterError(
                    f"propagate_labels: {n} nodes exceed the OpenCL kernel's 32-bit labels; "
                    "use the numpy backend"
                )
            log.debug("propagate_labels: %d nodes exceed 32-bit labels; using numpy", n)
            return self.fallback.propagate_labels(indptr, indices, nodes, n)
        rt = self._rt
        cl = rt.cl
        changed = np.zeros(1, dtype=np.int32)
        with _lock:
            d_indptr = rt.to_device(indptr)
            d_indices = rt.to_device(indices.astype(np.int32))
            d_nodes = rt.to_device(nodes.astype(np.int32))
            mf = cl.mem_flags
            d_lab = cl.Buffer(
                rt.ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=np.arange(n, dtype=np.int32)
            )
            d_changed = rt.empty(4)
            zero = np.zeros(1, dtype=np.int32)
            iterations = 0
            while True:
                iterations += 1
                cl.enqueue_copy(rt.queue, d_changed, zero)
                rt.run(rt.k_hook, k, d_indptr, d_indices, d_nodes, k, d_lab, d_changed)
                rt.run(rt.k_jump, k, d_nodes, k, d_lab)
                cl.enqueue_copy(rt.queue, changed, d_changed)
                if changed[0] == 0:
                    break
                if iterations > n + 1:  # cannot happen: every flagged pass lowers a label
                    raise RuntimeError("OpenCL label propagation did not converge")
            out = np.empty(n, dtype=np.int32)
            rt.read(out, d_lab)
        log.debug("propagate_labels: %d nodes, %d passes", n, iterations)
        return out.astype(np.int64)


def runtime_info() -> Dict[str, str]:
    """Device and platform of the cached runtime (creates it); for logs and reports."""
    rt = _runtime()
    return {
        "device": str(rt.device.name).strip(),
        "platform": str(rt.device.platform.name).strip(),
        "version": str(rt.device.version).strip(),
    }
