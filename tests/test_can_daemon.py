"""``fieldlog acquire --can slcan://...`` as a real subprocess against ``fieldlog sim --serve --can`` on three ptys,
with the SLCAN adapter unplugged for a while and garbage on every line; the MCAP is read back and rebuilt."""
from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import can
from fieldlog.drive import messages
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata, read_metadata_records
from fieldlog.tools.rebuild import iter_raw, rebuild
from fieldlog.tools.sim import vehicle
from fieldlog.tools.sim.serve import corrupt_stream, delivered, simulated_streams
from test_daemon import wait_caught_up
from test_serve import wait_served

ROOT = Path(__file__).resolve().parents[1]
SPEED = 10
CORRUPT = 0.001


def _start(args: list[str], until: str, lines_out: int = 0) -> tuple[subprocess.Popen, list[str]]:
    """Start ``fieldlog ARGS``; wait for ``lines_out`` stdout lines, or for a stderr line containing ``until``."""
    p = subprocess.Popen([sys.executable, "-m", "fieldlog", *args], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    got = []
    if lines_out:
        got = [p.stdout.readline() for _ in range(lines_out)]
        assert all(got), p.stderr.read()
        return p, got
    while True:
        line = p.stderr.readline()
        assert line, f"{args[0]} exited early: {''.join(got)}"
        got.append(line)
        if until in line:
            return p, got


@pytest.mark.slow
def test_daemon_records_every_slcan_byte_decodes_rebuilds_and_survives_an_unplug(tmp_path: Path) -> None:
    truth, ports = tmp_path / "truth.mcap", tmp_path / "ports"
    serve, lines = _start(["sim", "--serve", "--scenario", "figure8", "--duration", "40", "--seed", "5", "--speed",
                           str(SPEED), "--can", "--hold", "--truth", str(truth), "--unplug", "can:15:3",
                           "--corrupt", str(CORRUPT), "--link-dir", str(ports)], "", lines_out=3)
    assert [ln.split()[0] for ln in lines] == ["daq", "gps", "can"]
    cfg = tmp_path / "acquire.toml"
    cfg.write_text("[can]\nlatency_s = 0.005\n[can.signals]\n" +
                   "".join(f'{k} = "{v}"\n' for k, v in vehicle.SIGNALS.items()))
    d = None
    try:
        d, _ = _start(["acquire", "--daq", str(ports / "daq"), "--gps", str(ports / "gps"), "--can",
                       f"slcan://{ports / 'can'}@500000", "--dbc", str(vehicle.DBC_PATH), "--config", str(cfg),
                       "--time-scale", str(SPEED), "--out", str(tmp_path / "drives"), "--quiet"], "recording")
        serve.send_signal(signal.SIGUSR1)
        wait_served(serve, d, 60)
        wait_caught_up(d)
        d.send_signal(signal.SIGTERM)
        assert d.wait(30) == 0, d.stderr.read()
    finally:
        for p in (serve, d):
            if p is not None and p.poll() is None:
                p.kill()
    (f,) = sorted((tmp_path / "drives").glob("*/*.mcap"))
    meta = read_metadata(truth)["serve"]
    assert meta["can"] == "True" and meta["can_gaps"] and meta["can_undrained_unplugs"] == "0"
    full = corrupt_stream(simulated_streams(meta)["can"], CORRUPT, 5, "can")[0]
    want, _ = delivered(full, meta["can_gaps"])
    got = b"".join(r.data for r in iter_raw(f, "can"))
    assert got == want                                   # every byte the adapter sent, and only those
    # the decoded topics: one twist per intact wheel-speed record delivered
    wheel_id = 0x1D0
    intact = sum(1 for fr in can.SlcanFramer().feed(want) if fr.can_id == wheel_id and not fr.extended)
    t, _, p = reader.read_payloads(f, "/vehicle/twist")
    assert len(t) == intact > 1000
    tw = messages.decode_twist(p)
    assert np.all(tw["covariance"][:, 0] > 0) and set(np.unique(messages.decode_twist(p)["valid"])) == {True}
    step = np.diff(tw["stamp_ns"]) / 1e6
    step = step[len(step) // 3:]                         # after the lock (before it the host clock is not scaled)
    steady = step[step < 100]                            # (the unplug and corrupted frames apart)
    near = np.mean(np.abs(steady - 20.0) <= 2.0)          # 50 Hz on the GPS-disciplined clock
    assert near > 0.8 and 19.0 <= np.median(steady) <= 21.0, (near, np.median(steady))
    counters = read_metadata(f)["acquire.counters"]
    assert int(counters["port.can.disconnects"]) >= 1 and int(counters["can.bad_records"]) > 0
    events = [d for name, d in read_metadata_records(f) if name == "acquire.port_event" and d["port"] == "can"]
    assert [e["event"] for e in events][:2] == ["lost", "back"]
    # rebuild re-derives the vehicle topics bit for bit from /raw/can
    out = tmp_path / "rebuilt.mcap"
    rebuild(f, out)
    for topic in ("/vehicle/twist", "/vehicle/wheel_speeds"):
        a, b = reader.read_payloads(f, topic), reader.read_payloads(out, topic)
        np.testing.assert_array_equal(a[0], b[0])
        assert a[2].to_list() == b[2].to_list(), topic


def test_socketcan_vcan_records_frames_sent_by_python_can(tmp_path: Path) -> None:
    import can as pycan

    try:
        sender = pycan.Bus(interface="socketcan", channel="vcan0")
    except Exception:  # noqa: BLE001 - no vcan0 here (the vcan kernel module and the interface)
        pytest.skip("needs a vcan0 interface (modprobe vcan; ip link add vcan0 type vcan; ip link set vcan0 up)")
    ports = tmp_path / "ports"
    serve, _ = _start(["sim", "--serve", "--scenario", "static", "--duration", "30", "--speed", "10", "--hold",
                       "--link-dir", str(ports)], "", lines_out=2)
    sent = [pycan.Message(arbitration_id=0x100 + i, data=bytes([i % 256] * (i % 9)), is_extended_id=i % 4 == 0)
            for i in range(300)]
    d = None
    try:
        d, _ = _start(["acquire", "--daq", str(ports / "daq"), "--gps", str(ports / "gps"), "--can",
                       "socketcan://vcan0", "--out", str(tmp_path / "drives"), "--quiet"], "recording")
        serve.send_signal(signal.SIGUSR1)
        for m in sent:
            sender.send(m)
        time.sleep(1.0)                                  # (wall time: let the reader drain the socket)
        d.send_signal(signal.SIGTERM)
        assert d.wait(30) == 0, d.stderr.read()
    finally:
        sender.shutdown()
        for p in (serve, d):
            if p is not None and p.poll() is None:
                p.kill()
    (f,) = sorted((tmp_path / "drives").glob("*/*.mcap"))
    assert read_metadata(f)["can"]["wire"] == "frames"
    dec = can.RecordDecoder()
    got = [fr for r in iter_raw(f, "can") for fr in dec.feed(r.data)]
    assert [(g.can_id, g.data, g.extended) for g in got] == [(m.arbitration_id, bytes(m.data), m.is_extended_id)
                                                            for m in sent]
    assert all(g.adapter_ns > 0 for g in got)            # the kernel's receive time
