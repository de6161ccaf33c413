"""The daemon's raw path never waits for its derived path (acquire/daemon.py), as a real subprocess on
``fieldlog sim --serve`` ptys: a PPS line flagged on every frame, and a derived path made slow on purpose (a
subclass of the Daemon whose derived step sleeps), each for 25 s at real speed, then SIGINT. Every DAQ byte
written to the pty is recorded, and the file is finished within the daemon's stop bound. A derived path that
fails (a subclass whose derived step raises) is logged, closes the live bus and leaves the recording going."""
from __future__ import annotations

import dataclasses
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import pytest

from fieldlog.acquire import daemon
from fieldlog.acquire.daemon import is_finished
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim import simulate, trajectory
from test_daemon import raw_stream, wait_until
from test_serve import ROOT, start_serve, wait_served

NS = 1_000_000_000
SECONDS = 25.0

# the daemon with its derived path slowed on purpose: DELAY_S of sleep before each read is processed
SLOW_DAEMON = """
import sys, time
from fieldlog.acquire import config, daemon

daq, gps, out, delay_s, queue_mb = sys.argv[1:6]

class SlowDerived(daemon.Daemon):
    def derive_read(self, h):
        time.sleep(float(delay_s))
        super().derive_read(h)

daemon.setup_logging(0)
cfg = config.load(None, {"daq": daq, "gps": gps, "out": out})
cfg.daemon.derived_queue_mb = float(queue_mb)
sys.exit(daemon.run_daemon(cfg, daemon_class=SlowDerived))
"""

# the daemon with a live bus and a derived path that raises, outside the Pipeline's own guard, at read FAIL_AT
FAILING_DAEMON = """
import sys
from fieldlog.acquire import config, daemon

daq, gps, out, bus, fail_at = sys.argv[1:6]

class FailingDerived(daemon.Daemon):
    taken = 0

    def derive_read(self, h):
        self.taken += 1
        if self.taken == int(fail_at):
            raise RuntimeError("injected")
        super().derive_read(h)

daemon.setup_logging(0)
cfg = config.load(None, {"daq": daq, "gps": gps, "out": out})
cfg.daemon.bus = bus
sys.exit(daemon.run_daemon(cfg, daemon_class=FailingDerived))
"""


def floating_pps_scenario(tmp_path: Path) -> Path:
    """figure8 with the PPS flag set on every DAQ frame (a floating PPS input)."""
    p = tmp_path / "floating-pps.toml"
    p.write_text('extends = "figure8"\nname = "figure8-floating-pps"\n[clock]\nglitch_pps = 1000000000\n')
    return p


def sent_daq(truth: Path, scenario: str | Path) -> tuple[bytes, dict[str, str]]:
    """The DAQ bytes the serve process wrote to its pty (none were lost: no unplug), and its metadata."""
    meta = read_metadata(truth)["serve"]
    assert meta["completed"] == "True" and meta["daq_lost_bytes"] == "0"
    sc = trajectory.load_scenario(scenario)
    sc = dataclasses.replace(sc, clock={**sc.clock, "start_utc_ns": int(meta["drive_start_utc_ns"])})
    reads = simulate.make_reads(sc, float(meta["duration_s"]), int(meta["seed"]), meta["pps_mode"])[0]
    stream = b"".join(r.data for r in reads if r.port == "daq")
    assert len(stream) == int(meta["daq_bytes"])
    return stream, meta


def run_and_interrupt(tmp_path: Path, argv: list[str], scenario: str | Path, seed: int, seconds: float = SECONDS,
                      on_recording: Callable[[], None] = lambda: None) -> tuple[Path, str, float, Path]:
    """Serve ``scenario`` for ``seconds`` at real speed to the daemon started by ``argv`` (it prints 'recording'
    once its ports are open; then ``on_recording`` is called), SIGINT it as soon as the serve has ended; returns
    the one drive file, the daemon's log, the host seconds from SIGINT to its exit, and the truth file."""
    truth = tmp_path / "truth.mcap"
    serve, paths = start_serve("--scenario", str(scenario), "--duration", str(seconds), "--seed", str(seed),
                               "--speed", "1", "--hold", "--truth", str(truth))
    try:
        ports = {f"{{{name}}}": path for name, path in paths.items()}
        err = tmp_path / "daemon.log"            # (a file: a pipe nobody reads while it runs could fill)
        d = subprocess.Popen([ports.get(a, a) for a in argv], cwd=ROOT, stdout=subprocess.DEVNULL,
                             stderr=err.open("w"), text=True)
        wait_until(lambda: "recording" in err.read_text() or d.poll() is not None, "the daemon's ports open")
        assert d.poll() is None, err.read_text()
        on_recording()
        serve.send_signal(signal.SIGUSR1)
        wait_served(serve, d, 300)
    finally:
        if serve.poll() is None:
            serve.kill()
    t0 = time.monotonic()
    d.send_signal(signal.SIGINT)
    code = d.wait(120)
    exit_s = time.monotonic() - t0
    log = err.read_text()
    assert code == 0, log
    (f,) = sorted((tmp_path / "drives").glob("*/*.mcap"))
    assert is_finished(f)
    return f, log, exit_s, truth


def check_raw_kept_and_stop_bounded(f: Path, truth: Path, scenario: str | Path, exit_s: float) -> dict[str, str]:
    """Every DAQ byte written is recorded, in order; the file was closed within ``daemon.STOP_S`` of the signal
    (the daemon's own record of it); returns the ``acquire.stop`` record."""
    sent, _ = sent_daq(truth, scenario)
    got, _ = raw_stream(f, "daq")
    assert len(got) >= 0.95 * len(sent) and got == sent[:len(got)]
    assert len(got) == len(sent)                  # (the serve drained the pty before the signal)
    stop = read_metadata(f)["acquire.stop"]
    latency_s = (int(stop["close_mono_ns"]) - int(stop["signal_mono_ns"])) / NS
    assert 0 < latency_s <= daemon.STOP_S, stop
    assert exit_s < daemon.STOP_S + 30         # the process ends after the file is closed (a loaded host: slack)
    print(f"stop: file closed {latency_s:.3f} s after SIGINT, process exit {exit_s:.3f} s; {stop}")
    return stop


@pytest.mark.slow
def test_a_floating_pps_neither_costs_raw_bytes_nor_delays_the_stop(tmp_path: Path) -> None:
    scenario = floating_pps_scenario(tmp_path)
    argv = [sys.executable, "-m", "fieldlog", "acquire", "--daq", "{daq}", "--gps", "{gps}",
            "--out", str(tmp_path / "drives"), "--quiet"]
    f, log, exit_s, truth = run_and_interrupt(tmp_path, argv, scenario, seed=8)
    stop = check_raw_kept_and_stop_bounded(f, truth, scenario, exit_s)
    assert "PPS is implausible" in log
    c = read_metadata(f)["acquire.counters"]
    frames = int(c["daq.frames"])
    assert frames == SECONDS * 500
    assert int(c["pps_implausible"]) > 0.99 * frames and int(c["processing_errors"]) == 0
    assert stop["derived"] == "complete" and int(c["daemon.derived_dropped_reads"]) == 0
    assert len(reader.read_topic(f, "/imu")["log_time_ns"]) == frames      # the derived path kept up


@pytest.mark.slow
def test_a_slow_derived_path_lags_and_drops_while_every_raw_byte_is_kept_and_the_stop_is_bounded(
        tmp_path: Path) -> None:
    # 20 ms per read: the derived path takes ~50 reads a second of the ~150 (~30 kB) the ports deliver, its queue
    # of 100 kB fills within seconds and the reads are dropped while it is half full (counted); SIGINT then finds
    # it behind
    scenario = floating_pps_scenario(tmp_path)
    argv = [sys.executable, "-c", SLOW_DAEMON, "{daq}", "{gps}", str(tmp_path / "drives"), "0.02", "0.1"]
    f, log, exit_s, truth = run_and_interrupt(tmp_path, argv, scenario, seed=9)
    stop = check_raw_kept_and_stop_bounded(f, truth, scenario, exit_s)
    c = read_metadata(f)["acquire.counters"]
    dropped = int(c["daemon.derived_dropped_reads"])
    reads = int(c["reads.daq"]) + int(c["reads.gps"])
    assert 0 < dropped < reads and int(c["port.daq.dropped_reads"]) == 0
    assert "reads are recorded and not processed" in log
    assert any("derived" in line and "behind" in line and "reads not processed" in line
               for line in log.splitlines() if "fr/s" in line)                 # the status line says so
    assert stop["derived"] == "cut" and int(stop["reads_not_processed"]) >= dropped
    assert "the derived topics end there" in log
    # the derived path decoded part of the frames: those of the reads it processed
    assert 0 < int(c["daq.frames"]) < SECONDS * 500 * 0.9


@pytest.mark.slow
def test_a_failing_derived_path_closes_the_bus_and_recording_goes_on(tmp_path: Path) -> None:
    # the derived step raises at its 300th read (~2 s in): one error line, the bus's client sees its end then,
    # and the raw path records the rest of the drive; rebuild derives the whole of it from the raw bytes
    seconds, bus = 8.0, tmp_path / "bus.sock"
    scenario = "figure8"
    argv = [sys.executable, "-c", FAILING_DAEMON, "{daq}", "{gps}", str(tmp_path / "drives"), str(bus), "300"]
    client: dict[str, int] = {"bytes": 0}

    def listen() -> None:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as c:
            c.connect(str(bus))
            client["connected_ns"] = time.monotonic_ns()
            while data := c.recv(1 << 16):
                client["bytes"] += len(data)
            client["end_ns"] = time.monotonic_ns()

    listener = threading.Thread(target=listen, daemon=True)
    f, log, exit_s, truth = run_and_interrupt(tmp_path, argv, scenario, seed=10, seconds=seconds,
                                              on_recording=listener.start)
    listener.join(30)
    stop = check_raw_kept_and_stop_bounded(f, truth, scenario, exit_s)
    assert "Traceback" not in log
    failed = [line for line in log.splitlines() if "the derived path failed" in line]
    assert len(failed) == 1 and "RuntimeError: injected" in failed[0] and "fieldlog rebuild" in failed[0], log
    assert any("derived FAILED" in line for line in log.splitlines() if "fr/s" in line)   # the status line
    c = read_metadata(f)["acquire.counters"]
    assert c["daemon.derived_error"].startswith("RuntimeError: injected")
    reads = int(c["reads.daq"]) + int(c["reads.gps"])
    dropped = int(c["daemon.derived_dropped_reads"])
    # every read after the one that raised is recorded and not processed: queued before the failure, or not queued
    assert stop["derived"] == "failed" and int(stop["reads_not_processed"]) == reads - 300 and dropped > 0
    # the bus sent frames, then ended at the failure, well before the SIGINT
    assert client["bytes"] > 0 and client["connected_ns"] < client["end_ns"] < int(stop["signal_mono_ns"])
    assert 0 < int(c["daq.frames"]) < 0.9 * seconds * 500      # the frames of the reads before the failure
    rebuilt = tmp_path / "rebuilt.mcap"
    r = subprocess.run([sys.executable, "-m", "fieldlog", "rebuild", str(f), "--out", str(rebuilt)], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert len(reader.read_topic(rebuilt, "/imu")["log_time_ns"]) == seconds * 500
