"""3D displacement fields by Particle Image Velocimetry (PIV) on gridded elevation (DEMs).

Implements the PIV-TLS workflow of Aryal (section 3.2.1; Aryal et al. 2012, 2013):

1. grid both epochs to elevation images ``I1`` (before) and ``I2`` (after) of cell ``GR``
   (:mod:`slipmap.core.dem`, mean z per cell, no extrapolation, empty cells NaN);
2. for each interrogation window ``WC`` of ``I1`` find the shift of ``WC`` inside a larger search
   window ``WI`` of ``I2`` that maximises the normalised cross-correlation

   ``r_N(s) = sum (I1 - mu_1)(I2(. + s) - mu_2) / sqrt(sum (I1 - mu_1)^2 sum (I2(. + s) - mu_2)^2)``

   (means and sums over the pixels of the overlap that are valid in *both* images: the masked
   NCC of Padfield 2012, so DEM gaps do not bias the correlation), located to sub-pixel
   precision with a three-point Gaussian fit in each axis; refined by multi-pass window
   deformation (Huang et al. 1993; Scarano 2002 "WIDIM"): later passes correlate smaller windows
   of ``I1`` with ``I2`` warped by the current displacement field and add the correction;
   after each pass vectors are validated (signal-to-noise ratio, normalised median test of
   Westerweel & Scarano 2005) and outliers replaced by the mean of their valid neighbours;
3. the vertical component is ``dz = I2(x + d) - I1(x)`` (Fig. 3.3): the mean over the final
   interrogation window of the pixel-wise difference between ``I2`` warped by the final
   displacement field and ``I1``.

With breaklines (scarps, faults, slab edges; :mod:`slipmap.core.breaklines`) the field may
jump across them: the predictor is interpolated per side, windows crossed by a line are
correlated on their centre's side only, the median test and replacement use same-side
neighbours, and the vectors whose window a line crosses are flagged (``near_break``).

Correlations of all windows of a pass are computed at once with batched real FFTs
(:func:`masked_ncc`); :func:`masked_ncc_reference` is the obvious loop over shifts used as the
test oracle. Positions inside the module are image pixels (row down = south, column right =
east); results are in metres with ``+x`` east and ``+y`` north.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import fft as sfft
from scipy import ndimage

from .dem import Grid, common_grid, grid_elevation
from .errors import InputDataError, InvalidParameterError
from .progress import ProgressCallback, report, scaled

log = logging.getLogger(__name__)

__all__ = [
    "PIVResult",
    "PeakFit",
    "masked_ncc",
    "masked_ncc_reference",
    "piv",
    "piv_from_points",
    "replace_outliers",
    "subpixel_peak",
    "validate_vectors",
]

#: a window/overlap whose centred sum of squares is below this fraction of the window's total
#: sum of squares is treated as flat (correlation undefined, NaN)
FLAT_RELATIVE = 1e-10

#: memory budget (bytes) of one chunk of batched FFT correlations
CHUNK_BYTES = 96 * 2**20


# --------------------------------------------------------------------------------------------
# masked normalised cross-correlation
# --------------------------------------------------------------------------------------------


def _centre_masked(a: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """(values minus the mean of the valid ones, 0 where invalid; mask as float)."""
    m = np.isfinite(a)
    cnt = m.sum(axis=(-2, -1), keepdims=True)
    s = np.where(m, a, 0.0).sum(axis=(-2, -1), keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(cnt > 0, s / np.maximum(cnt, 1), 0.0)
    return np.where(m, a - mean, 0.0), m.astype(np.float64)


def _check_ncc_shapes(templates: np.ndarray, searches: np.ndarray) -> None:
    if templates.ndim != 3 or searches.ndim != 3 or templates.shape[0] != searches.shape[0]:
        raise InvalidParameterError(
            "templates must be (n, h, w) and searches (n, H, W) with the same n; got "
            f"{templates.shape} and {searches.shape}"
        )
    if searches.shape[1] < templates.shape[1] or searches.shape[2] < templates.shape[2]:
        raise InvalidParameterError(
            f"search windows {searches.shape[1:]} must be at least as large as the templates "
            f"{templates.shape[1:]}"
        )


def masked_ncc(
    templates,
    searches,
    *,
    min_overlap_fraction: float = 0.5,
    workers: Optional[int] = None,
) -> np.ndarray:
    """Masked normalised cross-correlation of templates inside search windows (batched FFT).

    For every integer shift ``(u, v)`` with the template fully inside its search window,
    ``r[k, u, v]`` is the Pearson correlation of ``templates[k, i, j]`` and
    ``searches[k, i + u, j + v]`` over the pixels ``(i, j)`` where both are finite (Padfield
    2012). It is computed from six FFT cross-correlations (masks, masked values, squared masked
    values), so NaN gaps neither poison nor bias the result.

    Parameters
    ----------
    templates : (n, h, w) float
        Interrogation windows of image 1 (NaN = no data).
    searches : (n, H, W) float
        Search windows of image 2, ``H >= h``, ``W >= w`` (NaN = no data).
    min_overlap_fraction : float
        A shift needs at least ``min_overlap_fraction * h * w`` pixels valid in both, else NaN.
    workers : int, optional
        Threads for ``scipy.fft`` (default: all cores).

    Returns
    -------
    (n, H - h + 1, W - w + 1) float64
        Correlation in [-1, 1]; index ``(u, v)`` means template pixel ``(i, j)`` pairs with
        search pixel ``(i + u, j + v)``. NaN where the overlap is too small or flat.
    """
    t = np.asarray(templates, dtype=np.float64)
    s = np.asarray(searches, dtype=np.float64)
    _check_ncc_shapes(t, s)
    n, h, w = t.shape
    big_h, big_w = s.shape[1:]
    oh, ow = big_h - h + 1, big_w - w + 1
    out = np.full((n, oh, ow), np.nan)
    if n == 0:
        return out
    if workers is None:
        workers = -1
    l1 = sfft.next_fast_len(big_h, real=True)
    l2 = sfft.next_fast_len(big_w, real=True)
    per_window = (6 * l1 * (l2 // 2 + 1)) * 16 * 2 + 6 * l1 * l2 * 8 + 4 * big_h * big_w * 8
    chunk = max(1, int(CHUNK_BYTES // per_window))
    min_count = max(1.0, float(min_overlap_fraction) * h * w)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        out[a:b] = _masked_ncc_chunk(t[a:b], s[a:b], (l1, l2), (oh, ow), min_count, workers)
    return out


def _box_sums(a: np.ndarray, h: int, w: int, oshape) -> np.ndarray:
    """Sums of ``a`` (n, H, W) over every h x w sub-window: (n, oh, ow), running sums."""
    n, big_h, big_w = a.shape
    oh, ow = oshape
    c = np.empty((n, big_h, big_w + 1))
    c[:, :, 0] = 0.0
    np.cumsum(a, axis=2, out=c[:, :, 1:])
    rows = c[:, :, w : w + ow] - c[:, :, :ow]  # (n, H, ow)
    c2 = np.empty((n, big_h + 1, ow))
    c2[:, 0] = 0.0
    np.cumsum(rows, axis=1, out=c2[:, 1:])
    return c2[:, h : h + oh] - c2[:, :oh]


def _masked_ncc_chunk(t, s, fshape, oshape, min_count, workers):
    full = np.isfinite(t).all(axis=(1, 2)) & np.isfinite(s).all(axis=(1, 2))
    if full.all():
        return _ncc_full_chunk(t, s, fshape, oshape, workers)
    out = np.empty((t.shape[0],) + tuple(oshape))
    if full.any():
        out[full] = _ncc_full_chunk(t[full], s[full], fshape, oshape, workers)
    part = ~full
    out[part] = _ncc_masked_chunk(t[part], s[part], fshape, oshape, min_count, workers)
    return out


def _ncc_full_chunk(t, s, fshape, oshape, workers):
    """NCC when template and search window have no gaps: one FFT product plus box sums."""
    h, w = t.shape[1:]
    axes = (-2, -1)
    t0 = t - t.mean(axis=(1, 2), keepdims=True)
    s0 = s - s.mean(axis=(1, 2), keepdims=True)
    ft = sfft.rfft2(t0, s=fshape, axes=axes, workers=workers)
    fs = sfft.rfft2(s0, s=fshape, axes=axes, workers=workers)
    np.conjugate(ft, out=ft)
    ft *= fs
    del fs
    sts = sfft.irfft2(ft, s=fshape, axes=axes, workers=workers)[:, : oshape[0], : oshape[1]]
    cnt = float(h * w)
    ss = _box_sums(s0, h, w, oshape)
    sss = _box_sums(s0 * s0, h, w, oshape)
    var_t = (t0 * t0).sum(axis=(1, 2))[:, None, None]  # sum T = 0 over the whole template
    var_s = sss - ss * ss / cnt
    tot_s = (s0 * s0).sum(axis=(1, 2))[:, None, None]
    ok = (var_t > 0) & (var_s > FLAT_RELATIVE * tot_s)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = sts / np.sqrt(np.where(ok, var_t * var_s, 1.0))
    r = np.clip(r, -1.0, 1.0)
    r[~ok] = np.nan
    return r


def _ncc_masked_chunk(t, s, fshape, oshape, min_count, workers):
    t0, mt = _centre_masked(t)
    s0, ms = _centre_masked(s)
    axes = (-2, -1)
    ft = sfft.rfft2(np.stack([t0, t0 * t0, mt], axis=1), s=fshape, axes=axes, workers=workers)
    fs = sfft.rfft2(np.stack([s0, s0 * s0, ms], axis=1), s=fshape, axes=axes, workers=workers)
    np.conjugate(ft, out=ft)
    prods = np.empty((t.shape[0], 6) + ft.shape[2:], dtype=ft.dtype)
    np.multiply(ft[:, 2], fs[:, 2], out=prods[:, 0])  # N
    np.multiply(ft[:, 0], fs[:, 2], out=prods[:, 1])  # sum T
    np.multiply(ft[:, 1], fs[:, 2], out=prods[:, 2])  # sum T^2
    np.multiply(ft[:, 2], fs[:, 0], out=prods[:, 3])  # sum S
    np.multiply(ft[:, 2], fs[:, 1], out=prods[:, 4])  # sum S^2
    np.multiply(ft[:, 0], fs[:, 0], out=prods[:, 5])  # sum T S
    del ft, fs
    c = sfft.irfft2(prods, s=fshape, axes=axes, workers=workers)[:, :, : oshape[0], : oshape[1]]
    cnt = np.rint(c[:, 0])
    ok = cnt >= min_count
    cnt = np.where(ok, cnt, 1.0)
    st, stt, ss, sss, sts = c[:, 1], c[:, 2], c[:, 3], c[:, 4], c[:, 5]
    var_t = stt - st * st / cnt
    var_s = sss - ss * ss / cnt
    tot_t = (t0 * t0).sum(axis=(1, 2))[:, None, None]
    tot_s = (s0 * s0).sum(axis=(1, 2))[:, None, None]
    ok &= (var_t > FLAT_RELATIVE * tot_t) & (var_s > FLAT_RELATIVE * tot_s)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = (sts - st * ss / cnt) / np.sqrt(np.where(ok, var_t * var_s, 1.0))
    r = np.clip(r, -1.0, 1.0)
    r[~ok] = np.nan
    return r


def masked_ncc_reference(template, search, *, min_overlap_fraction: float = 0.5) -> np.ndarray:
    """Slow, obvious masked NCC of one template in one search window (test oracle).

    Same definition and conventions as :func:`masked_ncc` for a single ``(h, w)`` template
    and ``(H, W)`` search window: a direct loop over shifts computing the Pearson correlation
    of the pixels valid in both.
    """
    t = np.asarray(template, dtype=np.float64)
    s = np.asarray(search, dtype=np.float64)
    _check_ncc_shapes(t[None], s[None])
    h, w = t.shape
    big_h, big_w = s.shape
    # same flatness reference as the fast version: sums of squares about the window means
    tc, _ = _centre_masked(t)
    sc, _ = _centre_masked(s)
    tot_t = float((tc * tc).sum())
    tot_s = float((sc * sc).sum())
    min_count = max(1.0, float(min_overlap_fraction) * h * w)
    out = np.full((big_h - h + 1, big_w - w + 1), np.nan)
    for u in range(big_h - h + 1):
        for v in range(big_w - w + 1):
            a = t
            b = s[u : u + h, v : v + w]
            m = np.isfinite(a) & np.isfinite(b)
            k = int(m.sum())
            if k < min_count:
                continue
            # centre with the same constants as the fast path, then about the overlap means
            da = (a - (t[np.isfinite(t)].mean()))[m]
            db = (b - (s[np.isfinite(s)].mean()))[m]
            da = da - da.mean()
            db = db - db.mean()
            va = float(da @ da)
            vb = float(db @ db)
            if va <= FLAT_RELATIVE * tot_t or vb <= FLAT_RELATIVE * tot_s:
                continue
            out[u, v] = min(1.0, max(-1.0, float(da @ db) / math.sqrt(va * vb)))
    return out


# --------------------------------------------------------------------------------------------
# peak location
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PeakFit:
    """Sub-pixel correlation peaks of a batch of correlation maps.

    Attributes
    ----------
    row, col : (n,) float64
        Sub-pixel peak position in correlation-map indices (NaN where no usable peak: the
        maximum on the map border, or undefined correlation around it).
    peak : (n,) float64
        Correlation value at the integer maximum.
    snr : (n,) float64
        Peak divided by the highest *other local maximum* outside the peak neighbourhood
        (``inf`` when there is none or it is <= 0; 0 when the peak is <= 0).
    """

    row: np.ndarray
    col: np.ndarray
    peak: np.ndarray
    snr: np.ndarray


def _fit3(cm: np.ndarray, c0: np.ndarray, cp: np.ndarray) -> np.ndarray:
    """Sub-pixel offset of a three-point peak: Gaussian, parabolic where a value <= 0."""
    with np.errstate(invalid="ignore", divide="ignore"):
        pos = (cm > 0) & (c0 > 0) & (cp > 0)
        lm = np.log(np.where(pos, cm, 1.0))
        l0 = np.log(np.where(pos, c0, 1.0))
        lp = np.log(np.where(pos, cp, 1.0))
        den_g = lm - 2.0 * l0 + lp
        den_p = cm - 2.0 * c0 + cp
        d_g = (lm - lp) / (2.0 * den_g)
        d_p = (cm - cp) / (2.0 * den_p)
        d = np.where(pos & (den_g < 0), d_g, d_p)
        bad = ~(np.isfinite(cm) & np.isfinite(cp)) | ((den_p >= 0) & ~(pos & (den_g < 0)))
    d = np.clip(d, -0.5, 0.5)
    d[bad] = np.nan
    return d


def subpixel_peak(corr, *, exclusion_px: int = 2) -> PeakFit:
    """Locate the correlation peak of each map with a three-point Gaussian fit per axis.

    Parameters
    ----------
    corr : (n, a, b) float
        Correlation maps (NaN = undefined).
    exclusion_px : int
        Half-size of the square around the peak ignored when searching the second peak.

    Returns
    -------
    PeakFit
        Positions in map indices. The fit is ``d = (ln c- - ln c+) / (2 (ln c- - 2 ln c0 +
        ln c+))``; where a neighbour is <= 0 the parabolic ``(c- - c+) / (2 (c- - 2 c0 + c+))``.
    """
    c = np.asarray(corr, dtype=np.float64)
    if c.ndim != 3:
        raise InvalidParameterError(f"corr must be (n, a, b), got shape {c.shape}")
    n, a, b = c.shape
    cf = np.where(np.isfinite(c), c, -np.inf)
    k = cf.reshape(n, -1).argmax(axis=1)
    ar = np.arange(n)
    pi, pj = np.divmod(k, b)
    peak = cf.reshape(n, -1)[ar, k]
    inside = (pi > 0) & (pi < a - 1) & (pj > 0) & (pj < b - 1) & np.isfinite(peak)
    pic = np.clip(pi, 1, max(1, a - 2)) if a >= 3 else pi
    pjc = np.clip(pj, 1, max(1, b - 2)) if b >= 3 else pj
    if a >= 3 and b >= 3:
        cn = cf[ar, pic - 1, pj]
        cs = cf[ar, pic + 1, pj]
        cw = cf[ar, pi, pjc - 1]
        ce = cf[ar, pi, pjc + 1]
        dr = _fit3(cn, peak, cs)
        dc = _fit3(cw, peak, ce)
    else:
        dr = dc = np.full(n, np.nan)
    row = np.where(inside, pi + dr, np.nan)
    col = np.where(inside, pj + dc, np.nan)

    # second peak: highest local maximum outside the neighbourhood of the first
    pad = np.pad(cf, ((0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    is_max = np.isfinite(cf)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            is_max &= cf >= pad[:, 1 + di : 1 + di + a, 1 + dj : 1 + dj + b]
    ii = np.arange(a)[None, :, None]
    jj = np.arange(b)[None, None, :]
    near = (np.abs(ii - pi[:, None, None]) <= exclusion_px) & (
        np.abs(jj - pj[:, None, None]) <= exclusion_px
    )
    second = np.where(is_max & ~near, cf, -np.inf).reshape(n, -1).max(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        snr = np.where(second > 0, peak / np.where(second > 0, second, 1.0), np.inf)
    snr = np.where(peak > 0, snr, 0.0)
    snr = np.where(np.isfinite(peak), snr, np.nan)
    peak = np.where(np.isfinite(peak), peak, np.nan)
    return PeakFit(row=row, col=col, peak=peak, snr=snr)


# --------------------------------------------------------------------------------------------
# vector validation and replacement
# --------------------------------------------------------------------------------------------


def _neighbours(f: np.ndarray) -> np.ndarray:
    """(8, ny, nx) the 8 neighbours of each cell, NaN outside."""
    p = np.pad(f, 1, constant_values=np.nan)
    ny, nx = f.shape
    out = []
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di or dj:
                out.append(p[1 + di : 1 + di + ny, 1 + dj : 1 + dj + nx])
    return np.stack(out)


def _nanmedian0(a: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Median along axis 0 ignoring NaN (fast for short axes); and the number of values."""
    s = np.sort(a, axis=0)  # NaN last
    k = np.isfinite(a).sum(axis=0)
    lo = np.clip((k - 1) // 2, 0, a.shape[0] - 1)
    hi = np.clip(k // 2, 0, a.shape[0] - 1)
    m = 0.5 * (
        np.take_along_axis(s, lo[None], axis=0)[0] + np.take_along_axis(s, hi[None], axis=0)[0]
    )
    m = np.where(k > 0, m, np.nan)
    return m, k


def _neighbours_ok(f: np.ndarray, neighbour_ok: Optional[np.ndarray]) -> np.ndarray:
    """:func:`_neighbours`, NaN where ``neighbour_ok`` (8, ny, nx) is False."""
    nb = _neighbours(f)
    if neighbour_ok is not None:
        nb[~np.asarray(neighbour_ok, dtype=bool)] = np.nan
    return nb


def _median_residual(
    f: np.ndarray, eps: float, neighbour_ok: Optional[np.ndarray] = None
) -> Tuple[np.ndarray, np.ndarray]:
    nb = _neighbours_ok(f, neighbour_ok)
    med, k = _nanmedian0(nb)
    rm, _ = _nanmedian0(np.abs(nb - med[None]))
    with np.errstate(invalid="ignore"):
        r = np.abs(f - med) / (rm + eps)
    return r, k


def validate_vectors(
    u,
    v,
    *,
    snr=None,
    snr_min: float = 0.0,
    median_threshold: float = 2.0,
    median_eps_px: float = 0.1,
    neighbour_ok=None,
) -> np.ndarray:
    """Flag spurious vectors of a regular vector grid.

    A vector is an outlier when it is not finite (global test), when ``snr < snr_min``, or
    when the normalised median test (Westerweel & Scarano 2005) fails for either component:
    ``|u0 - u_m| / (r_m + eps) > median_threshold`` with ``u_m`` the median of the (up to 8)
    finite neighbours and ``r_m`` the median of their residuals ``|u_i - u_m|``. Vectors with
    fewer than two finite neighbours are not median-tested.

    Parameters
    ----------
    u, v : (ny, nx) float
        Displacement components (pixels).
    snr : (ny, nx) float, optional
        Signal-to-noise ratio of each vector.
    snr_min : float
        Minimum accepted SNR.
    median_threshold : float
        Threshold of the normalised median test (2 in Westerweel & Scarano 2005).
    median_eps_px : float
        Noise level ``eps`` (pixels) of the normalised median test (0.1 px).
    neighbour_ok : (8, ny, nx) bool, optional
        Which of the 8 neighbours (rows then columns of the offsets -1, 0, 1, the centre
        left out) each vector may be compared with; with breaklines, those on its own side
        (:func:`piv`). Default: all.

    Returns
    -------
    (ny, nx) bool
        True for outliers.
    """
    uu = np.asarray(u, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    if uu.shape != vv.shape or uu.ndim != 2:
        raise InvalidParameterError(f"u and v must be 2-D of one shape, got {uu.shape}, {vv.shape}")
    bad = ~(np.isfinite(uu) & np.isfinite(vv))
    if snr is not None and snr_min > 0:
        s = np.asarray(snr, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            bad |= ~(s >= snr_min)
    if median_threshold is not None and median_threshold > 0:
        uf = np.where(bad, np.nan, uu)
        vf = np.where(bad, np.nan, vv)
        ru, ku = _median_residual(uf, median_eps_px, neighbour_ok)
        rv, _ = _median_residual(vf, median_eps_px, neighbour_ok)
        with np.errstate(invalid="ignore"):
            bad |= (ku >= 2) & ((ru > median_threshold) | (rv > median_threshold))
    return bad


def replace_outliers(
    field, outlier, *, max_iter: int = 10, fill_all: bool = True, neighbour_ok=None
) -> np.ndarray:
    """Replace flagged vectors by the mean of their valid neighbours (iterative inpainting).

    Each iteration sets every still-missing cell with at least one known 8-neighbour to the
    mean of its known neighbours (as OpenPIV's ``replace_outliers`` with ``kernel_size=1``);
    after ``max_iter`` iterations, cells still missing are given their nearest known value when
    ``fill_all`` (a predictor for window deformation must be defined everywhere).

    Parameters
    ----------
    field : (ny, nx) float
        Values (NaN counts as missing too).
    outlier : (ny, nx) bool
        Cells to replace.
    neighbour_ok : (8, ny, nx) bool, optional
        The neighbours each cell may take its value from (as :func:`validate_vectors`);
        with breaklines those on its own side, so a flagged vector is never given the other
        side's motion. The final nearest-value fill (``fill_all``) ignores it.

    Returns
    -------
    (ny, nx) float64
        A new array; unchanged where not missing. All NaN if nothing is known.
    """
    f = np.array(field, dtype=np.float64)
    miss = np.asarray(outlier, dtype=bool) | ~np.isfinite(f)
    f[miss] = np.nan
    if miss.all() or not miss.any():
        return f
    for _ in range(max_iter):
        nb = _neighbours_ok(f, neighbour_ok)
        k = np.isfinite(nb).sum(axis=0)
        fillable = miss & (k > 0)
        if not fillable.any():
            break
        s = np.where(np.isfinite(nb), nb, 0.0).sum(axis=0)
        f[fillable] = s[fillable] / k[fillable]
        miss &= ~fillable
        if not miss.any():
            break
    if fill_all and miss.any():
        idx = ndimage.distance_transform_edt(miss, return_distances=False, return_indices=True)
        f = f[tuple(idx)]
    return f


# --------------------------------------------------------------------------------------------
# PIV driver
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PIVResult:
    """A PIV displacement field on a regular grid of vectors.

    Attributes
    ----------
    x, y : (n_rows_v, n_cols_v) float64
        Map coordinates of the vectors (m): centres of the final interrogation windows in the
        before-image. Row 0 is north.
    dx, dy, dz : (n_rows_v, n_cols_v) float64
        Displacement from before to after (m): ``+x`` east, ``+y`` north, ``+z`` up. NaN where
        the before-DEM has too little data in the window.
    snr : (n_rows_v, n_cols_v) float64
        Correlation signal-to-noise ratio of the final pass (peak / second local peak).
    valid : (n_rows_v, n_cols_v) bool
        False where the vector was missing or an outlier (and replaced by its neighbours' mean),
        has no data, or could not be checked: fewer than two of its 8 neighbours (on its
        side of any breakline) are valid, so the normalised median test had nothing to
        compare it with (it keeps its value).
    spacing_m : float
        Vector spacing (m).
    origin_xy : (float, float)
        Upper-left corner of the vector grid seen as a raster whose pixel centres are the
        vectors (for GeoTIFF geotransforms: ``(x0, spacing, 0, y0, 0, -spacing)``).
    windows_px : tuple of int
        Interrogation window sizes of the passes (pixels).
    search_px : int
        First-pass search margin on each side (pixels).
    cell_m : float
        DEM cell size (m).
    near_break : (n_rows_v, n_cols_v) bool, optional
        True where the final interrogation window crosses a breakline (:func:`piv`'s
        ``breaklines``): the vector was correlated on its centre's side of the line only,
        from fewer pixels, and its window may hold ground that moved differently. None (all
        False) without breaklines.
    """

    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    dz: np.ndarray
    snr: np.ndarray
    valid: np.ndarray
    spacing_m: float
    origin_xy: Tuple[float, float]
    windows_px: Tuple[int, ...]
    search_px: int
    cell_m: float
    near_break: Optional[np.ndarray] = None

    @property
    def shape(self) -> Tuple[int, int]:
        """``(n_rows_v, n_cols_v)``."""
        return tuple(self.x.shape)  # type: ignore[return-value]

    def near_break_or_false(self) -> np.ndarray:
        """:attr:`near_break`, all False when None: (n_rows_v, n_cols_v) bool."""
        if self.near_break is None:
            return np.zeros(self.x.shape, dtype=bool)
        return np.asarray(self.near_break, dtype=bool)

    def to_columns(self) -> Dict[str, np.ndarray]:
        """Flattened (row-major) ``x, y, dx, dy, dz, snr, valid, near_break`` arrays."""
        return {
            "x": self.x.ravel().copy(),
            "y": self.y.ravel().copy(),
            "dx": self.dx.ravel().copy(),
            "dy": self.dy.ravel().copy(),
            "dz": self.dz.ravel().copy(),
            "snr": self.snr.ravel().copy(),
            "valid": self.valid.ravel().copy(),
            "near_break": self.near_break_or_false().ravel().copy(),
        }


@dataclass(frozen=True)
class _Layout:
    """Window layout of one pass: top-left pixels r0 (ny,), c0 (nx,), window size, step."""

    r0: np.ndarray
    c0: np.ndarray
    size: int
    step: int

    @property
    def rc(self) -> np.ndarray:  # centre rows (fractional pixel index)
        return self.r0 + (self.size - 1) / 2.0

    @property
    def cc(self) -> np.ndarray:
        return self.c0 + (self.size - 1) / 2.0


def _layout(
    n_rows: int, n_cols: int, size: int, step: int, frame: Optional[Tuple[int, ...]] = None
) -> _Layout:
    """Windows of ``size`` every ``step`` pixels, centred in the DEM; with ``frame = (N_rows,
    N_cols, row0, col0)`` the windows of a DEM of ``N_rows x N_cols`` of which this one is the
    part starting at ``(row0, col0)``, those that lie wholly inside this part."""

    def one(n, n_all, first):
        k = (n_all - size) // step + 1
        off = ((n_all - size) - (k - 1) * step) // 2
        pos = off + step * np.arange(k) - first
        return pos[(pos >= 0) & (pos + size <= n)]

    if frame is None:
        frame = (n_rows, n_cols, 0, 0)
    f_rows, f_cols, row0, col0 = (int(v) for v in frame)
    return _Layout(r0=one(n_rows, f_rows, row0), c0=one(n_cols, f_cols, col0), size=size, step=step)


def _interp_sep(f: np.ndarray, pos_r: np.ndarray, pos_c: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``f`` (ny, nx) on the tensor grid of fractional indices
    ``pos_r`` x ``pos_c`` (clamped to the edges): (len(pos_r), len(pos_c))."""

    def weights(p, n):
        p = np.clip(p, 0.0, n - 1.0)
        i0 = np.minimum(np.floor(p).astype(np.int64), max(n - 2, 0))
        t = p - i0
        i1 = np.minimum(i0 + 1, n - 1)
        return i0, i1, t

    ny, nx = f.shape
    c0, c1, tc = weights(np.asarray(pos_c, dtype=np.float64), nx)
    g = f[:, c0] * (1.0 - tc) + f[:, c1] * tc
    r0, r1, tr = weights(np.asarray(pos_r, dtype=np.float64), ny)
    return g[r0] * (1.0 - tr)[:, None] + g[r1] * tr[:, None]


def _field_at(f: np.ndarray, lay: _Layout, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Vector field ``f`` of layout ``lay`` interpolated at pixel rows x cols (tensor grid)."""
    pr = (rows - lay.rc[0]) / lay.step
    pc = (cols - lay.cc[0]) / lay.step
    return _interp_sep(f, pr, pc)


class _Warper:
    """Warps image 2 by a per-pixel displacement field (NaN-aware)."""

    def __init__(self, img: np.ndarray, mask: np.ndarray, order: int):
        self.order = order
        self.shape = img.shape
        if mask.all():
            filled = img
        elif mask.any():
            idx = ndimage.distance_transform_edt(~mask, return_distances=False, return_indices=True)
            filled = img[tuple(idx)]
        else:
            filled = np.zeros_like(img)
        if order > 1:
            self.coef = ndimage.spline_filter(filled, order=order, mode="mirror")
            # a warped pixel is valid only if its whole spline support was valid
            support = ~ndimage.binary_dilation(~mask, structure=np.ones((3, 3), bool))
        else:
            self.coef = filled
            support = mask
        self.support = support.astype(np.float64)
        self.all_valid = bool(mask.all())

    def warp(self, dr: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """``img(r + dr, c + dc)`` for every pixel, NaN where not supported by valid data."""
        n_rows, n_cols = self.shape
        rr = np.arange(n_rows, dtype=np.float64)[:, None] + dr
        cc = np.arange(n_cols, dtype=np.float64)[None, :] + dc
        coords = np.stack([rr, cc])
        del rr, cc
        out = ndimage.map_coordinates(
            self.coef, coords, order=self.order, mode="nearest", prefilter=False
        )
        m = ndimage.map_coordinates(self.support, coords, order=1, mode="constant", cval=0.0)
        out[m < 1.0 - 1e-9] = np.nan
        return out


def _window_sums(a: np.ndarray, lay: _Layout) -> np.ndarray:
    """Sums of ``a`` over the windows of ``lay`` (integral image): (ny, nx)."""
    ii = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
    ii[1:, 1:] = a.cumsum(axis=0).cumsum(axis=1)
    r0, c0, w = lay.r0[:, None], lay.c0[None, :], lay.size
    return ii[r0 + w, c0 + w] - ii[r0, c0 + w] - ii[r0 + w, c0] + ii[r0, c0]


def _window_stack(a: np.ndarray, lay: _Layout, idx: np.ndarray) -> np.ndarray:
    """The (n, w, w) pixels of ``a`` in the windows ``idx`` (2, n) of ``lay``."""
    w = lay.size
    view = sliding_window_view(a, (w, w))
    return view[lay.r0[idx[0]], lay.c0[idx[1]]]


def _finite_window_sums(a: np.ndarray, lay: _Layout):
    """Sums of the finite values of ``a`` over each window of ``lay``, their counts, and the
    finite mask of ``a``."""
    ok = np.isfinite(a)
    return _window_sums(np.where(ok, a, 0.0), lay), _window_sums(ok.astype(np.float64), lay), ok


def _vertical_predictor(img2w, img1, lay, rows, cols, sides, nb_ok) -> np.ndarray:
    """The elevation change at every pixel (m): the mean of the deformed image 2 less image 1
    over each window of the previous pass's layout ``lay`` (windows with under a quarter of
    their pixels valid filled from their neighbours, on their side of any breakline), then
    interpolated to the pixels as the horizontal predictor is (:func:`_predictor`). What
    :func:`piv` reports as ``dz`` at the end, made at every deformed pass."""
    s, cnt, _ = _finite_window_sums(img2w - img1, lay)
    with np.errstate(invalid="ignore", divide="ignore"):
        mz = np.where(cnt >= 0.25 * lay.size**2, s / cnt, np.nan)
    if not np.isfinite(mz).any():
        return np.zeros_like(img1)
    mz = replace_outliers(mz, ~np.isfinite(mz), fill_all=True, neighbour_ok=nb_ok)
    return _predictor(mz, lay, rows, cols, sides)


def _predictor(f, lay, rows, cols, sides) -> np.ndarray:
    """The previous pass's vectors ``f`` at every pixel: bilinear, per side with breaklines."""
    if sides is None:
        return _field_at(f, lay, rows, cols)
    return sides.field_at(f, lay, rows, cols)


# --------------------------------------------------------------------------------------------
# breaklines: sides on the pixel grid
# --------------------------------------------------------------------------------------------

#: neighbour offsets in the order of :func:`_neighbours`
_OFFSETS = tuple((di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj)


def _clip_segment(p0, p1, lo, hi):
    """Parameters ``(t0, t1)`` of the part of ``p0 -> p1`` inside the box ``lo..hi``
    (Liang-Barsky), or None when it misses the box."""
    t0, t1 = 0.0, 1.0
    d = p1 - p0
    for k in range(2):
        if d[k] == 0.0:
            if p0[k] < lo[k] or p0[k] > hi[k]:
                return None
            continue
        a, b = (lo[k] - p0[k]) / d[k], (hi[k] - p0[k]) / d[k]
        t0, t1 = max(t0, min(a, b)), min(t1, max(a, b))
        if t0 > t1:
            return None
    return t0, t1


class _Sides:
    """Breaklines on the pixel grid of one PIV run: which windows they cross, which pixels
    and vectors lie on which side (:func:`slipmap.core.breaklines.crossings` between their
    centres), and the predictor interpolated per side.

    The exact segment tests run only where a breakline is near: the pixels a breakline
    passes through, dilated by one pixel, are marked once, and an integral image of the marks
    says in O(1) whether a box of pixels can hold a crossing.
    """

    def __init__(self, lines, grid: Grid):
        self.lines = lines
        self.grid = grid
        n_rows, n_cols = grid.shape
        cell = grid.cell_m
        mark = np.zeros((n_rows, n_cols), dtype=bool)
        lo = np.array([grid.x_min - cell, grid.y_min - cell])
        hi = np.array([grid.x_max + cell, grid.y_max + cell])
        for seg in lines.segments:
            p0, p1 = seg[:2], seg[2:]
            tt = _clip_segment(p0, p1, lo, hi)
            if tt is None:
                continue
            a, b = p0 + tt[0] * (p1 - p0), p0 + tt[1] * (p1 - p0)
            n = int(math.ceil(4.0 * float(np.hypot(*(b - a))) / cell)) + 2
            t = np.linspace(0.0, 1.0, n)[:, None]
            pts = a + t * (b - a)
            c = np.floor((pts[:, 0] - grid.x_min) / cell).astype(np.int64)
            r = np.floor((grid.y_max - pts[:, 1]) / cell).astype(np.int64)
            ok = (r >= 0) & (r < n_rows) & (c >= 0) & (c < n_cols)
            mark[r[ok], c[ok]] = True
        mark = ndimage.binary_dilation(mark, structure=np.ones((3, 3), dtype=bool))
        self.any = bool(mark.any())
        ii = np.zeros((n_rows + 1, n_cols + 1), dtype=np.int64)
        ii[1:, 1:] = mark.cumsum(axis=0).cumsum(axis=1)
        self.ii = ii

    def box_has_line(self, r_lo, r_hi, c_lo, c_hi) -> np.ndarray:
        """Whether the pixel box rows ``r_lo..r_hi``, columns ``c_lo..c_hi`` (inclusive,
        fractional values widened to whole pixels, broadcast) holds a marked pixel."""
        n_rows, n_cols = self.grid.shape
        r0 = np.clip(np.floor(r_lo).astype(np.int64), 0, n_rows)
        r1 = np.clip(np.ceil(r_hi).astype(np.int64) + 1, 0, n_rows)
        c0 = np.clip(np.floor(c_lo).astype(np.int64), 0, n_cols)
        c1 = np.clip(np.ceil(c_hi).astype(np.int64) + 1, 0, n_cols)
        ii = self.ii
        return (ii[r1, c1] - ii[r0, c1] - ii[r1, c0] + ii[r0, c0]) > 0

    def xy(self, rows, cols) -> np.ndarray:
        """(N, 2) map coordinates of pixel positions (flattened)."""
        x, y = self.grid.xy_of(rows, cols)
        return np.column_stack([np.ravel(x), np.ravel(y)])

    def same(self, r1, c1, r2, c2) -> np.ndarray:
        """True where the segment between pixel positions ``(r1, c1)`` and ``(r2, c2)``
        (arrays of one shape) crosses no breakline."""
        from .breaklines import same_side

        shape = np.broadcast(r1, c1, r2, c2).shape
        r1, c1, r2, c2 = (np.broadcast_to(a, shape) for a in (r1, c1, r2, c2))
        return same_side(self.xy(r1, c1), self.xy(r2, c2), self.lines).reshape(shape)

    def window_masks(self, lay: _Layout):
        """The windows of ``lay`` that a breakline crosses and, for each, the pixels on its
        centre's side.

        Returns
        -------
        near : (ny, nx) bool
            Windows with pixels on both sides of a breakline.
        idx : (2, n) int
            Their indices ``(i, j)``.
        masks : (n, w, w) bool
            Per window, True on the pixels on its centre's side.
        """
        w = lay.size
        ny, nx = lay.r0.size, lay.c0.size
        near = np.zeros((ny, nx), dtype=bool)
        empty = (np.zeros((2, 0), dtype=np.int64), np.zeros((0, w, w), dtype=bool))
        if not self.any or ny == 0 or nx == 0:
            return (near,) + empty
        cand = self.box_has_line(
            lay.r0[:, None], lay.r0[:, None] + w - 1, lay.c0[None, :], lay.c0[None, :] + w - 1
        )
        ci, cj = np.nonzero(cand)
        if ci.size == 0:
            return (near,) + empty
        k = np.arange(w)
        pr = (lay.r0[ci][:, None, None] + k[None, :, None]).astype(np.float64)
        pc = (lay.c0[cj][:, None, None] + k[None, None, :]).astype(np.float64)
        pr, pc = np.broadcast_arrays(pr, pc)
        masks = self.same(
            pr, pc, lay.rc[ci][:, None, None] + 0 * pr, lay.cc[cj][:, None, None] + 0 * pc
        )
        crossed = ~masks.all(axis=(1, 2))
        ci, cj, masks = ci[crossed], cj[crossed], masks[crossed]
        near[ci, cj] = True
        return near, np.stack([ci, cj]), masks

    def neighbour_ok(self, lay: _Layout) -> np.ndarray:
        """(8, ny, nx) bool: the neighbour in the direction :data:`_OFFSETS` ``[k]`` is on the
        vector's side (the segment between their window centres crosses no breakline)."""
        ny, nx = lay.r0.size, lay.c0.size
        ok = np.ones((8, ny, nx), dtype=bool)
        if not self.any:
            return ok
        rc, cc = lay.rc, lay.cc
        ii, jj = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        for k, (di, dj) in enumerate(_OFFSETS):
            i2, j2 = np.clip(ii + di, 0, ny - 1), np.clip(jj + dj, 0, nx - 1)
            r_a, r_b = rc[ii], rc[i2]
            c_a, c_b = cc[jj], cc[j2]
            cand = self.box_has_line(
                np.minimum(r_a, r_b), np.maximum(r_a, r_b), np.minimum(c_a, c_b),
                np.maximum(c_a, c_b),
            )  # fmt: skip
            if cand.any():
                ok[k][cand] = self.same(r_a[cand], c_a[cand], r_b[cand], c_b[cand])
        return ok

    def field_at(self, f: np.ndarray, lay: _Layout, rows, cols) -> np.ndarray:
        """:func:`_field_at` per side: a pixel takes the bilinear weights of only the four
        surrounding vectors on its side (renormalised), or, when none of them is, the
        inverse-distance mean of those of the 4 x 4 around it on its side (the plain
        bilinear value where there is none)."""
        out = _field_at(f, lay, rows, cols)
        ny, nx = f.shape
        if not self.any or ny < 2 or nx < 2:
            return out

        def nodes(pos, centres, n):
            p = np.clip((pos - centres[0]) / lay.step, 0.0, n - 1.0)
            i0 = np.minimum(np.floor(p).astype(np.int64), n - 2)
            return i0, p - i0

        i0, tr = nodes(rows, lay.rc, ny)
        j0, tc = nodes(cols, lay.cc, nx)
        rc, cc = lay.rc, lay.cc
        r_lo = np.minimum(rows, rc[i0])[:, None]
        r_hi = np.maximum(rows, rc[i0 + 1])[:, None]
        c_lo = np.minimum(cols, cc[j0])[None, :]
        c_hi = np.maximum(cols, cc[j0 + 1])[None, :]
        sr, sc = np.nonzero(self.box_has_line(r_lo, r_hi, c_lo, c_hi))
        if sr.size == 0:
            return out
        pr, pc = rows[sr], cols[sc]
        num = np.zeros(sr.size)
        den = np.zeros(sr.size)
        for a, wa in ((0, 1.0 - tr[sr]), (1, tr[sr])):
            for b, wb in ((0, 1.0 - tc[sc]), (1, tc[sc])):
                ni, nj = i0[sr] + a, j0[sc] + b
                same = self.same(pr, pc, rc[ni], cc[nj])
                wgt = np.where(same, wa * wb, 0.0)
                num += wgt * f[ni, nj]
                den += wgt
        good = den > 1e-9
        out[sr[good], sc[good]] = num[good] / den[good]
        lone = np.flatnonzero(~good)
        if lone.size:
            num = np.zeros(lone.size)
            den = np.zeros(lone.size)
            qr, qc = pr[lone], pc[lone]
            for a in (-1, 0, 1, 2):
                for b in (-1, 0, 1, 2):
                    ni = np.clip(i0[sr[lone]] + a, 0, ny - 1)
                    nj = np.clip(j0[sc[lone]] + b, 0, nx - 1)
                    same = self.same(qr, qc, rc[ni], cc[nj])
                    d2 = (qr - rc[ni]) ** 2 + (qc - cc[nj]) ** 2
                    wgt = np.where(same, 1.0 / (d2 + 1e-6), 0.0)
                    num += wgt * f[ni, nj]
                    den += wgt
            ok = den > 0
            out[sr[lone[ok]], sc[lone[ok]]] = num[ok] / den[ok]
        return out


def _correlate_pass(
    img1: np.ndarray,
    img2: np.ndarray,
    lay: _Layout,
    margin: int,
    has_data: np.ndarray,
    min_valid_fraction: float,
    workers: Optional[int],
    progress: Optional[ProgressCallback],
    sides: Optional[Tuple[np.ndarray, np.ndarray, float]] = None,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Correlation peaks (offsets from zero shift, pixels) and SNR per window of ``lay``.

    ``sides = (idx, masks, min_fraction)``: the windows ``idx`` (2, n) that a breakline
    crosses correlate only the template pixels ``masks`` (n, w, w) on their centre's side,
    with ``min_fraction`` as their minimum overlap.
    """
    w = lay.size
    ny, nx = len(lay.r0), len(lay.c0)
    dr = np.full((ny, nx), np.nan)
    dc = np.full((ny, nx), np.nan)
    snr = np.full((ny, nx), np.nan)
    padded = np.pad(img2, margin, constant_values=np.nan)
    tview = sliding_window_view(img1, (w, w))
    sview = sliding_window_view(padded, (w + 2 * margin, w + 2 * margin))
    big = w + 2 * margin
    l1 = sfft.next_fast_len(big, real=True)
    per_window = 6 * l1 * (l1 // 2 + 1) * 16 * 2 + 6 * l1 * l1 * 8 + 8 * big * big * 8
    chunk = max(1, int(CHUNK_BYTES // per_window))
    groups = []
    if sides is None or sides[0].shape[1] == 0:
        groups.append((np.nonzero(has_data), None, min_valid_fraction))
    else:
        idx, masks, side_fraction = sides
        crossed = np.zeros((ny, nx), dtype=bool)
        crossed[idx[0], idx[1]] = True
        groups.append((np.nonzero(has_data & ~crossed), None, min_valid_fraction))
        keep = has_data[idx[0], idx[1]]
        groups.append(((idx[0][keep], idx[1][keep]), masks[keep], side_fraction))
    n = sum(g[0][0].size for g in groups)
    if n == 0:
        return dr, dc, snr
    done = 0
    for (sel_i, sel_j), masks, fraction in groups:
        for a in range(0, sel_i.size, chunk):
            b = min(sel_i.size, a + chunk)
            ri = lay.r0[sel_i[a:b]]
            ci = lay.c0[sel_j[a:b]]
            templates = tview[ri, ci]
            if masks is not None:
                templates = np.where(masks[a:b], templates, np.nan)
            corr = masked_ncc(
                templates,
                sview[ri, ci],
                min_overlap_fraction=fraction,
                workers=workers,
            )
            pk = subpixel_peak(corr)
            dr[sel_i[a:b], sel_j[a:b]] = pk.row - margin
            dc[sel_i[a:b], sel_j[a:b]] = pk.col - margin
            snr[sel_i[a:b], sel_j[a:b]] = pk.snr
            done += b - a
            report(progress, done / n, f"correlated {done}/{n} windows")
    return dr, dc, snr


def _check_windows(windows_px, shape) -> Tuple[int, ...]:
    if isinstance(windows_px, (int, np.integer)):
        windows_px = (int(windows_px),)
    try:
        wins = tuple(int(w) for w in windows_px)
    except (TypeError, ValueError):
        raise InvalidParameterError(
            f"windows_px must be a sequence of window sizes in pixels, got {windows_px!r}"
        ) from None
    if not wins:
        raise InvalidParameterError("windows_px must list at least one window size (pixels)")
    if any(w != float(x) for w, x in zip(wins, windows_px)):
        raise InvalidParameterError(f"windows_px must be whole numbers, got {windows_px!r}")
    if min(wins) < 4:
        raise InvalidParameterError(f"windows_px must be >= 4 pixels each, got {wins}")
    if max(wins) > min(shape):
        raise InvalidParameterError(
            f"windows_px={wins}: a window of {max(wins)} px does not fit in the "
            f"{shape[0]} x {shape[1]} px DEM; use smaller windows or a smaller cell size"
        )
    return wins


def piv(
    z_before,
    z_after,
    *,
    grid: Grid,
    windows_px: Sequence[int] = (64, 32, 16, 16, 16),
    overlap: float = 0.5,
    search_px: Optional[int] = None,
    expected_max_displacement_m: Optional[float] = None,
    refine_search_px: Optional[int] = None,
    snr_min: float = 1.2,
    median_threshold: float = 1.5,
    median_eps_px: float = 0.1,
    min_valid_fraction: float = 0.5,
    interpolation_order: int = 3,
    breaklines=None,
    vertical_compensation: bool = True,
    workers: Optional[int] = None,
    window_frame: Optional[Tuple[int, int, int, int]] = None,
    progress: Optional[ProgressCallback] = None,
) -> PIVResult:
    """3D displacement field between two DEMs on the same grid by multi-pass masked PIV.

    Parameters
    ----------
    z_before, z_after : (n_rows, n_cols) float
        Elevation images (m) of the two epochs on ``grid`` (NaN = no data).
    grid : Grid
        Their grid (row 0 north).
    windows_px : sequence of int
        Interrogation window side ``WC`` of each pass (pixels); repeat the last size to
        iterate. The default ``(64, 32, 16, 16, 16)`` repeats the final size twice: on a
        deforming lobe the first repeat halved the RMSE, and on lone-star at GR 0.15 m (a
        lobe; a lobe beside a scarp) the second one, with ``median_threshold=1.5``, brought
        every case to <= 0.22 cell (docs/fields.md). At ``GR = 0.04 m`` it gives 2.56 m,
        1.28 m and 0.64 m windows and a vector every 0.32 m.
    overlap : float
        Window overlap in [0, 0.95]; the vector step is ``round(WC * (1 - overlap))`` pixels.
    search_px : int, optional
        First-pass search margin ``m`` on each side (pixels): the search window is
        ``WI = WC + 2 m`` and displacements up to ``m - 1`` pixels can be found.
        Default: from ``expected_max_displacement_m`` (``ceil(d_max / GR) + 2``), else
        ``WC // 4``.
    expected_max_displacement_m : float, optional
        Largest expected displacement ``d_max`` (m). A warning is logged when the first window
        breaks the study's rule of thumb ``WC >= 2 d_max`` or the search margin is too small.
    refine_search_px : int, optional
        Search margin of the later (deformed-window) passes; default ``max(3, WC // 8)``.
    snr_min : float
        Vectors with a peak-to-second-peak ratio below this are outliers (0 disables).
    median_threshold, median_eps_px : float
        Normalised median test threshold and noise level (pixels); ``median_threshold=0``
        disables the test. The default 1.5 (Westerweel & Scarano suggest 2) flags a few more
        vectors and removed the clustered wrong ones of lone-star's sparse windows
        (docs/fields.md).
    min_valid_fraction : float
        Minimum fraction of a window (and of each correlated overlap) with data.
    interpolation_order : {1, 3}
        Bilinear or bicubic-spline image warping between passes.
    breaklines : Breaklines or sequence of (M, 2) polylines, optional
        Lines across which the field may jump (scarps, faults, slab edges; map coordinates,
        m; :mod:`slipmap.core.breaklines`). The field is then smooth on each side only:

        * the predictor that deforms image 2 is interpolated per side (a pixel takes the
          displacement of the vectors on its own side only, :func:`slipmap.core.breaklines.
          same_side` between the pixel and the vector's window centre);
        * a window that a breakline crosses is correlated on its centre's side only (the
          other side's pixels are masked in the template; it needs half of
          ``min_valid_fraction`` there), and its predictor average and ``dz`` are taken on
          that side;
        * the normalised median test and the replacement of outliers use the neighbours on
          the vector's side only;
        * the vectors whose final window crosses a breakline are flagged
          (:attr:`PIVResult.near_break`).

        Breaklines that touch no window change nothing.
    vertical_compensation : bool
        In every deformed pass, remove the elevation change the previous pass measured
        (its ``dz`` per window, interpolated to the pixels as the horizontal predictor is)
        from the deformed image 2 before correlating. The correlation ignores a window's
        mean, but not a change that varies across the window: a lobe's flank that drops by
        centimetres over a window reads as a horizontal shift. On lone-star's landslide cases
        (GR 0.15 m) it took the fault's flank from 0.28-0.32 to 0.20-0.23 cell and moved the
        other cases' means by -0.01 to +0.015 cell; on sparse airborne DEMs (GR 0.5 m, a
        handful of vectors) it was mixed (docs/fields.md). A synthetic DEM of 5 cm texture
        with a 10 cm change field: 0.27 -> 0.06 px RMS. False: the change is only reported
        (``dz``).
    workers : int, optional
        FFT threads (default all cores).
    window_frame : (n_rows, n_cols, row0, col0), optional
        Place the windows of every pass as on a DEM of ``n_rows x n_cols`` pixels of which
        these DEMs are the block starting at pixel ``(row0, col0)`` (only the windows wholly
        inside the block are used). A tiled run computes blocks of a DEM too large for memory
        with the whole DEM's windows this way; the vectors far enough from the block's edges
        (the windows, search margins and neighbour tests of every pass) are the whole run's.
    progress : ProgressCallback, optional

    Returns
    -------
    PIVResult

    Raises
    ------
    InvalidParameterError
        Bad options (window sizes not fitting the DEM, overlap, margins...).
    InputDataError
        DEMs of different shapes / not matching ``grid``, all NaN, or no window with enough data.
    """
    z1 = np.asarray(z_before, dtype=np.float64)
    z2 = np.asarray(z_after, dtype=np.float64)
    if not isinstance(grid, Grid):
        raise InvalidParameterError("grid must be a slipmap.core.dem.Grid")
    if z1.ndim != 2 or z1.shape != z2.shape:
        raise InputDataError(
            f"z_before and z_after must be 2-D rasters of the same shape, got {z1.shape} and "
            f"{z2.shape}: grid both epochs on one grid (core.dem.common_grid)"
        )
    if z1.shape != grid.shape:
        raise InputDataError(f"the DEMs have shape {z1.shape} but the grid is {grid.shape}")
    wins = _check_windows(windows_px, z1.shape)
    if not (0.0 <= float(overlap) <= 0.95):
        raise InvalidParameterError(f"overlap must be in [0, 0.95] (e.g. 0.5), got {overlap!r}")
    if not (0.0 < float(min_valid_fraction) <= 1.0):
        raise InvalidParameterError(
            f"min_valid_fraction must be in (0, 1] (e.g. 0.5), got {min_valid_fraction!r}"
        )
    if interpolation_order not in (1, 3):
        raise InvalidParameterError(
            f"interpolation_order must be 1 (bilinear) or 3 (bicubic), got {interpolation_order}"
        )
    m1 = np.isfinite(z1)
    m2 = np.isfinite(z2)
    if not m1.any():
        raise InputDataError("z_before has no data (all NaN): check the gridding / overlap")
    if not m2.any():
        raise InputDataError("z_after has no data (all NaN): check the gridding / overlap")
    cell = grid.cell_m
    w1 = wins[0]

    if search_px is not None:
        if int(search_px) != search_px or int(search_px) < 1:
            raise InvalidParameterError(f"search_px must be a whole number >= 1, got {search_px}")
        margin1 = int(search_px)
    if expected_max_displacement_m is not None:
        d = float(expected_max_displacement_m)
        if not math.isfinite(d) or d < 0:
            raise InvalidParameterError(
                "expected_max_displacement_m must be a finite number >= 0 (metres), got "
                f"{expected_max_displacement_m!r}"
            )
        d_px = d / cell
        if w1 < 2 * d_px:
            log.warning(
                "first window %d px (%.3g m) is smaller than 2 x expected_max_displacement "
                "(%.3g m, rule of thumb WC >= 2 d_max): use a larger first window",
                w1,
                w1 * cell,
                d,
            )
        if search_px is None:
            margin1 = int(math.ceil(d_px)) + 2
        elif margin1 < d_px + 1:
            log.warning(
                "search_px=%d cannot find displacements of %.1f px (%.3g m): increase it",
                margin1,
                d_px,
                d,
            )
    elif search_px is None:
        margin1 = max(2, w1 // 4)
    if refine_search_px is not None and (
        int(refine_search_px) != refine_search_px or int(refine_search_px) < 1
    ):
        raise InvalidParameterError(
            f"refine_search_px must be a whole number >= 1, got {refine_search_px}"
        )
    if w1 + 2 * margin1 < 3 * (margin1 - 1):
        log.warning("search window WI < 3 d_max (rule of thumb): use a larger first window")

    # work relative to one elevation so that FFT sums keep precision; dz is unaffected
    ref = float(np.nanmean(z1))
    img1 = np.where(m1, z1 - ref, np.nan)
    img2 = np.where(m2, z2 - ref, np.nan)
    warper = _Warper(np.where(m2, img2, 0.0), m2, interpolation_order)
    sides = None
    if breaklines is not None:
        from .breaklines import from_sequence

        lines = from_sequence(breaklines)
        if lines is not None:
            sides = _Sides(lines, grid)
            if not sides.any:
                sides = None
    n_rows, n_cols = z1.shape
    rows_px = np.arange(n_rows, dtype=np.float64)
    cols_px = np.arange(n_cols, dtype=np.float64)
    m1f = m1.astype(np.float64)

    prev_lay: Optional[_Layout] = None
    prev_r = prev_c = None
    prev_nb_ok = None
    # each pass costs about the same (n_windows ~ 1/WC^2, FFT area ~ WC^2)
    weights = np.arange(1, len(wins) + 1) / len(wins)
    lay = None
    for k, w in enumerate(wins):
        sub = scaled(progress, 0.95 * (weights[k - 1] if k else 0.0), 0.95 * weights[k])
        report(sub, 0.0, f"PIV pass {k + 1}/{len(wins)} ({w} px windows)")
        step = max(1, int(round(w * (1.0 - float(overlap)))))
        lay = _layout(n_rows, n_cols, w, step, window_frame)
        if lay.r0.size == 0 or lay.c0.size == 0:
            raise InvalidParameterError(
                f"no {w} px window of pass {k + 1} lies inside the DEM block (window_frame "
                f"{window_frame}): use a larger block"
            )
        has_data = _window_sums(m1f, lay) >= min_valid_fraction * w * w
        near = nb_ok = side_args = None
        if sides is not None:
            near, sidx, smasks = sides.window_masks(lay)
            nb_ok = sides.neighbour_ok(lay)
            if sidx.shape[1]:
                # a crossed window needs half the usual data on its own side
                side_fraction = 0.5 * min_valid_fraction
                side_count = (smasks & _window_stack(m1, lay, sidx)).sum(axis=(1, 2))
                has_data[sidx[0], sidx[1]] = side_count >= side_fraction * w * w
                side_args = (sidx, smasks, side_fraction)
        if k == 0 and not has_data.any():
            raise InputDataError(
                f"no {w} x {w} px window of z_before has >= {min_valid_fraction:.0%} data: "
                "use a larger cell size, smaller windows_px or lower min_valid_fraction"
            )
        if k == 0:
            margin = margin1
            img2_k = img2
        else:
            margin = int(refine_search_px) if refine_search_px is not None else max(3, w // 8)
            pr = _predictor(prev_r, prev_lay, rows_px, cols_px, sides)
            pc = _predictor(prev_c, prev_lay, rows_px, cols_px, sides)
            img2_k = warper.warp(pr, pc)
            if vertical_compensation:
                # the elevation change varies across a window (a lobe's flank, a tilting
                # block): left in, its ramp biases the horizontal peak; the previous pass's
                # change is removed as the horizontal predictor is applied
                img2_k = img2_k - _vertical_predictor(
                    img2_k, img1, prev_lay, rows_px, cols_px, sides, prev_nb_ok
                )
            # the correlation measures the residual averaged over the window, so the
            # predictor is added as its window average too (consistent update)
            base_r = _window_sums(pr, lay) / (w * w)
            base_c = _window_sums(pc, lay) / (w * w)
            if side_args is not None:  # crossed windows: the average on their side
                sidx, smasks = side_args[0], side_args[1]
                cnt = np.maximum(smasks.sum(axis=(1, 2)), 1)
                for base, p in ((base_r, pr), (base_c, pc)):
                    stack = _window_stack(p, lay, sidx)
                    base[sidx[0], sidx[1]] = np.where(smasks, stack, 0.0).sum(axis=(1, 2)) / cnt
            del pr, pc
        cr, cc, snr = _correlate_pass(
            img1,
            img2_k,
            lay,
            margin,
            has_data,
            min_valid_fraction,
            workers,
            scaled(sub, 0, 1),
            sides=side_args,
        )
        del img2_k
        if k > 0:
            cr = cr + base_r
            cc = cc + base_c
        cr[~has_data] = np.nan
        cc[~has_data] = np.nan
        bad = validate_vectors(
            cr,
            cc,
            snr=snr,
            snr_min=snr_min,
            median_threshold=median_threshold,
            median_eps_px=median_eps_px,
            neighbour_ok=nb_ok,
        )
        n_bad = int((bad & has_data).sum())
        log.info(
            "PIV pass %d: %d px windows, %d vectors with data, %d outliers replaced",
            k + 1,
            w,
            int(has_data.sum()),
            n_bad,
        )
        fr = replace_outliers(cr, bad, fill_all=True, neighbour_ok=nb_ok)
        fc = replace_outliers(cc, bad, fill_all=True, neighbour_ok=nb_ok)
        if not np.isfinite(fr).any():
            raise InputDataError(
                f"PIV found no valid displacement in pass {k + 1} ({w} px windows): check "
                "that the DEMs overlap, increase search_px / expected_max_displacement_m, "
                "the window sizes or lower min_valid_fraction"
            )
        prev_lay, prev_r, prev_c, prev_nb_ok = lay, fr, fc, nb_ok
        final_bad, final_snr, final_has = bad, snr, has_data
        final_near, final_sides, final_nb_ok = near, side_args, nb_ok

    # vertical component: mean over the final window of I2(x + d) - I1(x)
    report(progress, 0.96, "vertical component")
    pr = _predictor(prev_r, prev_lay, rows_px, cols_px, sides)
    pc = _predictor(prev_c, prev_lay, rows_px, cols_px, sides)
    diff = warper.warp(pr, pc) - img1
    del pr, pc
    s, cnt, ok = _finite_window_sums(diff, lay)
    need = np.full(s.shape, min_valid_fraction * lay.size**2)
    if final_sides is not None:  # crossed windows: their own side's pixels
        sidx, smasks, side_fraction = final_sides
        on_side = smasks & _window_stack(ok, lay, sidx).astype(bool)
        s[sidx[0], sidx[1]] = np.where(on_side, _window_stack(diff, lay, sidx), 0.0).sum(
            axis=(1, 2)
        )
        cnt[sidx[0], sidx[1]] = on_side.sum(axis=(1, 2))
        need[sidx[0], sidx[1]] = side_fraction * lay.size**2
    with np.errstate(invalid="ignore", divide="ignore"):
        dz = s / cnt
    dz[cnt < need] = np.nan

    dr_out = np.where(final_has, prev_r, np.nan)
    dc_out = np.where(final_has, prev_c, np.nan)
    dz[~final_has] = np.nan
    # a vector with fewer than two good neighbours (on its side) escaped the median test:
    # nothing confirms it, so it is not reported valid (it keeps its value)
    good = np.where(final_has & ~final_bad, 1.0, np.nan)
    confirmed = np.isfinite(_neighbours_ok(good, final_nb_ok)).sum(axis=0) >= 2
    valid = final_has & ~final_bad & confirmed
    rr, cc_ = np.meshgrid(lay.rc, lay.cc, indexing="ij")
    x, y = grid.xy_of(rr, cc_)
    spacing = lay.step * cell
    origin = (float(x[0, 0] - spacing / 2.0), float(y[0, 0] + spacing / 2.0))
    report(progress, 1.0, "PIV done")
    return PIVResult(
        x=x,
        y=y,
        dx=dc_out * cell,
        dy=-dr_out * cell,
        dz=dz,
        snr=np.where(final_has, final_snr, np.nan),
        valid=valid,
        spacing_m=float(spacing),
        origin_xy=origin,
        windows_px=wins,
        search_px=int(margin1),
        cell_m=float(cell),
        near_break=np.zeros(dr_out.shape, dtype=bool) if final_near is None else final_near,
    )


def piv_from_points(
    before,
    after,
    *,
    cell_m: float,
    grid_overlap: str = "intersection",
    progress: Optional[ProgressCallback] = None,
    **options,
) -> PIVResult:
    """Grid two point clouds on a common grid and run :func:`piv`.

    Parameters
    ----------
    before, after : (N, 3) float64
        Point clouds of the two epochs (m), in the same CRS.
    cell_m : float
        Grid size ``GR`` (m).
    grid_overlap : {"intersection", "union"}
        Extent of the common grid (see :func:`slipmap.core.dem.common_grid`).
    progress : ProgressCallback, optional
    **options
        Keyword options of :func:`piv` (``windows_px``, ``overlap``, ``search_px``,
        ``expected_max_displacement_m``, ...).

    Returns
    -------
    PIVResult
    """
    report(progress, 0.0, "gridding")
    grid = common_grid(before, after, cell_m=cell_m, overlap=grid_overlap)
    zb = grid_elevation(before, grid=grid)
    za = grid_elevation(after, grid=grid)
    report(progress, 0.05, "gridded")
    return piv(zb, za, grid=grid, progress=scaled(progress, 0.05, 1.0), **options)
