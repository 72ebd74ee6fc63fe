"""Helpers of the application-layer tests: checksums and folder listings."""

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
