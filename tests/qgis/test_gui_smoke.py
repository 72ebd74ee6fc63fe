"""The QGIS desktop starts with the plugin and opens the Fault slip dialog (a screenshot).

Runs the ``qgis`` binary under Xvfb with a throw-away profile in which the plugin is enabled;
``--code`` opens ``slipmap:displacement``'s dialog and saves it as a PNG. Skipped where there
is no QGIS desktop (``qgis``) or no ``xvfb-run``. About 10 s; ``SLIPMAP_GUI_SHOT=PATH`` keeps
the screenshot there (docs/img/qgis_displacement_dialog.png is refreshed that way).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

import slipmap

pytestmark = pytest.mark.qgis

QGIS = shutil.which("qgis.bin") or shutil.which("qgis")  # Debian's qgis is a shell wrapper
XVFB = shutil.which("xvfb-run")

SCRIPT = """
import os
from qgis.PyQt.QtCore import QTimer

out = os.environ["SLIPMAP_SHOT"]


def open_dialog():
    from qgis import processing

    dlg = processing.createAlgorithmDialog("slipmap:displacement")
    dlg.resize(1100, 780)
    dlg.show()

    def grab():
        ok = dlg.grab().save(out)
        with open(out + ".txt", "w") as f:
            f.write(f"{ok}|{dlg.windowTitle()}|{dlg.algorithm().id()}\\n")
        os._exit(0)  # QGIS 3.22 may abort on a scripted exit; the picture is saved

    QTimer.singleShot(2500, grab)


QTimer.singleShot(3000, open_dialog)
"""


@pytest.mark.skipif(QGIS is None, reason="no QGIS desktop binary (apt install qgis)")
@pytest.mark.skipif(XVFB is None, reason="no xvfb-run (apt install xvfb)")
def test_fault_slip_dialog_opens_in_the_desktop(tmp_path):
    profile = tmp_path / "profiles" / "default"
    (profile / "python" / "plugins").mkdir(parents=True)
    (profile / "QGIS").mkdir()
    (profile / "python" / "plugins" / "slipmap").symlink_to(Path(slipmap.__file__).resolve().parent)
    (profile / "QGIS" / "QGIS3.ini").write_text("[PythonPlugins]\nslipmap=true\n")
    script = tmp_path / "shot.py"
    script.write_text(SCRIPT)
    shot = Path(os.environ.get("SLIPMAP_GUI_SHOT") or tmp_path / "dialog.png").resolve()
    env = dict(os.environ, SLIPMAP_SHOT=str(shot))
    env.pop("QT_QPA_PLATFORM", None)  # the desktop on Xvfb, not offscreen
    cmd = [XVFB, "-a", "-s", "-screen 0 1400x1000x24", QGIS, "--profiles-path", str(tmp_path)]
    cmd += ["--nologo", "--noversioncheck", "--code", str(script)]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=55)
    marker = Path(str(shot) + ".txt")
    assert marker.is_file(), (run.returncode, run.stdout[-2000:], run.stderr[-2000:])
    ok, title, alg_id = marker.read_text().strip().split("|")
    marker.unlink()
    assert ok == "True" and alg_id == "slipmap:displacement" and "Fault slip" in title
    assert shot.stat().st_size > 20_000  # a rendered dialog, not an empty picture
