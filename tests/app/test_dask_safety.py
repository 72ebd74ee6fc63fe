"""Dask as a user meets it (issue #31, bad cases 4 and 6, ``--workers 1000`` of bad case 1).

Scheduler addresses refused before connecting, naming ``--scheduler`` (the QGIS face goes
through the same :meth:`JobSpec.parse`); a port that listens but does not speak Dask (a silent
listener, an HTTP server) refused within the handshake timeout; ``--workers`` clamped to the
machine; a Ctrl-C on a local cluster: one line, exit 130, no traceback. Every run that could
hang is a subprocess killed by the harness after :data:`LIMIT_S` seconds (a kill is a
failure); no assertion on how long anything took.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from slipmap.app.engine import (
    MIN_WORKER_MEMORY_BYTES,
    check_scheduler_address,
    clamp_workers,
    local_worker_bound,
)
from slipmap.app.options import OptionError
from slipmap.app.planes import SPEC as PLANES
from slipmap.cli import main
from slipmap.core.io.las import PointCloud, write_las
from slipmap.core.synthetic import make_scene

pytestmark = pytest.mark.usefixtures("drop_cli_log_handlers")

#: the harness's bound on a subprocess (seconds); the handshake timeout given to it is 3 s
LIMIT_S = 60


@pytest.fixture(scope="module")
def tiles(tmp_path_factory):
    root = tmp_path_factory.mktemp("dask_tiles")
    scene = make_scene("mls", seed=5, n_buildings=2, extent_m=40.0, origin=(500000, 4200000, 10))
    folder = root / "tiles"
    folder.mkdir()
    k = np.floor((scene.points[:, :2] - [500000, 4200000]) / 20.0).astype(int)
    for key in np.unique(k, axis=0):
        sel = np.all(k == key, axis=1)
        write_las(folder / f"t{key[0]}{key[1]}.laz", PointCloud(xyz=scene.points[sel]))
    whole = root / "whole.laz"
    write_las(whole, PointCloud(xyz=scene.points))
    return folder, whole


@pytest.mark.parametrize(
    "address, words",
    [
        ("xyz://127.0.0.1:1", ["unknown scheme", "tcp://"]),
        ("tcp://127.0.0.1", ["no port", "tcp://127.0.0.1:8786"]),
        ("tcp://:8786", ["no host"]),
        ("tcp://host:99999", ["1..65535"]),
        ("tcp://host:0", ["1..65535"]),
        ("tcp://host:port", ["1..65535"]),
        ("http://host:8786", ["unknown scheme"]),
        ("host:8786", ["not an address", "tcp://host:8786"]),
        ("tcp://host:8786/status", ["host:port"]),
    ],
)
def test_bad_scheduler_address_refused_naming_the_option(address, words, tiles, tmp_path, capsys):
    folder, _ = tiles
    out = tmp_path / "out"
    rc = main(["planes", str(folder), "--out", str(out), "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "--scheduler" in err[0] and all(w in err[0] for w in words), err
    assert not out.exists()
    with pytest.raises(OptionError) as exc:  # the shared check, as QGIS's face meets it
        PLANES.parse({"input": str(folder), "scheduler": address}, face="qgis")
    assert exc.value.key == "scheduler"
    assert '"Dask scheduler address' in PLANES.render_error(exc.value, "qgis")


@pytest.mark.parametrize(
    "address",
    ["tcp://127.0.0.1:8786", "tls://sched.example.org:8786", "tcp://[::1]:8786", "ws://h:1"],
)
def test_good_scheduler_addresses_pass(address):
    assert check_scheduler_address(f"  {address} ") == address


def _listener(kind):
    """A local TCP server on 127.0.0.1 that accepts and never speaks (``silent``) or answers
    every connection as an HTTP server would (``http``)."""
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held = []

    def serve():
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            held.append(conn)
            if kind == "http":
                try:
                    conn.recv(1024)
                    conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
                except OSError:
                    pass

    threading.Thread(target=serve, daemon=True).start()
    return srv, held


def _default_sigint():
    """In the child: SIGINT's default action, as in a terminal (a parent started as a
    background job of a script passes SIGINT on ignored, and Python then keeps it ignored)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _slipmap(argv, **kw):
    env = dict(os.environ, DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT="3s")
    return subprocess.Popen(
        [sys.executable, "-m", "slipmap.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_default_sigint,
        **kw,
    )


def _finish(proc):
    try:
        out, err = proc.communicate(timeout=LIMIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"killed after {LIMIT_S} s: the run hung")
    return proc.returncode, err


@pytest.mark.parametrize("kind, words", [("silent", "did not answer"), ("http", "not as a Dask")])
def test_a_port_that_does_not_speak_dask_is_refused(kind, words, tiles, tmp_path):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    folder, _ = tiles
    srv, held = _listener(kind)
    try:
        port = srv.getsockname()[1]
        out = tmp_path / "out"
        proc = _slipmap(["planes", str(folder), "--out", str(out), "--scheduler",
                         f"tcp://127.0.0.1:{port}"])  # fmt: skip
        rc, err = _finish(proc)
    finally:
        srv.close()
        for c in held:
            c.close()
    assert rc == 2, err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert "--scheduler" in line and words in line and f"127.0.0.1:{port}" in line
    if kind == "silent":
        assert "within 3 s" in line
    assert not out.exists()


def test_workers_bounded_by_the_machine(caplog):
    gib = 1 << 30
    assert local_worker_bound(cores=8, memory_bytes=64 * gib) == 8
    assert local_worker_bound(cores=64, memory_bytes=4 * gib) == 4  # memory binds
    assert local_worker_bound(cores=4, memory_bytes=gib // 2) == 1  # at least one
    assert MIN_WORKER_MEMORY_BYTES == gib
    bound = local_worker_bound()
    with caplog.at_level("WARNING", logger="slipmap.app"):
        assert clamp_workers(1000) == bound
    assert any("1000 asked for" in r.getMessage() for r in caplog.records)
    caplog.clear()
    assert clamp_workers(1) == 1 and not caplog.records


def test_workers_1000_runs_on_what_the_machine_has(tiles, tmp_path, capsys):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    folder, _ = tiles
    out = tmp_path / "out"
    rc = main(["planes", str(folder), "--out", str(out), "--workers", "1000"])
    err = capsys.readouterr().err
    assert rc == 0, err
    bound = local_worker_bound()
    assert f"1000 asked for, but this machine has room for {bound}" in err
    assert f"local cluster, {bound} worker(s)" in err


def test_ctrl_c_on_a_local_cluster_one_line_no_traceback(tiles, tmp_path):
    """Ctrl-C in a terminal sends SIGINT to the whole process group (the workers too): the
    subprocess runs in its own group and the group gets SIGINT, twice, once the cluster is
    up; expected: exit 130, one 'interrupted' line, no traceback, nothing written."""
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    _, whole = tiles
    out = tmp_path / "out"
    proc = _slipmap(
        ["planes", str(whole), "--out", str(out), "--workers", "2", "--tile-size", "2"],
        start_new_session=True,
    )
    lines = []
    deadline = time.monotonic() + LIMIT_S
    try:
        for line in proc.stderr:  # the cluster is up once the engine is described
            lines.append(line)
            if "Dask: " in line or time.monotonic() > deadline:
                break
        assert any("Dask: " in x for x in lines), "".join(lines)
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)
        time.sleep(0.3)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)  # the impatient second Ctrl-C
        rc, rest = _finish(proc)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    err = "".join(lines) + rest
    assert rc == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1] == "slipmap: interrupted", err
    assert not out.exists() or not any(out.iterdir())


def test_a_port_where_nothing_listens_is_refused(tiles, tmp_path):
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    folder, _ = tiles
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    out = tmp_path / "out"
    rc, err = _finish(
        _slipmap(
            ["planes", str(folder), "--out", str(out), "--scheduler", f"tcp://127.0.0.1:{port}"]
        )
    )
    assert rc == 2 and "Traceback" not in err, err
    line = err.strip().splitlines()[-1]
    assert "--scheduler" in line and "cannot reach" in line and "scheduler is running" in line
    assert not out.exists()


def test_a_local_cluster_leaves_no_gc_callback_for_a_ctrl_c_to_break():
    """Dask's GC diagnosis (a gc callback the in-process scheduler turns on) is off: a Ctrl-C
    inside it left its timer half-started and later collections printed tracebacks (CI)."""
    pytest.importorskip("distributed", reason="dask.distributed is not installed")
    import gc

    from distributed import gc as dgc

    from slipmap.app.engine import make_engine

    with make_engine(workers=1) as eng:
        assert eng.n_workers == 1
        assert not dgc._gc_diagnosis.enabled
        assert not any("GCDiagnosis" in repr(cb) for cb in gc.callbacks)
