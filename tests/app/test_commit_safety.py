"""Staging always cleaned (issue #31, item 4): every job, through the CLI's ``main()``, with
its commit or a write made to fail.

For each job: a first run writes the outputs (and counts the moves of its commit); then, into
that same output folder,

* the commit's first move fails, then its last (``os.replace`` raising ENOSPC at the Nth call),
* a write fails half-way (the plan's temporary path for the middle output raising ENOSPC: the
  outputs asked for before it are already staged),

and each time: a non-zero exit with one line and no traceback, no ``.slipmap-partial-*``
folder anywhere, the output folder exactly as the first run left it (what a half-done commit
had replaced is put back), the inputs byte-identical.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os

import numpy as np
import pyproj
import pytest

from slipmap.app.outputs import OutputPlan
from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.io.table import write_csv_columns
from slipmap.core.synthetic import make_fault_pair

pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")

UTM12 = pyproj.CRS.from_epsg(32612)
UTM10 = pyproj.CRS.from_epsg(32610)


def listing(folder):
    """(relative path, sha256) of every file under ``folder``."""
    return sorted(
        (str(p.relative_to(folder)), hashlib.sha256(p.read_bytes()).hexdigest())
        for p in folder.rglob("*")
        if p.is_file()
    )


def _rough(n, seed, side=16.0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, side, (n, 2))
    x, y = xy[:, 0], xy[:, 1]
    z = (
        0.5 * np.sin(x / 2.7) * np.cos(y / 3.1)
        + 0.06 * np.sin(x / 0.21 + 1.3 * np.sin(y / 0.37))
        + 0.05 * np.cos(y / 0.17 + 0.8 * np.sin(x / 0.29))
    )
    return np.column_stack([xy + [512000.0, 4780000.0], z + 1500.0])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Every job's inputs in one folder: a rough pair shifted by (0.12, -0.2, 0.05) m, a fault
    pair with a trace, tiles of the rough patch, a displacement field CSV."""
    d = tmp_path_factory.mktemp("inputs")
    write_las(d / "b.las", PointCloud(xyz=_rough(20000, 1), crs=UTM12))
    write_las(d / "a.las", PointCloud(xyz=_rough(20000, 2) + [0.12, -0.2, 0.05], crs=UTM12))
    tiles = d / "tiles"
    tiles.mkdir()
    xyz = _rough(20000, 3)
    k = (xyz[:, 0] - 512000.0 >= 8.0).astype(int)
    for i in (0, 1):
        write_las(tiles / f"t{i}.las", PointCloud(xyz=xyz[k == i], crs=UTM12))
    fp = make_fault_pair("mls", seed=7, origin=(498000.0, 4234000.0, 20.0))
    for name, sc in (("before", fp.before), ("after", fp.after)):
        attrs = {"Classification": sc.classification}
        write_las(d / f"{name}.laz", PointCloud(xyz=sc.points, attributes=attrs, crs=UTM10))
    tr = pyproj.Transformer.from_crs(UTM10, "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(fp.trace_xy[:, 0], fp.trace_xy[:, 1])
    feature = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "LineString", "coordinates": [[a, b] for a, b in zip(lon, lat)]},
    }
    (d / "fault.geojson").write_text(
        json.dumps({"type": "FeatureCollection", "features": [feature]})
    )
    x, y = np.meshgrid(500000.0 + np.arange(8) * 2.0, 4200000.0 + np.arange(6) * 2.0)
    write_csv_columns(
        d / "field.csv",
        {"x": x.ravel(), "y": y.ravel(), "dx": 2e-3 * (y.ravel() - 4200000.0), "dy": 0 * x.ravel()},
    )
    return d


GDAL = {"piv", "icp", "dem-diff", "strain", "displacement"}

#: job -> argv (``{d}`` the inputs folder, ``{out}`` the output folder)
JOBS = {
    "planes": ["planes", "{d}/b.las", "--out", "{out}"],
    "planes-tiles": ["planes", "{d}/tiles", "--out", "{out}", "--tile-size", "8"],
    "displacement": [
        "displacement", "{d}/before.laz", "{d}/after.laz", "--fault", "{d}/fault.geojson",
        "--sigma", "0.02", "--out", "{out}",
    ],
    "roughness": ["roughness", "{d}/b.las", "--cell", "4", "--out", "{out}"],
    "roughness-tiles": ["roughness", "{d}/tiles", "--cell", "4", "--out", "{out}"],
    "accuracy": ["accuracy", "{d}/b.las", "--sigma", "0.02", "--out", "{out}/b_pa.las"],
    "piv": [
        "piv", "{d}/b.las", "{d}/a.las", "--grid", "0.25", "--window", "16", "8",
        "--max-displacement", "0.5", "--out", "{out}", "--no-progress",
    ],
    "icp": ["icp", "{d}/b.las", "{d}/a.las", "--cell", "8", "--out", "{out}", "--no-progress"],
    "dem-diff": ["dem-diff", "{d}/b.las", "{d}/a.las", "--grid", "0.5", "--out", "{out}"],
    "strain": ["strain", "{d}/field.csv", "--out", "{out}", "--crs", "EPSG:32612"],
}  # fmt: skip


def _argv(job, d, out):
    return ["-q"] + [a.format(d=d, out=out) for a in JOBS[job]]


def _partials(*roots):
    return [p for r in roots for p in r.rglob(".slipmap-partial-*")]


def _fail_at(n, real):
    """A stand-in for ``real`` that raises ENOSPC at its ``n``-th call (1-based)."""
    calls = {"n": 0}

    def fake(*args, **kw):
        calls["n"] += 1
        if calls["n"] == n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(*args, **kw)

    fake.calls = calls
    return fake


@pytest.mark.parametrize("job", list(JOBS))
def test_a_failed_commit_or_write_leaves_nothing_behind(job, inputs, tmp_path, monkeypatch, capsys):
    if job in GDAL:
        pytest.importorskip("osgeo.gdal", reason="GDAL's Python bindings (python3-gdal) missing")
    root = tmp_path / "outputs"
    out = root / "o"
    before_inputs = listing(inputs)

    counter = _fail_at(0, os.replace)  # never fails: counts the moves
    paths = _fail_at(0, OutputPlan.path)  # counts the temporary paths asked for
    monkeypatch.setattr(os, "replace", counter)
    monkeypatch.setattr(OutputPlan, "path", paths)
    rc = main(_argv(job, inputs, out))
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert rc == 0, err
    moves = counter.calls["n"]
    assert moves >= 1 and paths.calls["n"] >= 1
    first = listing(root)
    assert first and not _partials(root, inputs)

    faults = [("replace", 1), ("replace", moves), ("path", paths.calls["n"] // 2 + 1)]
    for what, n in faults:
        if what == "replace":
            monkeypatch.setattr(os, "replace", _fail_at(n, os.replace))
        else:
            monkeypatch.setattr(OutputPlan, "path", _fail_at(n, OutputPlan.path))
        rc = main(_argv(job, inputs, out))
        monkeypatch.undo()
        err = capsys.readouterr().err
        where = f"{job}: {what} #{n}"
        assert rc in (1, 2), (where, err)
        assert "Traceback" not in err and "No space left" in err, (where, err)
        assert not _partials(root, inputs), where
        assert listing(root) == first, where  # the first run's outputs, byte-identical
        assert sorted(p.name for p in root.rglob("*")) == sorted(
            p.name for p in root.rglob("*") if not p.name.startswith(".")
        ), where
    assert listing(inputs) == before_inputs
