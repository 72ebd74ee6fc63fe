"""The floor of the slip's error on a kind of survey: the best any estimator could do (issue #30).

On a synthetic pair of ``accuracy_slip.py`` the error model is known. TLS: each setup of
each epoch moves rigidly, a translation ``N(0, level² I3)`` and a turn ``N(0, rotation²
I3)`` about its instrument. MLS: a drift of the trajectory, a stationary Gaussian process of
the path length (squared-exponential kernel, per axis), plus a lever arm fixed in the
vehicle's frame. Every point has white noise along its surface's normal. Given also which
points lie on which true plane (a perfect segmentation) and the planes' flatness, but not
where the planes are, the slip is a parameter of a linear Gaussian model over both epochs:

    y_i = x_iᵀ β + z_iᵀ u + e_i,    u ~ N(0, I),  e ~ N(0, σ² I)

``y_i`` the point's distance to its true plane; ``β`` an offset and two tilts per plane and
side of the trace (shared by the epochs) and the after-epoch's rigid motion per side (small
angles about the side's centre, as :func:`slipmap.core.synthetic.fit_true_surfaces`
linearises it); ``z_i`` the survey's shared error at the point (setups; drift and lever
arm), scaled to unit variance, independent between epochs. Generalised least squares
(``Σ = σ² I + Z Zᵀ``, inverted by Woodbury: a few hundred effects) is then the
minimum-variance unbiased estimator and its covariance the Cramér-Rao bound: no estimator
of the slip from these points that knows no more than this has a smaller error variance.
An estimator that must also find the planes, or that does not know the error model, can
only do worse. (The "true surfaces" row of ``accuracy_slip.py`` is ordinary least squares
with the planes known: it ignores the shared error.)

Each row gives, per pair, the floor's σ (fault-parallel, fault-normal, vertical, metres)
and its GLS fit's realised error. ``--table ROWS... --against KINDS_ROWS...`` joins them
with SlipMap's, the ICP peer's and the true-surface fit's errors of the same pairs
(``accuracy_slip.py`` rows) and prints RMS over the pairs.

``--patch-m S`` gives the same floor on other observations: each epoch's points of a plane
averaged over cubes of side ``S`` metres, or (``plane``) each epoch's least-squares plane
fits: what an estimator that observes patches, or planes, instead of points could reach.

``--model-drift SECONDS:MM[:offset] ...`` adds, per pair, the σ under the true error of the
fit that models the MLS drift as SlipMap does (:mod:`slipmap.core.unit_drift`: a hat basis
in GpsTime per pass, independent knots every SECONDS of MM per axis) instead of the truth;
``:offset``: the model's drift acts on each plane fit's offset only, not on its tilts, as
in SlipMap's stochastic model (with ``--patch-m plane``; docs/accuracy.md, "What the drift
model misses"); ``:split``: on the offsets and the tilts, but the two uncorrelated (the
cross-covariance between a plane's offset and the tilts dropped: a model that keeps the
offsets' and the tilts' adjustments apart, as SlipMap's does); ``:sides``: the model's drift
independent between the two sides of the trace, as when each side is adjusted alone and
the motions differenced (SlipMap's sides; combines with the others, ``6:3:offset:sides``).

Run: ``python benchmarks/slip_floor.py --case tls-6-setups --seeds 30 --first-seed 3000``
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_slip as harness  # noqa: E402

from slipmap.core.fault import fault_trace  # noqa: E402

KINDS = ("tls-6-setups", "mls-3mm-lever-crossing", "mls-3mm")


#: points per chunk of the accumulated normal matrices
CHUNK = 100_000
#: the drift's covariance factor keeps the eigenvalues above this share of the largest
#: (what it drops is about 1e-5 of the variance on the harness's paths)
RANK_CUT = 1e-6


def _setup_centres(model, extent_m: float) -> np.ndarray:
    """(S, 3) instrument positions in the scene's local frame, as the synthetic layout
    places them (a grid over the scene's square; they depend on the square alone)."""
    import slipmap.core.synthetic as synthetic

    probe = np.zeros((1, 3))
    _, centres, _ = synthetic._tls_layout(probe, np.zeros(2), np.full(2, float(extent_m)), model, 0)
    return centres


def _tls_effects(p, n, source, model, scene):
    """Random-effect columns (N, 6 S) of the TLS setups, scaled to unit variance: each
    setup's translation and turn about its instrument."""
    inst = _setup_centres(model, scene.extent_m) + np.asarray(scene.origin, dtype=np.float64)
    unit = source.astype(np.int64) - 1
    z = np.zeros((p.shape[0], 6 * inst.shape[0]))
    rows = np.arange(p.shape[0])
    arm = np.cross(p - inst[unit], n)
    for j in range(3):
        z[rows, 6 * unit + j] = n[:, j] * model.level_m
        z[rows, 6 * unit + 3 + j] = arm[:, j] * model.rotation_rad
    return z


def _mls_basis(scene, model):
    """For an MLS epoch: a function of point indices giving the random-effect columns of
    the trajectory drift (a stationary Gaussian process of the path length with the
    squared-exponential kernel, per axis, linearly interpolated between the path's
    samples as the synthetic survey draws it; as a low-rank factor of its covariance) and
    of the lever arm (forward, left, up in the vehicle's frame)."""
    import scipy.sparse as sp

    import slipmap.core.synthetic as synthetic

    local = np.asarray(scene.points, dtype=np.float64) - np.asarray(scene.origin)
    lo, hi = synthetic._survey_area(scene, local)
    s, line, heading, total, step = synthetic._mls_path(local, lo, hi, model)
    grid = np.linspace(0.0, total, max(2, int(math.ceil(total / step)) + 1))
    ell = model.correlation_length_m
    kern = model.level_m**2 * np.exp(-0.5 * ((grid[:, None] - grid[None, :]) / ell) ** 2)
    lam, vec = np.linalg.eigh(kern)
    keep = lam > RANK_CUT * lam.max()
    factor = vec[:, keep] * np.sqrt(lam[keep])  # (G, r): kern ≈ factor factorᵀ
    k = np.clip(np.searchsorted(grid, s, side="right") - 1, 0, grid.size - 2)
    t = np.clip((s - grid[k]) / (grid[k + 1] - grid[k]), 0.0, 1.0)
    rows = np.repeat(np.arange(s.size), 2)
    interp = sp.csr_matrix(
        (np.column_stack([1.0 - t, t]).ravel(), (rows, np.column_stack([k, k + 1]).ravel())),
        shape=(s.size, grid.size),
    )

    def effects(idx, n):
        b = interp[idx] @ factor  # (m, r)
        cols = [n[:, [j]] * b for j in range(3)]
        if model.lever_arm_m > 0.0:
            h = heading[idx]
            lever = np.column_stack(
                [
                    n[:, 0] * h[:, 0] + n[:, 1] * h[:, 1],
                    -n[:, 0] * h[:, 1] + n[:, 1] * h[:, 0],
                    n[:, 2],
                ]
            )
            cols.append(lever * model.lever_arm_m)
        return np.hstack(cols)

    knots = {}

    def hat_knots(interval_s):
        """Each point's time in knot spacings, its knot, and the (pass, knot) ids of the
        whole epoch, once per spacing."""
        if interval_s not in knots:
            x = s / synthetic._MLS_SPEED_M_S / float(interval_s)
            k = np.floor(x).astype(np.int64)
            ids = np.unique(np.concatenate([line * (1 << 32) + k, line * (1 << 32) + k + 1]))
            knots[interval_s] = (x, k, ids)
        return knots[interval_s]

    def hat(idx, n, interval_s, sigma_m):
        """Columns (m, 3 V) of SlipMap's model of the drift (:mod:`slipmap.core.unit_drift`):
        a hat basis in time with knots every ``interval_s`` seconds per pass, independent
        coefficients of ``sigma_m`` per axis; V the (pass, knot) pairs of the whole epoch."""
        x, k, ids = hat_knots(interval_s)
        ki = k[idx]
        w = x[idx] - ki
        b = np.zeros((idx.size, ids.size))
        rows = np.arange(idx.size)
        b[rows, np.searchsorted(ids, line[idx] * (1 << 32) + ki)] = 1.0 - w
        b[rows, np.searchsorted(ids, line[idx] * (1 << 32) + ki + 1)] += w
        return np.hstack([n[:, [j]] * b * float(sigma_m) for j in range(3)])

    hat.columns = lambda interval_s: 3 * hat_knots(interval_s)[2].size
    effects.hat = hat
    effects.kinds = np.array(
        ["drift"] * 3 * factor.shape[1] + ["lever arm"] * (3 if model.lever_arm_m > 0 else 0)
    )
    return effects


def _patch_means(x, z, y, group):
    """Rows of each group replaced by their mean times ``sqrt(count)``: generalised least
    squares on the groups' means (white noise ``σ² / count`` each) with the scalar weight
    of single points. ``x`` sparse (m, p), ``z`` (m, q), ``y`` (m,), ``group`` (m,) int."""
    import scipy.sparse as sp

    _, g = np.unique(group, return_inverse=True)
    g = g.reshape(-1)
    count = np.bincount(g).astype(np.float64)
    scale = 1.0 / np.sqrt(count)  # mean times sqrt(count): each row's sum / sqrt(count)
    agg = sp.csr_matrix((scale[g], (g, np.arange(g.size))), shape=(count.size, g.size))
    return agg @ x, agg @ z, agg @ y


def _plane_fits(x, z, y, group, basis):
    """Rows of each group replaced by their projections on an orthonormal basis of the
    group's ``basis`` rows (m_g, 3): ``Qᵀ x, Qᵀ z, Qᵀ y``, three rows a group whose white
    noise is still ``σ² I``. With ``basis`` a plane's offset and two tilts these are its
    least-squares plane fit: the support of an estimator that observes each epoch's planes
    (offset and normal) and not their points."""
    import scipy.sparse as sp

    rows_x, rows_z, rows_y, first = [], [], [], []
    for g in np.unique(group):
        m = np.flatnonzero(group == g)
        q, r = np.linalg.qr(basis[m])
        q = q[:, np.abs(np.diag(r)) > 1e-9 * np.abs(r).max()]
        rows_x.append(np.asarray((x[m].T @ q).T))
        rows_z.append(q.T @ z[m])
        rows_y.append(q.T @ y[m])
        first.append(np.arange(q.shape[1]) == 0)
    return (
        sp.csr_matrix(np.vstack(rows_x)),
        np.vstack(rows_z),
        np.concatenate(rows_y),
        np.concatenate(first),
    )


def _joint(fp, sides, model_b, model_a, side_centres, min_points=10, patch_m=None, model_drifts=()):
    """Both epochs in one GLS, the planes' positions and tilts unknown: ``(cov, beta,
    planes, partial)``, ``cov`` (12, 12) and ``beta`` (12,) of the after-epoch's two rigid
    motions (left rotation, left translation, right rotation, right translation; radians,
    metres at ``side_centres``), ``planes`` how many planes, ``partial`` the motions'
    covariance of the fit that models one kind of shared error only, per kind and "none".

    The floor for an estimator that knows which points lie on which plane and the survey's
    error model but not where the planes are: each true plane seen by both epochs (at least
    ``min_points`` each) gets an offset and two tilts about its before-points' centroid,
    shared by the epochs, on each side of the trace apart (as SlipMap's planes and the ICP
    peer's sides: nothing ties the two sides before the event, so a plane that crosses the
    trace, the ground, is two planes); the after-epoch's points also move with their side.
    The surveys' shared errors are independent random effects per epoch (``Σ = σ² I + Z
    Zᵀ``). ``patch_m``: each epoch's points of a plane averaged over cubes of that side
    before the fit (what an estimator that observes patch means instead of points could
    reach); ``"plane"``: each epoch's least-squares plane fits instead of its points.
    ``model_drifts``: (interval_s, sigma_m) pairs; each adds to ``partial`` (as ``"hat Δ s
    σ mm"``) the covariance, under the true error model, of the fit that models the MLS
    drift as SlipMap does (a hat basis in time per pass) instead."""
    import scipy.sparse as sp

    surf_b = fp.before.surfaces
    normals = np.array([np.asarray(sf.normal, dtype=np.float64) for sf in surf_b])
    offsets = np.array([float(sf.d) for sf in surf_b])
    scenes = (
        (fp.before, sides[0], fp.source_before, model_b),
        (fp.after, sides[1], fp.source_after, model_a),
    )
    n_surf = len(surf_b)
    keeps = [np.flatnonzero((sc.labels >= 0) & (sd != 0)) for sc, sd, _, _ in scenes]

    def plane_of(sc, sd, idx):  # plane id: the true surface on one side of the trace
        return 2 * sc.labels[idx].astype(np.int64) + (sd[idx] > 0)

    counts = [
        np.bincount(plane_of(sc, sd, k), minlength=2 * n_surf)
        for (sc, sd, _, _), k in zip(scenes, keeps)
    ]
    planes = np.flatnonzero((counts[0] >= min_points) & (counts[1] >= min_points))
    col = np.full(2 * n_surf, -1)
    col[planes] = np.arange(planes.size)
    centroid = np.zeros((2 * n_surf, 3))
    np.add.at(centroid, plane_of(fp.before, sides[0], keeps[0]), fp.before.points[keeps[0]])
    centroid /= np.maximum(counts[0], 1)[:, None]
    # two unit tangents per plane
    ref = np.where(np.abs(normals[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(normals, ref)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    n_fixed = 3 * planes.size + 12
    w = 1.0 / float(fp.before.noise_m) ** 2
    if float(fp.after.noise_m) != float(fp.before.noise_m):
        raise SystemExit("the joint floor assumes one point noise for both epochs")
    effects = [_mls_basis(sc, model) if model.kind == "mls" else None for sc, _, _, model in scenes]
    xtx = sp.csr_matrix((n_fixed, n_fixed))
    xty = np.zeros(n_fixed)
    xtz, ztz, zty, kinds = [], [], [], []
    for e, ((sc, sd, src, model), keep) in enumerate(zip(scenes, keeps)):
        keep = keep[col[plane_of(sc, sd, keep)] >= 0]
        xtz_e = ztz_e = zty_e = None
        if patch_m is None:
            chunks = [keep[lo : lo + CHUNK] for lo in range(0, keep.size, CHUNK)]
        elif patch_m == "plane":  # whole planes per chunk
            keep = keep[np.argsort(plane_of(sc, sd, keep), kind="stable")]
            bounds = np.flatnonzero(np.diff(plane_of(sc, sd, keep))) + 1
            chunks = np.split(keep, bounds)
        else:  # patches: the epoch at once
            chunks = [keep]
        for idx in chunks:
            p = sc.points[idx]
            lab = sc.labels[idx].astype(np.int64)
            pl = plane_of(sc, sd, idx)
            n, d = normals[lab], offsets[lab]
            y = np.einsum("ij,ij->i", n, p) + d
            m = idx.size
            rel = p - centroid[pl]
            c0 = 3 * col[pl]
            rows = [np.repeat(np.arange(m), 3)]
            cols = [np.column_stack([c0, c0 + 1, c0 + 2]).ravel()]
            vals = [np.column_stack([np.ones(m), np.einsum("ij,ij->i", rel, t1[lab]),
                                     np.einsum("ij,ij->i", rel, t2[lab])]).ravel()]  # fmt: skip
            if e == 1:  # the after-epoch's points move with their side
                sv = sd[idx]
                for k, side in enumerate((-1, 1)):
                    mk = np.flatnonzero(sv == side)
                    blk = np.hstack([np.cross(p[mk] - side_centres[side], n[mk]), n[mk]])
                    rows.append(np.repeat(mk, 6))
                    cols.append(np.tile(3 * planes.size + 6 * k + np.arange(6), mk.size))
                    vals.append(blk.ravel())
            x = sp.csr_matrix(
                (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                shape=(m, n_fixed),
            )
            z = (
                effects[e](idx, n)
                if effects[e] is not None
                else _tls_effects(p, n, src[idx], model, sc)
            )
            n_true = z.shape[1]
            if model_drifts and effects[e] is not None:
                side_of = np.where(sd[idx] > 0, 1, 0)
                z = np.hstack(
                    [z]
                    + [
                        _hat_copies(effects[e].hat(idx, n, dt, sg), how, side_of)
                        for dt, sg, *how in model_drifts
                    ]
                )
            if patch_m == "plane":
                x, z, y, offset_row = _plane_fits(x, z, y, pl, np.reshape(vals[0], (m, 3)))
                at = n_true
                for dt, _, *how in model_drifts:
                    v = effects[e].hat.columns(dt)
                    for _ in range(2 if "sides" in how else 1):
                        if "offset" in how:  # the model sees the offsets only
                            z[~offset_row, at : at + v] = 0.0
                        elif "split" in how:  # offsets and tilts, uncorrelated
                            z[~offset_row, at : at + v] = 0.0
                            at += v
                            z[offset_row, at : at + v] = 0.0
                        at += v
            elif patch_m is not None:
                cube = np.floor((p - p.min(axis=0)) / float(patch_m)).astype(np.int64)
                # one group per (plane, cube): the distinct rows, whatever the cubes' count
                _, group = np.unique(np.column_stack([pl, cube]), axis=0, return_inverse=True)
                x, z, y = _patch_means(x, z, y, group.reshape(-1))
            xtx = xtx + (x.T @ x)
            xty += x.T @ y
            parts = (np.asarray(x.T @ z), z.T @ z, z.T @ y)
            if xtz_e is None:
                xtz_e, ztz_e, zty_e = parts
            else:
                xtz_e, ztz_e, zty_e = (u + v for u, v in zip((xtz_e, ztz_e, zty_e), parts))
        xtz.append(xtz_e)
        ztz.append(ztz_e)
        zty.append(zty_e)
        kinds_e = list(effects[e].kinds) if effects[e] is not None else ["setups"] * n_true
        if model_drifts and effects[e] is not None:
            for dt, sg, *how in model_drifts:
                v = effects[e].hat.columns(dt) * _copies(how)
                kinds_e += [f"hat {dt:g} s {1e3 * sg:g} mm" + "".join(f" {h}" for h in how)] * v
        kinds.append(kinds_e)
    from scipy.linalg import block_diag

    xtz_all = np.hstack(xtz)
    ztz_all = block_diag(*ztz)
    all_kinds = np.concatenate(kinds)
    hats = sorted({k for k in all_kinds if k.startswith("hat ")})
    truth = ~np.isin(all_kinds, hats)
    xtz, ztz = xtz_all[:, truth], ztz_all[np.ix_(truth, truth)]
    zty_all = np.concatenate(zty)
    zty = zty_all[truth]
    kinds = all_kinds[truth]
    xtx = xtx.toarray()
    inner = np.linalg.inv(np.eye(ztz.shape[0]) + w * ztz)
    info = w * xtx - w * w * xtz @ inner @ xtz.T
    cov = np.linalg.inv(info)
    beta = cov @ (w * xty - w * w * xtz @ inner @ zty)
    sl = slice(3 * planes.size, n_fixed)
    # the same fit knowing only part of the error model, its covariance under the true one
    partial = {
        name: _misspecified(xtx, xtz, ztz, w, kinds == name)[sl, sl]
        for name in sorted(set(kinds)) + ["none"]
    }
    fits = {}
    for name in hats:
        partial[name] = _model_cov(xtx, xtz_all, ztz_all, w, all_kinds == name, truth)[sl, sl]
        fits[name] = _model_beta(xtx, xty, xtz_all, zty_all, ztz_all, w, all_kinds == name)[sl]
    return cov[sl, sl], beta[sl], int(planes.size), partial, fits


def _model_gls(xtx, xtz, ztz, w, m):
    """The GLS of the model ``Σ_m = I / w + Z_m Z_mᵀ`` (the columns ``m``, indices) by
    Woodbury: ``(C, inner, Xᵀ Z_m)``, ``C = (Xᵀ Σ_m⁻¹ X)⁻¹``, ``inner = (I + w Z_mᵀZ_m)⁻¹``."""
    inner = np.linalg.inv(np.eye(m.size) + w * ztz[np.ix_(m, m)])
    xm = xtz[:, m]
    return np.linalg.inv(w * xtx - w * w * xm @ inner @ xm.T), inner, xm


def _model_beta(xtx, xty, xtz, zty, ztz, w, model) -> np.ndarray:
    """The estimate of the GLS fit whose model is ``Σ_m = I / w + Z_m Z_mᵀ`` (columns
    ``model``) on the pair's points: its realised error beside its σ (:func:`_model_cov`)."""
    m = np.flatnonzero(model)
    c, inner, xm = _model_gls(xtx, xtz, ztz, w, m)
    return c @ (w * xty - w * w * xm @ inner @ zty[m])


def _copies(how) -> int:
    """Copies of a model drift's columns: two for ``split`` (offsets, tilts), two per side
    for ``sides``."""
    return (2 if "split" in how else 1) * (2 if "sides" in how else 1)


def _hat_copies(hat, how, side_of):
    """The model drift's point-level columns ``hat`` (m, v) in :func:`_copies` copies:
    ``sides``: one copy per side of the trace (``side_of`` (m,) 0 or 1), each zero on the
    other side's points, so that the model's drift is independent between the sides, as
    when each side is adjusted alone; ``split``: each (side's) copy twice, the offset rows
    of one and the tilt rows of the other zeroed after the plane fits."""
    per_side = [hat * (side_of == k)[:, None] for k in (0, 1)] if "sides" in how else [hat]
    reps = 2 if "split" in how else 1
    return np.hstack([c for c in per_side for _ in range(reps)])


def _model_cov(xtx, xtz, ztz, w, model, truth) -> np.ndarray:
    """Covariance under the true ``Σ = I / w + Z_t Z_tᵀ`` (columns ``truth``) of the GLS fit
    whose model is ``Σ_m = I / w + Z_m Z_mᵀ`` (columns ``model``, bool over Z's columns):
    ``C - C B_m B_mᵀ C + C B Bᵀ C``, ``C = (Xᵀ Σ_m⁻¹ X)⁻¹``, ``B = Xᵀ Σ_m⁻¹ Z_t``,
    ``B_m = Xᵀ Σ_m⁻¹ Z_m``."""
    m, t = np.flatnonzero(model), np.flatnonzero(truth)
    c, inner, xm = _model_gls(xtx, xtz, ztz, w, m)
    b = w * xtz[:, t] - w * w * xm @ inner @ ztz[np.ix_(m, t)]
    bm = w * xm - w * w * xm @ inner @ ztz[np.ix_(m, m)]
    return c - c @ bm @ bm.T @ c + c @ b @ b.T @ c


def _misspecified(xtx, xtz, ztz, w, known) -> np.ndarray:
    """Covariance under the true ``Σ = I / w + Z Zᵀ`` of the GLS fit that models only the
    effects ``known`` (bool over Z's columns; none: ordinary least squares): :func:`_model_cov`
    with the model's columns a subset of the truth's, ``C + C B Bᵀ C``, ``B = Xᵀ Σ_k⁻¹ Z_u``
    for the unknown ``Z_u``."""
    return _model_cov(xtx, xtz, ztz, w, known, np.ones(known.size, bool))


def one(case_name: str, seed: int, patch_m=None, model_drifts=()) -> dict:
    c = harness.CASES[case_name]
    for model in (c["before"], c["after"]):
        if model is None or model.kind not in ("tls", "mls") or model.nonflat_m > 0:
            raise SystemExit(f"{case_name}: only TLS setups and MLS drift are modelled here")
    fp = harness.draw_pair(case_name, seed)
    trace = fault_trace([fp.trace_xy])
    truth = np.asarray(fp.relative_offset_m)
    d = fp.trace_xy[1] - fp.trace_xy[0]
    strike = math.atan2(float(d[0]), float(d[1]))
    sides, centres = harness.sides_and_centres(fp, trace)
    out = {"case": case_name, "seed": seed}
    # the planes unknown: both epochs at once; its motion is the after-epoch's (the
    # before-epoch defines the planes); the relative motion right - left
    jcov, jbeta, out["planes_n"], partial, fits = _joint(
        fp, sides, c["before"], c["after"], centres, patch_m=patch_m, model_drifts=model_drifts
    )
    if patch_m is not None:
        out["patch_m"] = patch_m if patch_m == "plane" else float(patch_m)
    k = np.zeros((3, 12))
    k[:, 9:12] = np.eye(3)
    k[:, 3:6] = -np.eye(3)
    rel, cov = k @ jbeta, k @ jcov @ k.T
    jp = np.array([math.sin(strike), math.cos(strike), 0.0])
    jn = np.array([math.cos(strike), -math.sin(strike), 0.0])
    axes = (jp, jn, np.array([0.0, 0.0, 1.0]))
    out["floor"] = {
        "err": harness._errors(rel, truth, strike),
        "sigma": [float(math.sqrt(v @ cov @ v)) for v in axes],
    }
    # the σ of the same fit modelling one kind of shared error only ("none": least squares)
    out["knowing_only"] = {
        name: [float(math.sqrt(v @ (k @ pc @ k.T) @ v)) for v in axes]
        for name, pc in partial.items()
    }
    if fits:  # the realised error of each fit that models the drift as SlipMap does
        out["model_err"] = {
            name: harness._errors(k @ beta, truth, strike) for name, beta in fits.items()
        }
    return out


def _rms(v):
    v = np.asarray([x for x in v if x is not None and np.isfinite(x)], dtype=np.float64)
    return float(np.sqrt(np.mean(v**2))) if v.size else math.nan


def table(rows, against) -> str:
    """RMS over the pairs (mm) of the floor's σ and of each estimator's error, per kind: the
    floor fit's own RMS(err/σ) (its model's check: 1 expected), the σ of the same fit knowing
    one kind of shared error only ("none": least squares with the planes unknown), and each
    estimator's error over the floor with a 90 % bootstrap interval over the pairs."""
    peers = {(r["case"], r["seed"]): r for r in against}
    lines = [
        "| kind | pairs | floor σ ∥ / ⊥ / z | its RMS(err/σ) ∥ | knowing only: σ ∥ | "
        "true surfaces ∥ | ICP ∥ | SlipMap ∥ | ICP / floor ∥ [90 %] | SlipMap / floor ∥ [90 %] | "
        "SlipMap ⊥ / z | ICP ⊥ / z |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def mm(v):
        return f"{1e3 * v:.2f}"

    for case in sorted({r["case"] for r in rows}):
        rs = [
            r
            for r in rows
            if r["case"] == case
            and "err" in peers.get((case, r["seed"]), {}).get("full", {})
            and "err" in peers.get((case, r["seed"]), {}).get("icp", {})
        ]
        if not rs:
            continue
        full = np.array([peers[(case, r["seed"])]["full"]["err"] for r in rs])
        icp = np.array([peers[(case, r["seed"])]["icp"]["err"] for r in rs])
        ols = [peers[(case, r["seed"])].get("truth", {}).get("err", [None])[0] for r in rs]
        sig = np.array([r["floor"]["sigma"] for r in rs])
        floor = [_rms(sig[:, i]) for i in range(3)]
        z = _rms([r["floor"]["err"][0] / r["floor"]["sigma"][0] for r in rs])
        known = ", ".join(
            f"{name} {mm(_rms([r['knowing_only'][name][0] for r in rs]))}"
            for name in rs[0].get("knowing_only", {})
        )
        ratios = [harness._ratio_interval(e[:, 0], sig[:, 0]) for e in (icp, full)]
        lines.append(
            f"| {case} | {len(rs)} | {' / '.join(mm(v) for v in floor)} | {z:.2f} | {known} | "
            f"{mm(_rms(ols))} | {mm(_rms(icp[:, 0]))} | {mm(_rms(full[:, 0]))} | "
            + " | ".join(f"{r:.2f} [{lo:.2f}, {hi:.2f}]" for r, lo, hi in ratios)
            + f" | {mm(_rms(full[:, 1]))} / {mm(_rms(full[:, 2]))} | "
            f"{mm(_rms(icp[:, 1]))} / {mm(_rms(icp[:, 2]))} |"
        )
    return "\n".join(lines)


def _read(paths):
    rows = []
    for p in paths:
        for line in Path(p).read_text(encoding="utf-8").splitlines():
            if line.strip():
                rows.append(json.loads(line))
    return rows


def _features(count: int) -> None:
    """In a worker: the synthetic MLS drift's number of random Fourier features (0: its
    own). A benchmark device: the module constant is set in the worker process."""
    if count > 0:
        import slipmap.core.synthetic as synthetic

        synthetic._N_FOURIER = int(count)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", default="tls-6-setups", choices=KINDS)
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=3000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, help="JSON lines, one per pair")
    ap.add_argument(
        "--fourier-features",
        type=int,
        default=0,
        help="MLS drift drawn with this many random Fourier features instead of the "
        "synthetic's 64 (a check of the floor's calibration: other pairs, the same kernel)",
    )
    ap.add_argument(
        "--patch-m",
        type=lambda v: v if v == "plane" else float(v),
        default=None,
        help="observe each epoch's points of a plane as means over cubes of this side "
        "(metres): the floor of an estimator that works on patches instead of points; "
        "'plane': on each epoch's least-squares plane fits",
    )
    ap.add_argument(
        "--model-drift",
        nargs="+",
        default=[],
        metavar="SECONDS:MM",
        help="also the σ, under the true error, of the fit that models the MLS drift as "
        "SlipMap does: a hat basis in time per pass, knots every SECONDS, MM per axis",
    )
    ap.add_argument("--table", type=Path, nargs="+", help="only print the table of these rows")
    ap.add_argument(
        "--against", type=Path, nargs="+", default=[], help="accuracy_slip.py rows to join"
    )
    args = ap.parse_args(argv)
    if args.table:
        print(table(_read(args.table), _read(args.against)))
        return 0
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    rows = []
    with ProcessPoolExecutor(
        max_workers=max(1, args.jobs), initializer=_features, initargs=(args.fourier_features,)
    ) as pool:
        drifts = tuple(
            (float(v.split(":")[0]), 1e-3 * float(v.split(":")[1]), *v.split(":")[2:])
            for v in args.model_drift
        )
        flags = {"offset", "split", "sides"}
        if any(not set(d[2:]) <= flags or {"offset", "split"} <= set(d[2:]) for d in drifts):
            ap.error("--model-drift takes SECONDS:MM[:offset|:split][:sides]")
        if any(set(d[2:]) & {"offset", "split"} for d in drifts) and args.patch_m != "plane":
            ap.error("--model-drift ...:offset|split needs --patch-m plane (plane fits)")
        for row in pool.map(
            one,
            [args.case] * len(seeds),
            seeds,
            [args.patch_m] * len(seeds),
            [drifts] * len(seeds),
        ):
            rows.append(row)
            print(json.dumps(row), flush=True)
            if args.out:
                with args.out.open("a", encoding="utf-8") as fh:
                    fh.write(json.dumps(row) + "\n")
    if args.against:
        print(table(rows, _read(args.against)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
