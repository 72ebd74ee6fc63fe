"""``slipmap accuracy`` writes per-point sigmas that ``--pa columns`` reads back."""

import json
from pathlib import Path

import numpy as np
import pytest

from slipmap.cli import main
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.synthetic import make_scene


@pytest.fixture(scope="module")
def cloud_file(tmp_path_factory):
    sc = make_scene("tls", seed=2, n_buildings=1, extent_m=40.0, origin=(500000, 4200000, 10))
    sub = np.random.default_rng(0).choice(sc.points.shape[0], 20000, replace=False)
    path = tmp_path_factory.mktemp("acc") / "tls.las"
    write_las(
        path, PointCloud(xyz=sc.points[sub], attributes={"Classification": sc.classification[sub]})
    )
    return path


def test_axis_model_writes_sigmas(cloud_file, tmp_path):
    out = tmp_path / "a.las"
    assert (
        main(
            [
                "-q",
                "accuracy",
                str(cloud_file),
                "--out",
                str(out),
                "--pa",
                "axis",
                "--sigma-xyz",
                "0.01",
                "0.02",
                "0.03",
                "--full-covariance",
            ]
        )
        == 0
    )
    c = read_las(out)
    assert np.allclose(c.attributes["SigmaX"], 0.01) and np.allclose(c.attributes["SigmaZ"], 0.03)
    assert np.allclose(c.attributes["CovYY"], 0.02**2) and np.allclose(c.attributes["CovXY"], 0)
    assert np.array_equal(c.xyz, read_las(cloud_file).xyz)


def test_tls_propagated_then_columns(cloud_file, tmp_path):
    out = tmp_path / "p.las"
    centre = read_las(cloud_file).xyz.mean(axis=0)
    rc = main(
        [
            "-q",
            "accuracy",
            str(cloud_file),
            "--out",
            str(out),
            "--pa",
            "propagated",
            "--scanner-spec",
            "riegl-vz400",
            "--scanner-position",
            str(centre[0] - 30),
            str(centre[1]),
            str(centre[2]),
        ]
    )
    assert rc == 0
    c = read_las(out)
    s = np.column_stack([c.attributes[k] for k in ("SigmaX", "SigmaY", "SigmaZ")])
    assert np.all(np.isfinite(s)) and np.all(s > 0)
    # the same numbers as the core models on the same points
    from slipmap.core.accuracy import (
        SCANNERS,
        covariance_to_sigmas,
        footprint_covariance,
        tls_covariance,
        total_covariance,
    )

    pos = centre - [30, 0, 0]
    spec = SCANNERS["riegl-vz400"]
    pts = read_las(cloud_file).xyz
    want = covariance_to_sigmas(
        total_covariance(
            tls_covariance(pts, pos, spec),
            footprint_covariance(pts, np.broadcast_to(pos, pts.shape), spec),
        )
    )
    assert np.allclose(s, want, rtol=1e-9, atol=1e-12)
    assert np.median(s) > 0.9 * spec.range_sigma_m / np.sqrt(3)


def test_bad_settings_exit_2(cloud_file, tmp_path, capsys):
    rc = main(["accuracy", str(cloud_file), "--out", str(tmp_path / "x.las"), "--pa", "columns"])
    assert rc == 2 and "SigmaX" in capsys.readouterr().err
    rc = main(["accuracy", str(cloud_file), "--out", str(tmp_path / "x.las"), "--pa", "propagated"])
    assert rc == 2 and "scanner" in capsys.readouterr().err
    cfg = tmp_path / "pa.json"
    cfg.write_text(json.dumps({"before": {"model": "constant", "sigmaa": 1}}))
    rc = main(
        ["accuracy", str(cloud_file), "--out", str(tmp_path / "x.las"), "--pa-config", str(cfg)]
    )
    assert rc == 2 and "sigmaa" in capsys.readouterr().err
    rc = main(["accuracy", str(cloud_file), "--out", str(cloud_file)])
    assert rc == 2 and "input" in capsys.readouterr().err


def test_propagated_mobile_with_sbet_and_smrmsg(tmp_path):
    """An ALS flight line written as SBET, the real SMRMSG accuracy file, a LAS with GpsTime
    and ScanAngle: the CLI gives the core model's covariances for the same inputs."""
    import pyproj

    from slipmap.core.accuracy import SCANNERS, covariance_to_sigmas, georeferencing_covariance
    from slipmap.core.io.trajectory import read_smrmsg

    data = Path(__file__).resolve().parents[1] / "data"
    acc = read_smrmsg(data / "smrmsg.smrmsg")
    t0 = float(acc.time_s[0]) + 100.0
    utm = pyproj.CRS.from_epsg(32610)
    # platform flies north along x = 500000 at 500 m, 50 m/s
    tt = t0 + np.arange(0, 40.0, 0.5)
    px, py, pz = np.full(tt.size, 500000.0), 4200000.0 + 50.0 * (tt - t0), np.full(tt.size, 500.0)
    to_geo = pyproj.Transformer.from_crs(utm, "EPSG:4979", always_xy=True)
    lon, lat, h = to_geo.transform(px, py, pz)
    rec = np.zeros((tt.size, 17))
    rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3] = tt, np.radians(lat), np.radians(lon), h
    sbet = tmp_path / "line.sbet"
    rec.astype("<f8").tofile(sbet)
    # ground points under the line, each seen when the platform passes
    rng = np.random.default_rng(1)
    gx = 500000.0 + rng.uniform(-200, 200, 3000)
    gy = 4200000.0 + rng.uniform(100, 1800, 3000)
    gz = rng.normal(0, 0.05, 3000)
    gt = t0 + (gy - 4200000.0) / 50.0
    scan = np.degrees(np.arctan2(gx - 500000.0, 500.0 - gz))
    las = tmp_path / "als.las"
    write_las(
        las,
        PointCloud(
            xyz=np.column_stack([gx, gy, gz]),
            attributes={"GpsTime": gt, "ScanAngle": scan},
            crs=utm,
        ),
    )
    out = tmp_path / "pa.las"
    rc = main(
        [
            "-q",
            "accuracy",
            str(las),
            "--out",
            str(out),
            "--pa",
            "propagated",
            "--trajectory",
            str(sbet),
            "--trajectory-accuracy",
            str(data / "smrmsg.smrmsg"),
            "--scanner-spec",
            "leica-als60",
            "--no-footprint",
        ]
    )
    assert rc == 0
    c = read_las(out)
    got = np.column_stack([c.attributes[k] for k in ("SigmaX", "SigmaY", "SigmaZ")])
    # the core model on the same (read-back) inputs
    a = acc.interpolate(c.attributes["GpsTime"])
    plat = np.column_stack(
        [
            np.full(len(c), 500000.0),
            4200000.0 + 50.0 * (c.attributes["GpsTime"] - t0),
            np.full(len(c), 500.0),
        ]
    )
    want = covariance_to_sigmas(
        georeferencing_covariance(
            platform_xyz=plat,
            roll=np.zeros(len(c)),
            pitch=np.zeros(len(c)),
            heading=np.zeros(len(c)),
            range_m=np.linalg.norm(c.xyz - plat, axis=1),
            scan_angle_rad=np.radians(c.attributes["ScanAngle"]),
            sigma_position_m=np.column_stack([a["east_m"], a["north_m"], a["down_m"]]),
            sigma_attitude_rad=np.column_stack([a["roll_rad"], a["pitch_rad"], a["heading_rad"]]),
            spec=SCANNERS["leica-als60"],
        )
    )
    assert np.allclose(got, want, rtol=1e-3)  # platform positions went through geodetic coords
    assert np.all(got[:, 2] > 0.0) and np.median(got[:, 2]) < 0.5


def test_propagated_without_gpstime_is_exit_2(cloud_file, tmp_path, capsys):
    data = Path(__file__).resolve().parents[1] / "data"
    rc = main(
        [
            "accuracy",
            str(cloud_file),
            "--out",
            str(tmp_path / "x.las"),
            "--pa",
            "propagated",
            "--trajectory",
            str(data / "smrmsg.txt"),
            "--trajectory-accuracy",
            str(data / "smrmsg.smrmsg"),
            "--scanner-spec",
            "leica-als60",
        ]
    )
    assert rc == 2 and "GpsTime" in capsys.readouterr().err
