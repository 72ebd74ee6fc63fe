"""Tiled inputs (app/tiled.py) in process and on a 2-worker Dask LocalCluster (app/engine.py).

Known answers: the whole-cloud functions on the same points (roughness: grid_roughness_multi;
slip: estimate_slip with the same tile size, the study's tiles), to 1e-9 relative; in process
against Dask; one file against many tiles of another layout; a plane crossing tile borders
against its known geometry; a missing tile, a killed worker and a cancel end in clear errors.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pyproj
import pytest

from slipmap.app.engine import InProcess, make_engine
from slipmap.app.tiled import Selection, planes_tiled, roughness_tiled, slip_tiled
from slipmap.core.displacement import estimate_slip
from slipmap.core.errors import (
    CancelledError,
    InvalidParameterError,
    SlipMapError,
    SlipMapFileError,
)
from slipmap.core.fault import fault_trace
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.io.tiles import open_collection
from slipmap.core.roughness import grid_roughness_multi
from slipmap.core.synthetic import make_fault_pair

ORIGIN = (500000.0, 4200000.0, 10.0)
CRS = pyproj.CRS.from_epsg(32611)
SIG = dict(sigma_before=0.02, sigma_after=0.02)
TILE = 35.0
SIZES = (1.0, 0.5)


def _rel(a, b):
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def _write_tiles(cloud, folder, edge):
    folder.mkdir()
    k = np.floor((cloud.xyz[:, :2] - cloud.xyz[:, :2].min(0) + 3.0) / edge).astype(int)
    for key in np.unique(k, axis=0):
        write_las(folder / f"t_{key[0]}_{key[1]}.laz", cloud.subset(np.all(k == key, axis=1)))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A fault pair as one LAZ file per epoch and as tiles of 37 / 41 m (not the 35 m tiles)."""
    root = tmp_path_factory.mktemp("tiled")
    pair = make_fault_pair(
        "mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0), vegetation=False
    )
    out = {"trace": fault_trace([pair.trace_xy])}
    for name, scene, edge in (("before", pair.before, 37.0), ("after", pair.after, 41.0)):
        rng = np.random.default_rng(len(name))
        cls = np.where(rng.random(len(scene.points)) < 0.1, 7, 6).astype(np.uint8)
        write_las(root / f"{name}.laz", PointCloud(scene.points, {"Classification": cls}, CRS))
        cloud = read_las(root / f"{name}.laz")
        _write_tiles(cloud, root / f"{name}_tiles", edge)
        out[name] = cloud
        out[f"{name}_file"] = open_collection(root / f"{name}.laz", label=name)
        out[f"{name}_tiles"] = open_collection(root / f"{name}_tiles", label=name)
    out["root"] = root
    return out


@pytest.fixture(scope="module")
def slip_ref(data):
    return estimate_slip(
        data["before"].xyz, data["after"].xyz, data["trace"], tile_size_m=TILE,
        stochastic_model="full", **SIG,
    )  # fmt: skip


def _slip(data, which, engine=None, **kw):
    return slip_tiled(
        data[f"before_{which}"], data[f"after_{which}"], data["trace"], tile_size_m=TILE,
        stochastic_model="full", units="none", engine=engine, **SIG, **kw,
    )  # fmt: skip


def _same_slip(got, ref, rel=1e-9):
    assert _rel(got.relative, ref.relative) < rel
    # the covariance goes through the REML profiles (two families since stop 45), whose
    # iterations carry the sums' rounding (~1e-12) to ~1e-9
    assert _rel(got.relative_covariance, ref.relative_covariance) < 10 * rel
    for g, r in ((got.left, ref.left), (got.right, ref.right)):
        assert g.rigid.n_planes == r.rigid.n_planes and g.rigid.n_points == r.rigid.n_points
        assert len(g.matches) == len(r.matches)
        # a side's own motion is tiny (no slip on the left): against the whole-cloud path,
        # whose sums of UTM coordinates round at ~1e-10 m, compare with an absolute floor
        assert np.allclose(g.rigid.params, r.rigid.params, rtol=rel, atol=rel * 1e-2)
        ok = np.isfinite(r.plane_mean_residual_m)
        assert np.allclose(g.plane_mean_residual_m[ok], r.plane_mean_residual_m[ok], atol=1e-8)
    assert [(t.side, t.ix, t.iy, t.status) for t in got.tiles] == [
        (t.side, t.ix, t.iy, t.status) for t in ref.tiles
    ]
    for g, r in zip(got.tiles, ref.tiles):
        if r.status == "ok":
            assert _rel(g.displacement, r.displacement) < 1e-8


def _same_grids(got, ref):
    for g, r in zip(got, ref):
        assert np.array_equal(g.index, r.index) and np.array_equal(g.n_points, r.n_points)
        assert g.n_cells_skipped == r.n_cells_skipped and g.n_points_total == r.n_points_total
        assert np.array_equal(g.degenerate, r.degenerate)
        ok = ~r.degenerate
        for name in ("theta_odr", "theta_ols", "centroid_m", "eigenvalues_m2"):
            assert _rel(getattr(g, name)[ok], getattr(r, name)[ok]) < 1e-9, name


# --------------------------------------------------------------------------- in process


def test_slip_tiled_equals_estimate_slip_with_tiles(data, slip_ref):
    runs = [_slip(data, which) for which in ("file", "tiles")]  # one file; tiles of 37/41 m
    for got in runs:
        _same_slip(got, slip_ref)
    _same_slip(runs[1], runs[0], rel=1e-12)  # the tiled path: layout-independent


def test_slip_tiled_random_tilt_equals_estimate_slip(data):
    """The random tilt per plane on tiled inputs: the same slip and the same estimated tilt
    per side as the one-file run with tiles."""
    ref = estimate_slip(
        data["before"].xyz, data["after"].xyz, data["trace"], tile_size_m=TILE,
        stochastic_model="plane", random_tilt=True, **SIG,
    )  # fmt: skip
    got = slip_tiled(
        data["before_tiles"], data["after_tiles"], data["trace"], tile_size_m=TILE,
        stochastic_model="plane", units="none", random_tilt=True, **SIG,
    )  # fmt: skip
    _same_slip(got, ref)
    assert got.parameters["random_tilt"] is True
    for g, r in ((got.left, ref.left), (got.right, ref.right)):
        tg, tr = g.rigid.variance_components.tilt, r.rigid.variance_components.tilt
        assert tg.source == tr.source == "estimated"
        assert tg.sigma_rad == pytest.approx(tr.sigma_rad, rel=1e-6, abs=1e-12)


def test_slip_tiled_combine_tiles(data):
    ref = estimate_slip(
        data["before"].xyz, data["after"].xyz, data["trace"], tile_size_m=TILE,
        combine="tiles", stochastic_model="white", **SIG,
    )  # fmt: skip
    got = slip_tiled(
        data["before_tiles"], data["after_tiles"], data["trace"], tile_size_m=TILE,
        combine="tiles", stochastic_model="white", **SIG,
    )  # fmt: skip
    _same_slip(got, ref)


def test_slip_tiled_units_from_point_source_id(tmp_path):
    """The full model with acquisition units (MLS passes as PointSourceId) tile by tile."""
    from slipmap.core.synthetic import SurveyError

    err = SurveyError(kind="mls", level_m=0.003)
    pair = make_fault_pair(
        "mls", seed=9, origin=ORIGIN, vegetation=False, error_before=err, error_after=err
    )
    colls, clouds = [], []
    for name, scene, src in (
        ("before", pair.before, pair.source_before),
        ("after", pair.after, pair.source_after),
    ):
        path = tmp_path / f"{name}.laz"
        write_las(path, PointCloud(scene.points, {"PointSourceId": src}, CRS))
        clouds.append(read_las(path))
        _write_tiles(clouds[-1], tmp_path / name, 33.0)
        colls.append(open_collection(tmp_path / name))
    units = [c.attributes["PointSourceId"] for c in clouds]
    assert all(np.unique(u).size > 1 for u in units)
    ref = estimate_slip(
        clouds[0].xyz, clouds[1].xyz, fault_trace([pair.trace_xy]), tile_size_m=TILE,
        stochastic_model="full", unit_before=units[0], unit_after=units[1], **SIG,
    )  # fmt: skip
    got = slip_tiled(
        colls[0], colls[1], fault_trace([pair.trace_xy]), tile_size_m=TILE,
        stochastic_model="full", units="auto", **SIG,
    )  # fmt: skip
    # REML's fixed-point iterations carry the ~1e-12 m rounding of the whole-cloud path's
    # centroid sums (absolute UTM coordinates) a little further than the white model
    _same_slip(got, ref, rel=1e-8)
    assert got.parameters["acquisition_units"]["before"] == np.unique(units[0]).size
    vc = got.left.rigid.variance_components
    assert vc.component("unit_before") is not None


def test_roughness_tiled_equals_whole_cloud(data):
    ref = grid_roughness_multi(data["before"].xyz, cell_sizes_m=SIZES)
    for which in ("file", "tiles"):
        _same_grids(roughness_tiled(data[f"before_{which}"], cell_sizes_m=SIZES,
                                    tile_size_m=23.0), ref)  # fmt: skip


def test_roughness_tiled_selection_and_auto_axis(data):
    cloud = data["before"]
    keep = cloud.attributes["Classification"] != 7
    ref = grid_roughness_multi(cloud.xyz[keep], cell_sizes_m=(0.5,), ols_axis="auto")
    got = roughness_tiled(
        data["before_tiles"], cell_sizes_m=(0.5,), ols_axis="auto", tile_size_m=30.0,
        selection=Selection(exclude_classes=(7,)),
    )  # fmt: skip
    assert got[0].ols_axis == ref[0].ols_axis
    _same_grids(got, ref)


def test_options_refused(data):
    with pytest.raises(InvalidParameterError, match="GPS"):
        slip_tiled(
            data["before_tiles"], data["after_tiles"], data["trace"], tile_size_m=TILE,
            units="GpsTime",
        )  # fmt: skip
    with pytest.raises(InvalidParameterError, match="per-point"):
        slip_tiled(
            data["before_tiles"], data["after_tiles"], data["trace"], tile_size_m=TILE,
            sigma_before=np.full((5, 3), 0.02),
        )  # fmt: skip
    with pytest.raises(InvalidParameterError, match="tile_size_m"):
        roughness_tiled(data["before_tiles"], cell_sizes_m=SIZES, tile_size_m=0.0)


def _roof_scene(tmp_path):
    """A 84 m x 16 m roof (10 % slope) crossing two tile borders, a wall, and ground."""
    rng = np.random.default_rng(11)
    o = np.array(ORIGIN)
    n = 60_000
    uv = rng.uniform([2.0, 30.0], [86.0, 46.0], (n, 2))
    roof = np.column_stack([uv, 8.0 + 0.1 * (uv[:, 1] - 30.0)])
    m = 20_000
    wall = np.column_stack([rng.uniform(10.0, 40.0, m), np.full(m, 10.0), rng.uniform(0.5, 6.0, m)])
    g = 40_000
    ground = np.column_stack([rng.uniform(0, 90, g), rng.uniform(0, 25, g), np.zeros(g)])
    pts = np.concatenate([roof, wall, ground]) + o
    pts += rng.normal(0, 0.01, pts.shape)
    truth = np.repeat([0, 1, 2], [n, m, g])
    cls = np.where(truth == 2, 2, 6).astype(np.uint8)
    path = tmp_path / "roof.laz"
    write_las(path, PointCloud(pts, {"Classification": cls}, CRS))
    normal = np.array([0.0, -0.1, 1.0]) / np.linalg.norm([0.0, -0.1, 1.0])
    return path, n, normal


def test_plane_crossing_tile_borders_is_one_plane(tmp_path):
    path, n_roof, normal = _roof_scene(tmp_path)
    coll = open_collection(path)
    got = planes_tiled(coll, tile_size_m=30.0)  # borders at x = 30 and 60 m (local)
    roof = int(np.argmax(got.n_points))
    assert got.tiles[roof] >= 3  # the roof spans three tiles ...
    assert got.n_tile_planes > len(got)  # ... found as several tile planes, merged
    assert got.n_points[roof] >= 0.97 * n_roof and got.n_points[roof] <= n_roof
    assert abs(abs(got.normals[roof] @ normal) - 1.0) < 1e-4
    assert got.extent_max[roof][0] - got.extent_min[roof][0] > 80.0
    assert got.n_points_total == 80_000  # ground (class 2) left out by default
    assert len(got) == 2  # roof and wall


def test_missing_tile_names_it(data, tmp_path):
    folder = tmp_path / "copy"
    folder.mkdir()
    for p in sorted((data["root"] / "before_tiles").iterdir()):
        (folder / p.name).write_bytes(p.read_bytes())
    coll = open_collection(folder)
    victim = coll.files[len(coll.files) // 2].path
    victim.unlink()
    with pytest.raises(SlipMapFileError, match=victim.name):
        roughness_tiled(coll, cell_sizes_m=SIZES, tile_size_m=30.0)


def test_cancel_in_process_stops_between_tiles(data):
    seen = []

    def progress(fraction, message):
        seen.append(fraction)
        if fraction > 0:
            raise CancelledError("cancelled")

    with pytest.raises(CancelledError):
        roughness_tiled(data["before_tiles"], cell_sizes_m=SIZES, tile_size_m=30.0,
                        engine=InProcess(), progress=progress)  # fmt: skip
    assert len(seen) == 2  # started, one tile, then stopped


# --------------------------------------------------------------------------- Dask


@pytest.fixture(scope="module")
def cluster():
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the test's task functions
    with make_engine(workers=2) as eng:
        yield eng


def test_dask_two_workers_equal_in_process(data, cluster, slip_ref):
    assert cluster.n_workers == 2
    _same_slip(_slip(data, "tiles", engine=cluster), slip_ref)
    ref = roughness_tiled(data["before_file"], cell_sizes_m=SIZES, tile_size_m=23.0)
    _same_grids(roughness_tiled(data["before_tiles"], cell_sizes_m=SIZES, tile_size_m=23.0,
                                engine=cluster), ref)  # fmt: skip
    p1 = planes_tiled(data["before_tiles"], tile_size_m=40.0)
    p2 = planes_tiled(data["before_file"], tile_size_m=40.0, engine=cluster)
    assert np.array_equal(p1.n_points, p2.n_points) and np.array_equal(p1.tiles, p2.tiles)
    assert _rel(p2.centroids, p1.centroids) < 1e-9 and _rel(p2.normals, p1.normals) < 1e-9


def test_dask_missing_tile_names_it(data, cluster, tmp_path):
    folder = tmp_path / "copy"
    folder.mkdir()
    for p in sorted((data["root"] / "after_tiles").iterdir()):
        (folder / p.name).write_bytes(p.read_bytes())
    coll = open_collection(folder)
    victim = coll.files[0].path
    victim.unlink()
    with pytest.raises(SlipMapFileError, match=victim.name):
        roughness_tiled(coll, cell_sizes_m=SIZES, tile_size_m=30.0, engine=cluster)


def test_dask_cancel(cluster):
    def progress(fraction, message):
        if fraction > 0:
            raise CancelledError("cancelled")

    with pytest.raises(CancelledError):
        cluster.map(_slow_double, list(range(8)), progress=progress)


def _slow_double(x):
    import time

    time.sleep(0.2)
    return 2 * x


def _die_once(item):
    marker, value = item
    if not os.path.exists(marker):
        with open(marker, "w"):
            pass
        os._exit(1)  # the worker process dies in the middle of the task
    return 2 * value


def _die_always(item):
    if item == 3:
        os._exit(1)
    return 2 * item


def test_dask_killed_worker_is_retried(cluster, tmp_path):
    marker = str(tmp_path / "died")
    items = [(marker if v == 2 else str(tmp_path / "never") + "x", v) for v in range(5)]
    open(str(tmp_path / "never") + "x", "w").close()
    assert cluster.map(_die_once, items) == [0, 2, 4, 6, 8]
    assert os.path.exists(marker)  # the worker did die once


def test_dask_worker_dying_every_time_is_a_clear_error(cluster):
    # the tile named is one the dying worker held: item 3 (tile 4), or a tile queued beside it
    # on that worker when it died (Dask counts those as suspicious too), whichever is reported
    # first
    with pytest.raises(SlipMapError, match=r"tile [1-5]: the Dask worker running it died"):
        cluster.map(_die_always, list(range(5)))
    assert cluster.map(_slow_double, [1, 2]) == [2, 4]  # the cluster still works
