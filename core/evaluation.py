"""Scores of a segmentation against ground-truth surface labels (tests, demo, benchmarks)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InvalidParameterError


@dataclass(frozen=True)
class SegmentationScores:
    """How well predicted plane labels recover true surfaces.

    Attributes
    ----------
    n_surfaces : int
        True surfaces with at least ``min_surface_points`` points.
    n_recovered : int
        Of those, surfaces with at least ``min_fraction`` of their points under one label.
    recall : float
        ``n_recovered / n_surfaces``.
    precision : float
        Fraction of labelled points (label >= 0) that belong to a true surface.
    labelled_fraction : float
        Fraction of truly planar points that received a label.
    n_merged : int
        Predicted planes that hold at least ``merge_fraction`` of the points of two or more
        true surfaces (each with ``merge_min_points`` or more points there): distinct surfaces
        joined into one plane.
    purity : float
        Fraction of labelled true-surface points whose plane's majority surface is their own
        (1 - contamination, e.g. by points near a corner that went to the other wall).
    n_planes : int
        Predicted planes.
    """

    n_surfaces: int
    n_recovered: int
    recall: float
    precision: float
    labelled_fraction: float
    n_merged: int
    purity: float
    n_planes: int

    def as_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def score_segmentation(
    true_labels: np.ndarray,
    pred_labels: np.ndarray,
    *,
    min_surface_points: int = 200,
    min_fraction: float = 0.7,
    merge_fraction: float = 0.2,
    merge_min_points: int = 50,
) -> SegmentationScores:
    """Compare predicted plane labels with true surface labels.

    Parameters
    ----------
    true_labels : (N,) int
        True surface id per point, -1 for non-planar clutter.
    pred_labels : (N,) int
        Predicted plane id per point, -1 for none.
    min_surface_points : int
        Surfaces smaller than this are not counted in recall.
    min_fraction : float
        Share of a surface's points that one label must hold for the surface to count as
        recovered.
    merge_fraction, merge_min_points
        Thresholds of the merge count (see :class:`SegmentationScores`).
    """
    t = np.asarray(true_labels).astype(np.int64)
    p = np.asarray(pred_labels).astype(np.int64)
    if t.shape != p.shape or t.ndim != 1:
        raise InvalidParameterError(
            f"true_labels and pred_labels must be 1-D of equal length, got {t.shape}, {p.shape}"
        )
    both = (t >= 0) & (p >= 0)
    nt = int(t.max()) + 1 if t.size and t.max() >= 0 else 0
    npred = int(p.max()) + 1 if p.size and p.max() >= 0 else 0
    table = np.zeros((max(nt, 1), max(npred, 1)), dtype=np.int64)
    np.add.at(table, (t[both], p[both]), 1)
    sizes = np.bincount(t[t >= 0], minlength=nt) if nt else np.zeros(0, np.int64)
    big = np.flatnonzero(sizes >= min_surface_points)
    best = table[big].max(axis=1) if big.size and npred else np.zeros(big.size)
    recovered = int(np.count_nonzero(best >= min_fraction * sizes[big]))
    labelled = p >= 0
    precision = float(np.mean(t[labelled] >= 0)) if labelled.any() else 1.0
    planar = t >= 0
    labelled_fraction = float(np.mean(labelled[planar])) if planar.any() else 0.0
    merged = 0
    purity = 1.0
    if npred and nt:
        share = table / np.maximum(sizes, 1)[:, None]  # share of each surface in each plane
        big_share = (share >= merge_fraction) & (table >= merge_min_points)
        merged = int(np.count_nonzero(big_share.sum(axis=0) >= 2))
        total = table.sum()
        purity = float(table.max(axis=0).sum() / total) if total else 1.0
    return SegmentationScores(
        n_surfaces=int(big.size),
        n_recovered=recovered,
        recall=recovered / big.size if big.size else 1.0,
        precision=precision,
        labelled_fraction=labelled_fraction,
        n_merged=merged,
        purity=purity,
        n_planes=npred,
    )
