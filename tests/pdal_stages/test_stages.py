"""filters.python contract of the SlipMap stages, run without PDAL (see pdal_harness)."""

import json

import numpy as np
import pytest
from pdal_harness import call, load_stage, make_ins, nodes, parse_add_dimension

from slipmap.core.displacement import estimate_slip
from slipmap.core.fault import fault_trace
from slipmap.core.planes import segment_planes
from slipmap.core.roughness import grid_roughness, roughness_per_point
from slipmap.core.synthetic import make_fault_pair, make_scene
from slipmap.pdal_filters._stage import StageError

PLANES = parse_add_dimension(["PlaneId=int32", "Planarity"])
ROUGH = parse_add_dimension("Roughness")
DISP = parse_add_dimension(["PlaneId=int32", "Residual"])
ORIGIN = (500000.0, 4200000.0, 10.0)


def stage(name, pdalargs=None, **kw):
    return load_stage(name, pdalargs, **kw)


@pytest.fixture(scope="module")
def scene():
    return make_scene("als", seed=3, n_buildings=3, extent_m=60.0, origin=ORIGIN)


@pytest.fixture(scope="module")
def pair():
    return make_fault_pair("mls", seed=7, origin=ORIGIN, vegetation=False, density_pts_m2=30.0)


def _trace_wkt(fp):
    (x0, y0), (x1, y1) = fp.trace_xy
    return f"LINESTRING ({float(x0)!r} {float(y0)!r}, {float(x1)!r} {float(y1)!r})"


def _epochs(fp):
    pts = np.vstack([fp.before.points, fp.after.points])
    tag = np.r_[np.ones(len(fp.before.points)), np.full(len(fp.after.points), 2.0)]
    return pts, tag


# --------------------------------------------------------------------------- planes


@pytest.mark.parametrize("as_json", [False, True])
def test_planes_equal_core(scene, as_json):
    args = {"min_plane_points": 40, "backend": "numpy"}
    mod = stage("planes", json.dumps(args) if as_json else args)
    outs = call(mod, make_ins(scene.points), PLANES)
    core = segment_planes(scene.points, min_plane_points=40)
    assert set(outs) == {"PlaneId", "Planarity"}
    np.testing.assert_array_equal(outs["PlaneId"], core.labels)
    np.testing.assert_array_equal(outs["Planarity"], core.planarity.astype(np.float64))
    assert nodes(mod)["n_planes"] == len(core) > 0


def test_planes_no_pdalargs_and_empty_view():
    mod = stage("planes", None)
    outs = call(mod, make_ins(np.empty((0, 3))), PLANES)
    assert outs["PlaneId"].shape == (0,) and outs["Planarity"].dtype == np.float64


def test_planes_several_views(scene):
    mod = stage("planes", {})
    a = call(mod, make_ins(scene.points[:5000]), PLANES)
    b = call(mod, make_ins(scene.points), PLANES)
    assert a["PlaneId"].shape == (5000,) and b["PlaneId"].shape == (len(scene.points),)


# --------------------------------------------------------------------------- roughness


@pytest.mark.parametrize("method", ["odr", "ols"])
def test_roughness_equal_core(scene, method):
    args = {"cell": 2.0, "method": method, "signed": True}
    mod = stage("roughness", json.dumps(args))
    outs = call(mod, make_ins(scene.points), ROUGH)
    grid = grid_roughness(scene.points, cell_size_m=2.0, signed=True)
    want = roughness_per_point(scene.points, grid, value="theta_" + method)
    np.testing.assert_array_equal(outs["Roughness"], want)
    assert np.isfinite(outs["Roughness"]).any()


def test_roughness_defaults_and_empty(scene):
    mod = stage("roughness", "")
    outs = call(mod, make_ins(scene.points[:2000]), ROUGH)
    grid = grid_roughness(scene.points[:2000], cell_size_m=0.5)
    np.testing.assert_array_equal(outs["Roughness"], roughness_per_point(scene.points[:2000], grid))
    assert call(mod, make_ins(np.empty((0, 3))), ROUGH)["Roughness"].shape == (0,)


# --------------------------------------------------------------------------- displacement


@pytest.fixture(scope="module")
def slip_run(pair):
    pts, tag = _epochs(pair)
    mod = stage(
        "displacement", {"trace": _trace_wkt(pair), "sigma_before": 0.02, "sigma_after": 0.02}
    )
    outs = call(mod, make_ins(pts, Epoch=tag), DISP)
    core = estimate_slip(
        pair.before.points,
        pair.after.points,
        fault_trace([pair.trace_xy]),
        sigma_before=0.02,
        sigma_after=0.02,
    )
    return mod, outs, core


def test_displacement_summary_equals_core(slip_run):
    from slipmap.app.slip import summary_payload
    from slipmap.app.summaries import json_safe

    mod, outs, core = slip_run
    md = nodes(mod)
    summary = md["summary"]
    params = summary.pop("parameters")
    units = params["acquisition_unit_sources"]
    expect = json_safe(summary_payload(core))  # the core's result in the sign convention
    core_params = expect.pop("parameters")
    assert summary == expect  # the job spells out default options in its record
    for key in ("buffer_m", "combine", "stochastic_model"):
        assert params[key] == core_params[key]
    assert md["right_lateral_slip"] == pytest.approx(0.0181, abs=0.002)
    # the sign convention: + = dextral, no fault-frame names, the meaning stated
    comp = core.components()
    assert md["right_lateral"] == md["right_lateral_slip"] == -comp["fault_parallel"]
    assert md["opening"] == pytest.approx(comp["fault_normal"], abs=1e-12)
    assert not [k for k in md if "fault_" in k] and "right-lateral" in md["headline"]
    assert md["headline"].startswith("right-lateral slip +")
    assert summary["fault"]["right_side"] == "east"
    # the default model is full; the view has no PointSourceId: no units
    assert md["stochastic_model"] == "full" == params["stochastic_model"]
    assert units["units_option"] == "auto"
    assert units["before"] == {
        "source": "none",
        "n_units": 0,
        "note": "auto: no PointSourceId dimension",
    }
    vc = md["variance_components"]
    assert vc["model"] == "full"
    assert vc["sigma_right_lateral"] == pytest.approx(core.components()["sigma_fault_parallel"])
    assert vc["sigma_right_lateral_white"] < vc["sigma_right_lateral"]
    for side in ("left", "right"):
        ref = core.left if side == "left" else core.right
        vcs = ref.rigid.variance_components
        assert vc[side]["n_eff"] == pytest.approx(vcs.n_eff)
        assert vc[side]["white_m"] == pytest.approx(vcs.component("white").sigma_m)
        assert vc[side]["unit_before_source"] == "off"


def test_displacement_per_point_dims(pair, slip_run):
    _, outs, core = slip_run
    from slipmap.core.fault import fault_geometry, side_masks

    trace = fault_trace([pair.trace_xy])
    nb = len(pair.before.points)
    for key, cloud, off in (("before", pair.before.points, 0), ("after", pair.after.points, nb)):
        left, right = side_masks(fault_geometry(cloud[:, :2], trace), buffer_m=10.0)
        for side, mask in (("left", left), ("right", right)):
            ps = getattr(getattr(core, side), "planes_" + key)
            ix = off + np.flatnonzero(mask)
            np.testing.assert_array_equal(outs["PlaneId"][ix], ps.labels)
        buffer = off + np.flatnonzero(~(left | right))
        assert (outs["PlaneId"][buffer] == -1).all()
    on = outs["PlaneId"] >= 0
    assert on.any()
    assert np.isfinite(outs["Residual"][on]).all() and np.isnan(outs["Residual"][~on]).all()
    assert np.abs(outs["Residual"][on]).max() < 0.5  # points lie near their planes
    assert np.sqrt(np.mean(outs["Residual"][on] ** 2)) < 0.05


def test_displacement_empty_view_and_other_epoch_name(pair):
    mod = stage("displacement", {"trace": _trace_wkt(pair), "epoch_dimension": "Survey"})
    outs = call(mod, make_ins(np.empty((0, 3)), Survey=[]), DISP)
    assert outs["PlaneId"].dtype == np.int32 and outs["Residual"].shape == (0,)


def test_displacement_multilinestring_wkt():
    from slipmap.pdal_filters._stage import parse_wkt_lines

    parts = parse_wkt_lines("MULTILINESTRING Z ((0 0 1, 0 10 1), (0 10 0, 5 20 0))")
    assert [p.shape for p in parts] == [(2, 2), (2, 2)]
    assert parse_wkt_lines("LINESTRING(1 2,3 4)")[0].tolist() == [[1, 2], [3, 4]]


def test_displacement_trace_file_reprojected_to_the_views_srs(pair, slip_run, tmp_path):
    """A WGS 84 trace file with the view's SRS as PDAL 2.8 passes it (a dict): the stage
    reprojects the trace and gives the slip of the same trace in WKT."""
    import pyproj

    utm = pyproj.CRS.from_epsg(32611)
    to_ll = pyproj.Transformer.from_crs(utm, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(pair.trace_xy[:, 0], pair.trace_xy[:, 1])
    geo = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {},
                "geometry": {
                    "type": "LineString",
                    "coordinates": [[a, b] for a, b in zip(lon, lat)],
                },
            }
        ],
    }
    path = tmp_path / "trace.geojson"
    path.write_text(json.dumps(geo))
    pytest.importorskip("osgeo")
    pts, tag = _epochs(pair)
    args = {"trace": str(path), "sigma_before": 0.02, "sigma_after": 0.02}
    mod = stage("displacement", args, spatialreference=utm.to_wkt())
    assert isinstance(mod._harness["spatialreference"], dict)  # what real PDAL passes
    call(mod, make_ins(pts, Epoch=tag), DISP)
    ref, _, core = slip_run
    got = nodes(mod)["right_lateral_slip"]
    assert got == pytest.approx(core.components()["right_lateral_slip"], abs=1e-6)


def test_srs_wkt_reads_pdal_forms():
    from pdal_harness import srs_metadata

    from slipmap.pdal_filters._stage import StageError, srs_wkt

    assert srs_wkt(srs_metadata(None)) is None and srs_wkt(None) is None and srs_wkt(" ") is None
    full = srs_metadata("EPSG:32611")
    assert "32611" in srs_wkt(full) or "UTM zone 11N" in srs_wkt(full)
    assert srs_wkt("PROJCS[...]") == "PROJCS[...]"
    full["srs"]["compoundwkt"] = "COMPD_CS[...]"
    assert srs_wkt(full) == "COMPD_CS[...]"  # horizontal + vertical when there is one
    with pytest.raises(StageError, match="unknown form"):
        srs_wkt(42)


def test_slipmap_path_without_a_package_names_the_option(tmp_path, monkeypatch):
    """The script's one bootstrap: a slipmap_path holding no slipmap is refused by name."""
    import sys

    monkeypatch.delitem(sys.modules, "slipmap")  # as in a PDAL whose Python lacks slipmap
    mod = stage("roughness", {"slipmap_path": str(tmp_path)})
    with pytest.raises(RuntimeError, match="option 'slipmap_path'.*holds no slipmap package"):
        call(mod, make_ins(np.zeros((5, 3))), ROUGH)


def test_metadata_nodes_typed_as_pdal_reads_them():
    from pdal_harness import _typed

    from slipmap.pdal_filters._stage import metadata_node

    for value in (True, 3, np.int32(7), 0.1 + 0.2, np.float32(1.5), "text", {"a": [1.0, np.nan]}):
        node = metadata_node("x", value)
        assert isinstance(node["value"], str)
        back = _typed(node["value"], node["type"])
        if isinstance(value, dict):
            assert back == {"a": [1.0, None]}
        else:
            assert back == value
    assert metadata_node("x", float("nan"))["type"] == "json"  # null, not the text "nan"


@pytest.fixture(scope="module")
def drift_pair():
    """A small pair with 3 mm of MLS trajectory drift, PointSourceId and GpsTime per epoch."""
    from slipmap.core.synthetic import SurveyError

    err = SurveyError(kind="mls", level_m=0.003)
    return make_fault_pair(
        "mls",
        seed=11,
        origin=ORIGIN,
        vegetation=False,
        n_buildings=4,
        extent_m=70.0,
        right_offset_m=(0.0, -0.0181, 0.0),
        error_before=err,
        error_after=err,
    )


def _drift_ins(fp):
    pts, tag = _epochs(fp)
    return make_ins(
        pts,
        Epoch=tag,
        PointSourceId=np.r_[fp.source_before, fp.source_after],
        GpsTime=np.r_[fp.gps_time_before, fp.gps_time_after],
    )


@pytest.mark.parametrize("units", ["auto", "gpstime"])
def test_displacement_units_equal_core(drift_pair, units):
    """units auto reads PointSourceId, GpsTime the segments of the GPS times: the slip and
    the components equal the core's with the same unit arrays."""
    from slipmap.app.stochasticmodel import gps_time_segments

    fp = drift_pair
    args = {"trace": _trace_wkt(fp), "sigma_before": 0.02, "sigma_after": 0.02, "units": units}
    mod = stage("displacement", {**args, "gps_gap_s": 2.0})
    call(mod, _drift_ins(fp), DISP)
    md = nodes(mod)
    if units == "auto":
        ub, ua = fp.source_before, fp.source_after
        source = "PointSourceId"
    else:
        ub = gps_time_segments(fp.gps_time_before, 2.0)
        ua = gps_time_segments(fp.gps_time_after, 2.0)
        source = "GpsTime"
    acq = md["acquisition_units"]
    assert acq["units_option"] == ("auto" if units == "auto" else "GpsTime")
    assert acq["before"]["source"] == source
    assert acq["before"]["n_units"] == int(np.unique(ub).size)
    assert acq["after"]["n_units"] == int(np.unique(ua).size) > 1
    core = estimate_slip(
        fp.before.points,
        fp.after.points,
        fault_trace([fp.trace_xy]),
        sigma_before=0.02,
        sigma_after=0.02,
        unit_before=ub,
        unit_after=ua,
    )
    summary = md["summary"]
    assert summary["relative"]["right_lateral_slip"] == pytest.approx(
        core.components()["right_lateral_slip"], abs=1e-9
    )
    vc = summary["left"]["variance_components"]
    for name in ("white", "plane", "spatial", "unit_before", "unit_after"):
        c = vc["components"][name]
        assert c["source"] in ("estimated", "prior", "fixed", "off")
        assert c["sigma_m"] is not None and 0.0 <= c["sigma_m"] < 0.05
    assert vc["components"]["unit_before"]["source"] != "off"  # the units reached the core
    assert 1.0 <= vc["n_eff"] <= vc["n_planes"]


def test_displacement_fixed_components_and_white(drift_pair):
    fp = drift_pair
    base = {"trace": _trace_wkt(fp), "sigma_before": 0.02, "sigma_after": 0.02}
    mod = stage("displacement", {**base, "fixed_components": "plane=0.002, spatial=0"})
    call(mod, _drift_ins(fp), DISP)
    summary = nodes(mod)["summary"]
    for side in ("left", "right"):
        comps = summary[side]["variance_components"]["components"]
        assert comps["plane"]["source"] == "fixed"
        assert comps["plane"]["sigma_m"] == pytest.approx(0.002, abs=1e-12)
    assert summary["parameters"]["components"] == {"plane": 0.002, "spatial": 0.0}
    mod = stage("displacement", {**base, "stochastic_model": "white", "units": "PointSourceId"})
    call(mod, _drift_ins(fp), DISP)
    md = nodes(mod)
    summary = md["summary"]
    assert md["stochastic_model"] == "white"
    assert "variance_components" not in summary["left"]
    assert "sigma_right_lateral_white" not in summary["relative"]
    assert md["acquisition_units"]["before"]["source"] == "none"


def test_displacement_stochastic_options_parse():
    from slipmap.app.slip import fixed_components
    from slipmap.pdal_filters import _stage
    from slipmap.pdal_filters import displacement as mod

    table = mod.TABLE

    def parse(value):
        return _stage.job_options(mod.SPEC, table.parse(value))

    opts = parse(
        {
            "trace": "LINESTRING (0 0, 1 1)",
            "units": "pointsourceid",
            "stochastic_model": "PLANE",
            "fixed_components": "plane=0.002, spatial_range_m=30",
        }
    )
    assert opts["units"] == "PointSourceId" and opts["stochastic_model"] == "plane"
    assert opts["gps_gap_s"] == 1.0
    assert fixed_components(opts) == {"plane": 0.002, "spatial_range_m": 30.0}
    opts = parse({"trace": "x", "fixed_components": {"unit_after": 0.003}})
    assert opts["units"] == "auto" and opts["stochastic_model"] == "full"
    assert fixed_components(opts) == {"unit_after": 0.003}
    opts = parse('{"trace": "x", "fixed_components": "{\\"plane\\": 0.001}"}')
    assert fixed_components(opts) == {"plane": 0.001}
    assert fixed_components(parse({"trace": "x"})) is None


def test_displacement_gps_time_units_need_the_dimension(drift_pair):
    fp = drift_pair
    ins = _drift_ins(fp)
    del ins["GpsTime"]
    mod = stage("displacement", {"trace": _trace_wkt(fp), "units": "GpsTime"})
    with pytest.raises(StageError, match="option units: GpsTime.*no GpsTime dimension"):
        call(mod, ins, DISP)


# --------------------------------------------------------------------------- bad options


@pytest.mark.parametrize(
    "name, args, match",
    [
        ("planes", {"min_plane_points": -3}, "min_plane_points"),
        ("planes", {"bogus": 1}, "bogus"),
        ("planes", {"backend": "cuda"}, "backend"),
        ("planes", "{not json", "pdalargs"),
        ("roughness", {"cell": 0}, "cell"),
        ("roughness", {"cell": "abc"}, "cell"),
        ("roughness", {"method": "lsq"}, "method"),
        ("roughness", {"signed": "maybe"}, "signed"),
        ("roughness", '{"cel": 1}', "cel"),
        ("displacement", {}, "trace"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "buffer_m": -1}, "buffer_m"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "combine": "x"}, "combine"),
        ("displacement", {"trace": "/no/such/file.gpkg"}, "trace"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "epoch_dimension": "E"}, "E"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "stochastic_model": "red"}, "model"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "units": "strips"}, "'units'"),
        ("displacement", {"trace": "LINESTRING (0 0, 1 1)", "gps_gap_s": 0}, "gps_gap_s"),
        ("displacement", {"trace": "x", "fixed_components": "plane"}, "fixed_components"),
        ("displacement", {"trace": "x", "fixed_components": [1, 2]}, "fixed_components"),
        ("displacement", {"trace": "x", "fixed_components": "bogus=1"}, "fixed_.*bogus"),
        ("displacement", {"trace": "x", "fixed_components": "plane=-1"}, "fixed_.*plane"),
        ("displacement", {"trace": "x", "fixed_components": {"plane": "a"}}, "fixed_.*plane"),
        (
            "displacement",
            {"trace": "x", "stochastic_model": "white", "fixed_components": "plane=0.001"},
            "fixed_components.*white",
        ),
    ],
)
def test_bad_options_name_the_option(name, args, match):
    mod = stage(name, args)
    pts = np.random.default_rng(0).uniform(0, 20, (500, 3))
    with pytest.raises(StageError, match=match):
        call(mod, make_ins(pts, Epoch=np.r_[np.ones(250), np.full(250, 2.0)]), {})


def test_core_errors_become_stage_errors():
    mod = stage("displacement", {"trace": "LINESTRING (1000 0, 1000 10)"})
    pts = np.random.default_rng(0).uniform(0, 20, (500, 3))
    with pytest.raises(StageError, match="slipmap displacement"):
        call(mod, make_ins(pts, Epoch=np.r_[np.ones(250), np.full(250, 2.0)]), DISP)


def test_options_parsed_once_per_raw_value(monkeypatch):
    from slipmap.pdal_filters.roughness import options_table

    table = options_table()
    a = table.parse('{"cell": 1}')
    calls = []
    monkeypatch.setattr(
        "slipmap.pdal_filters._stage.load_pdalargs", lambda *a: calls.append(a) or {}
    )
    assert table.parse('{"cell": 1}') == a and not calls
    table.parse({"cell": 2.0})  # another raw value: parsed again
    assert len(calls) == 1


def test_real_pdal_helpers_resolve():
    """What test_real_pdal.py needs from SlipMap resolves here too, where PDAL is not needed:
    a moved module fails this run, not only a run on a machine with PDAL."""
    from pdal_harness import ROUGHNESS_ATOL_M, demo_runner

    assert callable(demo_runner()) and 0 < ROUGHNESS_ATOL_M < 1e-9


def test_slipmap_path_makes_a_checkout_importable(tmp_path):
    """Without slipmap installed, pdalargs slipmap_path (the package root) is enough."""
    import subprocess
    import sys
    import textwrap

    from pdal_harness import ROOT

    code = textwrap.dedent(
        f"""
        import sys
        sys.path[:] = [p for p in sys.path if 'site-packages' not in p and p not in ('', '.')]
        sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()
                            and 'editable' not in getattr(f, '__module__', '')]
        import numpy  # noqa: F401  (found in the dist-packages of the system)
        try:
            import slipmap  # noqa: F401
            raise SystemExit('slipmap still importable')
        except ImportError:
            pass
        sys.path.insert(0, {str(ROOT / "tests" / "pdal_stages")!r})
        from pdal_harness import load_stage, make_ins, call
        import numpy as np
        mod = load_stage('roughness', {{"slipmap_path": {str(ROOT)!r}}}, module_name='r')
        pts = np.random.default_rng(0).uniform(0, 5, (300, 3))
        out = call(mod, make_ins(pts), {{"Roughness": np.dtype(np.float64)}})
        print('ok', out['Roughness'].shape)
        """
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    if "No module named 'numpy'" in r.stderr:
        pytest.skip("numpy only in site-packages of this venv")
    assert r.returncode == 0 and "ok (300,)" in r.stdout, r.stderr[-2000:]
