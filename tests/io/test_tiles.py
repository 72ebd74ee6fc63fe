"""Tile collections (core/io/tiles.py): header index, region reads, errors naming tiles."""

from __future__ import annotations

import numpy as np
import pyproj
import pytest

from slipmap.core.errors import SlipMapFileError
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.io.tiles import (
    Region,
    is_collection_spec,
    open_collection,
    region_grid,
)

CRS = pyproj.CRS.from_epsg(32611)
ORIGIN = np.array([500000.0, 4200000.0, 100.0])


def _cloud(n=20000, seed=0, crs=CRS):
    rng = np.random.default_rng(seed)
    xyz = ORIGIN + rng.uniform([0, 0, 0], [90.0, 70.0, 5.0], (n, 3))
    cls = rng.integers(1, 7, n).astype(np.uint8)
    return PointCloud(xyz=xyz, attributes={"Classification": cls}, crs=crs)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """One LAZ file and the same points cut into 4 x 3 LAZ tiles of an unrelated layout."""
    root = tmp_path_factory.mktemp("tiles")
    whole = root / "whole.laz"
    write_las(whole, _cloud())
    cloud = read_las(whole)  # quantized coordinates, as the tiles will hold them
    tdir = root / "tiles"
    tdir.mkdir()
    k = np.floor((cloud.xyz[:, :2] - ORIGIN[:2]) / [23.0, 27.0]).astype(int)
    for key in np.unique(k, axis=0):
        write_las(tdir / f"t_{key[0]}_{key[1]}.laz", cloud.subset(np.all(k == key, axis=1)))
    return whole, tdir, cloud


def _sorted(xyz):
    return xyz[np.lexsort((xyz[:, 2], xyz[:, 1], xyz[:, 0]))]


def test_index_from_file_folder_glob_and_list(files):
    whole, tdir, cloud = files
    one = open_collection(whole)
    folder = open_collection(tdir)
    glob = open_collection(str(tdir / "t_*.laz"))
    listed = open_collection(sorted(tdir.iterdir()))
    assert len(one) == 1 and one.n_points == len(cloud)
    assert len(folder) == len(glob) == len(listed) > 1
    assert folder.n_points == glob.n_points == listed.n_points == len(cloud)
    lo, hi = folder.bounds
    assert np.allclose(lo, cloud.xyz.min(0)) and np.allclose(hi, cloud.xyz.max(0))
    assert pyproj.CRS.from_wkt(folder.crs_wkt).equals(CRS)
    assert not any(f.copc for f in folder.files)
    assert is_collection_spec(tdir) and is_collection_spec(str(tdir / "*.laz"))
    assert is_collection_spec([whole, whole]) and not is_collection_spec(whole)


def test_regions_partition_the_points_and_layout_does_not_matter(files):
    whole, tdir, cloud = files
    one, many = open_collection(whole), open_collection(tdir)
    regions = region_grid(many.bounds, 30.0, collections=[many])
    assert regions == region_grid(one.bounds, 30.0, collections=[one])
    parts = []
    for r in regions:
        a = one.read_region(r, attributes=("Classification",), chunk_points=3000)
        b = many.read_region(r, attributes=("Classification",))
        assert np.array_equal(a.xyz, b.xyz)  # canonical order: same array, bit for bit
        assert np.array_equal(a.attributes["Classification"], b.attributes["Classification"])
        assert np.all(r.contains(a.xyz))
        parts.append(a.xyz)
    allp = np.concatenate(parts)
    assert allp.shape[0] == len(cloud)  # every point once
    assert np.array_equal(_sorted(allp), _sorted(cloud.xyz))


def test_halo_adds_the_margin(files):
    _, tdir, cloud = files
    many = open_collection(tdir)
    r = Region(ORIGIN[0] + 30, ORIGIN[1] + 30, ORIGIN[0] + 60, ORIGIN[1] + 60, 1, 1)
    got = many.read_region(r, halo_m=2.5).xyz
    x, y = cloud.xyz[:, 0], cloud.xyz[:, 1]
    want = (x >= r.xmin - 2.5) & (x < r.xmax + 2.5) & (y >= r.ymin - 2.5) & (y < r.ymax + 2.5)
    assert got.shape[0] == int(want.sum())


def test_missing_file_names_it(files, tmp_path):
    _, tdir, _ = files
    gone = tmp_path / "nope.laz"
    with pytest.raises(SlipMapFileError, match="nope.laz"):
        open_collection([next(tdir.iterdir()), gone])
    with pytest.raises(SlipMapFileError, match="no file matches"):
        open_collection(str(tmp_path / "*.laz"))
    with pytest.raises(SlipMapFileError, match="holds no .las or .laz"):
        open_collection(tmp_path)


def test_tile_removed_after_indexing_names_it(files, tmp_path):
    _, tdir, _ = files
    for p in tdir.iterdir():
        (tmp_path / p.name).write_bytes(p.read_bytes())
    coll = open_collection(tmp_path)
    victim = coll.files[0]
    victim.path.unlink()
    r = Region(victim.mins[0], victim.mins[1], victim.maxs[0] + 1, victim.maxs[1] + 1)
    with pytest.raises(SlipMapFileError, match=victim.path.name + ".*not found"):
        coll.read_region(r)


def test_corrupt_tiles_name_the_tile(files, tmp_path):
    _, tdir, _ = files
    src = sorted(tdir.iterdir())[0]
    data = src.read_bytes()
    truncated = tmp_path / "truncated.laz"
    truncated.write_bytes(data[: len(data) // 2])
    coll = open_collection(truncated)
    f = coll.files[0]
    r = Region(f.mins[0], f.mins[1], f.maxs[0] + 1, f.maxs[1] + 1)
    with pytest.raises(SlipMapFileError, match="truncated.laz"):
        coll.read_region(r)
    garbage = tmp_path / "garbage.laz"
    garbage.write_bytes(b"not a las file at all" * 10)
    with pytest.raises(SlipMapFileError, match="garbage.laz"):
        open_collection([src, garbage])


def test_tiles_in_different_crs_refused_unless_crs_given(files, tmp_path):
    whole, _, _ = files
    other = tmp_path / "other.laz"
    write_las(other, _cloud(n=100, seed=3, crs=pyproj.CRS.from_epsg(32612)))
    with pytest.raises(SlipMapFileError, match="other.laz"):
        open_collection([whole, other])
    coll = open_collection([whole, other], crs="EPSG:32611")
    assert coll.crs.equals(CRS)


def test_tiles_without_an_attribute_read_zeros(files, tmp_path):
    whole, _, _ = files
    plain = tmp_path / "plain.laz"
    rng = np.random.default_rng(5)
    write_las(plain, PointCloud(xyz=ORIGIN + rng.uniform(0, 5, (50, 3)), crs=CRS))
    coll = open_collection([whole, plain])
    r = Region(ORIGIN[0], ORIGIN[1], ORIGIN[0] + 6, ORIGIN[1] + 6)
    got = coll.read_region(r, attributes=("PointSourceId",))
    assert got.attributes["PointSourceId"].shape == (len(got),)
