"""What the windowed ICP's two engines share (:mod:`.icp`, the per-cell fits and their
reference; :mod:`.icp_cells`, the batched cells): tuning constants and the fit options. A
module of its own so that neither engine imports the other at module level."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

__all__ = ["EIG_RTOL", "HUBER_K", "NULL_RTOL", "TUKEY_C"]

TUKEY_C = 4.685  # Tukey biweight tuning constant (95 % Gaussian efficiency), in robust sigmas
HUBER_K = 1.345  # Huber tuning constant (95 % Gaussian efficiency), in robust sigmas
EIG_RTOL = 1e-10  # directions of the (Jacobi-scaled) normal matrix below this are degenerate
NULL_RTOL = 1e-6  # an output depends on an undetermined direction above this relative size


@dataclass(frozen=True)
class _Options:
    max_iterations: int
    tolerance_m: float
    tolerance_rad: float
    tolerance_sigma: float
    max_correspondence_m: Optional[float]
    trim_fraction: float
    robust: Optional[str]
    neighbours_k: int
