"""``fieldlog sim --serve``: real subprocess, real ptys, bytes compared with the simulator's reads."""
from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import tempfile
import tty
from pathlib import Path

import numpy as np
import pytest

from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim.serve import corrupt_stream, simulated_streams

ROOT = Path(__file__).resolve().parents[1]


def stacks(pid: int) -> str:
    """The Python and native stacks of every thread of process pid (py-spy, a dev dependency), or why not."""
    try:
        return subprocess.run([Path(sys.executable).with_name("py-spy"), "dump", "--native", "--pid", str(pid)],
                              capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError) as e:
        return f"(no stacks: {e})"


def wait_served(serve: subprocess.Popen, reader_proc: subprocess.Popen, timeout_s: float) -> None:
    """Until ``serve`` (``start_serve``) has ended with exit code 0: its drive streamed and ``reader_proc`` (the
    daemon or gpsd reading its ports) drained the ptys. One still running after ``timeout_s`` fails the test with
    the stacks of both processes (``stacks``) and their logs, both then killed: an intermittent hang says where
    each waited."""
    try:
        rc = serve.wait(timeout_s)
    except subprocess.TimeoutExpired:
        report = []
        for name, p in (("sim --serve", serve), ("its reader", reader_proc)):
            state = f"exited {p.returncode}" if p.poll() is not None else f"running; its threads:\n{stacks(p.pid)}"
            p.kill()
            p.wait()
            report.append(f"{name} (pid {p.pid}), {state}\nits log:\n{p.stderr.read() if p.stderr else ''}")
        pytest.fail(f"sim --serve had not ended after {timeout_s:g} s\n" + "\n".join(report))
    assert rc == 0, serve.stderr.read()


def start_serve(*args: str) -> tuple[subprocess.Popen, dict[str, str]]:
    """Start ``fieldlog sim --serve`` and return it with ``{port: path}``: the links of a ``--link-dir`` of its own
    (a new temporary folder) unless ``args`` name one, else its ``{port: pty path}`` lines.

    Through the links, a reader that outlives its drive (a daemon or gpsd retrying a lost port) finds no file
    once the serve has closed its ptys; given the pty path itself it could open the next pty of that number,
    which a test running beside it may have been given (ptys are numbered lowest free first)."""
    links = None
    if "--link-dir" not in args:
        links = Path(tempfile.mkdtemp(prefix="serve-")) / "ports"
        args = (*args, "--link-dir", str(links))
    p = subprocess.Popen([sys.executable, "-m", "fieldlog", "sim", "--serve", *args], cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    paths = {}
    for _ in range(2):
        name, path = p.stdout.readline().split()
        paths[name] = str(links / name) if links is not None else path
    return p, paths


def expected_bytes(truth_path: Path, scenario: str, duration_s: float, seed: int) -> dict[str, bytes]:
    """The simulator's byte streams per port, for the drive start the serve process used (checking that it
    served this scenario, duration and seed)."""
    meta = read_metadata(truth_path)["serve"]
    assert (meta["scenario"], float(meta["duration_s"]), int(meta["seed"])) == (scenario, duration_s, seed)
    return simulated_streams(meta)


def test_serve_streams_exactly_the_simulated_bytes(tmp_path: Path) -> None:
    truth = tmp_path / "truth.mcap"
    p, paths = start_serve("--scenario", "figure8", "--duration", "6", "--seed", "3", "--speed", "20",
                           "--hold", "--truth", str(truth))
    assert set(paths) == {"daq", "gps"} and all(os.path.realpath(v).startswith("/dev/pts/") for v in paths.values())
    fds = {}
    for name, path in paths.items():
        fds[name] = os.open(path, os.O_RDONLY | os.O_NOCTTY)
        tty.setraw(fds[name])
    got = {name: bytearray() for name in fds}
    p.send_signal(signal.SIGUSR1)
    open_fds = dict(fds)
    while open_fds:
        ready, _, _ = select.select(list(open_fds.values()), [], [], 5.0)
        assert ready, "serve stopped sending without closing the ptys"
        for name, fd in list(open_fds.items()):
            if fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    data = b""
                if not data:
                    del open_fds[name]
                got[name] += data
    assert p.wait(300) == 0
    for fd in fds.values():
        os.close(fd)
    want = expected_bytes(truth, "figure8", 6.0, 3)
    assert bytes(got["daq"]) == want["daq"]
    assert bytes(got["gps"]) == want["gps"]
    meta = read_metadata(truth)["serve"]
    assert meta["completed"] == "True"
    assert int(meta["daq_frames"]) == 3000 == len(want["daq"]) // 38
    assert int(meta["nmea_lines"]) == want["gps"].count(b"\n") > 0
    assert reader.read_topic(truth, "/truth/imu")["log_time_ns"].shape == (3000,)


def test_serve_stops_on_sigterm_and_writes_truth(tmp_path: Path) -> None:
    truth = tmp_path / "truth.mcap"
    p, paths = start_serve("--scenario", "static", "--duration", "60", "--speed", "1", "--truth", str(truth))
    fd = os.open(paths["daq"], os.O_RDONLY | os.O_NOCTTY)
    tty.setraw(fd)
    assert select.select([fd], [], [], 10.0)[0]          # it streams
    p.send_signal(signal.SIGTERM)
    assert p.wait(300) == 0
    os.close(fd)
    meta = read_metadata(truth)["serve"]
    assert meta["completed"] == "False"
    assert 0 < int(meta["daq_frames"]) < 30000


def test_corrupt_stream_changes_exactly_the_positions_it_reports() -> None:
    data = bytes(range(256)) * 100
    out, pos = corrupt_stream(data, 0.01, 3, "daq")
    changed = np.flatnonzero(np.frombuffer(out, np.uint8) != np.frombuffer(data, np.uint8))
    assert np.array_equal(changed, pos) and pos.size == 256
    assert corrupt_stream(data, 0.01, 3, "daq")[0] == out != corrupt_stream(data, 0.01, 3, "gps")[0]
