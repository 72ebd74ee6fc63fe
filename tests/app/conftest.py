"""Helpers of the application-layer tests: checksums, folder listings, a fault pair as the
files a user gives the slip job."""

import hashlib

import pytest


def sha256(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def listing(folder):
    """(relative path, size, sha256) of every file under ``folder``: 'untouched' means equal."""
    return sorted(
        (str(p.relative_to(folder)), p.stat().st_size, sha256(p))
        for p in folder.rglob("*")
        if p.is_file()
    )


@pytest.fixture
def snapshot():
    """``snap = snapshot(folder_or_file, ...)``; later ``snap.unchanged()`` is True when every
    file is byte-identical and no file was added or removed."""

    class Snap:
        def __init__(self, *paths):
            self.paths = paths
            self.before = [self._state(p) for p in paths]

        @staticmethod
        def _state(p):
            if p.is_dir():
                return listing(p)
            return sha256(p) if p.exists() else None

        def unchanged(self):
            return [self._state(p) for p in self.paths] == self.before

    return Snap


@pytest.fixture
def fault_pair_files(line_file):
    """``paths, fault = fault_pair_files(folder, fp, crs)``: ``fp`` (a
    :class:`slipmap.core.synthetic.FaultPair`) written as ``before.laz`` and ``after.laz``
    (with their classes) and its trace as ``fault.gpkg`` in ``folder``, all in ``crs``; the
    two epoch paths and the trace path, as strings."""
    from slipmap.core.io.las import PointCloud, write_las

    def write(folder, fp, crs):
        paths = []
        for epoch, sc in (("before", fp.before), ("after", fp.after)):
            p = folder / f"{epoch}.laz"
            write_las(p, PointCloud(sc.points, {"Classification": sc.classification}, crs=crs))
            paths.append(str(p))
        line_file(folder / "fault.gpkg", fp.trace_xy, crs)
        return paths, str(folder / "fault.gpkg")

    return write
