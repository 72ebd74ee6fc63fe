"""Which components of the relative slip a side's planes barely determine, and why.

A side whose matched planes all face one way (an airborne epoch that sees roofs and ground
but no facades; a street of parallel fronts) leaves the motion along the other directions
nearly undetermined: the adjustment's σ along them is then large and honest, but a bare
"± 86 mm" does not say that the data hold nothing there, nor that the other components are
still well determined. :func:`weak_components` names each such component of the relative
motion, the side responsible and the reason, so that the faces can say it beside the
headline.

A component is reported when both hold on one side:

* its σ on that side is more than :data:`SIGMA_RATIO` times the side's best-determined
  direction's σ (the square root of the smallest eigenvalue of the side's displacement
  covariance): the side determines it an order of magnitude worse than it can, and
* the side's adjusted planes give the component's axis ``u`` less than :data:`SHARE` of
  their geometric weight, ``Σ_j (n_j·u)² / P`` over the planes' unit normals (an isotropic
  set of planes gives 1/3; flat roofs and ground give a horizontal axis 0; 30°-pitched gable
  roofs half of the planes give it about 0.06): the geometry, not the noise, is the reason.

The two conditions together keep a well-determined but relatively weaker direction (a few
walls beside a large ground plane, ± 0.3 mm against ± 0.02 mm vertically; the horizontal of
an airborne side with gable roofs, 3-4× its vertical σ) from being called undetermined, and
say the reason in words a surveyor checks in the field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence, Tuple

import numpy as np

#: a side's σ along a component beyond this multiple of its best direction's σ is weak
SIGMA_RATIO = 10.0
#: ... when the planes give the component's axis less than this share of their weight
SHARE = 0.02

COMPONENTS = ("fault_parallel", "fault_normal", "dz")


@dataclass(frozen=True)
class WeakComponent:
    """One component of the relative motion that one side barely determines.

    Attributes
    ----------
    component : str
        "fault_parallel", "fault_normal" or "dz" (the fault frame of
        :func:`slipmap.core.displacement.strike_axes`).
    side : str
        "left" or "right": the side whose planes leave it undetermined.
    sigma_m : float
        The side's σ along the component (metres).
    best_sigma_m : float
        The side's σ along its best-determined direction (metres).
    share : float
        ``Σ_j (n_j·u)² / P``: the share of the planes' geometric weight along the axis ``u``
        (1/3 for an isotropic set).
    n_planes : int
        The side's adjusted planes ``P``.
    """

    component: str
    side: str
    sigma_m: float
    best_sigma_m: float
    share: float
    n_planes: int

    @property
    def ratio(self) -> float:
        """``sigma_m / best_sigma_m``."""
        return self.sigma_m / self.best_sigma_m if self.best_sigma_m > 0 else math.inf

    def to_dict(self) -> dict:
        return {
            "component": self.component,
            "side": self.side,
            "sigma_m": self.sigma_m,
            "best_sigma_m": self.best_sigma_m,
            "ratio": self.ratio,
            "share": self.share,
            "n_planes": self.n_planes,
        }


def weak_components(
    covariances: Sequence[np.ndarray],
    normals: Sequence[np.ndarray],
    axes: Sequence[np.ndarray],
    *,
    sides: Sequence[str] = ("left", "right"),
    sigma_ratio: float = SIGMA_RATIO,
    share: float = SHARE,
) -> Tuple[WeakComponent, ...]:
    """The components of the relative motion that a side's planes barely determine.

    Parameters
    ----------
    covariances : sequence of (3, 3) float64
        Each side's displacement covariance, m².
    normals : sequence of (P_s, 3) float64
        Each side's adjusted planes' unit normals (rejected planes left out; rows with NaN
        are ignored).
    axes : sequence of three (3,) float64
        Unit vectors of the components, in the order of :data:`COMPONENTS`.
    sides : sequence of str
        The sides' names, in the order of ``covariances``.
    sigma_ratio : float
        See :data:`SIGMA_RATIO`.
    share : float
        See :data:`SHARE`.

    Returns
    -------
    tuple of WeakComponent
        Ordered by side, then component; empty when every component is determined.
    """
    out = []
    for side, cov, nrm in zip(sides, covariances, normals):
        c = np.asarray(cov, dtype=np.float64)
        if not np.isfinite(c).all():
            continue
        best = math.sqrt(max(float(np.linalg.eigvalsh(c)[0]), 0.0))
        n = np.asarray(nrm, dtype=np.float64).reshape(-1, 3)
        n = n[np.isfinite(n).all(axis=1)]
        for name, u in zip(COMPONENTS, axes):
            u = np.asarray(u, dtype=np.float64)
            sigma = math.sqrt(max(float(u @ c @ u), 0.0))
            weight = float(np.mean((n @ u) ** 2)) if len(n) else 0.0
            if sigma > sigma_ratio * best and weight < share:
                out.append(WeakComponent(name, side, sigma, best, weight, int(len(n))))
    return tuple(out)
