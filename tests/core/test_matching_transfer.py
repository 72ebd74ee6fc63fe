"""Transferred planes (core/transfer.py): planes of the dense epoch observed by the points of
a second epoch too sparse to segment them, on a synthetic scene with a known motion."""

import numpy as np
import pytest

from slipmap.core.displacement import DEFAULT_TRANSFER_PLANES, register_side
from slipmap.core.errors import InvalidParameterError
from slipmap.core.matching import TRANSFERRED_TO_AFTER
from slipmap.core.rotation import rotation_matrix
from slipmap.core.transfer import (
    append_planes,
    gather_plane_points,
    gather_plane_points_reference,
    inverse_motion,
    move_planes,
)

NOISE_M = 0.01
CENTRE = np.array([0.0, 0.0, 3.0])
ROTVEC = np.array([0.0, 0.0, 2e-4])  # radians
SHIFT = np.array([0.03, -0.02, 0.01])  # metres, at CENTRE

#: true surfaces: (name, sampler) with sampler(rng, density) -> (N, 3)
SLOPE = np.tan(np.radians(30.0))


def _grid(rng, area, n_per_m2):
    n = rng.poisson(area * n_per_m2)
    return rng.uniform(0.0, 1.0, (n, 2))


def _surface(rng, name, density):
    if name == "ground":  # 40 x 40 m at z = 0
        uv = _grid(rng, 1600.0, density)
        return np.c_[uv * 40.0 - 20.0, np.zeros(len(uv))]
    if name == "roof_x":  # 10 x 10 m in plan, rising along +x by 30 degrees
        uv = _grid(rng, 100.0 / np.cos(np.radians(30)), density)
        x, y = 5.0 + 10.0 * uv[:, 0], 5.0 + 10.0 * uv[:, 1]
        return np.c_[x, y, 6.0 + (x - 5.0) * SLOPE]
    if name == "roof_y":  # rising along +y
        uv = _grid(rng, 100.0 / np.cos(np.radians(30)), density)
        x, y = -15.0 + 10.0 * uv[:, 0], 5.0 + 10.0 * uv[:, 1]
        return np.c_[x, y, 6.0 + (y - 5.0) * SLOPE]
    if name == "wall_x":  # x = 10, y in [-15, -3], z in [0, 7]: meets the ground
        uv = _grid(rng, 84.0, density)
        return np.c_[np.full(len(uv), 10.0), -15.0 + 12.0 * uv[:, 0], 7.0 * uv[:, 1]]
    if name == "wall_y":  # y = -12, x in [-15, -3]
        uv = _grid(rng, 84.0, density)
        return np.c_[-15.0 + 12.0 * uv[:, 0], np.full(len(uv), -12.0), 7.0 * uv[:, 1]]
    if name == "fence":  # 0.6 m in front of wall_x, 2 m high, after epoch only
        uv = _grid(rng, 24.0, density)
        return np.c_[np.full(len(uv), 10.6), -15.0 + 12.0 * uv[:, 0], 2.0 * uv[:, 1]]
    if name == "block":  # a wall_y-parallel box face 1 m behind wall_y's plane, after only
        uv = _grid(rng, 20.0, density)
        return np.c_[-15.0 + 10.0 * uv[:, 0], np.full(len(uv), -11.0), 2.0 * uv[:, 1]]
    raise KeyError(name)


def _epoch(rng, densities, motion=False):
    pts, lab = [], []
    for k, (name, density) in enumerate(densities):
        p = _surface(rng, name, density)
        pts.append(p)
        lab.append(np.full(len(p), k))
    pts = np.concatenate(pts)
    if motion:
        pts = (pts - CENTRE) @ rotation_matrix(ROTVEC).T + CENTRE + SHIFT
    return pts + rng.normal(0.0, NOISE_M, pts.shape), np.concatenate(lab)


@pytest.fixture(scope="module")
def scene():
    """Dense first epoch (25 pts/m² on every surface); the second epoch as dense on the
    ground and roofs but with 1 pt/m² on the walls (too sparse to segment), plus a fence in
    front of one wall and a box face behind the other (other surfaces, second epoch only)."""
    rng = np.random.default_rng(30)
    names = ["ground", "roof_x", "roof_y", "wall_x", "wall_y"]
    before, lb = _epoch(rng, [(n, 25.0) for n in names])
    after, la = _epoch(
        rng,
        [("ground", 25.0), ("roof_x", 25.0), ("roof_y", 25.0), ("wall_x", 1.0),
         ("wall_y", 1.0), ("fence", 25.0), ("block", 25.0)],
        motion=True,
    )  # fmt: skip
    return before, lb, after, la


def _side(scene, transfer):
    before, _, after, _ = scene
    return register_side(
        before, after, side="left", sigma_before=NOISE_M, sigma_after=NOISE_M,
        stochastic={"stochastic_model": "white"}, transfer_planes=transfer,
    )  # fmt: skip


def _truth_at(centre):
    """The true displacement of the material at ``centre``."""
    return (centre - CENTRE) @ rotation_matrix(ROTVEC).T + CENTRE + SHIFT - centre


def test_sparse_walls_are_transferred_and_the_motion_recovered(scene):
    _, _, _, la = scene
    plain = _side(scene, False)
    res = _side(scene, True)
    m = res.matches
    assert m.n_transferred == 2 == (m.kind == TRANSFERRED_TO_AFTER).sum()  # the two walls
    assert len(m) == len(plain.matches) + 2
    # the gathered points are the walls' own, never the fence's, the box's or the ground's
    new = m.after[m.kind == TRANSFERRED_TO_AFTER]
    for j in new:
        truth = np.unique(la[res.planes_after.labels == j])
        assert truth.size == 1 and truth[0] in (3, 4)
        assert res.planes_after.n_points[j] >= 50  # most of a 84 m² wall at 1 pt/m²
    # the motion within 4 sigma and 2 mm of the truth, the horizontal sigma smaller
    for r in (plain.rigid, res.rigid):
        err = r.displacement - _truth_at(r.centre)
        sig = np.sqrt(np.diag(r.displacement_covariance))
        assert np.all(np.abs(err) < 4 * sig + 1e-4), (err, sig)
    err = res.rigid.displacement - _truth_at(res.rigid.centre)
    assert np.all(np.abs(err) < 0.002)
    s0 = np.sqrt(np.diag(plain.rigid.displacement_covariance))
    s1 = np.sqrt(np.diag(res.rigid.displacement_covariance))
    assert s1[0] < 0.8 * s0[0] and s1[1] < 0.8 * s0[1]
    assert res.rigid.n_planes == plain.rigid.n_planes + 2


def test_without_anything_to_transfer_nothing_changes(scene):
    before, _, _, _ = scene
    res = register_side(
        before, before, side="left", sigma_before=NOISE_M, sigma_after=NOISE_M,
        stochastic={"stochastic_model": "white"}, transfer_planes=True,
    )  # fmt: skip
    assert res.matches.n_transferred == 0


def _walls(scene):
    """The first epoch's segmentation and its wall planes (the fixture's wall ids)."""
    from slipmap.core.planes import segment_planes

    before, lb, _, _ = scene
    pb = segment_planes(before, quiet=True)
    walls = [int(np.bincount(pb.labels[(lb == w) & (pb.labels >= 0)]).argmax()) for w in (3, 4)]
    return pb, np.array(walls)


def _kw(**over):
    kw = dict(
        rotation=rotation_matrix(ROTVEC), translation=SHIFT, centre=CENTRE,
        band_m=3 * NOISE_M, edge_margin_m=0.3, min_points=20, angle_threshold_deg=3.0,
        max_rms_m=1.5 * NOISE_M, max_offset_m=NOISE_M,
    )  # fmt: skip
    kw.update(over)
    return kw


def test_gathering_agrees_with_the_reference(scene):
    before, _, after, la = scene
    pb, walls = _walls(scene)
    sub = np.flatnonzero(np.abs(after[:, 1] + 9.0) < 7.0)  # the walls' surroundings, fewer
    cand = np.zeros(len(after), dtype=bool)
    cand[sub] = True
    for over in ({}, {"edge_margin_m": 0.0, "band_m": 0.5, "max_rms_m": 1.0, "max_offset_m": 1.0}):
        fast = gather_plane_points(pb, before, walls, after, cand, **_kw(**over))
        ref = gather_plane_points_reference(pb, before, walls, after, cand, **_kw(**over))
        assert len(fast) == len(ref) >= 1
        np.testing.assert_array_equal(fast.source, ref.source)
        np.testing.assert_array_equal(fast.point_index, ref.point_index)
        np.testing.assert_array_equal(fast.plane, ref.plane)
        np.testing.assert_allclose(fast.rms_m, ref.rms_m, rtol=1e-9)
        np.testing.assert_allclose(fast.offset_m, ref.offset_m, rtol=1e-9, atol=1e-12)


def test_safeguards_refuse_another_surface(scene):
    before, _, after, la = scene
    pb, walls = _walls(scene)
    cand = np.ones(len(after), dtype=bool)
    ok = gather_plane_points(pb, before, walls, after, cand, **_kw())
    assert set(np.unique(la[ok.point_index]).tolist()) <= {3, 4}
    # a wide band and no edge margin take in the fence, the ground and the box: the
    # safeguards (RMS, offset) refuse those planes
    wide = gather_plane_points(pb, before, walls, after, cand, **_kw(band_m=1.2, edge_margin_m=0.0))
    assert len(wide) == 0 and wide.n_rejected == 2
    # the wrong motion (30 cm off along x) finds wall_x's plane empty of points on it
    off = gather_plane_points(
        pb, before, walls[:1], after, cand, **_kw(translation=SHIFT + [0.3, 0, 0])
    )
    assert len(off) == 0
    with pytest.raises(InvalidParameterError, match="band_m"):
        gather_plane_points(pb, before, walls, after, cand, **_kw(band_m=0))


def test_moved_planes_and_inverse_motion():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = rng.normal(size=5)
    p = -d[:, None] * n + np.cross(n, rng.normal(size=(5, 3)))  # a point on each plane
    r = rotation_matrix(np.array([1e-3, -2e-3, 5e-3]))
    t, c = np.array([0.1, -0.2, 0.3]), np.array([5.0, 6.0, 7.0])
    n2, d2 = move_planes(n, d, rotation=r, translation=t, centre=c)
    q = (p - c) @ r.T + c + t
    np.testing.assert_allclose(np.einsum("ij,ij->i", n2, q) + d2, 0.0, atol=1e-12)
    ri, ti, ci = inverse_motion(r, t, c)
    np.testing.assert_allclose((q - ci) @ ri.T + ci + ti, p, atol=1e-12)


def test_append_planes_refuses_labelled_points(scene):
    before, _, _, _ = scene
    pb, walls = _walls(scene)
    idx = np.flatnonzero(pb.labels == walls[0])[:10]
    with pytest.raises(InvalidParameterError, match="already on a plane"):
        append_planes(pb, before, idx, np.zeros(10, dtype=np.int64))


def test_the_slip_jobs_default_is_the_cores():
    """On by default (docs/accuracy.md, "Transferred planes"), and every face's default (the
    slip job's option) is the core call's."""
    from slipmap.app.slip import SPEC

    assert DEFAULT_TRANSFER_PLANES
    assert SPEC["transfer_planes"].default is DEFAULT_TRANSFER_PLANES
