"""PIV on DEMs: masked NCC against a direct loop oracle, sub-pixel peaks, known shifts of
textured synthetic DEMs (with gaps), the vertical component, vector validation, invariances,
bad input and a realistic check on lone-star.laz. Runs in both venvs (numpy/scipy only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from slipmap.core import dem, piv
from slipmap.core.errors import CancelledError, InputDataError, InvalidParameterError

DATA = Path(__file__).resolve().parents[1] / "data"
UTM_XY = (515_369.0, 4_918_340.0)
N = 192  # synthetic DEM side (pixels)
CELL = 0.1
SHIFT = (1.3, -2.7)  # (rows, cols) pixels: content moves 1.3 px south, 2.7 px west


def _spectrum(n: int, sigma_px: float, seed: int) -> np.ndarray:
    """Fourier spectrum of a periodic, Gaussian-smoothed white-noise field (unit std)."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n)
    kk = k[:, None] ** 2 + k[None, :] ** 2
    f = np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-2 * np.pi**2 * sigma_px**2 * kk)
    return f / np.real(np.fft.ifft2(f)).std()


def _shifted(f: np.ndarray, dr: float, dc: float) -> np.ndarray:
    """Field whose content is moved by (dr, dc) pixels: out(r, c) = in(r - dr, c - dc) (exact)."""
    k = np.fft.fftfreq(f.shape[0])
    return np.real(np.fft.ifft2(f * np.exp(-2j * np.pi * (k[:, None] * dr + k[None, :] * dc))))


@pytest.fixture(scope="module")
def textured():
    f = _spectrum(N, 3.0, seed=1)
    z1 = 5.0 * _shifted(f, 0.0, 0.0) + 2300.0
    z2 = 5.0 * _shifted(f, *SHIFT) + 2300.0
    grid = dem.Grid(x_min=UTM_XY[0], y_max=UTM_XY[1], cell_m=CELL, n_rows=N, n_cols=N)
    return z1, z2, grid


def _errors_px(res: piv.PIVResult, dr: float, dc: float, border: int = 2):
    inner = np.s_[border:-border, border:-border]
    ex = res.dx[inner] / res.cell_m - dc
    ey = -res.dy[inner] / res.cell_m - dr
    return np.abs(ex), np.abs(ey)


def _holes(z: np.ndarray, rng, *, n_holes: int, radius: float) -> np.ndarray:
    out = z.copy()
    rr, cc = np.mgrid[: z.shape[0], : z.shape[1]]
    for _ in range(n_holes):
        r0, c0 = rng.uniform(0, z.shape[0], 2)
        out[(rr - r0) ** 2 + (cc - c0) ** 2 < radius**2] = np.nan
    return out


# ------------------------------------------------------------------ masked NCC vs. reference


@pytest.mark.parametrize("with_nan", [False, True])
def test_fast_ncc_matches_direct_loop(with_nan):
    rng = np.random.default_rng(5)
    n, h, w, big_h, big_w = 6, 8, 9, 14, 13
    t = rng.normal(size=(n, h, w)) * 3 + 1000.0
    s = rng.normal(size=(n, big_h, big_w)) * 3 + 1000.0
    s[:, 2 : 2 + h, 3 : 3 + w] = t + 0.5 * rng.normal(size=t.shape)  # true match at (2, 3)
    if with_nan:
        t[rng.random(t.shape) < 0.15] = np.nan
        s[rng.random(s.shape) < 0.15] = np.nan
        s[0, :5, :] = np.nan  # some shifts with too little overlap
    fast = piv.masked_ncc(t, s, min_overlap_fraction=0.5)
    assert fast.shape == (n, big_h - h + 1, big_w - w + 1)
    for k in range(n):
        ref = piv.masked_ncc_reference(t[k], s[k], min_overlap_fraction=0.5)
        np.testing.assert_array_equal(np.isnan(fast[k]), np.isnan(ref))
        np.testing.assert_allclose(fast[k], ref, rtol=0, atol=1e-10, equal_nan=True)
    if with_nan:
        assert np.isnan(fast[0]).any() and np.isfinite(fast[0]).any()
    best = np.nanargmax(fast[1:].reshape(n - 1, -1), axis=1)  # window 0: true shift hidden
    assert (best == 2 * (big_w - w + 1) + 3).all()


def test_ncc_of_flat_window_is_nan_and_inputs_untouched():
    t = np.ones((1, 6, 6))
    s = np.random.default_rng(0).normal(size=(1, 10, 10))
    s_copy = s.copy()
    assert np.isnan(piv.masked_ncc(t, s)).all()
    assert np.isnan(piv.masked_ncc_reference(t[0], s[0])).all()
    np.testing.assert_array_equal(s, s_copy)
    with pytest.raises(InvalidParameterError):
        piv.masked_ncc(np.ones((1, 6, 6)), np.ones((1, 5, 8)))


def test_subpixel_gaussian_peak_exact_and_parabolic_fallback():
    ii, jj = np.mgrid[:9, :9]
    r0, c0 = 4.3, 3.8
    g = np.exp(-((ii - r0) ** 2 + (jj - c0) ** 2) / (2 * 1.5**2))
    pk = piv.subpixel_peak(g[None])
    assert pk.row[0] == pytest.approx(r0, abs=1e-12)
    assert pk.col[0] == pytest.approx(c0, abs=1e-12)
    assert pk.snr[0] == np.inf  # no second local maximum
    # parabola with a negative neighbour -> parabolic fit is exact
    p = 1.0 - 0.9 * ((ii - 4.2) ** 2 + (jj - 4.4) ** 2)
    pk = piv.subpixel_peak(p[None])
    assert pk.row[0] == pytest.approx(4.2, abs=1e-12)
    assert pk.col[0] == pytest.approx(4.4, abs=1e-12)
    # a second bump gives a finite SNR; a peak on the border gives NaN
    two = g + 0.5 * np.exp(-((ii - 7) ** 2 + (jj - 7) ** 2) / 0.5)
    pk = piv.subpixel_peak(two[None])
    assert 1.0 < pk.snr[0] < 2.5
    edge = np.exp(-((ii - 0) ** 2 + (jj - 4) ** 2) / 2.0)
    assert np.isnan(piv.subpixel_peak(edge[None]).row[0])


# ------------------------------------------------------------------ known shifts


def test_subpixel_shift_recovered(textured):
    z1, z2, grid = textured
    res = piv.piv(z1, z2, grid=grid)
    ex, ey = _errors_px(res, *SHIFT)
    assert ex.mean() <= 0.05 and ey.mean() <= 0.05
    assert res.valid.mean() > 0.95
    # metres, +x east / +y north: content moved west and south
    assert np.nanmedian(res.dx) == pytest.approx(SHIFT[1] * CELL, abs=0.005)
    assert np.nanmedian(res.dy) == pytest.approx(-SHIFT[0] * CELL, abs=0.005)
    np.testing.assert_allclose(np.nanmedian(res.dz), 0.0, atol=0.02)


def test_shift_with_gaps_masked_beats_filled(textured):
    z1, z2, grid = textured
    rng = np.random.default_rng(7)
    h1 = _holes(z1, rng, n_holes=60, radius=5.0)
    h2 = _holes(z2, rng, n_holes=60, radius=5.0)
    assert 0.08 < np.isnan(h1).mean() < 0.3
    res = piv.piv(h1, h2, grid=grid)
    ex, ey = _errors_px(res, *SHIFT)
    ok = np.isfinite(ex)
    masked_err = 0.5 * (ex[ok].mean() + ey[ok].mean())
    assert masked_err <= 0.08
    # the unmasked approach (gaps filled with a constant) is clearly worse
    fill = float(np.nanmean(z1))
    res_f = piv.piv(np.nan_to_num(h1, nan=fill), np.nan_to_num(h2, nan=fill), grid=grid)
    fx, fy = _errors_px(res_f, *SHIFT)
    filled_err = 0.5 * (np.nanmean(fx) + np.nanmean(fy))
    assert filled_err > 2 * masked_err


def test_vertical_component_of_shift_and_uplift(textured):
    z1, z2, grid = textured
    res = piv.piv(z1, z2 + 0.37, grid=grid)
    inner = np.s_[2:-2, 2:-2]
    dz = res.dz[inner]
    assert np.isfinite(dz).mean() > 0.99
    np.testing.assert_allclose(np.nanmean(dz), 0.37, atol=0.01)
    assert np.nanmean(np.abs(dz - 0.37)) < 0.05
    ex, ey = _errors_px(res, *SHIFT)  # uplift does not change the horizontal answer
    assert ex.mean() <= 0.05 and ey.mean() <= 0.05


@pytest.mark.parametrize("amplitude_m", [0.1, 0.3])
def test_vertical_change_across_windows_compensated(amplitude_m):
    """A DEM of 5 cm texture shifted by (1.3, -2.7) px plus an elevation change that varies
    across the windows (a 0.1 or 0.3 m wave, a lobe's flank): left in, its ramp biases the
    correlation (0.27 / 0.50 px RMS, 60 % / 38 % of the vectors valid); removed between the
    passes (the default) every vector is within 0.35 px, the RMS ≤ 0.1 px and ≥ 90 % valid,
    and the reported dz follows the change field within 2 cm RMS."""
    f = _spectrum(N, 3.0, seed=1)
    grid = dem.Grid(x_min=UTM_XY[0], y_max=UTM_XY[1], cell_m=CELL, n_rows=N, n_cols=N)
    rr, cc = np.mgrid[:N, :N]
    change = amplitude_m * np.sin(2 * np.pi * cc / N) * np.cos(2 * np.pi * rr / N)
    z1 = 0.05 * _shifted(f, 0.0, 0.0) + 2300.0
    z2 = 0.05 * _shifted(f, *SHIFT) + 2300.0 + change
    out = {}
    for comp in (False, True):
        res = piv.piv(z1, z2, grid=grid, vertical_compensation=comp)
        ex, ey = _errors_px(res, *SHIFT)
        e = np.hypot(ex, ey)
        ok = np.isfinite(e)
        out[comp] = (float(np.sqrt(np.mean(e[ok] ** 2))), float(e[ok].max()), res)
    rms, worst, res = out[True]
    assert rms <= 0.1 and worst <= 0.35
    assert res.valid.mean() >= 0.9
    assert out[False][0] >= 2.5 * rms  # the bias the compensation removes
    # dz against the change field at the vectors (row, col of their window centres)
    inner = np.s_[2:-2, 2:-2]
    r = np.rint(-(res.y - grid.y_max) / CELL - 0.5).astype(int)
    c = np.rint((res.x - grid.x_min) / CELL - 0.5).astype(int)
    truth_dz = change[np.clip(r, 0, N - 1), np.clip(c, 0, N - 1)]
    d = (res.dz - truth_dz)[inner]
    assert np.sqrt(np.nanmean(d**2)) <= 0.02


def test_larger_displacement_with_expected_max(textured):
    _, _, grid = textured
    f = _spectrum(N, 3.0, seed=3)
    z1 = _shifted(f, 0.0, 0.0)
    z2 = _shifted(f, -9.4, 11.6)
    res = piv.piv(z1, z2, grid=grid, expected_max_displacement_m=1.6)
    assert res.search_px == 18
    ex, ey = _errors_px(res, -9.4, 11.6, border=3)
    assert ex.mean() <= 0.05 and ey.mean() <= 0.05


# ------------------------------------------------------------------ validation


def test_validation_flags_and_replaces_injected_outliers():
    ny, nx = 20, 25
    yy, xx = np.mgrid[:ny, :nx]
    u = 1.0 + 0.05 * xx + 0.02 * yy
    v = -0.5 + 0.03 * np.sin(0.3 * xx)
    spikes = [(3, 4), (10, 10), (15, 20), (0, 0), (19, 24)]
    ub, vb = u.copy(), v.copy()
    for i, j in spikes:
        ub[i, j] += 3.0
        vb[i, j] -= 2.0
    ub[7, 7] = np.nan  # a missing vector
    snr = np.full((ny, nx), 5.0)
    snr[12, 3] = 1.05  # weak peak
    bad = piv.validate_vectors(ub, vb, snr=snr, snr_min=1.2)
    expected = np.zeros((ny, nx), bool)
    for i, j in spikes + [(7, 7), (12, 3)]:
        expected[i, j] = True
    np.testing.assert_array_equal(bad, expected)
    fu = piv.replace_outliers(ub, bad)
    fv = piv.replace_outliers(vb, bad)
    assert np.isfinite(fu).all() and np.isfinite(fv).all()
    np.testing.assert_allclose(fu[bad], u[bad], atol=0.1)
    np.testing.assert_allclose(fv[bad], v[bad], atol=0.1)
    np.testing.assert_array_equal(fu[~bad], ub[~bad])


def test_piv_flags_and_repairs_corrupted_area(textured):
    z1, z2, grid = textured
    z2c = z2.copy()
    rng = np.random.default_rng(11)
    z2c[80:100, 80:100] = rng.normal(2300.0, 5.0, (20, 20))  # unrelated texture: no match
    res = piv.piv(z1, z2c, grid=grid, windows_px=(64, 32, 16))
    x_c, y_c = grid.xy_of(90, 90)
    near = (np.abs(res.x - x_c) < 0.6) & (np.abs(res.y - y_c) < 0.6)
    assert (~res.valid[near]).any()
    # replaced vectors are close to the true shift; the rest is untouched
    bad = ~res.valid
    assert np.isfinite(res.dx[bad]).all()
    np.testing.assert_allclose(res.dx[bad] / CELL, SHIFT[1], atol=1.0)
    np.testing.assert_allclose(-res.dy[bad] / CELL, SHIFT[0], atol=1.0)
    assert np.median(np.abs(res.dx[bad] / CELL - SHIFT[1])) < 0.3


# ------------------------------------------------------------------ invariances, result layout


@settings(max_examples=8)
@given(
    x0=st.floats(-1e6, 1e6, allow_nan=False),
    y0=st.floats(-1e6, 1e6, allow_nan=False),
)
def test_translation_moves_positions_not_displacements(x0, y0):
    f = _spectrum(96, 2.5, seed=2)
    z1 = _shifted(f, 0.0, 0.0)
    z2 = _shifted(f, 0.6, 0.9)
    g1 = dem.Grid(x_min=0.0, y_max=0.0, cell_m=0.2, n_rows=96, n_cols=96)
    g2 = dem.Grid(x_min=x0, y_max=y0, cell_m=0.2, n_rows=96, n_cols=96)
    a = piv.piv(z1, z2, grid=g1, windows_px=(32, 16))
    b = piv.piv(z1, z2, grid=g2, windows_px=(32, 16))
    np.testing.assert_array_equal(a.dx, b.dx)
    np.testing.assert_array_equal(a.dy, b.dy)
    np.testing.assert_array_equal(a.dz, b.dz)
    np.testing.assert_allclose(b.x, a.x + x0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(b.y, a.y + y0, rtol=0, atol=1e-6)


def test_result_layout_and_columns(textured):
    z1, z2, grid = textured
    res = piv.piv(z1, z2, grid=grid, windows_px=(32, 16), overlap=0.5)
    ny, nx = res.shape
    assert res.spacing_m == pytest.approx(8 * CELL)
    # vectors are the pixel centres of a raster with this origin and spacing
    np.testing.assert_allclose(res.x[0], res.origin_xy[0] + (np.arange(nx) + 0.5) * res.spacing_m)
    np.testing.assert_allclose(
        res.y[:, 0], res.origin_xy[1] - (np.arange(ny) + 0.5) * res.spacing_m
    )
    # window centres lie inside the DEM, rows go south
    assert grid.x_min < res.x.min() and res.x.max() < grid.x_max
    assert (np.diff(res.y[:, 0]) < 0).all()
    cols = res.to_columns()
    assert set(cols) == {"x", "y", "dx", "dy", "dz", "snr", "valid", "near_break"}
    assert not cols["near_break"].any()  # no breaklines
    assert all(v.shape == (ny * nx,) for v in cols.values())
    assert cols["valid"].dtype == bool
    np.testing.assert_array_equal(cols["dx"], res.dx.ravel())


def test_progress_and_cancel(textured):
    z1, z2, grid = textured
    seen = []
    piv.piv(z1, z2, grid=grid, windows_px=(32, 16), progress=lambda f, m: seen.append(f))
    assert seen[-1] == 1.0 and all(0.0 <= f <= 1.0 for f in seen)
    assert all(b >= a - 1e-12 for a, b in zip(seen, seen[1:]))

    def cancel(fraction, message):
        if fraction > 0.2:
            raise CancelledError("stop")

    with pytest.raises(CancelledError):
        piv.piv(z1, z2, grid=grid, windows_px=(32, 16), progress=cancel)


# ------------------------------------------------------------------ bad input


def test_bad_inputs(textured):
    z1, z2, grid = textured
    with pytest.raises(InvalidParameterError, match="windows_px"):
        piv.piv(z1, z2, grid=grid, windows_px=(256, 32))
    with pytest.raises(InvalidParameterError, match="windows_px"):
        piv.piv(z1, z2, grid=grid, windows_px=())
    with pytest.raises(InvalidParameterError, match="windows_px"):
        piv.piv(z1, z2, grid=grid, windows_px=(2,))
    with pytest.raises(InvalidParameterError, match="overlap"):
        piv.piv(z1, z2, grid=grid, overlap=1.0)
    with pytest.raises(InvalidParameterError, match="search_px"):
        piv.piv(z1, z2, grid=grid, search_px=0)
    with pytest.raises(InvalidParameterError, match="expected_max_displacement_m"):
        piv.piv(z1, z2, grid=grid, expected_max_displacement_m=-1.0)
    with pytest.raises(InputDataError, match="same shape"):
        piv.piv(z1, z2[:-1], grid=grid)
    with pytest.raises(InputDataError, match="grid"):
        piv.piv(z1[:-1, :-1], z2[:-1, :-1], grid=grid)
    with pytest.raises(InputDataError, match="all NaN"):
        piv.piv(np.full_like(z1, np.nan), z2, grid=grid)
    with pytest.raises(InputDataError, match="all NaN"):
        piv.piv(z1, np.full_like(z2, np.nan), grid=grid)
    sparse = np.full_like(z1, np.nan)
    sparse[::4, ::4] = 1.0
    with pytest.raises(InputDataError, match="min_valid_fraction"):
        piv.piv(sparse, z2, grid=grid)
    with pytest.raises(InvalidParameterError, match="cell_m"):
        piv.piv_from_points(np.zeros((3, 3)), np.zeros((3, 3)), cell_m=0.0)
    a = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    with pytest.raises(InputDataError, match="overlap"):
        piv.piv_from_points(a, a + [10.0, 10.0, 0.0], cell_m=0.1)


def test_rule_of_thumb_warning(textured, caplog):
    z1, z2, grid = textured
    with caplog.at_level("WARNING", logger="slipmap.core.piv"):
        piv.piv(z1, z2, grid=grid, windows_px=(32, 16), expected_max_displacement_m=2.0)
    assert "rule of thumb" in caplog.text


# ------------------------------------------------------------------ real data


def test_lone_star_known_shift():
    pytest.importorskip("laspy")
    from scipy import ndimage

    from slipmap.core.io.las import read_las

    xyz = read_las(DATA / "lone-star.laz").xyz
    rng = np.random.default_rng(0)
    half = rng.random(len(xyz)) < 0.5
    shift = np.array([0.3, -0.5, 0.1])
    before = xyz[half]
    after = xyz[~half] + shift
    res = piv.piv_from_points(before, after, cell_m=0.25)
    # interior: final windows >= 90 % covered by the before-DEM
    grid = dem.common_grid(before, after, cell_m=0.25)
    covered = np.isfinite(dem.grid_elevation(before, grid=grid)).astype(float)
    frac = ndimage.uniform_filter(covered, size=res.windows_px[-1], mode="constant")
    rows, cols = grid.index(np.column_stack([res.x.ravel(), res.y.ravel()]))
    interior = (frac[rows, cols] >= 0.9).reshape(res.shape) & np.isfinite(res.dx)
    assert interior.sum() >= 30
    ex = res.dx[interior] - shift[0]
    ey = res.dy[interior] - shift[1]
    rmse = float(np.sqrt(np.mean(ex**2 + ey**2)))
    assert rmse <= 0.25 * 0.25
    dz = res.dz[interior]
    assert abs(np.nanmedian(dz) - shift[2]) < 0.03
