"""``fieldlog acquire`` as a real subprocess against ``fieldlog sim --serve`` ptys; the MCAP is read back."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest

from fieldlog.acquire import gpsport, sbf
from fieldlog.drive import messages
from fieldlog.acquire.daemon import is_finished
from fieldlog.drive import reader
from fieldlog.replay import live
from test_serve import ROOT, expected_bytes, start_serve, wait_served
from fieldlog.drive.reader import read_metadata


def start_daemon(out: Path, paths: dict[str, str], *extra: str, **popen: Any) -> tuple[subprocess.Popen, str]:
    """Start the daemon (``popen``: more Popen arguments) and wait until it has opened both ports; returns it
    and its log up to then."""
    p = subprocess.Popen([sys.executable, "-m", "fieldlog", "acquire", "--daq", paths["daq"], "--gps", paths["gps"],
                          "--out", str(out), "--quiet", *extra], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, **popen)
    lines = []
    while True:
        line = p.stderr.readline()
        assert line, f"daemon exited early: {''.join(lines)}"
        lines.append(line)
        if "recording" in line:
            return p, "".join(lines)


def wait_until(ready: Callable[[], bool], what: str, timeout_s: float = 120.0) -> None:
    """Poll ``ready`` until it holds (a generous deadline: the host may be loaded; nothing is asserted on the time
    it took)."""
    end = time.monotonic() + timeout_s
    while not ready():
        assert time.monotonic() < end, f"{what}: not after {timeout_s:g} s"
        time.sleep(0.05)


def wait_caught_up(p: subprocess.Popen, quiet_s: float = 0.5) -> None:
    """Until the daemon ``p`` has processed what it recorded: its CPU time (``/proc/PID/stat``) grows by less than a
    tenth of ``quiet_s`` over ``quiet_s``. Its derived path may lag the raw bytes at x10 or x20 on a loaded host (the
    raw path never waits for it), and a stop leaves it only ``DERIVED_STOP_S`` to finish: a test that scores the
    derived topics of the whole drive waits for it before the stop."""
    def cpu_s() -> float:
        with open(f"/proc/{p.pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    prev = cpu_s()
    for _ in range(int(300 / quiet_s)):
        time.sleep(quiet_s)
        now = cpu_s()
        if now - prev < 0.1 * quiet_s:
            return
        prev = now


def bus_clients(path: Path) -> int:
    """Connections made to the Unix socket ``path`` (accepted or still queued): /proc/net/unix lists each with
    the socket's path, beside the listening socket itself."""
    with open("/proc/net/unix") as f:
        return sum(1 for line in f if line.rstrip().endswith(" " + str(path))) - 1


def wait_for_clients(path: Path, n: int) -> None:
    """Until ``n`` clients have connected to the live bus at ``path`` (before the drive streams: none misses a
    read)."""
    wait_until(lambda: bus_clients(path) >= n, f"{n} client(s) on {path}")


def raw_stream(path: Path, port: str) -> tuple[bytes, np.ndarray]:
    """The bytes recorded on ``/raw/<port>`` in order, and the host mono time of each read (a file may have
    no read of a port: a short rotated file on a loaded machine)."""
    if f"/raw/{port}" not in {t.topic for t in reader.topics(path)}:
        return b"", np.zeros(0, np.int64)
    msgs = reader.read_topic(path, f"/raw/{port}")["msgs"]
    return b"".join(bytes(m.data) for m in msgs), np.array([m.mono_ns for m in msgs], np.int64)


def byte_difference(got: bytes, want: bytes) -> str | None:
    """None when the two byte streams are equal; else one short line: their lengths and the first byte that
    differs (pytest's own diff of megabytes would take longer than the test)."""
    if got == want:
        return None
    n = min(len(got), len(want))
    d = np.flatnonzero(np.frombuffer(got[:n], np.uint8) != np.frombuffer(want[:n], np.uint8))
    i = int(d[0]) if len(d) else n
    return f"{len(got)} bytes recorded, {len(want)} expected; first difference at byte {i}"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fieldlog", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def gps_frames(data: bytes) -> dict[str, int]:
    """Checked frames per protocol in a GPS byte stream (what the daemon's counters should show)."""
    out: dict[str, int] = {}
    for kind, _ in gpsport.Framer().feed(data):
        out[kind] = out.get(kind, 0) + 1
    return out


@pytest.mark.parametrize("receiver", ["nmea", "ublox", "septentrio"])
def test_live_capture_at_speed_20_loses_nothing_across_rotations_and_on_the_bus(tmp_path: Path,
                                                                                  receiver: str) -> None:
    truth = tmp_path / "truth.mcap"
    bus = tmp_path / "bus.sock"
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(f'[rotation]\nmax_duration_s = 1.0\n[daemon]\nbus = "{bus}"\n')
    serve, paths = start_serve("--scenario", "figure8", "--duration", "40", "--seed", "5", "--speed", "20",
                               "--hold", "--truth", str(truth), "--receiver", receiver)
    d, _ = start_daemon(tmp_path / "drives", paths, "--config", str(cfg))
    blocks: list = []
    client = threading.Thread(target=lambda: blocks.extend(live.iter_blocks(str(bus), ["/imu", "/gps/fix"], 1.0,
                                                                            final=True)))
    client.start()
    wait_for_clients(bus, 1)
    serve.send_signal(signal.SIGUSR1)
    wait_served(serve, d, 300)                          # the drive ended and the daemon drained the ptys
    wait_caught_up(d)
    d.send_signal(signal.SIGTERM)
    assert d.wait(300) == 0, d.stderr.read()
    client.join(60)
    files = sorted((tmp_path / "drives").glob("*/*.mcap"))
    assert len(files) >= 2 and all(is_finished(f) for f in files)
    metas = [read_metadata(f) for f in files]
    assert [m["drive"]["previous_file"] for m in metas] == [""] + [f.name for f in files[:-1]]
    want = expected_bytes(truth, "figure8", 40.0, 5)
    got_daq = b"".join(raw_stream(f, "daq")[0] for f in files)
    got_gps = b"".join(raw_stream(f, "gps")[0] for f in files)
    mono = np.concatenate([raw_stream(f, "daq")[1] for f in files])
    assert got_daq == want["daq"]                       # every byte, in order: 0 lost DAQ frames
    assert got_gps == want["gps"]                       # 0 lost NMEA lines or UBX messages
    assert np.all(np.diff(mono) >= 0)                   # files follow each other seamlessly
    c = metas[-1]["acquire.counters"]                   # cumulative over the session
    assert int(c["daq.frames"]) == 20000 == int(read_metadata(truth)["serve"]["daq_frames"])
    assert int(c["daq.lost_frames"]) == 0 and int(c["daq.bad_crc"]) == 0
    frames = gps_frames(want["gps"])
    assert {k: int(c.get(f"gps.frames.{k}", 0)) for k in frames} == frames
    assert (receiver == "ublox") == (frames.get("ubx", 0) > 0) and int(c.get("ubx.undecodable", 0)) == 0
    assert (receiver == "septentrio") == (frames.get("sbf", 0) > 0) and int(c.get("sbf.undecodable", 0)) == 0
    assert int(c["port.daq.dropped_reads"]) == 0 and int(c["daemon.late_reads"]) == 0
    # /imu: one message per frame, increasing stamps, and frame k carries truth sample k (scored by index:
    # at x20 the stamps are host-clock based, see tools/sim/serve.py)
    parts = [reader.read_topic(f, "/imu") for f in files if "/imu" in {t.topic for t in reader.topics(f)}]
    imu = {k: np.concatenate([p[k] for p in parts]) for k in ("log_time_ns", "omega_ib_b", "f_b")}
    tru = reader.read_topic(truth, "/truth/imu")
    assert len(imu["log_time_ns"]) == len(tru["log_time_ns"]) == 20000
    assert np.all(np.diff(imu["log_time_ns"]) > 0)
    err = imu["omega_ib_b"] - tru["omega_ib_b"]
    assert np.sqrt(np.mean(err[:, 2] ** 2)) < 0.01                    # rad/s: noise + bias only
    f, f_true = imu["f_b"], tru["f_b"]
    assert np.ptp(f_true[:, 1]) > 0.5                                # it drives off at 30 s
    assert np.corrcoef(f[:, 1], f_true[:, 1])[0, 1] > 0.95           # forward acceleration lines up sample by sample
    # the live bus delivered the same IMU samples, in reader blocks
    live_t = np.concatenate([b.data["/imu"]["log_time_ns"] for b in blocks])
    live_f = np.concatenate([b.data["/imu"]["f_b"] for b in blocks])
    order = np.argsort(live_t, kind="stable")
    assert np.array_equal(live_t[order], imu["log_time_ns"]) and np.array_equal(live_f[order], f)
    fixes = sum(reader.read_topic(f, "/gps/fix")["log_time_ns"].size for f in files
                if "/gps/fix" in {t.topic for t in reader.topics(f)})
    # (u-blox: 3 messages an epoch, so the 5 the simulator drops cost up to 5 NAV-PVT)
    assert sum(len(b.data["/gps/fix"]["log_time_ns"]) for b in blocks) == fixes >= (38 if receiver == "nmea" else 33)
    if receiver == "ublox":     # one fix per NAV-PVT sent (the simulator drops 5 messages at random)
        assert fixes == sum(1 for k, fr in gpsport.Framer().feed(want["gps"]) if k == "ubx" and fr[2:4] == b"\x01\x07")
    if receiver == "septentrio":    # one fix per PVTGeodetic sent
        assert fixes == sum(1 for k, fr in gpsport.Framer().feed(want["gps"])
                            if k == "sbf" and sbf.block_name(fr) == "PVTGeodetic")


@pytest.mark.slow
def test_kill9_then_recover_and_restart(tmp_path: Path) -> None:
    out = tmp_path / "drives"
    serve, paths = start_serve("--scenario", "figure8", "--duration", "600", "--speed", "10", "--hold")
    try:
        d, _ = start_daemon(out, paths)
        serve.send_signal(signal.SIGUSR1)
        files = lambda: sorted(out.glob("*/*.mcap"))     # noqa: E731
        wait_until(lambda: files() and files()[0].stat().st_size > 300_000, "a recording with chunks")
        kill_mono = time.monotonic_ns()
        d.send_signal(signal.SIGKILL)
        d.wait(300)
        (cut,) = sorted(out.glob("*/*.mcap"))
        assert not is_finished(cut)
        r = run("recover", str(cut), "--out", str(tmp_path / "rescued.mcap"))
        assert r.returncode == 0, r.stderr
        _, mono = raw_stream(tmp_path / "rescued.mcap", "daq")
        assert len(mono) > 100
        assert (kill_mono - mono[-1]) / 1e9 <= 1.5     # at most 1.5 s of data before the kill is missing
        # a restart notices the unfinished file, recovers it next to the original, and SIGTERM finishes its own
        d2, log = start_daemon(out, paths)
        others = lambda: [p for p in files() if p != cut and not p.name.endswith(".recovered.mcap")]  # noqa: E731
        wait_until(lambda: others() and others()[0].stat().st_size > 100_000, "the restart's own file, with chunks")
        d2.send_signal(signal.SIGTERM)
        assert d2.wait(300) == 0
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(300)
    assert f"recovered unfinished {cut.name}" in log
    rec = cut.with_name(cut.stem + ".recovered.mcap")
    assert is_finished(rec) and not is_finished(cut)
    assert len(raw_stream(rec, "daq")[1]) == len(mono)
    new = [p for p in out.glob("*/*.mcap") if p not in (cut, rec)]
    assert len(new) == 1 and is_finished(new[0])
    assert reader.read_topic(new[0], "/raw/daq")["log_time_ns"].size > 0


@pytest.mark.parametrize("config, extra, key", [
    ("", ["--gps", "/dev/null"], "[daq] port"),                      # missing port
    ("[daq]\nbaud = 12345\n", ["--daq", "/dev/ptmx", "--gps", "/dev/null"], "[daq] baud"),
    ("[daq\nport = 1\n", ["--daq", "/dev/ptmx", "--gps", "/dev/null"], "not valid TOML"),
    ("[recorder]\nflush_interval_s = 5\n", ["--daq", "a", "--gps", "b"], "[recorder] flush_interval_s"),
    ("[gps]\nbaudrate = 9600\n", ["--daq", "a", "--gps", "b"], "[gps] baudrate"),
    ("", ["--daq", "/nonexistent/ttyUSB9", "--gps", "/nonexistent/ttyUSB8"], "[daq] port: cannot open"),
])
def test_bad_config_is_one_clear_line_and_exit_2(tmp_path: Path, config: str, extra: list[str], key: str) -> None:
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(config)
    r = run("acquire", "--config", str(cfg), "--out", str(tmp_path / "d"), *extra)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and key in lines[0] and "Traceback" not in r.stderr


def test_nmea_status_decoding_from_sink_payload() -> None:
    """The status line reads fix and satellites back from the /gps/nmea payload the sink saw."""
    from fieldlog.acquire import nmea

    line = nmea.format_gga("GN", 3600.0, 30.5, 104.0, 1, 11, 0.9, 500.0, -35.0).decode().strip()
    data = messages.encode_sentence(1, line)
    text = messages.decode_message("nmea_msgs/msg/Sentence", data).sentence
    body, ok = nmea.split_checksum(text.encode())
    g = nmea.decode_body(body)
    assert ok and g.num_sats == 11 and g.quality == 1


def test_log_lines_are_timestamped_and_levelled() -> None:
    """`acquire -q/-qq/-v`: one line per event with its UTC time and level, through `logging`."""
    import io
    import logging
    import re

    from fieldlog.acquire import daemon

    log = logging.getLogger("fieldlog.acquire")
    try:
        for verbosity, shown in ((-2, ["WARNING"]), (-1, ["INFO", "WARNING"]), (1, ["DEBUG", "INFO", "WARNING"])):
            buf = io.StringIO()
            daemon.setup_logging(verbosity, buf)
            log.debug("status line")
            log.info("recording x")
            log.warning("daq port lost: unplugged")
            lines = buf.getvalue().splitlines()
            assert [line.split()[1] for line in lines] == shown
            for line in lines:
                assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z [A-Z]+ fieldlog\.acquire: .+", line), line
    finally:
        logging.getLogger("fieldlog").handlers.clear()
