"""filters.python contract of the point-accuracy stage (pdal_filters/accuracy.py)."""

import json
from pathlib import Path

import numpy as np
import pyproj
import pytest
from pdal_harness import call, load_stage, make_ins, nodes, parse_add_dimension

from slipmap.core.accuracy import (
    SCANNERS,
    covariance_to_sigmas,
    covariance_to_six,
    footprint_covariance,
    georeferencing_covariance,
    tls_covariance,
)
from slipmap.core.io.trajectory import read_smrmsg
from slipmap.pdal_filters._stage import StageError

SIG = parse_add_dimension(["SigmaX", "SigmaY", "SigmaZ"])
FULL = parse_add_dimension(
    ["SigmaX", "SigmaY", "SigmaZ", "CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ"]
)
DATA = Path(__file__).resolve().parents[1] / "data"
UTM = pyproj.CRS.from_epsg(32610)


def stage(pdalargs=None, srs=""):
    return load_stage("accuracy", pdalargs, spatialreference=srs)


def _sigmas(outs):
    return np.column_stack([outs[k] for k in ("SigmaX", "SigmaY", "SigmaZ")])


@pytest.fixture(scope="module")
def pts():
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 30, (2000, 2))
    z = 0.2 * np.sin(xy[:, 0]) + 0.1 * xy[:, 1]
    return np.column_stack([xy, z]) + [500000.0, 4200000.0, 10.0]


@pytest.mark.parametrize("as_json", [False, True])
def test_constant_and_axis(pts, as_json):
    args = {"model": "constant", "sigma": 0.03}
    outs = call(stage(json.dumps(args) if as_json else args), make_ins(pts), SIG)
    assert set(outs) == set(SIG)
    np.testing.assert_allclose(_sigmas(outs), 0.03, rtol=0, atol=1e-15)
    for value in ([0.01, 0.02, 0.05], "0.01,0.02,0.05", "[0.01, 0.02, 0.05]"):
        outs = call(stage({"model": "axis", "sigma_xyz": value}), make_ins(pts), SIG)
        np.testing.assert_allclose(_sigmas(outs), [[0.01, 0.02, 0.05]] * len(pts), atol=1e-15)


def test_columns_model_reads_named_dimensions(pts):
    rng = np.random.default_rng(2)
    s = rng.uniform(0.005, 0.05, (len(pts), 3))
    ins = make_ins(pts, SX=s[:, 0], SY=s[:, 1], SZ=s[:, 2])
    outs = call(stage({"model": "columns", "columns": "SX,SY,SZ"}), ins, SIG)
    np.testing.assert_allclose(_sigmas(outs), s, rtol=1e-15)
    with pytest.raises(StageError, match="SigmaX"):  # default names are absent
        call(stage({"model": "columns"}), ins, SIG)


def test_tls_propagated_equals_core_with_full_covariance(pts):
    pos = [500015.0, 4199990.0, 12.0]
    args = {
        "model": "propagated",
        "scanner": "riegl-vz400",
        "scanner_position": pos,
        "full_covariance": True,
    }
    outs = call(stage(args), make_ins(pts), FULL)
    spec = SCANNERS["riegl-vz400"]
    sensors = np.broadcast_to(np.asarray(pos), pts.shape)
    want = tls_covariance(pts, np.asarray(pos), spec) + footprint_covariance(pts, sensors, spec)
    np.testing.assert_allclose(_sigmas(outs), covariance_to_sigmas(want), rtol=1e-12)
    got6 = np.column_stack(
        [outs[k] for k in ("CovXX", "CovYY", "CovZZ", "CovXY", "CovXZ", "CovYZ")]
    )
    np.testing.assert_allclose(got6, covariance_to_six(want), rtol=1e-12, atol=1e-18)


def test_mobile_propagated_reads_gpstime_scanangle_and_srs(tmp_path):
    """An ALS line as SBET + the real SMRMSG: the stage equals the core model, with the
    platform taken through geodetic coordinates into the view's spatial reference."""
    acc = read_smrmsg(DATA / "smrmsg.smrmsg")
    t0 = float(acc.time_s[0]) + 100.0
    tt = t0 + np.arange(0, 40.0, 0.5)
    px, py, pz = np.full(tt.size, 500000.0), 4200000.0 + 50.0 * (tt - t0), np.full(tt.size, 500.0)
    lon, lat, h = pyproj.Transformer.from_crs(UTM, "EPSG:4979", always_xy=True).transform(
        px, py, pz
    )
    rec = np.zeros((tt.size, 17))
    rec[:, 0], rec[:, 1], rec[:, 2], rec[:, 3] = tt, np.radians(lat), np.radians(lon), h
    sbet = tmp_path / "line.sbet"
    rec.astype("<f8").tofile(sbet)
    rng = np.random.default_rng(1)
    n = 1500
    g = np.column_stack(
        [500000.0 + rng.uniform(-200, 200, n), 4200000.0 + rng.uniform(100, 1800, n), np.zeros(n)]
    )
    gt = t0 + (g[:, 1] - 4200000.0) / 50.0
    scan = np.degrees(np.arctan2(g[:, 0] - 500000.0, 500.0 - g[:, 2]))
    ins = make_ins(g, GpsTime=gt, ScanAngleRank=scan)
    args = {
        "model": "propagated",
        "trajectory": str(sbet),
        "trajectory_accuracy": str(DATA / "smrmsg.smrmsg"),
        "scanner": "leica-als60",
        "footprint": False,
    }
    outs = call(stage(args, srs=UTM.to_wkt()), ins, SIG)
    a = acc.interpolate(gt)
    plat = np.column_stack([np.full(n, 500000.0), 4200000.0 + 50.0 * (gt - t0), np.full(n, 500.0)])
    want = covariance_to_sigmas(
        georeferencing_covariance(
            platform_xyz=plat,
            roll=np.zeros(n),
            pitch=np.zeros(n),
            heading=np.zeros(n),
            range_m=np.linalg.norm(g - plat, axis=1),
            scan_angle_rad=np.radians(scan),
            sigma_position_m=np.column_stack([a["east_m"], a["north_m"], a["down_m"]]),
            sigma_attitude_rad=np.column_stack([a["roll_rad"], a["pitch_rad"], a["heading_rad"]]),
            spec=SCANNERS["leica-als60"],
        )
    )
    np.testing.assert_allclose(_sigmas(outs), want, rtol=1e-3)
    # without a spatial reference the geodetic trajectory cannot be placed
    with pytest.raises(StageError, match="no CRS"):
        call(stage(args), ins, SIG)


def test_empty_view_and_no_pdalargs():
    outs = call(stage(None), make_ins(np.empty((0, 3))), SIG)
    assert all(outs[k].shape == (0,) and outs[k].dtype == np.float64 for k in SIG)


@pytest.mark.parametrize(
    "args, match",
    [
        ({"model": "kalman"}, "model"),
        ({"sigma": 0}, "sigma"),
        ({"model": "axis"}, "sigma-xyz|sigma_xyz"),
        ({"model": "axis", "sigma_xyz": "1,2"}, "sigma_xyz"),
        ({"model": "axis", "sigma_xyz": [0.1, -1, 0.1]}, "sigma_xyz"),
        ({"model": "columns", "columns": "A,B"}, "columns"),
        ({"model": "propagated"}, "scanner"),
        ({"model": "propagated", "scanner": "nope-9000", "scanner_position": [0, 0, 0]}, "nope"),
        ({"footprint": "sometimes"}, "footprint"),
        ({"sigma_x": 0.1}, "sigma_x"),
    ],
)
def test_bad_options_name_the_option(pts, args, match):
    with pytest.raises(StageError, match=match):
        call(stage(args), make_ins(pts), SIG)


def test_only_declared_dimensions_written(pts):
    """Without full_covariance nothing but SigmaX/Y/Z is written (PDAL rejects undeclared)."""
    outs = call(stage({"sigma": 0.02}), make_ins(pts), SIG)
    assert set(outs) == {"SigmaX", "SigmaY", "SigmaZ"}


def test_accuracy_then_displacement_uses_per_point_sigmas():
    """The chain of the pipelines: the accuracy stage writes SigmaX/Y/Z, the displacement
    stage reads them (sigma_dimensions) and equals the core run with those per-point sigmas."""
    from slipmap.core.displacement import estimate_slip
    from slipmap.core.fault import fault_trace
    from slipmap.core.synthetic import make_fault_pair

    fp = make_fault_pair(
        "mls", seed=7, origin=(500000.0, 4200000.0, 10.0), vegetation=False, density_pts_m2=30.0
    )
    nb = len(fp.before.points)
    pts = np.vstack([fp.before.points, fp.after.points])
    tag = np.r_[np.ones(nb), np.full(len(fp.after.points), 2.0)]
    rng = np.random.default_rng(0)
    s = rng.uniform(0.01, 0.04, (len(pts), 3))
    ins = make_ins(pts, Epoch=tag, SX=s[:, 0], SY=s[:, 1], SZ=s[:, 2])
    acc = call(stage({"model": "columns", "columns": ["SX", "SY", "SZ"]}), ins, SIG)
    ins.update(acc)
    (x0, y0), (x1, y1) = (map(float, v) for v in fp.trace_xy)  # plain floats for the WKT
    disp = load_stage(
        "displacement",
        {
            "trace": f"LINESTRING ({x0!r} {y0!r}, {x1!r} {y1!r})",
            "sigma_dimensions": "SigmaX,SigmaY,SigmaZ",
        },
    )
    call(disp, ins, parse_add_dimension(["PlaneId=int32", "Residual"]))
    summary = nodes(disp)["summary"]
    core = estimate_slip(
        fp.before.points,
        fp.after.points,
        fault_trace([fp.trace_xy]),
        sigma_before=s[:nb],
        sigma_after=s[nb:],
    )
    from slipmap.app.slip import summary_payload
    from slipmap.app.summaries import json_safe

    # the job records every option it passed (defaults spelled out); the results are the same,
    # in the sign convention every face writes (docs/methods.md)
    params = summary.pop("parameters")
    expect = json_safe(summary_payload(core))
    core_params = expect.pop("parameters")
    assert summary == expect
    for key in ("buffer_m", "combine", "stochastic_model"):
        assert params[key] == core_params[key]
    with pytest.raises(StageError, match="sigma_dimensions"):
        bad = load_stage(
            "displacement",
            {"trace": f"LINESTRING ({x0!r} {y0!r}, {x1!r} {y1!r})", "sigma_dimensions": "A,B,C"},
        )
        call(bad, ins, parse_add_dimension(["PlaneId=int32", "Residual"]))
