"""``fieldlog acquire --gps gpsd://...``: the receiver read through a real gpsd (Debian package ``gpsd``) that the
test starts on the simulator's GPS pseudo-terminal and a loopback port; the drive is read back and rebuilt."""
from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import config, gpsport
from fieldlog.acquire.daemon import is_finished
from fieldlog.acquire.gpsd import GpsdStream, watch_command
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata, read_metadata_records
from test_daemon import raw_stream, run
from test_daemon_faults import LOCKED, SPEED, record
from test_drive import messages_by_topic
from test_serve import expected_bytes

LOOPBACK = {"127.0.0.1", "::1"}


def free_loopback_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def listening_addresses(pid: int) -> set[str]:
    """The local addresses of every TCP/UDP socket process ``pid`` holds (from /proc)."""
    inodes = set()
    for fd in os.listdir(f"/proc/{pid}/fd"):
        target = os.readlink(f"/proc/{pid}/fd/{fd}")
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = set()
    for table, v6 in (("tcp", False), ("udp", False), ("tcp6", True), ("udp6", True)):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            cols = line.split()
            if cols[9] not in inodes:
                continue
            raw = bytes.fromhex(cols[1].split(":")[0])
            # /proc prints the address as host-order 32-bit words
            words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
            out.add(socket.inet_ntop(socket.AF_INET6 if v6 else socket.AF_INET, words))
    return out


class Gpsd:
    """A gpsd on ``device`` at 127.0.0.1:``port`` (no -G: loopback only), in the foreground, killed by ``stop``."""

    def __init__(self, device: str, port: int, ctl: Path) -> None:
        self.device, self.port, self.ctl = device, port, ctl
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(["gpsd", "-N", "-n", "-S", str(self.port), "-F", str(self.ctl), self.device],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 20
        while True:
            assert self.proc.poll() is None, f"gpsd exited: {self.proc.stderr.read().decode()}"
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return
            except OSError:
                assert time.monotonic() < deadline, "gpsd did not listen within 20 s"
                time.sleep(0.05)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        self.proc = None


@pytest.fixture
def gpsd_available() -> None:
    if shutil.which("gpsd") is None:
        pytest.skip("gpsd is not installed (Debian package gpsd)")


@pytest.fixture
def gpsd_factory(tmp_path: Path, gpsd_available: None) -> Iterator:
    started: list[Gpsd] = []

    def make(device: str) -> Gpsd:
        g = Gpsd(device, free_loopback_port(), tmp_path / "gpsd.sock")
        started.append(g)
        g.start()
        return g

    yield make
    for g in started:
        g.stop()


def test_gpsd_url_parsing() -> None:
    p = config.parse_gpsd_url
    assert p("/dev/ttyUSB1") is None
    assert p("gpsd://localhost") == config.GpsdAddress("localhost", 2947, "")
    assert p("gpsd://127.0.0.1:3000/dev/ttyACM0") == config.GpsdAddress("127.0.0.1", 3000, "/dev/ttyACM0")
    assert p("gpsd://[::1]:2948") == config.GpsdAddress("::1", 2948, "")
    assert str(p("gpsd://[::1]:2948/dev/gps0")) == "gpsd://[::1]:2948/dev/gps0"
    for bad in ("gpsd://", "gpsd://host:0", "gpsd://host:x/dev/a", "gpsd://[::1/dev/a", "gpsd://:2947"):
        with pytest.raises(config.ConfigError, match=r"\[gps\] port"):
            p(bad)
    with pytest.raises(config.ConfigError, match=r"\[daq\] port"):
        config.load(None, {"daq": "gpsd://localhost", "gps": "/dev/ttyUSB1"})


def test_gpsd_reports_are_taken_out_and_receiver_bytes_pass_unchanged() -> None:
    """gpsd's JSON lines between packets go; receiver bytes, including ones that look like the start of a
    report, pass in order whatever the read boundaries."""
    ubx = b"\xb5\x62\x01\x07\x04\x00{\"cl\x00\x00"                     # payload bytes like a report's start
    fake = b'{"class":"not json\r\n'                                     # a marker without a JSON line
    rx = [b"$GPGGA,1*00\r\n", ubx, fake, b"\xb5\x62\x01\x07\x02\x00{\""]  # ends in the marker's first bytes
    reports = [b'{"class":"VERSION","release":"3.22"}\r\n', b'{"class":"DEVICE","path":"/dev/pts/3"}\r\n',
               b'{"class":"ERROR","message":"unknown device"}\r\n']
    stream = reports[0] + rx[0] + reports[1] + rx[1] + rx[2] + reports[2] + rx[3]
    for cut in range(1, len(stream), 7):
        for step in (cut, len(stream)):
            s = GpsdStream()
            got = b"".join(s.feed(stream[i:i + step]) for i in range(0, len(stream), step)) + s.feed(b"\n")
            assert got == b"".join(rx) + b"\n" and s.reports_seen == 3
            assert [r["class"] for r in s.reports] == ["VERSION", "DEVICE", "ERROR"]
    assert watch_command("/dev/gps0") == b'?WATCH={"enable":true,"raw":2,"device":"/dev/gps0"}\n'


def _session(tmp_path: Path, gpsd_factory, receiver: str, duration: float, restart_at_s: float | None = None):
    """A drive recorded through a gpsd on the GPS pty; gpsd stopped for 0.5 s of host time ``restart_at_s``
    into the drive when given. Returns the drive file, the truth file, gpsd's socket addresses, the log."""
    started: list = []

    def attach(paths: dict[str, str]) -> dict[str, str]:
        g = gpsd_factory(paths["gps"])
        started.append((g, listening_addresses(g.proc.pid)))
        return {"daq": paths["daq"], "gps": f"gpsd://127.0.0.1:{g.port}{paths['gps']}"}

    def restart() -> None:
        time.sleep(restart_at_s / SPEED)
        g = started[0][0]
        g.stop()
        time.sleep(0.5)
        g.start()

    f, truth, log = record(tmp_path, "--receiver", receiver, duration=duration, seed=4, attach=attach,
                           during=restart if restart_at_s is not None else None)
    return f, truth, started[0][1], log


@pytest.mark.slow
@pytest.mark.parametrize("receiver", ["nmea", "ublox"])
def test_daemon_through_a_real_gpsd_records_the_receivers_bytes_and_locks(tmp_path: Path, gpsd_factory,
                                                                          receiver: str) -> None:
    f, truth, addresses, _ = _session(tmp_path, gpsd_factory, receiver, 120.0)
    assert addresses and addresses <= LOOPBACK                  # gpsd listens on loopback only
    assert is_finished(f)
    sent = expected_bytes(truth, "figure8", 120.0, 4)["gps"]
    got, mono = raw_stream(f, "gps")
    # the receiver's own bytes: one contiguous run of the stream the simulator wrote, from a packet boundary
    # (gpsd drops what it read before it recognised the receiver: about a second of host time, 20 s of this
    # x20 drive), with gpsd's JSON reports taken out
    assert len(got) > 0.5 * len(sent)
    start = sent.find(got)
    assert start >= 0 and start + len(got) == len(sent)
    fr = gpsport.Framer()
    fr.feed(sent)
    ends = {0, *fr.ends, *(e + 1 for e in fr.ends)}          # after a frame (and its LF)
    assert start in ends
    assert b'{"class"' not in got and np.all(np.diff(mono) >= 0)
    c = read_metadata(f)["acquire.counters"]
    assert int(c["port.gps.gpsd_reports"]) >= 3                 # VERSION, DEVICES, WATCH at least
    fix = reader.read_topic(f, "/gps/fix")
    frames = [k for k, fr_ in gpsport.Framer().feed(got) if k == "ubx" and fr_[2:4] == b"\x01\x07"]
    if receiver == "ublox":
        want_fixes = len(frames)
    else:  # a fix per epoch (the timed sentences of one time of day) from the first whose date is known (its
        # RMC or ZDA): gpsd's cut may fall inside an epoch, so the first may lack its GGA or its date
        epochs: dict[bytes, set[bytes]] = {}
        for kind, tod in re.findall(rb"\$..(GGA|RMC|GST|ZDA|GNS),(\d{6}(?:\.\d+)?),", got):
            epochs.setdefault(tod, set()).add(kind)
        want_fixes = len(epochs) - next(i for i, kinds in enumerate(epochs.values()) if kinds & {b"RMC", b"ZDA"})
    assert len(fix["log_time_ns"]) == want_fixes > 30
    sync = reader.read_topic(f, "/time/sync")["state"]
    assert sync[-1] == LOCKED
    # /imu stamped by the GPS-disciplined clock: within 3 ms of each sample's true time once locked
    imu = reader.read_topic(f, "/imu")
    tru = reader.read_topic(truth, "/truth/imu")
    assert len(imu["log_time_ns"]) == len(tru["log_time_ns"])
    assert abs(int(imu["log_time_ns"][-1]) - int(tru["log_time_ns"][-1])) < 3_000_000
    out = tmp_path / "rebuilt.mcap"
    r = run("rebuild", str(f), "--out", str(out))
    assert r.returncode == 0, r.stderr
    topics = ["/imu", "/gps/fix", "/gps/nmea", "/pps", "/time/sync", "/raw/daq", "/raw/gps"]
    written, rebuilt = messages_by_topic(f, topics), messages_by_topic(out, topics)
    for topic in topics:
        a, b = written[topic], rebuilt[topic]
        assert a == b and (len(a) > 0 or topic == "/gps/nmea" and receiver == "ublox"), topic


@pytest.mark.slow
def test_lost_gpsd_is_survived_as_an_unplugged_port(tmp_path: Path, gpsd_factory) -> None:
    f, truth, _, log = _session(tmp_path, gpsd_factory, "nmea", 160.0, restart_at_s=60.0)
    events = [d for name, d in read_metadata_records(f) if name == "acquire.port_event" and d["port"] == "gps"]
    assert [e["event"] for e in events[:2]] == ["lost", "back"]
    lost, back = (int(e["mono_ns"]) for e in events[:2])
    c = read_metadata(f)["acquire.counters"]
    assert int(c["port.gps.disconnects"]) == len([e for e in events if e["event"] == "lost"]) >= 1
    _, mono = raw_stream(f, "gps")
    assert np.any(mono < lost) and np.any(mono > back) and not np.any((mono > lost) & (mono < back))
    assert "gps port lost" in log and "gps port back" in log
    # locked, lost in the gap, locked again after it (not necessarily at the last second: at x20 a loaded host
    # delays a fix past the sync's host gates, and an edge near the end may be refused)
    state = reader.read_topic(f, "/time/sync")["state"]
    locked = np.flatnonzero(state == LOCKED)
    lost = np.flatnonzero(state[locked[0]:] != LOCKED) + locked[0]
    assert len(lost) and locked[-1] > lost[0]
