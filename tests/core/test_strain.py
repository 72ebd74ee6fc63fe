"""Tests of horizontal strain from gridded displacement (slipmap.core.strain)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from slipmap.core.errors import InputDataError, InvalidParameterError
from slipmap.core.fields import GriddedField
from slipmap.core.strain import (
    StrainField,
    displacement_gradient,
    displacement_gradient_reference,
    strain_field,
    strain_from_gradient,
)

UTM = (515369.0, 4918380.0)


def _field(fn, *, n_rows=7, n_cols=9, spacing=(2.0, 1.5), origin=UTM, gaps=None):
    """Field sampling ``fn(x, y) -> (u, v)`` (coordinates relative to ``origin``) at centres."""
    sx, sy = spacing
    xc = (np.arange(n_cols) + 0.5) * sx
    yc = -(np.arange(n_rows) + 0.5) * sy
    X, Y = np.meshgrid(xc, yc)
    u, v = fn(X, Y)
    u = np.broadcast_to(np.asarray(u, dtype=float), X.shape).copy()
    v = np.broadcast_to(np.asarray(v, dtype=float), X.shape).copy()
    if gaps is not None:
        u[gaps] = np.nan
        v[gaps] = np.nan
    return GriddedField(origin, spacing, u, v, np.zeros_like(u))


def _linear(L, c=(0.0, 0.0)):
    L = np.asarray(L, dtype=float)

    def fn(x, y):
        return L[0, 0] * x + L[0, 1] * y + c[0], L[1, 0] * x + L[1, 1] * y + c[1]

    return fn


def _assert_all(a, value, atol=1e-12):
    a = np.asarray(a)
    assert np.all(np.isfinite(a)), a
    np.testing.assert_allclose(a, value, rtol=0, atol=atol)


# --- known answers -------------------------------------------------------------------------


def test_uniform_simple_shear():
    g = 0.02
    s = strain_field(_field(lambda x, y: (g * y, 0.0 * x)))
    assert isinstance(s, StrainField)
    _assert_all(s.exx, 0.0)
    _assert_all(s.eyy, 0.0)
    _assert_all(s.exy, g / 2)
    _assert_all(s.rotation_rad, -g / 2)  # u = g y turns the material clockwise
    _assert_all(s.e1, g / 2)
    _assert_all(s.e2, -g / 2)
    _assert_all(s.max_shear, g / 2)  # tensor shear; engineering shear would be g
    _assert_all(s.dilatation, 0.0)
    _assert_all(s.e1_azimuth_deg, 45.0, atol=1e-9)  # extension towards NE
    neg = strain_field(_field(lambda x, y: (-g * y, 0.0 * x)))
    _assert_all(neg.e1_azimuth_deg, 135.0, atol=1e-9)  # towards SE (NW)


def test_uniform_extension():
    s = strain_field(_field(lambda x, y: (0.01 * x, -0.004 * y)))
    _assert_all(s.exx, 0.01)
    _assert_all(s.eyy, -0.004)
    _assert_all(s.exy, 0.0)
    _assert_all(s.e1, 0.01)
    _assert_all(s.e2, -0.004)
    _assert_all(s.dilatation, 0.006)
    _assert_all(s.rotation_rad, 0.0)
    _assert_all(s.e1_azimuth_deg, 90.0, atol=1e-9)  # e1 along east
    ns = strain_field(_field(lambda x, y: (-0.004 * x, 0.01 * y)))
    _assert_all(ns.e1_azimuth_deg, 0.0, atol=1e-9)  # e1 along north, reported as 0 not 180


def test_isotropic_extension_has_no_azimuth():
    s = strain_field(_field(lambda x, y: (0.01 * x, 0.01 * y)))
    _assert_all(s.e1, 0.01)
    _assert_all(s.e2, 0.01)
    assert np.all(np.isnan(s.e1_azimuth_deg))


def test_infinitesimal_rotation_gives_zero_strain():
    w = 1e-3
    s = strain_field(_field(lambda x, y: (-w * y, w * x)))
    for a in (s.exx, s.eyy, s.exy, s.e1, s.e2, s.max_shear, s.dilatation):
        _assert_all(a, 0.0, atol=1e-15)
    _assert_all(s.rotation_rad, w, atol=1e-15)


def test_small_finite_rotation():
    """A rigid rotation by a small angle: strain is second order (cos - 1), omega = sin."""
    a = 1e-4
    c, sn = math.cos(a), math.sin(a)
    s = strain_field(_field(lambda x, y: ((c - 1) * x - sn * y, sn * x + (c - 1) * y)))
    _assert_all(s.exy, 0.0, atol=1e-14)
    _assert_all(s.exx, c - 1, atol=1e-14)  # -5e-9
    _assert_all(s.rotation_rad, a, atol=1e-12)


def test_axes_and_signs_on_a_general_linear_field():
    L = np.array([[0.011, -0.007], [0.003, -0.005]])  # [[du/dx, du/dy], [dv/dx, dv/dy]]
    s = strain_field(_field(_linear(L, c=(5.0, -3.0))))
    _assert_all(s.dudx, L[0, 0])
    _assert_all(s.dudy, L[0, 1])
    _assert_all(s.dvdx, L[1, 0])
    _assert_all(s.dvdy, L[1, 1])
    E = 0.5 * (L + L.T)
    w, vec = np.linalg.eigh(E)
    _assert_all(s.e1, w[1])
    _assert_all(s.e2, w[0])
    e1x, e1y = vec[:, 1]
    az = math.degrees(math.atan2(e1x, e1y)) % 180.0
    _assert_all(s.e1_azimuth_deg, az, atol=1e-9)
    _assert_all(s.rotation_rad, 0.5 * (L[1, 0] - L[0, 1]))


def test_linear_field_with_gaps_is_exact_at_one_sided_cells():
    L = np.array([[0.02, 0.01], [-0.03, 0.005]])
    gaps = np.zeros((7, 9), dtype=bool)
    gaps[3, 3] = gaps[0, 2] = gaps[4, :3] = gaps[2:4, 6] = True
    f = _field(_linear(L), gaps=gaps)
    s = strain_field(f)
    # every valid cell has at least one neighbour on each axis here
    np.testing.assert_array_equal(s.valid, ~gaps)
    np.testing.assert_allclose(s.dudx[~gaps], L[0, 0], atol=1e-12)
    np.testing.assert_allclose(s.dudy[~gaps], L[0, 1], atol=1e-12)
    np.testing.assert_allclose(s.dvdx[~gaps], L[1, 0], atol=1e-12)
    np.testing.assert_allclose(s.dvdy[~gaps], L[1, 1], atol=1e-12)
    assert np.all(np.isnan(s.exx[gaps]))


def test_isolated_cell_along_an_axis_gets_nan():
    gaps = np.zeros((3, 3), dtype=bool)
    gaps[0, 1] = gaps[2, 1] = True  # the centre column's middle cell has no north/south data
    s = strain_field(_field(lambda x, y: (0.01 * x, 0.01 * y), n_rows=3, n_cols=3, gaps=gaps))
    assert np.isfinite(s.dudx[1, 1]) and np.isnan(s.dudy[1, 1]) and np.isnan(s.exy[1, 1])
    assert np.isfinite(s.exy[1, 0])
    assert np.isnan(s.dudx[0, 0])  # its only x neighbour is the gap at [0, 1]


def test_central_where_possible_one_sided_at_edges_and_gaps():
    """u = x**2: central differences are exact (2x), one-sided ones are off by sx."""
    sx = 2.0
    gaps = np.zeros((3, 6), dtype=bool)
    gaps[1, 3] = True
    f = _field(lambda x, y: (x**2, 0.0 * x), n_rows=3, n_cols=6, spacing=(sx, 1.0), gaps=gaps)
    s = strain_field(f)
    xc = (np.arange(6) + 0.5) * sx
    np.testing.assert_allclose(s.dudx[0, 1:5], 2 * xc[1:5])  # interior: central, exact
    assert s.dudx[0, 0] == pytest.approx(2 * xc[0] + sx)  # forward at the west edge
    assert s.dudx[0, 5] == pytest.approx(2 * xc[5] - sx)  # backward at the east edge
    assert s.dudx[1, 2] == pytest.approx(2 * xc[2] - sx)  # backward: east neighbour is a gap
    assert s.dudx[1, 4] == pytest.approx(2 * xc[4] + sx)  # forward: west neighbour is a gap


def test_translation_changes_nothing():
    L = np.array([[0.02, 0.01], [-0.03, 0.005]])
    a = strain_field(_field(_linear(L), origin=(0.0, 0.0)))
    b = strain_field(_field(_linear(L, c=(3.7, -12.0)), origin=UTM))
    for name, arr in a.bands().items():
        np.testing.assert_allclose(b.bands()[name], arr, rtol=1e-9, atol=1e-13, err_msg=name)
    assert b.origin_xy == UTM


# --- vectorised vs slow reference ----------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_vectorised_matches_reference_with_gaps(seed):
    rng = np.random.default_rng(seed)
    n_rows, n_cols = rng.integers(2, 12, size=2)
    dx = rng.normal(size=(n_rows, n_cols))
    dy = rng.normal(size=(n_rows, n_cols))
    dx[rng.random(dx.shape) < 0.3] = np.nan
    dy[rng.random(dy.shape) < 0.1] = np.nan  # a cell without dy is a gap too
    dx[0, 0] = dy[0, 0] = 1.0
    f = GriddedField(UTM, (1.5, 0.7), dx, dy)
    fast = displacement_gradient(f)
    slow = displacement_gradient_reference(f)
    for a, b in zip(fast, slow):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


# --- frame rotation property --------------------------------------------------------------


def _rot(theta):
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


@given(
    st.lists(st.floats(-0.05, 0.05), min_size=4, max_size=4),
    st.floats(0.0, 2 * math.pi),
)
def test_rotating_the_field_rotates_the_tensor(entries, theta):
    """Rotate a linear field by theta (counter-clockwise): L' = R L R^T.

    Invariants (e1, e2, dilatation, max shear, rotation) stay; the strain tensor becomes
    R E R^T and the e1 axis turns by theta (its azimuth decreases by theta).
    """
    L = np.array(entries, dtype=float).reshape(2, 2)
    R = _rot(theta)
    L2 = R @ L @ R.T
    a = strain_field(_field(_linear(L), n_rows=3, n_cols=3))
    b = strain_field(_field(_linear(L2), n_rows=3, n_cols=3))
    tol = 1e-12
    for name in ("e1", "e2", "dilatation", "max_shear", "rotation_rad"):
        np.testing.assert_allclose(getattr(b, name), getattr(a, name), atol=tol, err_msg=name)
    E = np.array([[a.exx[1, 1], a.exy[1, 1]], [a.exy[1, 1], a.eyy[1, 1]]])
    E2 = R @ E @ R.T
    assert b.exx[1, 1] == pytest.approx(E2[0, 0], abs=tol)
    assert b.eyy[1, 1] == pytest.approx(E2[1, 1], abs=tol)
    assert b.exy[1, 1] == pytest.approx(E2[0, 1], abs=tol)
    if a.max_shear[1, 1] > 1e-6:  # the azimuth is well conditioned
        expected = (a.e1_azimuth_deg[1, 1] - math.degrees(theta)) % 180.0
        diff = (b.e1_azimuth_deg[1, 1] - expected + 90.0) % 180.0 - 90.0
        assert abs(diff) < 1e-6


def test_strain_from_gradient_principal_values_are_eigenvalues():
    rng = np.random.default_rng(5)
    g = rng.normal(scale=0.01, size=(4, 50))
    out = strain_from_gradient(*g)
    for k in range(50):
        E = np.array([[g[0, k], 0.5 * (g[1, k] + g[2, k])], [0.5 * (g[1, k] + g[2, k]), g[3, k]]])
        w = np.linalg.eigvalsh(E)
        assert out["e1"][k] == pytest.approx(w[1], abs=1e-15)
        assert out["e2"][k] == pytest.approx(w[0], abs=1e-15)
        assert 0.0 <= out["e1_azimuth_deg"][k] < 180.0


def test_bands_order_and_shapes():
    s = strain_field(_field(lambda x, y: (0.01 * x, 0.0 * y)))
    bands = s.bands()
    assert list(bands) == [
        "exx",
        "eyy",
        "exy",
        "rotation_rad",
        "e1",
        "e2",
        "e1_azimuth_deg",
        "max_shear",
        "dilatation",
    ]
    assert all(b.shape == s.shape == (7, 9) for b in bands.values())


# --- bad input -----------------------------------------------------------------------------


def test_all_nan_field_is_refused():
    f = GriddedField((0.0, 0.0), (1.0, 1.0), np.full((3, 3), np.nan), np.full((3, 3), np.nan))
    with pytest.raises(InputDataError, match="no vector"):
        strain_field(f)


def test_isolated_vectors_are_refused():
    dx = np.full((3, 3), np.nan)
    dx[0, 0] = dx[2, 2] = 1.0
    with pytest.raises(InputDataError, match="neighbouring vector"):
        strain_field(GriddedField((0.0, 0.0), (1.0, 1.0), dx, dx))


@pytest.mark.parametrize("shape", [(1, 5), (5, 1), (1, 1)])
def test_too_small_field_is_refused(shape):
    f = GriddedField((0.0, 0.0), (1.0, 1.0), np.zeros(shape), np.zeros(shape))
    with pytest.raises(InputDataError, match="at least 2 x 2"):
        strain_field(f)


def test_bad_spacing_is_refused():
    with pytest.raises(InvalidParameterError, match="spacing_m"):
        strain_field(GriddedField((0.0, 0.0), (0.0, 1.0), np.zeros((3, 3)), np.zeros((3, 3))))
    with pytest.raises(InputDataError, match="GriddedField"):
        strain_field(np.zeros((3, 3)))  # type: ignore[arg-type]


# --- a smooth curved field: the landslide lobe ----------------------------------------------


def _lobe_strain_error(spacing):
    """RMS error of exy and dilatation against the lobe's exact gradient on a grid."""
    from slipmap.core.synthetic import LobeField

    lobe = LobeField((UTM[0] + 16.0, UTM[1] - 20.0), 10.0, 12.0, 25.0, (0.2, -1.0, -0.4))
    n_cols, n_rows = int(round(32 / spacing)), int(round(40 / spacing))
    f0 = GriddedField(
        UTM, (spacing, spacing), np.zeros((n_rows, n_cols)), np.zeros((n_rows, n_cols))
    )
    xy = np.column_stack([f0.x.ravel(), f0.y.ravel()])
    d = lobe(xy).reshape(n_rows, n_cols, 3)
    s = strain_field(GriddedField(UTM, (spacing, spacing), d[..., 0], d[..., 1], d[..., 2]))
    g = lobe.gradient(xy)
    truth = strain_from_gradient(g[:, 0, 0], g[:, 0, 1], g[:, 1, 0], g[:, 1, 1])
    err = {}
    for name in ("exy", "dilatation", "rotation_rad"):
        e = s.bands()[name].ravel() - truth[name]
        err[name] = float(np.sqrt(np.mean(e * e)))
    return err, float(np.max(np.abs(truth["dilatation"])))


def test_lobe_strain_converges_to_the_exact_gradient():
    fine, peak = _lobe_strain_error(0.25)
    coarse, _ = _lobe_strain_error(1.0)
    for name in fine:
        assert fine[name] < 0.01 * peak, (name, fine[name], peak)
        assert coarse[name] > 3.0 * fine[name], (name, coarse[name], fine[name])
