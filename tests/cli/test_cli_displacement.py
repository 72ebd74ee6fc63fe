"""``slipmap displacement`` and the default demo: outputs equal the core's, clear errors."""

import json

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.synthetic import make_fault_pair

pytest.importorskip("osgeo.ogr", reason="GDAL/OGR (python3-gdal) missing")

ORIGIN = (498000.0, 4234000.0, 20.0)
UTM10 = pyproj.CRS.from_epsg(32610)


def _geojson(path, xy_utm, geometry="LineString"):
    tr = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(xy_utm[:, 0], xy_utm[:, 1])
    coords = [[a, b] for a, b in zip(lon, lat)]
    if geometry == "Polygon":
        coords = [coords + [coords[0]]]
    feature = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": geometry, "coordinates": coords},
    }
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [feature]}))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("epochs")
    fp = make_fault_pair("mls", seed=7, origin=ORIGIN, right_offset_m=(0.0, -0.0181, 0.0))
    paths = []
    for name, sc in (("before", fp.before), ("after", fp.after)):
        p = d / f"{name}.laz"
        write_las(
            p,
            PointCloud(xyz=sc.points, attributes={"Classification": sc.classification}, crs=UTM10),
        )
        paths.append(p)
    fault = d / "fault.geojson"
    _geojson(fault, fp.trace_xy)
    return fp, paths, fault


def test_displacement_outputs_match_core(files, tmp_path):
    fp, (before, after), fault = files
    out = tmp_path / "out"
    rc = main(
        [
            "-q",
            "displacement",
            str(before),
            str(after),
            "--fault",
            str(fault),
            "--out",
            str(out),
            "--sigma",
            "0.02",
        ]
    )
    assert rc == 0
    js = json.loads((out / "displacement.json").read_text())
    for key in ("left", "right", "relative", "fault", "parameters", "runtime_s"):
        assert key in js
    for key in (
        "dx",
        "sigma_dx",
        "rx",
        "centroid",
        "n_planes",
        "variance_factor",
        "iterations",
        "rejected_planes",
    ):
        assert key in js["left"]
    for key in (
        "horizontal",
        "sigma_horizontal",
        "fault_parallel",
        "sigma_fault_parallel",
        "fault_normal",
        "sigma_fault_normal",
        "right_lateral_slip",
    ):
        assert key in js["relative"]
    assert js["fault"]["buffer_m"] == 10.0
    # the same numbers as the core on the same points (ground excluded as the CLI does)
    keep_b = fp.before.classification != 2
    keep_a = fp.after.classification != 2
    core = estimate_slip(
        fp.before.points[keep_b],
        fp.after.points[keep_a],
        fault_trace([fp.trace_xy]),
        sigma_before=0.02,
        sigma_after=0.02,
    ).components()
    # the trace went through WGS 84 and back: sub-millimetre changes of the trace only
    assert js["relative"]["right_lateral_slip"] == pytest.approx(
        core["right_lateral_slip"], abs=2e-5
    )
    assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.001
    assert (out / "displacement.gpkg").is_file() and (out / "report.html").is_file()
    assert (out / "residuals.png").is_file() and (out / "plane_residuals.png").is_file()


def test_polygon_fault_is_exit_2(files, tmp_path, capsys):
    fp, (before, after), _ = files
    poly = tmp_path / "poly.geojson"
    _geojson(poly, np.array([[0, 0], [1, 0], [1, 1]]) + fp.trace_xy[0], geometry="Polygon")
    rc = main(
        [
            "displacement",
            str(before),
            str(after),
            "--fault",
            str(poly),
            "--out",
            str(tmp_path / "o"),
        ]
    )
    assert rc == 2
    assert "polygon" in capsys.readouterr().err.lower()
    assert not (tmp_path / "o").exists()


def test_default_demo_recovers_the_slip(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    js = json.loads((out / "displacement.json").read_text())
    assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.001
    assert "recovered right-lateral slip" in capsys.readouterr().err


def test_tiles_strips_and_windows_outputs(files, tmp_path):
    from osgeo import gdal

    from slipmap.core.io.vector import read_gpkg_layer

    _, (before, after), fault = files
    out = tmp_path / "tsw"
    argv = ["-q", "displacement", str(before), str(after), "--fault", str(fault), "--out", str(out)]
    argv += ["--sigma", "0.02", "--tile-size", "50", "--strip-width", "50"]
    argv += ["--reference-slip", "0.0181"]
    argv += ["--window-size", "40", "--window-step", "20"]
    assert main(argv) == 0
    js = json.loads((out / "displacement.json").read_text())
    assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.001
    right = [s for s in js["strips"] if s["side"] == "right" and s["status"] == "ok"]
    assert right and all(abs(s["fault_parallel"] + 0.0181) < 0.002 for s in right)
    geoms, fields = read_gpkg_layer(out / "displacement.gpkg", "tiles")
    assert len(geoms) >= 4 and {"dx", "sigma_dx", "side", "n_planes"} <= set(fields)
    assert len(read_gpkg_layer(out / "displacement.gpkg", "strips")[0]) == len(js["strips"])
    ds = gdal.Open(str(out / "windows_dy.tif"))
    assert ds.GetGeoTransform()[1] == 20.0 and ds.GetGeoTransform()[5] == -20.0
    assert "UTM zone 10N" in ds.GetProjection()
    dy = ds.GetRasterBand(1).ReadAsArray()
    assert np.nanmin(dy) == pytest.approx(-0.0181, abs=0.002)
    assert (out / "strips.png").is_file()
    ref = js["reference"]
    assert ref["delta_displacement"] == pytest.approx(
        js["relative"]["right_lateral_slip"] - 0.0181, abs=1e-12
    )
    assert {"scale", "relative_scale", "variance_left", "variance_right"} <= set(ref)


def test_second_epoch_in_another_crs_is_reprojected(files, tmp_path):
    from slipmap.core.io.las import read_las

    _, (before, after), fault = files
    utm11 = pyproj.CRS.from_epsg(32611)
    cloud = read_las(after)
    tr = pyproj.Transformer.from_crs(UTM10, utm11, always_xy=True)
    x, y = tr.transform(cloud.xyz[:, 0], cloud.xyz[:, 1])
    moved = tmp_path / "after_utm11.laz"
    write_las(
        moved,
        PointCloud(
            xyz=np.column_stack([x, y, cloud.xyz[:, 2]]),
            attributes={"Classification": cloud.attributes["Classification"]},
            crs=utm11,
        ),
    )
    out = tmp_path / "o"
    argv = ["-q", "displacement", str(before), str(moved), "--fault", str(fault), "--out", str(out)]
    assert main(argv + ["--sigma", "0.02"]) == 0
    js = json.loads((out / "displacement.json").read_text())
    # the LAS scale (1 mm) rounds the reprojected coordinates: a little extra noise only
    assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.0015


def test_point_accuracy_per_epoch(files, tmp_path):
    """--pa columns reads SigmaX/Y/Z written by `slipmap accuracy`; --pa-config sets a model
    per epoch; both give the slip, with the sigma scaled by the variance factor."""
    _, (before, after), fault = files
    with_sigma = []
    for name, path, s in (("b", before, "0.02"), ("a", after, "0.03")):
        out = tmp_path / f"{name}.laz"
        assert (
            main(
                [
                    "-q",
                    "accuracy",
                    str(path),
                    "--out",
                    str(out),
                    "--pa",
                    "axis",
                    "--sigma-xyz",
                    s,
                    s,
                    s,
                ]
            )
            == 0
        )
        with_sigma.append(out)
    out = tmp_path / "cols"
    argv = ["-q", "displacement", str(with_sigma[0]), str(with_sigma[1]), "--fault", str(fault)]
    assert main(argv + ["--out", str(out), "--pa", "columns"]) == 0
    cols = json.loads((out / "displacement.json").read_text())
    cfg = tmp_path / "pa.json"
    cfg.write_text(
        json.dumps(
            {
                "before": {"model": "constant", "sigma": 0.02},
                "after": {"model": "axis", "sigma_xyz": [0.03, 0.03, 0.03]},
            }
        )
    )
    out2 = tmp_path / "cfg"
    assert main(argv + ["--out", str(out2), "--pa-config", str(cfg)]) == 0
    conf = json.loads((out2 / "displacement.json").read_text())
    for js in (cols, conf):
        assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.001
    assert cols["relative"]["right_lateral_slip"] == pytest.approx(
        conf["relative"]["right_lateral_slip"], abs=1e-9
    )
    assert conf["parameters"]["point_accuracy"]["after"]["model"] == "axis"


def test_crs_option_for_files_without_one(files, tmp_path):
    """Epochs written without a CRS: --crs places them, so the WGS 84 trace is reprojected
    into it and the slip is recovered; without it the geographic trace is refused."""
    from slipmap.core.io.las import read_las

    fp, paths, fault = files
    bare = []
    for p in paths:
        c = read_las(p)
        q = tmp_path / f"bare_{p.name}"
        write_las(
            q, PointCloud(xyz=c.xyz, attributes={"Classification": c.attributes["Classification"]})
        )
        bare.append(q)
    argv = ["-q", "displacement", str(bare[0]), str(bare[1]), "--fault", str(fault)]
    assert main(argv + ["--out", str(tmp_path / "no"), "--sigma", "0.02"]) == 2
    assert (
        main(argv + ["--out", str(tmp_path / "o"), "--sigma", "0.02", "--crs", "EPSG:32610"]) == 0
    )
    js = json.loads((tmp_path / "o" / "displacement.json").read_text())
    assert abs(js["relative"]["right_lateral_slip"] - 0.0181) < 0.001
