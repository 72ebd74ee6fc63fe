"""Missing packages (issue #28, finding 2): every algorithm stays listed, the toolbox, the
Plugin Manager, the log and qgis_process say what is missing with the one command that
installs it here, and a run refuses at once with that command.

laspy, lazrs and scipy are made missing for real in a child process: a ``sitecustomize`` on
its PYTHONPATH puts a meta-path finder first that refuses them (``import`` and
``importlib.util.find_spec`` both fail, as where the package is not installed)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import slipmap

pytestmark = pytest.mark.qgis

ROOT = Path(slipmap.__file__).resolve().parent
IDS = sorted(
    f"slipmap:{i}"
    for i in (
        "planes",
        "displacement",
        "roughness",
        "pointaccuracy",
        "piv",
        "windowedicp",
        "demdiff",
        "strain",
    )
)
BLOCKER = textwrap.dedent(
    """
    import importlib.abc, os, sys
    _BLOCKED = set(filter(None, os.environ.get("SLIPMAP_BLOCK", "").split(",")))
    class _Blocker(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in _BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None
    sys.meta_path.insert(0, _Blocker())
    """
)


@pytest.fixture(scope="module")
def blocker(tmp_path_factory):
    folder = tmp_path_factory.mktemp("blocker")
    (folder / "sitecustomize.py").write_text(BLOCKER)
    return folder


def _env(blocker, blocked, **extra):
    path = [str(blocker), str(ROOT.parent)] + [
        p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p
    ]
    return dict(
        os.environ,
        PYTHONPATH=os.pathsep.join(path),
        SLIPMAP_BLOCK=",".join(blocked),
        QT_QPA_PLATFORM="offscreen",
        **extra,
    )


CHILD = textwrap.dedent(
    """
    import json, sys
    from qgis.core import QgsApplication, QgsProcessingException
    app = QgsApplication([], False)
    app.initQgis()
    sys.path.append("/usr/share/qgis/python/plugins")
    from processing.core.Processing import Processing
    Processing.initialize()
    import processing
    logged = []
    QgsApplication.messageLog().messageReceived.connect(
        lambda text, tag, level: logged.append([text, tag, int(level)]))
    import slipmap
    plugin = slipmap.classFactory(None)
    plugin.initProcessing()
    provider = QgsApplication.processingRegistry().providerById("slipmap")
    out = {"name": provider.name(), "long_name": provider.longName(),
           "warning": provider.warningMessage(), "algorithms": {}, "logged": logged}
    for alg in provider.algorithms():
        ok, message = alg.canExecute()
        try:
            processing.run(alg.id(), {})
            run = "ran"
        except QgsProcessingException as exc:
            run = str(exc)
        out["algorithms"][alg.id()] = {
            "display": alg.displayName(), "group": alg.group(), "ok": ok, "message": message,
            "tooltip": alg.shortDescription(), "run": run,
            "stand_in": type(alg).__name__.startswith("StandIn")}
    from slipmap.qgis_plugin import compat
    out["expected"] = {k: compat.missing_message(compat.missing_packages(compat.needs(k)))
                       if compat.missing_packages(compat.needs(k)) else ""
                       for k in ("piv", "strain")}
    print("JSON" + json.dumps(out))
    plugin.unload()
    """
)


def _child(blocker, blocked):
    run = subprocess.run(
        [sys.executable, "-c", CHILD],
        env=_env(blocker, blocked),
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [t for t in run.stdout.splitlines() if t.startswith("JSON")]
    assert lines, run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads(lines[-1][4:])


def test_without_laspy_lazrs_scipy_all_eight_listed_and_refuse(blocker):
    from slipmap.qgis_plugin import compat

    out = _child(blocker, ["laspy", "lazrs", "scipy"])
    algs = out["algorithms"]
    assert sorted(algs) == IDS  # nothing vanishes
    names = {
        f"slipmap:{row[2]}": row[3]
        for row in __import__("slipmap.qgis_plugin.provider", fromlist=["ALGORITHMS"]).ALGORITHMS
    }
    assert {k: v["display"] for k, v in algs.items()} == names
    # the toolbox's provider node, qgis_process list's heading and the node's tooltip
    assert out["name"] == "SlipMap (cannot run: laspy, lazrs, scipy missing)"
    every = out["expected"]["piv"]
    assert every.startswith("SlipMap needs the Python packages laspy, lazrs, scipy")
    assert every in out["long_name"] and out["warning"] == every
    if compat.platform_kind() == "debian" and compat._externally_managed():
        assert every.endswith(
            "python3 -m pip install --user --break-system-packages laspy lazrs"
        ), every
        assert "sudo apt install" in every and "python3-scipy" in every
        assert "python -m" not in every  # Debian has no `python`
    # the plugin says it once when it loads (the Log Messages panel; qgis_process's stderr)
    assert [t for t, tag, _ in out["logged"] if tag == "SlipMap" and t == every]
    for alg_id, a in algs.items():
        expected = out["expected"]["strain" if alg_id == "slipmap:strain" else "piv"]
        assert not a["ok"], alg_id
        assert a["message"] == expected, alg_id
        assert a["tooltip"] == f"Cannot run yet. {expected}", alg_id
        assert a["run"].strip().endswith(expected.split(": ", 1)[1]), (alg_id, a["run"])
    # six modules import scipy when loaded: stand-ins take their place, the others load
    assert sum(a["stand_in"] for a in algs.values()) == 6
    assert not algs["slipmap:strain"]["stand_in"]
    assert out["expected"]["strain"].startswith("SlipMap needs the Python package scipy,")


def test_without_laspy_lazrs_the_real_algorithms_load(blocker):
    out = _child(blocker, ["laspy", "lazrs"])
    algs = out["algorithms"]
    assert sorted(algs) == IDS and not any(a["stand_in"] for a in algs.values())
    assert out["name"] == "SlipMap (cannot run: laspy, lazrs missing)"
    assert algs["slipmap:strain"]["ok"]  # reads a table or GeoTIFF: needs no laspy
    for alg_id, a in algs.items():
        if alg_id != "slipmap:strain":
            assert not a["ok"] and a["message"] == out["expected"]["piv"], alg_id
            assert "--break-system-packages laspy lazrs" in a["run"] or os.name == "nt"


def test_message_bar_on_load(qgis_app, monkeypatch):
    """The desktop (iface given) shows the missing packages and the command in the message
    bar when the plugin loads; nothing when all are there. (Placed before the tests that
    register the provider for the whole module.)"""
    from slipmap.qgis_plugin import compat

    pushed = []

    class Bar:
        def pushMessage(self, title, text, level, duration):  # noqa: N802
            pushed.append((title, text, duration))

    class Iface:
        def messageBar(self):  # noqa: N802
            return Bar()

    plugin = slipmap.classFactory(Iface())
    try:
        monkeypatch.setattr(compat, "missing_packages", lambda names=None: ["laspy", "lazrs"])
        plugin.initGui()
        assert pushed == [("SlipMap", compat.missing_message(["laspy", "lazrs"]), 0)]
        monkeypatch.setattr(compat, "missing_packages", lambda names=None: [])
        assert plugin.show_missing() == "" and len(pushed) == 1
    finally:
        plugin.unload()


def test_all_present_nothing_said(provider):
    from qgis.core import QgsApplication

    from slipmap.qgis_plugin import compat

    p = QgsApplication.processingRegistry().providerById("slipmap")
    assert compat.missing_packages() == []
    assert p.name() == "SlipMap" and p.warningMessage() == ""
    for alg in p.algorithms():
        assert alg.canExecute() == (True, ""), alg.id()
        assert not alg.shortDescription().startswith("Cannot run"), alg.id()


def test_stand_in_table_matches_the_algorithms(provider):
    from qgis.core import QgsApplication

    from slipmap.qgis_plugin.provider import ALGORITHMS

    registry = QgsApplication.processingRegistry()
    for _module, _cls, alg_id, name, group, group_id in ALGORITHMS:
        alg = registry.algorithmById(f"slipmap:{alg_id}")
        assert (alg.displayName(), alg.group(), alg.groupId()) == (name, group, group_id)


# --------------------------------------------------------------------------- one command each


@pytest.mark.parametrize(
    "kind, pip, managed, expected",
    [
        (
            "debian",
            True,
            True,
            "sudo apt install python3-scipy && "
            "python3 -m pip install --user --break-system-packages laspy lazrs",
        ),
        (
            "debian",
            False,
            True,
            "sudo apt install python3-pip python3-scipy && "
            "python3 -m pip install --user --break-system-packages laspy lazrs",
        ),
        (
            "debian",
            True,
            False,
            "sudo apt install python3-scipy && python3 -m pip install --user laspy lazrs",
        ),
        ("osgeo4w", True, False, "python -m pip install laspy lazrs scipy"),
        ("conda", True, False, "conda install -c conda-forge laspy lazrs-python scipy"),
    ],
)
def test_install_command_per_platform(monkeypatch, kind, pip, managed, expected):
    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat, "_externally_managed", lambda: managed)
    real = compat._importable
    monkeypatch.setattr(compat, "_importable", lambda n: pip if n == "pip" else real(n))
    assert compat.install_command(["laspy", "lazrs", "scipy"], kind) == expected


def test_install_command_macos_uses_the_running_app(monkeypatch):
    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat.sys, "executable", "/Applications/QGIS-LTR.app/Contents/MacOS/QGIS")
    assert compat.install_command(["laspy", "lazrs"], "macos") == (
        "/Applications/QGIS-LTR.app/Contents/MacOS/bin/python3 -m pip install laspy lazrs"
    )


def test_plugin_manager_and_docs_give_every_command():
    import configparser

    from slipmap.qgis_plugin import compat

    meta = configparser.ConfigParser()
    meta.read(ROOT / "metadata.txt", encoding="utf-8")
    about = meta["general"]["about"]
    docs = (ROOT / "docs" / "qgis.md").read_text(encoding="utf-8")
    for _, command in compat.PLATFORM_COMMANDS:
        assert command in about, command
        assert command in docs, command
        assert command in compat.INSTALL_HINT, command
    assert "python -m pip" not in about.split("Windows")[0]  # Debian: python3 only


# --------------------------------------------------------------------------- qgis_process


def _qgis_process():
    return shutil.which("qgis_process.bin") or shutil.which("qgis_process")


@pytest.mark.skipif(_qgis_process() is None, reason="no qgis_process binary (QGIS desktop)")
def test_qgis_process_list_help_and_run_say_what_is_missing(blocker, tmp_path):
    plugins = tmp_path / "profiles" / "default" / "python" / "plugins"
    plugins.mkdir(parents=True)
    (plugins / "slipmap").symlink_to(ROOT)
    env = _env(blocker, ["laspy", "lazrs", "scipy"], QGIS_CUSTOM_CONFIG_PATH=str(tmp_path))
    env.pop("PYTHONPATH")  # the plugin from the profile, the blocker only
    env["PYTHONPATH"] = str(blocker)
    exe = [_qgis_process()]
    subprocess.run(
        exe + ["plugins", "enable", "slipmap"], env=env, capture_output=True, timeout=120
    )

    def call(*args):
        r = subprocess.run(exe + list(args), env=env, capture_output=True, text=True, timeout=120)
        return r.returncode, r.stdout, r.stderr

    _, out, err = call("list")
    if "slipmap:" not in out:
        pytest.skip("qgis_process did not load the plugin: " + (out + err)[-300:])
    heading = out.split("SlipMap (cannot run:")[1]
    assert heading.startswith(" laspy, lazrs, scipy missing)\n")
    listed = sorted(t.split("\t")[1] for t in heading.split("\n\n")[0].splitlines()[1:])
    assert listed == IDS
    assert "--break-system-packages laspy lazrs" in err  # said once when the plugin loads
    _, out, _ = call("help", "slipmap:piv")
    assert "Cannot run yet. SlipMap needs the Python packages laspy, lazrs, scipy" in out
    code, out, err = call("run", "slipmap:piv", "--", "BEFORE=a.las")
    assert code != 0
    assert "--break-system-packages laspy lazrs" in err, err  # refused at once, the command


def test_a_missing_speedup_is_said_with_its_command(monkeypatch):
    """Numba is optional (issue #29): where it is missing the windowed ICP's log says what it
    would speed up and the command that installs it, per platform; installed: nothing."""
    from slipmap.qgis_plugin import compat

    monkeypatch.setattr(compat, "_importable", lambda name: name != "numba")
    line = compat.speedup_message("numba", "osgeo4w")
    assert "numba" in line and line.endswith("python -m pip install numba")
    assert "sudo apt install python3-numba" in compat.speedup_message("numba", "debian")
    assert compat.speedup_message("numba", "conda").endswith("conda install -c conda-forge numba")
    monkeypatch.setattr(compat, "_importable", lambda name: name not in ("numba", "threadpoolctl"))
    line = compat.speedup_message("threadpoolctl", "debian")  # one BLAS thread (core/threads.py)
    assert "BLAS" in line and line.endswith("sudo apt install python3-threadpoolctl")
    monkeypatch.setattr(compat, "_importable", lambda name: True)
    assert compat.speedup_message("numba", "osgeo4w") == ""
    assert compat.speedup_message("threadpoolctl", "osgeo4w") == ""
