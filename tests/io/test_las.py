"""Tests of the LAS/LAZ layer (slipmap.core.io.las) and the CRS helpers (slipmap.core.io.crs)."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import laspy
import numpy as np
import pyproj
import pytest

from slipmap.core.errors import (
    InputDataError,
    InvalidParameterError,
    SlipMapError,
    SlipMapFileError,
)
from slipmap.core.io.crs import crs_from_las, crs_to_wkt, crs_units, parse_crs, same_crs
from slipmap.core.io.las import (
    DEFAULT_ATTRIBUTES,
    LasHeaderInfo,
    PointCloud,
    available_attributes,
    iter_las_chunks,
    read_las,
    read_las_header,
    write_las,
    write_las_chunked,
)

DATA = Path(__file__).resolve().parents[1] / "data"
AUTZEN = DATA / "autzen_trim.laz"
LONE_STAR = DATA / "lone-star.laz"


@pytest.fixture(scope="module")
def autzen() -> PointCloud:
    return read_las(AUTZEN)


@pytest.fixture(scope="module")
def autzen_laspy() -> laspy.LasData:
    return laspy.read(AUTZEN)


def _extras(n: int) -> dict:
    rng = np.random.default_rng(0)
    plane_id = rng.integers(-1, 500, n).astype(np.int32)
    plane_id[:10] = -1
    planarity = rng.random(n)
    return {"PlaneId": plane_id, "Planarity": planarity}


def _files(directory: Path) -> list:
    return sorted(p.name for p in directory.iterdir())


# ------------------------------------------------------------------------------------ reading


def test_read_autzen(autzen: PointCloud, autzen_laspy: laspy.LasData) -> None:
    pc = autzen
    assert len(pc) == 110_000
    assert pc.xyz.shape == (110_000, 3)
    assert pc.xyz.dtype == np.float64
    assert pc.xyz.flags.c_contiguous
    np.testing.assert_array_equal(pc.xyz[:, 0], np.asarray(autzen_laspy.x, dtype=np.float64))
    np.testing.assert_array_equal(pc.xyz[:, 1], np.asarray(autzen_laspy.y, dtype=np.float64))
    np.testing.assert_array_equal(pc.xyz[:, 2], np.asarray(autzen_laspy.z, dtype=np.float64))

    cls = pc.attributes["Classification"]
    assert cls.dtype == np.uint8
    assert set(np.unique(cls).tolist()) == {1, 2}
    assert pc.attributes["GpsTime"].dtype == np.float64
    np.testing.assert_array_equal(pc.attributes["GpsTime"], np.asarray(autzen_laspy.gps_time))
    assert pc.attributes["ScanAngle"].dtype == np.float64
    np.testing.assert_array_equal(
        pc.attributes["ScanAngle"], pc.attributes["ScanAngleRank"].astype(np.float64)
    )
    assert pc.attributes["Intensity"].dtype == np.uint16
    assert pc.attributes["ReturnNumber"].dtype == np.uint8
    assert pc.attributes["NumberOfReturns"].dtype == np.uint8
    assert pc.attributes["PointSourceId"].dtype == np.uint16
    assert set(pc.attributes) == set(DEFAULT_ATTRIBUTES)
    for values in pc.attributes.values():
        assert values.shape == (110_000,)

    h = pc.header
    assert isinstance(h, LasHeaderInfo)
    assert (h.version, h.point_format, h.n_points) == ("1.2", 3, 110_000)
    np.testing.assert_array_equal(h.scales, [0.01, 0.01, 0.01])
    np.testing.assert_array_equal(h.offsets, [0.0, 0.0, 0.0])
    assert np.all(h.mins <= pc.xyz.min(axis=0)) and np.all(h.maxs >= pc.xyz.max(axis=0))
    assert pc.source == AUTZEN

    # Oregon Lambert, feet-based: the file says international foot (EPSG 9002, 0.3048 m)
    assert isinstance(pc.crs, pyproj.CRS)
    assert pc.crs.is_projected
    name, metres = crs_units(pc.crs)
    assert "foot" in name
    assert metres == pytest.approx(0.3048, abs=1e-6)


def test_read_lone_star_mislabelled_crs(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="slipmap.core.io.crs"):
        pc = read_las(LONE_STAR)
    assert len(pc) == 518_862
    assert pc.header.point_format == 1
    # UTM zone 12N coordinates (Yellowstone)...
    assert 500_000 < pc.xyz[:, 0].min() < pc.xyz[:, 0].max() < 520_000
    assert 4_900_000 < pc.xyz[:, 1].min() < pc.xyz[:, 1].max() < 4_930_000
    # ...but the GeoTIFF keys declare WGS 84 (degrees): ignored, with a warning
    assert pc.crs is None
    assert any("geographic" in r.getMessage() for r in caplog.records)
    assert "GpsTime" in pc.attributes
    assert set(np.unique(pc.attributes["Classification"]).tolist()) == {0}


def test_read_header_only(autzen: PointCloud) -> None:
    info, crs = read_las_header(AUTZEN)
    assert info.n_points == 110_000
    assert info.point_format == 3 and info.version == "1.2"
    np.testing.assert_array_equal(info.mins, autzen.header.mins)
    assert same_crs(crs, autzen.crs)


def test_attribute_subset_and_unknown() -> None:
    pc = read_las(AUTZEN, attributes=["Classification", "UserData", "X"])
    assert list(pc.attributes) == ["Classification", "UserData"]
    assert pc.xyz.shape == (110_000, 3)
    with pytest.raises(InvalidParameterError, match="'Bogus'") as info:
        read_las(AUTZEN, attributes=["Classification", "Bogus"])
    assert "Classification" in str(info.value) and "GpsTime" in str(info.value)
    with pytest.raises(InvalidParameterError, match="Infrared"):
        read_las(AUTZEN, attributes=["Infrared"])  # only point formats 8 and 10 have it
    assert read_las(AUTZEN, attributes=["Red"]).attributes["Red"].dtype == np.uint16


def test_available_attributes() -> None:
    names = available_attributes(0)
    assert "GpsTime" not in names and "ScanAngle" in names and "ScanAngleRank" in names
    names6 = available_attributes(6)
    assert "GpsTime" in names6 and "ScanAngleRank" not in names6


# ----------------------------------------------------------------------------------- writing


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_round_trip_with_extra_dims(
    tmp_path: Path, autzen: PointCloud, autzen_laspy: laspy.LasData, suffix: str
) -> None:
    extras = _extras(len(autzen))
    out = write_las(tmp_path / f"out{suffix}", autzen, extra_dims=extras)
    assert out == tmp_path / f"out{suffix}"
    assert _files(tmp_path) == [f"out{suffix}"]
    assert "PlaneId" not in autzen.attributes  # the source is unchanged
    assert list(autzen._las.point_format.extra_dimension_names) == []

    back = read_las(out)
    np.testing.assert_array_equal(back.xyz, autzen.xyz)
    raw = laspy.read(out)
    assert raw.header.are_points_compressed == (suffix == ".laz")
    np.testing.assert_array_equal(np.asarray(raw.X), np.asarray(autzen_laspy.X))
    np.testing.assert_array_equal(np.asarray(raw.Z), np.asarray(autzen_laspy.Z))
    for name in ("Classification", "GpsTime", "Intensity", "ScanAngleRank", "ReturnNumber"):
        np.testing.assert_array_equal(back.attributes[name], autzen.attributes[name])
    assert back.attributes["PlaneId"].dtype == np.int32
    assert back.attributes["Planarity"].dtype == np.float64
    np.testing.assert_array_equal(back.attributes["PlaneId"], extras["PlaneId"])
    np.testing.assert_array_equal(back.attributes["Planarity"], extras["Planarity"])
    assert (back.header.version, back.header.point_format) == ("1.2", 3)
    np.testing.assert_array_equal(back.header.scales, autzen.header.scales)
    np.testing.assert_array_equal(back.header.offsets, autzen.header.offsets)
    np.testing.assert_allclose(back.header.mins, autzen.header.mins)
    assert same_crs(back.crs, autzen.crs)
    # every original VLR is kept (GeoTIFF keys, WKT, the liblas one) plus extra bytes
    kept = {type(v).__name__ for v in raw.header.vlrs}
    assert {"GeoKeyDirectoryVlr", "WktCoordinateSystemVlr", "ExtraBytesVlr"} <= kept


def test_write_from_path_streams(tmp_path: Path, autzen: PointCloud) -> None:
    extras = _extras(len(autzen))
    out = write_las(tmp_path / "p.las", AUTZEN, extra_dims=extras)
    back = read_las(out)
    np.testing.assert_array_equal(back.xyz, autzen.xyz)
    np.testing.assert_array_equal(back.attributes["GpsTime"], autzen.attributes["GpsTime"])
    np.testing.assert_array_equal(back.attributes["PlaneId"], extras["PlaneId"])
    assert same_crs(back.crs, autzen.crs)


def test_overwrite_existing_dimension(tmp_path: Path, autzen: PointCloud) -> None:
    n = len(autzen)
    first = read_las(write_las(tmp_path / "a.las", autzen, extra_dims=_extras(n)))
    new_ids = np.arange(n, dtype=np.int32)
    cls = np.full(n, 6, dtype=np.uint8)
    second = read_las(
        write_las(tmp_path / "b.las", first, extra_dims={"PlaneId": new_ids, "Classification": cls})
    )
    assert list(second._las.point_format.extra_dimension_names) == ["PlaneId", "Planarity"]
    np.testing.assert_array_equal(second.attributes["PlaneId"], new_ids)
    np.testing.assert_array_equal(second.attributes["Classification"], cls)

    # dtype-checked: floats into an int32 dimension, values that do not fit a 5-bit class
    with pytest.raises(InvalidParameterError, match="PlaneId"):
        write_las(tmp_path / "c.las", first, extra_dims={"PlaneId": new_ids.astype(float)})
    with pytest.raises(InvalidParameterError, match="Classification"):
        write_las(tmp_path / "c.las", first, extra_dims={"Classification": cls * 10})
    with pytest.raises(InvalidParameterError, match="Infrared"):
        write_las(tmp_path / "c.las", first, extra_dims={"Infrared": new_ids})
    assert not (tmp_path / "c.las").exists()


def test_edited_attributes_are_written(tmp_path: Path, autzen: PointCloud) -> None:
    pc = autzen.subset(np.arange(1000))
    pc.attributes["Classification"][:] = 17
    pc.attributes["Roughness"] = np.linspace(0, 1, 1000, dtype=np.float32)
    back = read_las(write_las(tmp_path / "e.laz", pc))
    assert set(back.attributes["Classification"].tolist()) == {17}
    assert back.attributes["Roughness"].dtype == np.float32
    np.testing.assert_array_equal(back.attributes["Roughness"], pc.attributes["Roughness"])
    assert set(np.unique(autzen.attributes["Classification"]).tolist()) == {1, 2}


def test_xyz_replacement_keeps_scale_offset(tmp_path: Path, autzen: PointCloud) -> None:
    shifted = autzen.xyz + np.array([1.234, -5.0, 0.5])
    back = read_las(write_las(tmp_path / "s.laz", autzen, xyz=shifted))
    np.testing.assert_array_equal(back.header.scales, autzen.header.scales)
    np.testing.assert_array_equal(back.header.offsets, autzen.header.offsets)
    np.testing.assert_allclose(back.xyz, shifted, rtol=0, atol=0.005 + 1e-9)
    np.testing.assert_allclose(back.header.mins, autzen.header.mins + [1.234, -5.0, 0.5])
    np.testing.assert_array_equal(back.attributes["GpsTime"], autzen.attributes["GpsTime"])

    too_far = autzen.xyz.copy()
    too_far[0, 0] = 1e12
    with pytest.raises(InvalidParameterError, match="int32"):
        write_las(tmp_path / "t.laz", autzen, xyz=too_far)
    with pytest.raises(InvalidParameterError, match="shape"):
        write_las(tmp_path / "t.laz", autzen, xyz=autzen.xyz[:10])
    assert _files(tmp_path) == ["s.laz"]


def test_subset(tmp_path: Path, autzen: PointCloud) -> None:
    mask = autzen.attributes["Classification"] == 2
    ground = autzen.subset(mask)
    assert len(ground) == int(mask.sum())
    assert set(ground.attributes["Classification"].tolist()) == {2}
    assert ground.header is autzen.header and ground.crs is autzen.crs
    ground.xyz[:] = 0.0
    assert autzen.xyz.min() > 0  # subsets are copies
    idx = np.array([5, 3, 3, 0])
    picked = autzen.subset(idx)
    np.testing.assert_array_equal(picked.xyz, autzen.xyz[idx])
    back = read_las(write_las(tmp_path / "i.las", picked))
    np.testing.assert_array_equal(back.attributes["GpsTime"], autzen.attributes["GpsTime"][idx])
    assert len(autzen.subset(slice(10, 20))) == 10
    with pytest.raises(InvalidParameterError):
        autzen.subset(mask[:-1])
    with pytest.raises(InvalidParameterError):
        autzen.subset(np.array([len(autzen)]))


def test_in_memory_cloud(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    xyz = rng.uniform([500_000, 4_000_000, 100], [500_100, 4_000_100, 120], (500, 3))
    pc = PointCloud(
        xyz=xyz,
        attributes={"Classification": np.full(500, 2, np.uint8), "PlaneId": np.arange(500)},
        crs=pyproj.CRS.from_epsg(32612),
    )
    back = read_las(write_las(tmp_path / "m.laz", pc))
    np.testing.assert_allclose(back.xyz, xyz, rtol=0, atol=0.0005 + 1e-9)
    assert back.header.point_format == 6 and back.header.version == "1.4"
    assert same_crs(back.crs, "EPSG:32612")
    np.testing.assert_array_equal(back.attributes["PlaneId"], np.arange(500))
    assert back.attributes["PlaneId"].dtype == np.arange(500).dtype
    with pytest.raises(InvalidParameterError):
        PointCloud(xyz=np.zeros((5, 2)))
    with pytest.raises(InvalidParameterError):
        PointCloud(xyz=np.zeros((5, 3)), attributes={"a": np.zeros(4)})


def test_point_format_6_scan_angle_and_scaled_extra(tmp_path: Path) -> None:
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.scales = np.array([0.001, 0.001, 0.001])
    header.offsets = np.array([1000.0, 2000.0, 0.0])
    header.add_extra_dim(
        laspy.ExtraBytesParams("Sigma", "u2", scales=np.array([0.001]), offsets=np.array([0.0]))
    )
    las = laspy.LasData(header)
    las.x = np.array([1000.5, 1001.0, 1002.25])
    las.y = np.array([2000.0, 2000.5, 2001.0])
    las.z = np.array([1.0, 2.0, 3.0])
    las.scan_angle = np.array([-5000, 0, 2500], dtype=np.int16)
    las.gps_time = np.array([1.0, 2.0, 3.0])
    las.Sigma = np.array([0.005, 0.010, 0.123])
    src = tmp_path / "pf6.las"
    las.write(src)

    pc = read_las(src)
    assert "ScanAngleRank" not in pc.attributes
    np.testing.assert_allclose(pc.attributes["ScanAngle"], [-30.0, 0.0, 15.0])
    np.testing.assert_allclose(pc.attributes["Sigma"], [0.005, 0.010, 0.123])
    back = read_las(write_las(tmp_path / "pf6_out.laz", pc, extra_dims={"Flag": np.ones(3, bool)}))
    np.testing.assert_array_equal(
        np.asarray(laspy.read(tmp_path / "pf6_out.laz").scan_angle), [-5000, 0, 2500]
    )
    np.testing.assert_array_equal(back.attributes["Sigma"], pc.attributes["Sigma"])
    assert back.attributes["Flag"].dtype == np.uint8
    np.testing.assert_array_equal(back.xyz, pc.xyz)


# --------------------------------------------------------------------------- safety and errors


def test_failed_write_leaves_nothing(tmp_path: Path, autzen: PointCloud) -> None:
    out = tmp_path / "bad.laz"
    with pytest.raises(InvalidParameterError, match="PlaneId"):
        write_las(out, autzen, extra_dims={"PlaneId": np.zeros(10, np.int32)})
    assert _files(tmp_path) == []

    # a failure after points were written (second chunk adds another dimension)
    chunks = iter_las_chunks(AUTZEN, chunk_points=60_000)
    first, second = next(chunks), next(chunks)
    items = [
        (first, {"PlaneId": np.zeros(len(first), np.int32)}),
        (second, {"Other": np.zeros(len(second), np.int32)}),
    ]
    with pytest.raises(InvalidParameterError, match="same new dimensions"):
        write_las_chunked(out, items)
    assert _files(tmp_path) == []


def test_refuses_to_overwrite_input(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = tmp_path / "in.laz"
    shutil.copyfile(AUTZEN, src)
    before = src.read_bytes()
    pc = read_las(src)
    (tmp_path / "sub").mkdir()
    with pytest.raises(InvalidParameterError, match="input"):
        write_las(tmp_path / "sub" / ".." / "in.laz", pc)
    monkeypatch.chdir(tmp_path / "sub")
    with pytest.raises(InvalidParameterError, match="input"):
        write_las("../in.laz", pc)
    with pytest.raises(InvalidParameterError, match="input"):
        write_las("../in.laz", src)
    other = read_las(AUTZEN)
    with pytest.raises(InvalidParameterError, match="input"):
        write_las(src, other, inputs=["../in.laz"])
    assert src.read_bytes() == before
    assert _files(tmp_path) == ["in.laz", "sub"] and _files(tmp_path / "sub") == []


@pytest.mark.skipif(
    hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores file permissions"
)
def test_unwritable_directory(tmp_path: Path, autzen: PointCloud) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        with pytest.raises(SlipMapFileError):
            write_las(locked / "out.laz", autzen.subset(np.arange(10)))
    finally:
        locked.chmod(0o700)


def test_output_parent_is_a_file(tmp_path: Path, autzen: PointCloud) -> None:
    (tmp_path / "afile").write_text("x")
    with pytest.raises(SlipMapFileError):
        write_las(tmp_path / "afile" / "out.laz", autzen.subset(np.arange(10)))


def test_missing_and_corrupt_files(tmp_path: Path) -> None:
    missing = tmp_path / "nope.laz"
    for func in (read_las, read_las_header, iter_las_chunks):
        with pytest.raises(SlipMapFileError, match="file not found: .*nope.laz"):
            func(missing)
    with pytest.raises(SlipMapFileError, match="not found"):
        write_las(tmp_path / "o.las", missing)

    junk = tmp_path / "x.laz"
    junk.write_bytes(np.random.default_rng(2).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(SlipMapFileError, match="x.laz is not a readable LAS/LAZ file"):
        read_las(junk)
    with pytest.raises(SlipMapFileError, match="not a readable LAS/LAZ"):
        read_las_header(junk)

    truncated = tmp_path / "cut.laz"
    truncated.write_bytes(AUTZEN.read_bytes()[:50_000])
    with pytest.raises(SlipMapFileError, match="cut.laz"):
        read_las(truncated)
    with pytest.raises(SlipMapFileError, match="cut.laz"):
        list(iter_las_chunks(truncated, chunk_points=30_000))
    with pytest.raises(SlipMapFileError):
        write_las(tmp_path / "from_cut.las", truncated)
    assert not (tmp_path / "from_cut.las").exists()
    assert isinstance(SlipMapFileError("x"), SlipMapError)


# ---------------------------------------------------------------------------- chunks, empty


def test_chunked_reading_matches_full_read(tmp_path: Path, autzen: PointCloud) -> None:
    chunks = list(iter_las_chunks(AUTZEN, chunk_points=30_000))
    assert [len(c) for c in chunks] == [30_000, 30_000, 30_000, 20_000]
    np.testing.assert_array_equal(np.concatenate([c.xyz for c in chunks]), autzen.xyz)
    for name in autzen.attributes:
        np.testing.assert_array_equal(
            np.concatenate([c.attributes[name] for c in chunks]), autzen.attributes[name]
        )
    assert all(same_crs(c.crs, autzen.crs) and c.header.n_points == 110_000 for c in chunks)
    only = next(iter(iter_las_chunks(AUTZEN, chunk_points=5, attributes=["GpsTime"])))
    assert list(only.attributes) == ["GpsTime"] and len(only) == 5
    for bad in (0, -3, 2.5, True):
        with pytest.raises(InvalidParameterError, match="chunk_points"):
            iter_las_chunks(AUTZEN, chunk_points=bad)

    # chunked write gives the same points as a one-shot write
    extras = _extras(len(autzen))
    items, start = [], 0
    for c in iter_las_chunks(AUTZEN, chunk_points=30_000):
        sl = slice(start, start + len(c))
        items.append((c, {k: v[sl] for k, v in extras.items()}))
        start += len(c)
    back = read_las(write_las_chunked(tmp_path / "chunked.laz", iter(items)))
    np.testing.assert_array_equal(back.xyz, autzen.xyz)
    np.testing.assert_array_equal(back.attributes["PlaneId"], extras["PlaneId"])
    assert back.header.n_points == 110_000
    assert same_crs(back.crs, autzen.crs)


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_zero_point_file(tmp_path: Path, suffix: str) -> None:
    header = laspy.LasHeader(version="1.2", point_format=3)
    empty = tmp_path / f"empty{suffix}"
    laspy.LasData(header).write(empty)
    pc = read_las(empty)
    assert len(pc) == 0 and pc.xyz.shape == (0, 3) and pc.header.n_points == 0
    assert pc.attributes["Classification"].shape == (0,)
    assert pc.crs is None
    assert len(list(iter_las_chunks(empty))) == 0
    back = read_las(
        write_las(tmp_path / f"copy{suffix}", pc, extra_dims={"PlaneId": np.zeros(0, np.int32)})
    )
    assert len(back) == 0 and "PlaneId" in back.attributes


# ---------------------------------------------------------------------------------------- CRS


def test_crs_helpers() -> None:
    utm = parse_crs("EPSG:32612")
    assert same_crs(utm, 32612) and same_crs(None, None)
    assert not same_crs(utm, None) and not same_crs(utm, "EPSG:32611")
    assert same_crs("EPSG:4326", "OGC:CRS84")  # axis order ignored
    assert crs_units(utm) == ("metre", 1.0)
    name, metres = crs_units("EPSG:2264")  # NAD83 / North Carolina (ftUS)
    assert name == "US survey foot" and metres == pytest.approx(1200 / 3937)
    with pytest.raises(InputDataError, match="geographic"):
        crs_units("EPSG:4326")
    with pytest.raises(InvalidParameterError):
        crs_units(None)
    with pytest.raises(InvalidParameterError, match="CRS"):
        parse_crs("not a crs at all")
    assert crs_to_wkt(None) is None
    assert same_crs(pyproj.CRS.from_wkt(crs_to_wkt(utm)), utm)
    assert crs_to_wkt(utm, version="WKT1_GDAL").startswith("PROJCS")


def test_broken_crs_gives_warning_and_none(caplog: pytest.LogCaptureFixture) -> None:
    header = laspy.LasHeader(version="1.4", point_format=6)
    header.vlrs.append(laspy.vlrs.known.WktCoordinateSystemVlr("PROJCS[this is not wkt"))
    with caplog.at_level(logging.WARNING, logger="slipmap.core.io.crs"):
        assert crs_from_las(header, source="broken.las") is None
    assert any("broken.las" in r.getMessage() for r in caplog.records)
    good = laspy.LasHeader(version="1.4", point_format=6)
    good.add_crs(pyproj.CRS.from_epsg(32612))
    assert same_crs(crs_from_las(good), 32612)


def test_header_with_scale_zero_is_refused_naming_the_file(tmp_path):
    """A header whose scale factor is 0 (or not finite) cannot give coordinates: refused."""
    import struct

    from slipmap.core.errors import SlipMapFileError
    from slipmap.core.io.las import read_las_header

    path = tmp_path / "scale0.las"
    write_las(path, PointCloud(xyz=np.arange(30, dtype=np.float64).reshape(10, 3)))
    raw = bytearray(path.read_bytes())
    raw[131:139] = struct.pack("<d", 0.0)  # X scale factor (LAS 1.x public header)
    path.write_bytes(bytes(raw))
    for reader in (read_las, read_las_header):
        with pytest.raises(SlipMapFileError, match="scale") as raised:
            reader(path)
        assert str(path) in str(raised.value)
