"""PYQGIS_STARTUP for test_desktop.py: runs in the QGIS desktop's Python before any plugin.

Writes every message of QGIS's message log (the Log Messages panel: where a plugin's
load-time notices go) to ``SLIPMAP_DESKTOP_MESSAGES`` as JSON lines, and, with
``SLIPMAP_DESKTOP_BLOCK`` (comma-separated module names), makes those modules unimportable, as
on a machine where they are not installed (the missing-dependency path).
"""

import importlib.abc
import importlib.util
import json
import os
import sys

_blocked = {m for m in os.environ.get("SLIPMAP_DESKTOP_BLOCK", "").split(",") if m}


class _Block(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        if _blocked_name(fullname):
            raise ModuleNotFoundError(f"No module named '{fullname}'", name=fullname)
        return None


def _blocked_name(name):
    return str(name).split(".")[0] in _blocked


# QGIS may run this file twice in one namespace: set up once
_first = not getattr(sys, "_slipmap_desktop_startup", False)
sys._slipmap_desktop_startup = True

if _blocked and _first:
    sys.meta_path.insert(0, _Block())

    def _blocking(find_spec):
        def blocked_find_spec(name, package=None):
            """``importlib.util.find_spec`` answering None for a blocked module, as for one
            that is not installed (a plugin may ask before it imports)."""
            if _blocked_name(name):
                return None
            return find_spec(name, package)

        return blocked_find_spec

    importlib.util.find_spec = _blocking(importlib.util.find_spec)

_out = os.environ.get("SLIPMAP_DESKTOP_MESSAGES")
if _out and _first:
    from qgis.core import QgsApplication

    def _write(message, tag, level):
        with open(_out, "a", encoding="utf-8") as f:
            f.write(json.dumps([tag, int(level), message]) + "\n")

    QgsApplication.messageLog().messageReceived.connect(_write)
