"""``fieldlog replay --foxglove`` and ``fieldlog acquire --foxglove``: real subprocesses serving foxglove-sdk's
WebSocket server (the daemon against ``fieldlog sim --serve`` ptys), and real clients (the ``websockets``
package) speaking ``foxglove.websocket.v1``: advertise, subscribe, binary message data, CDR decoded with the
advertised schema (mcap_ros2's decoder)."""
from __future__ import annotations

import asyncio
import json
import re
import signal
import struct
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from fieldlog.drive import reader
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.fuse import fuse
from fieldlog.drive.reader import read_metadata
from test_daemon import start_daemon, wait_for_clients, wait_until
from test_serve import stacks, start_serve, wait_served

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")
ROOT = Path(__file__).resolve().parents[1]
WANT = ("/imu", "/fusion/kf/fix", "/fusion/kf/status")
# the live drive: as tests/test_live_view.py (x10, the daemon told the time scale), shorter
LIVE_DURATION_S, LIVE_SPEED = 60.0, 10.0
LOCK_WITHIN_S = 15.0  # the time sync locks within this much of the drive start (provisional /imu from then on)
# foxglove-sdk 0.30 speaks the Foxglove WebSocket protocol under this name (the successor of
# foxglove.websocket.v1: the same advertise / subscribe / message data framing)
SUBPROTOCOL = "foxglove.sdk.v1"


@pytest.fixture(scope="module")
def drive(tmp_path_factory, simulated) -> tuple[Path, list[tuple[int, bytes]]]:
    d = tmp_path_factory.mktemp("fox")
    path = simulated("figure8", 90, 1)
    fuse(path, "kf", d / "kf.mcap")
    with open(d / "kf.mcap", "rb") as f:
        ref = [(m.log_time, m.data) for _s, _c, m in make_reader(f).iter_messages(topics=["/fusion/kf/fix"])]
    return path, ref


async def client(url: str, stop_after: int | None = None, delay_s: float = 0.0,
                 subscribed: threading.Event | None = None) -> dict:
    """Subscribe to WANT as they are advertised; collect (log_time, payload) per topic until the server closes
    (or, with ``stop_after``, drop the connection after that many messages). ``subscribed`` is set once every
    topic of WANT is subscribed."""
    await asyncio.sleep(delay_s)
    got: dict[str, list] = {t: [] for t in WANT}
    chans: dict[int, dict] = {}
    subs: dict[int, str] = {}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
        n = 0
        try:
            async for frame in ws:
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        new = [c for c in msg["channels"] if c["topic"] in WANT]
                        for c in new:
                            chans[c["id"]] = c
                            subs[len(subs) + 1] = c["topic"]
                        if new:
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                {"id": sid, "channelId": next(c["id"] for c in new if c["topic"] == t)}
                                for sid, t in subs.items() if any(c["topic"] == t for c in new)]}))
                        if subscribed is not None and set(subs.values()) == set(WANT):
                            subscribed.set()
                    continue
                assert frame[0] == 0x01                       # message data
                sid, t = struct.unpack_from("<IQ", frame, 1)
                got[subs[sid]].append((t, bytes(frame[13:])))
                n += 1
                if stop_after is not None and n >= stop_after:
                    ws.transport.abort()                      # gone mid-stream, no close handshake
                    break
        except websockets.ConnectionClosed:
            pass
    return {"got": got, "channels": {c["topic"]: c for c in chans.values()}}


def decoders(channels: dict[str, dict]) -> dict:
    """CDR decoders of WANT from the advertised channels (ros2msg schemas)."""
    out = {}
    for i, topic in enumerate(WANT):
        ch = channels[topic]
        assert ch["encoding"] == "cdr" and ch["schemaEncoding"] == "ros2msg"
        schema = Schema(id=i, name=ch["schemaName"], encoding="ros2msg", data=ch["schema"].encode())
        out[topic] = DecoderFactory().decoder_for("cdr", schema)
    return out


@pytest.mark.slow
def test_clients_receive_and_decode_and_a_dropped_one_disturbs_nothing(drive) -> None:
    path, ref = drive
    p = subprocess.Popen([sys.executable, "-m", "fieldlog", "replay", str(path), "--foxglove", "127.0.0.1:0",
                          "--speed", "8"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = p.stdout.readline()
        assert line.startswith("foxglove: serving ws://127.0.0.1:"), line + p.stderr.read()
        url = line.split()[-1]

        async def main():
            return await asyncio.gather(client(url), client(url, delay_s=2.0), client(url, stop_after=200))

        a, b, dropped = asyncio.run(main())
        try:
            _, err = p.communicate(timeout=60)  # both pipes drained: a full one cannot hold the process up
        except subprocess.TimeoutExpired:
            pytest.fail(f"replay --foxglove did not exit after its clients; its threads:\n{stacks(p.pid)}")
        assert p.returncode == 0, err
    finally:
        if p.poll() is None:
            p.kill()
    assert sum(len(v) for v in dropped["got"].values()) == 200
    for c in (a, b):
        fixes = c["got"]["/fusion/kf/fix"]
        # every fused fix from the first one received on, in order, what `fieldlog fuse` writes (to rounding:
        # the live replay's 1 s blocks sum in another order than fuse's 10 s ones)
        assert len(fixes) > 20
        times = [t for t, _ in ref]
        i = times.index(fixes[0][0])
        assert [t for t, _ in fixes] == times[i:]
        imu = c["got"]["/imu"]
        assert len(imu) > 1000 and all(t1 > t0 for (t0, _), (t1, _) in zip(imu, imu[1:]))
        decode = decoders(c["channels"])
        m = decode["/imu"](imu[-1][1])
        assert m.header.frame_id == "imu" and abs(m.linear_acceleration.z - 9.8) < 0.5
        for (_, got), (_, want) in zip(fixes, ref[i:]):
            f, w = decode["/fusion/kf/fix"](got), decode["/fusion/kf/fix"](want)
            assert f.header.frame_id == w.header.frame_id == "imu"
            assert abs(f.latitude - w.latitude) < 1e-9 and abs(f.longitude - w.longitude) < 1e-9
            assert abs(f.altitude - w.altitude) < 1e-6
        status = [decode["/fusion/kf/status"](m) for _, m in c["got"]["/fusion/kf/status"]]
        assert len(status) >= len(fixes) and status[-1].status == 2 and status[-1].since_update_s < 1.5  # aided


@pytest.mark.slow
def test_acquire_serves_the_car_live_and_records_everything(tmp_path: Path) -> None:
    """``fieldlog acquire --foxglove 127.0.0.1:0`` on the simulator's ptys with a client subscribed all along: the
    daemon's /imu (live stamps) and the live kf fixes arrive and decode, and the recording misses nothing."""
    bus, out = tmp_path / "bus.sock", tmp_path / "drives"
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(f'[rotation]\nmax_duration_s = 0\n[daemon]\nbus = "{bus}"\n')
    serve, paths = start_serve("--scenario", "figure8", "--duration", f"{LIVE_DURATION_S:g}", "--seed", "4",
                               "--speed", f"{LIVE_SPEED:g}", "--hold")
    d, _ = start_daemon(out, paths, "--config", str(cfg), "--time-scale", f"{LIVE_SPEED:g}", "--view-method", "kf",
                        "--foxglove", "127.0.0.1:0")
    printed: list[str] = []

    def read_stdout() -> None:
        for line in d.stdout:
            printed.append(line)

    threading.Thread(target=read_stdout, daemon=True).start()
    got: list[dict] = []
    subscribed = threading.Event()
    try:
        wait_until(lambda: any(line.startswith("foxglove: ") for line in printed) or d.poll() is not None,
                   "the server's address")
        line = next((line for line in printed if line.startswith("foxglove: ")), "")
        assert re.fullmatch(r"foxglove: serving ws://127\.0\.0\.1:\d+\n", line), \
            "".join(printed) + (d.stderr.read() if d.poll() is not None else "")
        url = line.split()[-1]
        ws = threading.Thread(target=lambda: got.append(asyncio.run(client(url, subscribed=subscribed))))
        ws.start()
        wait_until(subscribed.is_set, "the client's subscriptions")
        wait_for_clients(bus, 1)                             # the server reads the bus before the drive starts
        serve.send_signal(signal.SIGUSR1)
        wait_served(serve, d, LIVE_DURATION_S + 300)
        d.send_signal(signal.SIGTERM)
        assert d.wait(300) == 0, d.stderr.read()            # the daemon waits for its server to finish
        ws.join(120)                                         # the server closes the connection when it stops
        assert not ws.is_alive() and got
    finally:
        for p in (serve, d):
            if p.poll() is None:
                p.kill()
                p.wait()
    assert any(line.startswith("served ") for line in printed), "".join(printed)

    # the recording is complete with a client connected: every sample, as the daemon counted it
    (drive,) = sorted(out.glob("*/*.mcap"))
    n_imu = len(reader.read_topic(drive, "/imu")["log_time_ns"])
    counters = read_metadata(drive)["acquire.counters"]
    assert n_imu == int(counters["imu_samples"]) == int(counters["daq.frames"]) == LIVE_DURATION_S * 500
    assert int(counters["daq.lost_frames"]) == 0 and int(counters["bus.dropped_clients"]) == 0

    c = got[0]
    decode = decoders(c["channels"])
    imu = c["got"]["/imu"]
    # the provisional /imu from the first PPS lock on, every sample, its stamps strictly increasing
    assert n_imu - LOCK_WITHIN_S * 500 <= len(imu) <= n_imu
    t_imu = np.array([t for t, _ in imu])
    assert np.all(np.diff(t_imu) > 0)
    for t, data in imu[::1000]:
        m = decode["/imu"](data)
        assert m.header.frame_id == "imu" and abs(m.linear_acceleration.z - 9.8) < 0.5
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
    fixes = c["got"]["/fusion/kf/fix"]
    print(f"\nfoxglove live: /imu {len(imu)} of {n_imu} samples, /fusion/kf/fix {len(fixes)}")
    assert len(fixes) > 20 and all(t1 > t0 for (t0, _), (t1, _) in zip(fixes, fixes[1:]))
    # the fused track follows the recorded GPS fixes (the same car, fused live)
    gps = reader.read_topic(drive, "/gps/fix")
    ok = gps["valid"]
    for t, data in fixes[::10]:
        f = decode["/fusion/kf/fix"](data)
        assert f.header.frame_id == "imu"
        i = int(np.argmin(np.abs(gps["log_time_ns"][ok] - t)))
        north = (f.latitude - gps["lat_deg"][ok][i]) * 111e3
        east = (f.longitude - gps["lon_deg"][ok][i]) * 111e3 * np.cos(np.radians(f.latitude))
        assert np.hypot(north, east) < 50.0


def test_foxglove_option_errors(tmp_path: Path, capsys, monkeypatch) -> None:
    """A bad address, or foxglove-sdk missing: one line, exit 2, before the daemon opens a port."""
    args = ["acquire", "--daq", str(tmp_path / "daq"), "--gps", str(tmp_path / "gps"), "--out", str(tmp_path)]
    assert cli_main([*args, "--foxglove", "localhost:http"]) == 2
    assert "--foxglove 'localhost:http': expected [HOST:]PORT" in capsys.readouterr().err
    assert cli_main(["view", str(tmp_path / "drive.mcap"), "--foxglove", "0"]) == 2
    assert "--foxglove is for --live" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "foxglove", None)
    for argv in (args, ["view", "--live", str(tmp_path / "bus.sock")]):
        assert cli_main([*argv, "--foxglove", "0"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "pip install 'fieldlog[foxglove]'" in err, err
