"""SBET / SMRMSG readers, text readers and trajectory interpolation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from slipmap.core.errors import InputDataError, InvalidParameterError, SlipMapFileError
from slipmap.core.io.trajectory import (
    SBET_FIELDS,
    Trajectory,
    TrajectoryAccuracy,
    read_accuracy_csv,
    read_sbet,
    read_smrmsg,
    read_trajectory,
    read_trajectory_accuracy,
    read_trajectory_csv,
)

DATA = Path(__file__).resolve().parents[1] / "data"
SMRMSG_BIN = DATA / "smrmsg.smrmsg"
SMRMSG_TXT = DATA / "smrmsg.txt"
ARCMIN = math.pi / (180 * 60)


def _wrapdiff(a, b):
    return (np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi


def _synthetic_sbet(m: int = 50) -> np.ndarray:
    rng = np.random.default_rng(7)
    d = rng.normal(size=(m, len(SBET_FIELDS)))
    d[:, 0] = 400_000.0 + 0.005 * np.arange(m)  # 200 Hz
    d[:, 1] = np.radians(45.0) + 1e-7 * np.arange(m)
    d[:, 2] = np.radians(-122.0) + 1e-7 * np.arange(m)
    d[:, 3] = 1000.0 + rng.normal(size=m)
    d[:, 7:11] = rng.uniform(-0.1, 0.1, size=(m, 4))
    d[:, 9] += np.radians(30.0)
    return d


# --------------------------------------------------------------------------- SMRMSG


def test_smrmsg_binary_equals_text_export():
    b = read_smrmsg(SMRMSG_BIN)
    t = read_accuracy_csv(SMRMSG_TXT)
    txt = np.loadtxt(SMRMSG_TXT, delimiter=",", skiprows=1)
    assert len(b) == len(t) == txt.shape[0] == 21902
    # the text file holds 6 decimals: agreement to half a unit of the last digit
    tol = 5.0001e-7
    np.testing.assert_allclose(b.time_s, t.time_s, rtol=0, atol=tol)
    for name in ("north_m", "east_m", "down_m"):
        np.testing.assert_allclose(getattr(b, name), getattr(t, name), rtol=0, atol=tol)
    np.testing.assert_allclose(b.velocity_ned_mps, t.velocity_ned_mps, rtol=0, atol=tol)
    for name in ("roll_rad", "pitch_rad", "heading_rad"):
        np.testing.assert_allclose(getattr(b, name), getattr(t, name), rtol=0, atol=tol * ARCMIN)
    # raw columns of the text file: position RMS in metres, attitude in arc-minutes
    np.testing.assert_allclose(b.north_m, txt[:, 1], rtol=0, atol=tol)
    np.testing.assert_allclose(b.velocity_ned_mps[:, 2], txt[:, 6], rtol=0, atol=tol)
    np.testing.assert_allclose(b.heading_rad / ARCMIN, txt[:, 9], rtol=0, atol=tol)
    np.testing.assert_allclose(t.roll_rad, txt[:, 7] * ARCMIN, rtol=1e-15, atol=0)
    # plausible magnitudes: cm-level position, sub-arc-minute roll, few arc-minute heading
    assert 0 < np.median(b.north_m) < 1
    assert 0 < np.median(b.roll_rad) < 1 * ARCMIN
    assert b.time_s[0] == 536258.0 and b.time_s[-1] == 558159.0


def test_smrmsg_interpolation_and_dispatch():
    acc = read_trajectory_accuracy(SMRMSG_BIN)
    assert isinstance(acc, TrajectoryAccuracy)
    acc_txt = read_trajectory_accuracy(SMRMSG_TXT)
    assert len(acc_txt) == len(acc)
    q = acc.time_s[100] + 0.5 * (acc.time_s[101] - acc.time_s[100])
    r = acc.interpolate([acc.time_s[100], q])
    assert r["north_m"][0] == acc.north_m[100]
    assert r["heading_rad"][1] == pytest.approx(0.5 * (acc.heading_rad[100] + acc.heading_rad[101]))
    assert r["velocity_ned_mps"].shape == (2, 3)
    with pytest.raises(InputDataError, match=r"536258\.000–558159\.000 s \(1 points outside\)"):
        acc.interpolate([536000.0, 540000.0])


def test_smrmsg_truncated_and_empty(tmp_path):
    raw = SMRMSG_BIN.read_bytes()[: 80 * 5 + 13]
    p = tmp_path / "cut.smrmsg"
    p.write_bytes(raw)
    with pytest.raises(SlipMapFileError, match=r"cut\.smrmsg.*413 bytes.*80-byte"):
        read_smrmsg(p)
    e = tmp_path / "empty.smrmsg"
    e.write_bytes(b"")
    with pytest.raises(SlipMapFileError, match="empty"):
        read_smrmsg(e)
    with pytest.raises(SlipMapFileError, match="does not exist"):
        read_smrmsg(tmp_path / "missing.smrmsg")


# --------------------------------------------------------------------------- SBET


def test_sbet_round_trip(tmp_path):
    d = _synthetic_sbet()
    p = tmp_path / "flight.sbet"
    d.astype("<f8").tofile(p)
    tr = read_sbet(p)
    assert isinstance(tr, Trajectory) and len(tr) == d.shape[0]
    np.testing.assert_array_equal(tr.time_s, d[:, 0])
    np.testing.assert_array_equal(tr.lat_rad, d[:, 1])
    np.testing.assert_array_equal(tr.lon_rad, d[:, 2])
    np.testing.assert_array_equal(tr.height_m, d[:, 3])
    np.testing.assert_array_equal(tr.roll_rad, d[:, 7])
    np.testing.assert_array_equal(tr.pitch_rad, d[:, 8])
    np.testing.assert_array_equal(tr.heading_rad, d[:, 9])
    np.testing.assert_array_equal(tr.wander_rad, d[:, 10])
    assert tr.xyz is None
    assert tr.span_s == (d[0, 0], d[-1, 0])
    for name in ("x.out", "x.bin"):
        q = tmp_path / name
        d.tofile(q)
        np.testing.assert_array_equal(read_trajectory(q).heading_rad, d[:, 9])


def test_sbet_truncated_empty_and_non_increasing(tmp_path):
    d = _synthetic_sbet(4)
    p = tmp_path / "cut.sbet"
    p.write_bytes(d.tobytes()[:-1])
    with pytest.raises(SlipMapFileError, match=r"cut\.sbet.*543 bytes.*136-byte"):
        read_sbet(p)
    e = tmp_path / "empty.sbet"
    e.write_bytes(b"")
    with pytest.raises(SlipMapFileError, match="empty"):
        read_sbet(e)
    d[2, 0] = d[1, 0]
    bad = tmp_path / "dup.sbet"
    d.tofile(bad)
    with pytest.raises(InputDataError, match="strictly increasing"):
        read_sbet(bad)
    with pytest.raises(InvalidParameterError, match="text files only"):
        read_trajectory(tmp_path / "cut.sbet", angle_units="deg")
    with pytest.raises(InvalidParameterError, match="unknown extension"):
        read_trajectory(tmp_path / "a.las")


# --------------------------------------------------------------------------- interpolation


def _simple(heading_deg):
    t = np.array([100.0, 150.0, 200.0])
    h = np.radians(heading_deg)
    return Trajectory(
        time_s=t,
        lat_rad=np.radians([10.0, 10.1, 10.2]),
        lon_rad=np.radians([20.0, 20.2, 20.4]),
        height_m=np.array([500.0, 510.0, 530.0]),
        roll_rad=np.radians([1.0, 2.0, -1.0]),
        pitch_rad=np.radians([0.5, 0.0, 0.25]),
        heading_rad=h,
        wander_rad=np.radians([0.0, 1.0, 2.0]),
        xyz=np.array([[0.0, 0.0, 500.0], [10.0, 20.0, 510.0], [30.0, 40.0, 530.0]]),
    )


def test_interpolation_at_records_and_midway():
    tr = _simple([10.0, 20.0, 40.0])
    at = tr.interpolate(tr.time_s)
    for name in ("lat_rad", "lon_rad", "height_m", "roll_rad", "pitch_rad", "heading_rad"):
        np.testing.assert_allclose(at[name], getattr(tr, name), rtol=0, atol=1e-12)
    np.testing.assert_allclose(at["xyz"], tr.xyz, rtol=0, atol=1e-12)
    mid = tr.interpolate([125.0, 175.0])
    for name in ("lat_rad", "height_m", "roll_rad", "pitch_rad", "heading_rad", "wander_rad"):
        v = getattr(tr, name)
        np.testing.assert_allclose(mid[name], 0.5 * (v[:-1] + v[1:]), rtol=0, atol=1e-12)
    np.testing.assert_allclose(mid["xyz"], 0.5 * (tr.xyz[:-1] + tr.xyz[1:]), atol=1e-12)
    # shape follows the query
    assert tr.interpolate(np.full((2, 3), 150.0))["xyz"].shape == (2, 3, 3)
    assert tr.interpolate(np.empty(0))["heading_rad"].shape == (0,)


@pytest.mark.parametrize("seq", [[358.0, 359.0, 1.0], [-179.0, 179.0, 177.0], [1.0, -1.0, 359.0]])
def test_heading_interpolates_the_short_way(seq):
    tr = _simple(seq)
    r = tr.interpolate([125.0, 175.0])
    h = np.radians(seq)
    expect = h[:-1] + 0.5 * _wrapdiff(h[1:], h[:-1])
    np.testing.assert_allclose(_wrapdiff(r["heading_rad"], expect), 0, atol=1e-12)
    assert np.all(r["heading_rad"] >= -np.pi) and np.all(r["heading_rad"] < np.pi)


def test_heading_359_to_1_midway_is_north():
    tr = _simple([358.0, 359.0, 1.0])
    h = tr.interpolate(175.0)["heading_rad"]
    assert abs(float(_wrapdiff(h, 0.0))) < 1e-12
    q = tr.interpolate(162.5)["heading_rad"]  # a quarter of the way from 359° to 1°
    assert float(_wrapdiff(q, np.radians(359.5))) == pytest.approx(0.0, abs=1e-12)


def test_time_outside_span_names_both_spans():
    tr = _simple([0.0, 1.0, 2.0])
    with pytest.raises(
        InputDataError,
        match=r"GpsTime 99\.000–250\.000 s outside the trajectory's span "
        r"100\.000–200\.000 s \(2 points outside\)",
    ):
        tr.interpolate([99.0, 150.0, 250.0])
    with pytest.raises(InputDataError, match="NaN"):
        tr.interpolate([np.nan])


def test_constructor_validation():
    with pytest.raises(InputDataError, match="strictly increasing"):
        Trajectory(
            time_s=[1.0, 1.0],
            lat_rad=[0, 0],
            lon_rad=[0, 0],
            height_m=[0, 0],
            roll_rad=[0, 0],
            pitch_rad=[0, 0],
            heading_rad=[0, 0],
        )
    with pytest.raises(InputDataError, match="position"):
        Trajectory(
            time_s=[1.0],
            lat_rad=None,
            lon_rad=None,
            height_m=None,
            roll_rad=[0],
            pitch_rad=[0],
            heading_rad=[0],
        )
    with pytest.raises(InputDataError, match="no records"):
        Trajectory(
            time_s=[],
            lat_rad=[],
            lon_rad=[],
            height_m=[],
            roll_rad=[],
            pitch_rad=[],
            heading_rad=[],
        )


# --------------------------------------------------------------------------- CSV


def _write_csv(path, header, rows, sep=","):
    lines = [sep.join(header)] + [sep.join(repr(float(v)) for v in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_trajectory_csv_deg_and_rad(tmp_path):
    t = np.array([10.0, 11.0, 12.0])
    xyz = np.array([[500000.0, 4e6, 100.0], [500010.0, 4e6 + 5, 101.0], [500020.0, 4e6 + 9, 99.0]])
    att_deg = np.array([[1.0, 2.0, 359.0], [1.5, 2.5, 1.0], [2.0, 3.0, 3.0]])
    header = ["GpsTime", "X", "Y", "Z", "Roll", "Pitch", "Heading"]
    pd = _write_csv(tmp_path / "deg.csv", header, np.column_stack([t, xyz, att_deg]))
    tr = read_trajectory_csv(pd)
    assert tr.lat_rad is None
    np.testing.assert_array_equal(tr.xyz, xyz)
    np.testing.assert_allclose(tr.heading_rad, np.radians(att_deg[:, 2]), rtol=1e-15)
    np.testing.assert_allclose(tr.interpolate(10.5)["heading_rad"], 0.0, atol=1e-12)
    pr = _write_csv(
        tmp_path / "rad.txt", header, np.column_stack([t, xyz, np.radians(att_deg)]), sep=" "
    )
    tr2 = read_trajectory(pr, angle_units="rad")
    np.testing.assert_allclose(tr2.roll_rad, tr.roll_rad, rtol=1e-15)
    np.testing.assert_allclose(tr2.heading_rad, tr.heading_rad, rtol=1e-15)
    with pytest.raises(InvalidParameterError, match="angle_units"):
        read_trajectory_csv(pd, angle_units="grad")


def test_trajectory_csv_geodetic_and_explicit_columns(tmp_path):
    rows = [
        [1.0, 45.0, -122.0, 100.0, 0.1, 0.2, 90.0],
        [2.0, 45.001, -122.0, 101.0, 0.1, 0.2, 91.0],
    ]
    header = ["t_gps", "Latitude", "Longitude", "Height", "r", "p", "Yaw"]
    p = _write_csv(tmp_path / "geo.csv", header, rows, sep=";")
    with pytest.raises(SlipMapFileError, match="lacks column"):
        read_trajectory_csv(p)
    tr = read_trajectory_csv(p, columns={"time": "t_gps", "roll": "r", "pitch": "p"})
    np.testing.assert_allclose(tr.lat_rad, np.radians([45.0, 45.001]), rtol=1e-15)
    np.testing.assert_allclose(tr.heading_rad, np.radians([90.0, 91.0]), rtol=1e-15)
    assert tr.xyz is None and tr.wander_rad is None
    with pytest.raises(InvalidParameterError, match="no column 'nope'"):
        read_trajectory_csv(p, columns={"time": "nope"})
    with pytest.raises(InvalidParameterError, match="unknown key"):
        read_trajectory_csv(p, columns={"when": "t_gps"})


def test_accuracy_csv_units(tmp_path):
    header = ["GpsTime", "North", "East", "Down", "RollRMS", "PitchRMS", "HeadingRMS"]
    rows = [[1.0, 0.05, 0.06, 0.07, 0.5, 0.6, 3.0], [2.0, 0.04, 0.05, 0.06, 0.4, 0.5, 2.0]]
    p = _write_csv(tmp_path / "acc.csv", header, rows)
    a = read_accuracy_csv(p)
    np.testing.assert_allclose(a.heading_rad, np.array([3.0, 2.0]) * ARCMIN, rtol=1e-15)
    assert a.velocity_ned_mps is None
    d = read_accuracy_csv(p, angle_units="deg")
    np.testing.assert_allclose(d.heading_rad, np.radians([3.0, 2.0]), rtol=1e-15)
    np.testing.assert_allclose(a.interpolate(1.5)["north_m"], 0.045, rtol=1e-12)
    with pytest.raises(InvalidParameterError, match="angle_units"):
        read_accuracy_csv(p, angle_units="mil")


def test_text_file_errors(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("GpsTime,X,Y,Z,Roll,Pitch,Heading\n1,2,3,4,5,6,abc\n")
    with pytest.raises(SlipMapFileError, match="not a number"):
        read_trajectory_csv(p)
    p.write_text("GpsTime,X,Y,Z,Roll,Pitch,Heading\n1,2,3,4,5,6\n")
    with pytest.raises(SlipMapFileError, match="line 2 has 6 values"):
        read_trajectory_csv(p)
    p.write_text("")
    with pytest.raises(SlipMapFileError, match="empty"):
        read_trajectory_csv(p)
    p.write_text("GpsTime,X,Y,Z,Roll,Pitch,Heading\n2,0,0,0,0,0,0\n1,0,0,0,0,0,0\n")
    with pytest.raises(InputDataError, match="strictly increasing"):
        read_trajectory_csv(p)
    with pytest.raises(SlipMapFileError, match="does not exist"):
        read_accuracy_csv(tmp_path / "none.txt")
