"""``slipmap accuracy`` writes per-point sigmas that ``--pa columns`` reads back."""

import json

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
