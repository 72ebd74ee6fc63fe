"""Run the peer estimators (Open3D, OpenPIV scripts in this folder) from the project's venv.

Open3D and OpenPIV are not SlipMap dependencies: they live in a throw-away venv made by
``benchmarks/peers/setup_peer_venv.sh`` (``$SLIPMAP_PEER_VENV``, default
``~/.cache/slipmap-peer-venv``). This module only needs numpy; it hands the arrays to that
venv's python through a temporary ``.npz`` and reads back the script's JSON.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

SCRIPT = Path(__file__).resolve().with_name("open3d_icp.py")
SETUP = Path(__file__).resolve().with_name("setup_peer_venv.sh")


def peer_venv() -> Path:
    """Where the peer venv is (or would be).

    Returns
    -------
    pathlib.Path
        ``$SLIPMAP_PEER_VENV`` if set, else ``~/.cache/slipmap-peer-venv``.
    """
    env = os.environ.get("SLIPMAP_PEER_VENV")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "slipmap-peer-venv"


def peer_python() -> str | None:
    """The peer venv's python, if the venv exists (nothing is installed here).

    Returns
    -------
    str or None
        Path of ``bin/python`` in :func:`peer_venv`, or None when it is missing (run
        ``bash benchmarks/peers/setup_peer_venv.sh`` to make it).
    """
    python = peer_venv() / "bin" / "python"
    return str(python) if python.is_file() and os.access(python, os.X_OK) else None


def peer_missing(module: str) -> str | None:
    """Why the peer ``module`` cannot run, in one line, or None when it can.

    Parameters
    ----------
    module : str
        The module the peer script imports (``"open3d"``, ``"openpiv"``).

    Returns
    -------
    str or None
        E.g. ``"no peer venv at ...: run bash .../setup_peer_venv.sh"``.
    """
    python = peer_python()
    if python is None:
        return f"no peer venv at {peer_venv()}: run `bash {SETUP}`"
    proc = subprocess.run([python, "-c", f"import {module}"], capture_output=True, text=True)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return f"{module} does not import in {peer_venv()} ({last}): run `bash {SETUP}`"
    return None


def run_script(script: str, arrays: dict, *, timeout_s: float = 1200) -> dict:
    """Run a peer script of this folder (``python SCRIPT IN.npz OUT.json``) in the peer venv.

    Parameters
    ----------
    script : str
        File name in ``benchmarks/peers`` (e.g. ``"openpiv_windef.py"``).
    arrays : dict
        What goes into ``IN.npz`` (arrays and scalars).
    timeout_s : float
        Wall-clock limit of the subprocess.

    Returns
    -------
    dict
        The script's JSON.

    Raises
    ------
    RuntimeError
        If no peer venv is found, or the script fails or times out (with its stderr).
    """
    python = peer_python()
    if python is None:
        raise RuntimeError(f"no peer venv at {peer_venv()}: run `bash {SETUP}` first")
    path = Path(__file__).resolve().with_name(script)
    with tempfile.TemporaryDirectory(prefix="slipmap-peer-") as tmp:
        in_path, out_path = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(in_path, **arrays)
        cmd = [python, str(path), str(in_path), str(out_path)]
        log.debug("running %s", cmd)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired as exc:
            raise RuntimeError(f"{script} timed out after {timeout_s} s") from exc
        if proc.returncode != 0 or not out_path.is_file():
            raise RuntimeError(f"{script} failed (exit {proc.returncode}):\n{proc.stderr.strip()}")
        with open(out_path, encoding="utf-8") as fh:
            return json.load(fh)


def icp_relative(
    before: Any,
    after: Any,
    side_before: Any,
    side_after: Any,
    centre_left: Any,
    centre_right: Any,
    *,
    max_corr_m: float = 0.25,
    normal_radius_m: float = 1.0,
    voxel_m: float = 0.0,
    python: str | None = None,
    timeout_s: float = 600,
) -> dict:
    """Open3D point-to-plane ICP of each side of a fault, run in the peer venv.

    Parameters
    ----------
    before, after : (N1, 3), (N2, 3) array-like
        The two epochs, map coordinates (metres).
    side_before, side_after : (N1,), (N2,) array-like of int
        -1 left, +1 right, 0 left out (e.g. a buffer around the trace).
    centre_left, centre_right : (3,) array-like
        Where each side's motion is reported (map coordinates).
    max_corr_m : float
        ICP maximum correspondence distance.
    normal_radius_m : float
        Radius of the target-normal search (at most 30 neighbours).
    voxel_m : float
        Voxel size of an optional downsampling of both clouds (0: none).
    python : str, optional
        Interpreter to run ``open3d_icp.py`` with (default :func:`peer_python`).
    timeout_s : float
        Wall-clock limit of the subprocess.

    Returns
    -------
    dict
        The script's JSON: ``left`` and ``right`` (``displacement`` before -> after at the
        side's centre, ``fitness``, ``inlier_rmse``, ``seconds``, ``information`` ...),
        ``relative`` (right minus left, metres), ``open3d_version`` and ``options``.

    Raises
    ------
    RuntimeError
        If no peer venv is found, or the script fails or times out (with its stderr).
    """
    python = python or peer_python()
    if python is None:
        raise RuntimeError(f"no Open3D peer venv at {peer_venv()}: run `bash {SETUP}` first")
    arrays = {
        "before": np.asarray(before, dtype=np.float64).reshape(-1, 3),
        "after": np.asarray(after, dtype=np.float64).reshape(-1, 3),
        "side_before": np.asarray(side_before, dtype=np.int8).reshape(-1),
        "side_after": np.asarray(side_after, dtype=np.int8).reshape(-1),
        "centre_left": np.asarray(centre_left, dtype=np.float64).reshape(3),
        "centre_right": np.asarray(centre_right, dtype=np.float64).reshape(3),
        "max_corr_m": np.float64(max_corr_m),
        "normal_radius_m": np.float64(normal_radius_m),
        "voxel_m": np.float64(voxel_m),
    }
    if len(arrays["side_before"]) != len(arrays["before"]) or len(arrays["side_after"]) != len(
        arrays["after"]
    ):
        raise ValueError("side_before/side_after must have one entry per point")
    with tempfile.TemporaryDirectory(prefix="slipmap-peer-") as tmp:
        in_path, out_path = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(in_path, **arrays)
        cmd = [python, str(SCRIPT), str(in_path), str(out_path)]
        log.debug("running %s", cmd)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired as exc:
            raise RuntimeError(f"open3d_icp.py timed out after {timeout_s} s") from exc
        if proc.returncode != 0 or not out_path.is_file():
            raise RuntimeError(
                f"open3d_icp.py failed (exit {proc.returncode}):\n{proc.stderr.strip()}"
            )
        if proc.stderr.strip():
            log.debug("open3d_icp.py stderr: %s", proc.stderr.strip())
        with open(out_path, encoding="utf-8") as fh:
            return json.load(fh)
