"""``slipmap displacement`` and the default demo: outputs equal the core's, clear errors."""

import json
import math

import numpy as np
import pyproj
import pytest

from slipmap.cli import main
from slipmap.core.displacement import estimate_slip
from slipmap.core.io.las import PointCloud, read_las, write_las
from slipmap.core.synthetic import SurveyError, make_fault_pair

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
        "right_lateral",
        "sigma_right_lateral",
        "opening",
        "sigma_opening",
        "right_lateral_slip",
    ):
        assert key in js["relative"]
    assert not [k for k in js["relative"] if k.startswith(("fault_", "sigma_fault_"))]
    assert js["fault"]["buffer_m"] == 10.0
    # the same numbers as the core on the same points: the stored (1 mm quantised)
    # coordinates, ground excluded as the CLI does
    b, a = (read_las(p) for p in (before, after))
    keep_b = b.attributes["Classification"] != 2
    keep_a = a.attributes["Classification"] != 2
    from slipmap.core.io.vector import read_fault_trace

    # the trace the CLI used: through WGS 84 and back (sub-micrometre changes, which move
    # points across the buffer's edge and so change the segmentation's inputs)
    trace = read_fault_trace(fault, target_crs=UTM10)
    core = estimate_slip(
        b.xyz[keep_b],
        a.xyz[keep_a],
        trace,
        sigma_before=0.02,
        sigma_after=0.02,
    ).components()
    assert js["relative"]["right_lateral_slip"] == pytest.approx(
        core["right_lateral_slip"], abs=1e-9
    )
    assert js["relative"]["sigma_right_lateral"] == pytest.approx(
        core["sigma_fault_parallel"], rel=1e-3
    )
    # the default full model: components per side, the white σ beside the model's
    assert js["parameters"]["stochastic_model"] == "full"
    assert 0 < js["relative"]["sigma_right_lateral_white"] < js["relative"]["sigma_right_lateral"]
    for side in ("left", "right"):
        vc = js[side]["variance_components"]
        assert vc["model"] == "full" and 1.0 <= vc["n_eff"] <= vc["n_planes"]
        white = vc["components"]["white"]
        assert white["sigma_m"] == pytest.approx(0.02, rel=0.05)  # the scene's 2 cm noise
        for name in ("plane", "spatial"):
            c = vc["components"][name]
            assert c["source"] in ("estimated", "prior") and 0.0 <= c["sigma_m"] < 0.01
        for name in ("unit_before", "unit_after"):  # PointSourceId all 0: no units
            assert vc["components"][name]["source"] == "off"
        assert js[side]["sigma_white_dy"] > 0
    acq = js["parameters"]["acquisition_unit_sources"]
    assert acq["units_option"] == "auto"
    assert acq["before"] == {
        "source": "none",
        "n_units": 0,
        "note": "auto: PointSourceId has a single value",
    }
    html = (out / "report.html").read_text()
    for text in ("Stochastic model", "n_eff", "white noise only", "unit_before", "down-weighted"):
        assert text in html, text
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
    """The demo's epochs carry 3 mm of MLS drift and PointSourceId: the full model reads the
    passes as units and its σ covers the error, which the white σ does not."""
    from slipmap.core.io.las import read_las

    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    js = json.loads((out / "displacement.json").read_text())
    rel = js["relative"]
    err = rel["right_lateral_slip"] - 0.0181
    assert abs(err) < 3 * rel["sigma_right_lateral"]
    assert abs(err) < 0.006  # a few mm of drift, not a blunder
    assert rel["sigma_right_lateral_white"] < 0.25 * rel["sigma_right_lateral"]
    acq = js["parameters"]["acquisition_unit_sources"]
    for epoch in ("before", "after"):
        assert acq[epoch]["source"] == "PointSourceId" and acq[epoch]["n_units"] > 1
        cloud = read_las(out / f"demo_{epoch}.laz")
        assert {"PointSourceId", "GpsTime"} <= set(cloud.attributes)
    assert js["left"]["variance_components"]["components"]["unit_before"]["source"] != "off"
    text = capsys.readouterr().err
    assert "recovered right-lateral slip" in text and "white noise only" in text
    assert "left side:" in text and "n_eff" in text and "unit_after" in text


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
    # each strip's own motion, + = dextral: the right (east) side moved 18.1 mm south
    assert right and all(abs(s["right_lateral"] - 0.0181) < 0.002 for s in right)
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


# --------------------------------------------------------------------------- stochastic model


@pytest.fixture(scope="module")
def drift_files(tmp_path_factory):
    """A small pair with 3 mm of MLS drift; the LAS files carry PointSourceId and GpsTime."""
    d = tmp_path_factory.mktemp("drift")
    err = SurveyError(kind="mls", level_m=0.003)
    fp = make_fault_pair(
        "mls",
        seed=11,
        origin=ORIGIN,
        n_buildings=4,
        extent_m=70.0,
        right_offset_m=(0.0, -0.0181, 0.0),
        error_before=err,
        error_after=err,
    )
    paths = []
    for name, sc, src, gps in (
        ("before", fp.before, fp.source_before, fp.gps_time_before),
        ("after", fp.after, fp.source_after, fp.gps_time_after),
    ):
        p = d / f"{name}.laz"
        attrs = {"Classification": sc.classification, "PointSourceId": src, "GpsTime": gps}
        write_las(p, PointCloud(xyz=sc.points, attributes=attrs, crs=UTM10))
        paths.append(p)
    fault = d / "fault.geojson"
    _geojson(fault, fp.trace_xy)
    return fp, paths, fault


def _run(paths, fault, out, *extra, quiet=False):
    argv = ["displacement", str(paths[0]), str(paths[1]), "--fault", str(fault)]
    return main(["-q"] * quiet + argv + ["--out", str(out), "--sigma", "0.02", *extra])


def _core_on_files(fault, paths, **kw):
    """The core on exactly what the CLI reads: stored coordinates, the trace from the file."""
    from slipmap.core.io.vector import read_fault_trace

    b, a = (read_las(p) for p in paths)
    kb, ka = b.attributes["Classification"] != 2, a.attributes["Classification"] != 2
    trace = read_fault_trace(fault, target_crs=b.crs)
    if kw.get("unit_before") is not None and kw.pop("times", True):
        # the job gives the full model the units' GpsTime (the unit_drift option, default on)
        kw.update(
            unit_time_before=b.attributes["GpsTime"][kb],
            unit_time_after=a.attributes["GpsTime"][ka],
        )
    kw.pop("times", None)
    res = estimate_slip(b.xyz[kb], a.xyz[ka], trace, sigma_before=0.02, sigma_after=0.02, **kw)
    return res, b.attributes["PointSourceId"][kb], a.attributes["PointSourceId"][ka]


def test_units_auto_reads_point_source_id(drift_files, tmp_path, capsys):
    """--units auto (the default) takes PointSourceId (3 MLS passes per epoch); the JSON
    equals the core with those units, with finite components, and strict JSON."""
    fp, paths, fault = drift_files
    out = tmp_path / "auto"
    assert _run(paths, fault, out) == 0
    logs = capsys.readouterr().err
    text = (out / "displacement.json").read_text()
    js = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in displacement.json"))
    _, ub, ua = _core_on_files(fault, paths)
    core, _, _ = _core_on_files(fault, paths, unit_before=ub, unit_after=ua)
    comp = core.components()
    rel = js["relative"]
    assert rel["right_lateral_slip"] == pytest.approx(comp["right_lateral_slip"], abs=1e-9)
    assert rel["sigma_right_lateral"] == pytest.approx(comp["sigma_fault_parallel"], rel=1e-6)
    assert rel["sigma_right_lateral_white"] == pytest.approx(
        comp["sigma_fault_parallel_white"], rel=1e-6
    )
    acq = js["parameters"]["acquisition_unit_sources"]
    assert acq["before"] == {
        "source": "PointSourceId", "n_units": 3, "note": "auto", "gps_time": True
    }  # fmt: skip
    assert acq["unit_drift"] is True
    assert acq["after"]["n_units"] == int(np.unique(ua).size) == 3
    assert js["parameters"]["acquisition_units"] == {"before": 3, "after": 3}
    for side in ("left", "right"):
        vc = js[side]["variance_components"]
        for name, c in vc["components"].items():
            assert c["source"] in ("estimated", "prior", "fixed", "off"), name
            assert np.isfinite(c["sigma_m"]) and 0.0 <= c["sigma_m"] < 0.05, name
        assert vc["components"]["unit_before"]["source"] != "off"
        # the knot spacing of the units' drift (null: rigid units), as the core chose it
        spacing = getattr(core, side).rigid.variance_components.unit_interval_s
        assert vc["unit_drift_interval_s"] == (spacing if math.isfinite(spacing) else None)
        assert np.isfinite(vc["n_eff"]) and 1.0 <= vc["n_eff"] <= vc["n_planes"]
        assert all(np.isfinite(v) for v in vc["sigma_white_m"])
    assert "before epoch (before.laz): 3 acquisition unit(s) from PointSourceId" in logs
    assert "white noise only" in logs and "n_eff" in logs
    # the GeoPackage of planes carries the per-plane weights and tests
    from slipmap.core.io.vector import read_gpkg_layer

    _, fields = read_gpkg_layer(out / "displacement.gpkg", "planes_left")
    assert {"weight", "w_test", "offset_mm", "misclosure_mm"} <= set(fields)
    w = np.asarray(fields["weight"], dtype=float)
    assert len(w) == len(core.left.matches)
    np.testing.assert_allclose(
        w[: core.left.rigid.plane_weights.size], core.left.rigid.plane_weights, equal_nan=True
    )


def test_units_gps_time_segments_nest_in_the_passes(drift_files, tmp_path):
    """--units gps-time --gps-gap 2: the MLS passes are separated by turns of several
    seconds, so every GPS-time segment lies within one pass (ground-only stretches of a pass,
    left out, split it further); the result is the core's with those segments."""
    from slipmap.app.stochasticmodel import gps_time_segments

    fp, paths, fault = drift_files
    out = tmp_path / "gps"
    assert _run(paths, fault, out, "--units", "gps-time", "--gps-gap", "2") == 0
    js = json.loads((out / "displacement.json").read_text())
    acq = js["parameters"]["acquisition_unit_sources"]
    # the options' own spelling of the choice (every face records the same)
    assert acq["units_option"] == "GpsTime" and acq["gps_gap_s"] == 2.0
    segs = []
    for p in paths:
        c = read_las(p)
        keep = c.attributes["Classification"] != 2
        seg = gps_time_segments(c.attributes["GpsTime"][keep], 2.0)
        pss = c.attributes["PointSourceId"][keep]
        assert all(np.unique(pss[seg == k]).size == 1 for k in np.unique(seg))
        assert np.unique(seg).size >= np.unique(pss).size
        segs.append(seg)
    assert acq["before"] == {
        "source": "GpsTime", "n_units": int(np.unique(segs[0]).size), "gps_time": True
    }  # fmt: skip
    assert acq["after"] == {
        "source": "GpsTime", "n_units": int(np.unique(segs[1]).size), "gps_time": True
    }  # fmt: skip
    core, _, _ = _core_on_files(fault, paths, unit_before=segs[0], unit_after=segs[1])
    assert js["relative"]["right_lateral_slip"] == pytest.approx(
        core.components()["right_lateral_slip"], abs=1e-9
    )


def test_no_unit_drift_keeps_one_rigid_error_per_unit(drift_files, tmp_path):
    """--no-unit-drift: the units' GpsTime is not used; the result is the core's with rigid
    units (no times), the record says so and the report has no knot spacing."""
    fp, paths, fault = drift_files
    out = tmp_path / "rigid"
    assert _run(paths, fault, out, "--no-unit-drift") == 0
    js = json.loads((out / "displacement.json").read_text())
    acq = js["parameters"]["acquisition_unit_sources"]
    assert acq["unit_drift"] is False and acq["before"]["gps_time"] is False
    _, ub, ua = _core_on_files(fault, paths)
    core, _, _ = _core_on_files(fault, paths, unit_before=ub, unit_after=ua, times=False)
    comp = core.components()
    assert js["relative"]["sigma_right_lateral"] == pytest.approx(
        comp["sigma_fault_parallel"], rel=1e-6
    )
    assert "unit_drift_interval_s" not in js["left"]["variance_components"]


def test_no_unit_contrasts_leaves_the_units_untied(drift_files, tmp_path):
    """--no-unit-contrasts: no plane ties two units in one epoch; the result is the core's
    with unit_contrasts=False and the record says so. By default the report says how many
    shared planes tied the units, as the core counted them."""
    fp, paths, fault = drift_files
    out = tmp_path / "untied"
    assert _run(paths, fault, out, "--no-unit-contrasts") == 0
    js = json.loads((out / "displacement.json").read_text())
    assert js["parameters"]["acquisition_unit_sources"]["unit_contrasts"] is False
    _, ub, ua = _core_on_files(fault, paths)
    core, _, _ = _core_on_files(fault, paths, unit_before=ub, unit_after=ua, unit_contrasts=False)
    comp = core.components()
    assert js["relative"]["right_lateral_slip"] == pytest.approx(
        comp["right_lateral_slip"], abs=1e-9
    )
    assert js["relative"]["sigma_right_lateral"] == pytest.approx(
        comp["sigma_fault_parallel"], rel=1e-6
    )
    for side in ("left", "right"):
        assert "unit_contrasts" not in js[side]["variance_components"]
    out = tmp_path / "tied"
    assert _run(paths, fault, out) == 0
    js = json.loads((out / "displacement.json").read_text())
    assert js["parameters"]["acquisition_unit_sources"]["unit_contrasts"] is True
    core, _, _ = _core_on_files(fault, paths, unit_before=ub, unit_after=ua)
    for side in ("left", "right"):
        n = getattr(core, side).rigid.variance_components.n_contrasts
        got = js[side]["variance_components"].get("unit_contrasts")
        assert min(n) > 0 and (got["before"], got["after"]) == n  # walls seen from two passes


def test_units_none_and_white_model(drift_files, tmp_path, capsys):
    fp, paths, fault = drift_files
    out = tmp_path / "none"
    assert _run(paths, fault, out, "--units", "none") == 0
    js = json.loads((out / "displacement.json").read_text())
    assert js["parameters"]["acquisition_unit_sources"]["before"]["source"] == "none"
    assert js["left"]["variance_components"]["components"]["unit_before"]["source"] == "off"
    out = tmp_path / "white"
    capsys.readouterr()
    assert _run(paths, fault, out, "--stochastic-model", "white", "--units", "gps-time") == 0
    logs = capsys.readouterr().err
    js = json.loads((out / "displacement.json").read_text())
    assert js["parameters"]["stochastic_model"] == "white"
    assert "variance_components" not in js["left"]
    assert "sigma_right_lateral_white" not in js["relative"]
    assert "units option (GpsTime) is not used by the white model" in logs
    assert "white noise only" not in logs
    core, _, _ = _core_on_files(fault, paths, stochastic_model="white")
    assert js["relative"]["sigma_right_lateral"] == pytest.approx(
        core.components()["sigma_fault_parallel"], rel=1e-6
    )


def test_fixed_component_reaches_the_core(drift_files, tmp_path):
    fp, paths, fault = drift_files
    out = tmp_path / "fixed"
    argv = ["--stochastic-model", "plane", "--fixed-component", "plane=0.002"]
    assert _run(paths, fault, out, *argv) == 0
    js = json.loads((out / "displacement.json").read_text())
    assert js["parameters"]["components"] == {"plane": 0.002}
    for side in ("left", "right"):
        comps = js[side]["variance_components"]["components"]
        assert comps["plane"] == {"sigma_m": 0.002, "sd_m": None, "source": "fixed"}
        assert comps["unit_before"]["source"] == "off"  # the plane model has no units


def test_gps_time_units_on_a_file_without_gps_time_is_exit_2(drift_files, tmp_path, capsys):
    """Point format 0 has no GpsTime: --units gps-time is a one-line error naming --units."""
    import laspy

    fp, paths, fault = drift_files
    las = laspy.read(paths[1])
    no_gps = tmp_path / "after_pf0.las"
    laspy.convert(las, point_format_id=0).write(no_gps)
    out = tmp_path / "o"
    rc = _run([paths[0], no_gps], fault, out, "--units", "gps-time", quiet=True)
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "--units: GpsTime" in err[0] and "after epoch (after_pf0.las)" in err[0]
    assert "no GpsTime dimension" in err[0]
    assert not (out / "displacement.json").exists()


@pytest.mark.parametrize(
    "values, words",
    [
        (["plane"], ("--fixed-component", "NAME=SIGMA_M")),
        (["plane="], ("--fixed-component", "NAME=SIGMA_M")),
        (["bogus=0.001"], ("--fixed-component", "bogus", "unit_before")),
        (["plane=abc"], ("--fixed-component", "plane must be a number")),
        (["plane=-0.001"], ("--fixed-component", ">= 0")),
        (["spatial_range_m=0"], ("--fixed-component", "> 0")),
        (["plane=nan"], ("--fixed-component", "finite")),
        (["plane=0.001,plane=0.002"], ("--fixed-component", "plane is given twice")),
    ],
)
def test_bad_fixed_component_is_exit_2(files, tmp_path, capsys, values, words):
    _, (before, after), fault = files
    argv = ["displacement", str(before), str(after), "--fault", str(fault)]
    argv += ["--out", str(tmp_path / "o")]
    for v in values:
        argv += ["--fixed-component", v]
    with pytest.raises(SystemExit) as raised:
        main(argv)
    assert raised.value.code == 2
    err = capsys.readouterr().err
    for word in words:
        assert word in err, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--fixed-component", "plane=0.001", "--fixed-component", "plane=0.002"], ("twice",)),
        (["--stochastic-model", "white", "--fixed-component", "plane=0.001"], ("white",)),
    ],
)
def test_inconsistent_fixed_components_are_exit_2(files, tmp_path, capsys, extra, words):
    _, (before, after), fault = files
    argv = ["displacement", str(before), str(after), "--fault", str(fault)]
    rc = main(argv + ["--out", str(tmp_path / "o"), *extra])
    assert rc == 2
    err = capsys.readouterr().err
    assert "--fixed-component" in err and all(w in err for w in words), err


@pytest.mark.parametrize(
    "argv, word",
    [
        (["--stochastic-model", "red"], "--stochastic-model"),
        (["--units", "strips"], "--units"),
        (["--gps-gap", "0"], "--gps-gap"),
    ],
)
def test_bad_stochastic_options_are_exit_2(files, tmp_path, capsys, argv, word):
    _, (before, after), fault = files
    with pytest.raises(SystemExit) as raised:
        main(["displacement", str(before), str(after), "--fault", str(fault), "--out", "o"] + argv)
    assert raised.value.code == 2
    assert word in capsys.readouterr().err


def test_help_names_the_models_and_units(capsys):
    with pytest.raises(SystemExit):
        main(["displacement", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for word in (
        "--stochastic-model {white,plane,full}",
        "--units {auto,point-source-id,gps-time,none}",
        "--gps-gap S",
        "--fixed-component NAME=SIGMA_M",
        "white: independent point errors only",
        "plane: white noise plus one random offset per plane",
        "full: plane plus spatially correlated",
    ):
        assert word in text, word
