"""PIV at discontinuities (issue #29): a textured DEM pair with a step in the motion (the two
sides of a tilted line shifted by different known amounts), recovered on both sides with the
breakline given; the smearing without it shown (documented, not a goal); a breakline far from
the data changes nothing; the same-side neighbour rules of the median test and of the
replacement; the per-side predictor against a direct per-pixel loop."""

from __future__ import annotations

import numpy as np
import pytest

from slipmap.core import dem, piv
from slipmap.core.breaklines import breaklines, distance_m, same_side

N = 192
CELL = 0.1
X0, Y0 = 515_000.0, 4_918_000.0
WEST = (1.3, -2.7)  # (rows, cols) pixels of the content west of the line
EAST = (-0.8, 1.6)


def _spectrum(n: int, sigma_px: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(n)
    kk = k[:, None] ** 2 + k[None, :] ** 2
    f = np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-2 * np.pi**2 * sigma_px**2 * kk)
    return f / np.real(np.fft.ifft2(f)).std()


def _shifted(f: np.ndarray, dr: float, dc: float) -> np.ndarray:
    """Content moved by (dr, dc) pixels (exact, periodic)."""
    k = np.fft.fftfreq(f.shape[0])
    return np.real(np.fft.ifft2(f * np.exp(-2j * np.pi * (k[:, None] * dr + k[None, :] * dc))))


def _line_col(r):
    """The step: column of the line at row r (tilted: 0.2 column per row)."""
    return 100.0 + 0.2 * (np.asarray(r, dtype=np.float64) - 96.0)


def _east(r, c) -> np.ndarray:
    return np.asarray(c) > _line_col(r)


@pytest.fixture(scope="module")
def step():
    f = _spectrum(N, 3.0, seed=1)
    z1 = 5.0 * _shifted(f, 0.0, 0.0) + 2300.0
    rr, cc = np.mgrid[:N, :N]
    z2 = np.where(_east(rr, cc), 5.0 * _shifted(f, *EAST), 5.0 * _shifted(f, *WEST)) + 2300.0
    grid = dem.Grid(x_min=X0, y_max=Y0, cell_m=CELL, n_rows=N, n_cols=N)
    ends = np.array([grid.xy_of(r, _line_col(r)) for r in (-60.0, N + 60.0)])
    return z1, z2, grid, breaklines([ends])


def _errors_px(res, grid):
    """Per-vector horizontal error (pixels) against the step's truth, and the vectors'
    pixel positions."""
    rows = (grid.y_max - res.y) / CELL - 0.5
    cols = (res.x - grid.x_min) / CELL - 0.5
    e = _east(rows, cols)
    tr = np.where(e, EAST[0], WEST[0])
    tc = np.where(e, EAST[1], WEST[1])
    err = np.hypot(-res.dy / CELL - tr, res.dx / CELL - tc)
    inner = (rows > 8) & (rows < N - 9) & (cols > 8) & (cols < N - 9)
    return err, e, inner


def test_step_recovered_on_both_sides_with_the_breakline(step):
    z1, z2, grid, lines = step
    res = piv.piv(z1, z2, grid=grid, breaklines=lines)
    err, east, inner = _errors_px(res, grid)
    far = inner & ~res.near_break
    assert far.sum() > 300 and (far & east).sum() > 100 and (far & ~east).sum() > 100
    for side in (east, ~east):
        m = far & side
        assert np.sqrt(np.mean(err[m] ** 2)) <= 0.1  # px
        assert err[m].max() <= 0.25
    # the windows the line crosses are flagged, and only those
    d = distance_m(np.column_stack([res.x.ravel(), res.y.ravel()]), lines).reshape(res.shape)
    half = 16 * CELL / 2
    assert res.near_break[d < 0.5 * half].all()
    assert not res.near_break[d > np.sqrt(2) * half + CELL].any()
    # correlated on their own side, they are right too, not a blend of the two motions
    nb = inner & res.near_break
    assert nb.sum() >= 30
    assert np.sqrt(np.mean(err[nb] ** 2)) <= 0.1
    assert err[nb].max() <= 0.3
    assert res.to_columns()["near_break"].sum() == res.near_break.sum()


def test_step_smeared_without_the_breakline(step):
    """Documents today's behaviour without a breakline (not a goal): the windows across the
    step see a blend of both motions and the vectors within a window of the line are pixels
    off (the two motions differ by 3.8 px)."""
    z1, z2, grid, lines = step
    res = piv.piv(z1, z2, grid=grid)
    err, _, inner = _errors_px(res, grid)
    d = distance_m(np.column_stack([res.x.ravel(), res.y.ravel()]), lines).reshape(res.shape)
    assert not res.near_break.any()
    assert err[inner & (d < 0.8)].max() > 1.0
    # far from the line the field is right
    assert np.sqrt(np.mean(err[inner & (d > 3.0)] ** 2)) <= 0.1


def test_breakline_far_from_the_data_changes_nothing():
    f = _spectrum(128, 3.0, seed=4)
    z1 = 5.0 * _shifted(f, 0.0, 0.0)
    # a smooth field: content moves by a smooth, varying amount (bilinear warp of z1)
    rr, cc = np.mgrid[:128, :128].astype(np.float64)
    dr = 1.0 + 0.6 * np.sin(rr / 40.0)
    dc = -1.5 + 0.5 * np.cos(cc / 35.0)
    from scipy import ndimage

    z2 = ndimage.map_coordinates(z1, [rr - dr, cc - dc], order=3, mode="wrap")
    grid = dem.Grid(x_min=X0, y_max=Y0, cell_m=CELL, n_rows=128, n_cols=128)
    far = breaklines([np.array([[X0 + 100.0, Y0 + 100.0], [X0 + 140.0, Y0 + 120.0]])])
    a = piv.piv(z1, z2, grid=grid)
    b = piv.piv(z1, z2, grid=grid, breaklines=far)
    c = piv.piv(z1, z2, grid=grid, breaklines=[])
    for res in (b, c):
        for k in ("dx", "dy", "dz", "snr", "valid"):
            np.testing.assert_array_equal(getattr(res, k), getattr(a, k))
        assert not res.near_break.any()


def test_median_test_and_replacement_use_same_side_neighbours():
    """A field of two constant halves: without side information the vectors next to the jump
    fail the median test and are replaced by a blend; with it, nothing is flagged, and a
    spike is replaced from its own side only."""
    ny, nx = 9, 12
    u = np.where(np.arange(nx)[None, :] < 6, 0.0, 4.0) * np.ones((ny, 1))
    v = np.zeros((ny, nx))
    ok = np.ones((8, ny, nx), dtype=bool)
    for k, (_, dj) in enumerate(piv._OFFSETS):
        jj = np.clip(np.arange(nx) + dj, 0, nx - 1)
        ok[k] = ((np.arange(nx) < 6)[None, :] == (jj < 6)[None, :]) & np.ones((ny, 1), bool)
    # a straight column jump is 'smooth' to the 3x3 median test (the median is on the
    # vector's own side); a 2-column-wide strip on the other side is not
    u2 = u.copy()
    u2[:, 6] = 0.0  # the strip's first column moved with the west side: a one-column step
    u2[4, 2] = 9.0  # spike on the west side
    bad_all = piv.validate_vectors(u2, v, median_threshold=2.0)
    bad_side = piv.validate_vectors(u2, v, median_threshold=2.0, neighbour_ok=ok)
    assert bad_side[4, 2] and bad_all[4, 2]
    # the column next to the line is compared with the east side only once sides are known
    assert bad_side[:, 6].all()
    # replacement: from the spike's own side only
    fu = piv.replace_outliers(u, np.eye(ny, nx, k=3, dtype=bool), neighbour_ok=ok)
    west = np.eye(ny, nx, k=3, dtype=bool) & (np.arange(nx)[None, :] < 6)
    east = np.eye(ny, nx, k=3, dtype=bool) & (np.arange(nx)[None, :] >= 6)
    np.testing.assert_allclose(fu[west], 0.0)
    np.testing.assert_allclose(fu[east], 4.0)
    blend = piv.replace_outliers(u, np.eye(ny, nx, k=3, dtype=bool))
    assert np.abs(blend[west | east] - np.where(west, 0.0, 4.0)[west | east]).max() > 0.4


def test_per_side_predictor_matches_a_per_pixel_loop(step):
    """The predictor of the next pass, per side, against the obvious loop over pixels: the
    bilinear weights of the four surrounding vectors on the pixel's side, renormalised."""
    _, _, grid, lines = step
    lay = piv._layout(N, N, 32, 16)
    rng = np.random.default_rng(3)
    f = rng.normal(size=(lay.r0.size, lay.c0.size))
    sides = piv._Sides(lines, grid)
    rows = np.arange(N, dtype=np.float64)
    got = sides.field_at(f, lay, rows, rows)
    plain = piv._field_at(f, lay, rows, rows)
    ny, nx = f.shape
    for r in range(0, N, 7):
        for c in range(0, N, 3):
            pr = np.clip((r - lay.rc[0]) / lay.step, 0, ny - 1)
            pc = np.clip((c - lay.cc[0]) / lay.step, 0, nx - 1)
            i0, j0 = min(int(pr), ny - 2), min(int(pc), nx - 2)
            num = den = 0.0
            for i, wi in ((i0, 1 - (pr - i0)), (i0 + 1, pr - i0)):
                for j, wj in ((j0, 1 - (pc - j0)), (j0 + 1, pc - j0)):
                    p = np.array([grid.xy_of(r, c)])
                    q = np.array([grid.xy_of(lay.rc[i], lay.cc[j])])
                    if same_side(p, q, lines)[0]:
                        num += wi * wj * f[i, j]
                        den += wi * wj
            if den > 1e-9:
                assert got[r, c] == pytest.approx(num / den, abs=1e-12)
            # far from the line the predictor is the plain bilinear one
            d = distance_m(np.array([grid.xy_of(r, c)]), lines)[0]
            if d > 3.0 * lay.step * CELL:
                assert got[r, c] == plain[r, c]
