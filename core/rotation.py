"""Rotations: one SO(3) implementation for the project.

The exponential and logarithm maps are scipy's :class:`~scipy.spatial.transform.Rotation`;
only what scipy does not provide (the cross-product matrix, the left Jacobian of the
exponential map used by the ICP covariance) is written here.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["left_jacobian", "rotation_matrix", "rotation_vector", "skew"]


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]x`` of (..., 3) vectors: ``[v]x @ u == v x u``.

    Parameters
    ----------
    v : (..., 3) float64

    Returns
    -------
    (..., 3, 3) float64
    """
    v = np.asarray(v, dtype=np.float64)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis times angle, radians): scipy's
    :class:`~scipy.spatial.transform.Rotation`, the project's one SO(3) implementation.

    Parameters
    ----------
    rotvec : (3,) or (K, 3) float64

    Returns
    -------
    (3, 3) or (K, 3, 3) float64
    """
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()


def rotation_vector(rot: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, radians) of a rotation matrix (inverse of
    :func:`rotation_matrix`; scipy's :class:`~scipy.spatial.transform.Rotation`).

    Parameters
    ----------
    rot : (3, 3) or (K, 3, 3) float64

    Returns
    -------
    (3,) or (K, 3) float64
    """
    return Rotation.from_matrix(np.asarray(rot, dtype=np.float64)).as_rotvec()


def left_jacobian(rotvec: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian: ``exp([r + dr]x) ~ exp([J_l(r) dr]x) exp([r]x)``.

    Written here because scipy's Rotation has no Jacobians of the exponential map."""
    r = np.asarray(rotvec, dtype=np.float64)
    th = float(np.linalg.norm(r))
    k = skew(r)
    if th < 1e-4:
        a, b = 0.5 - th * th / 24.0, 1.0 / 6.0 - th * th / 120.0
    else:
        a = (1.0 - math.cos(th)) / (th * th)
        b = (th - math.sin(th)) / (th**3)
    return np.eye(3) + a * k + b * (k @ k)
