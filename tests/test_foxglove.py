"""``fieldlog replay --foxglove``: a real subprocess serving foxglove-sdk's WebSocket server, and real clients
(the ``websockets`` package) speaking ``foxglove.websocket.v1``: advertise, subscribe, binary message data,
CDR decoded with the advertised schema (mcap_ros2's decoder)."""
from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Schema
from mcap_ros2.decoder import DecoderFactory

from fieldlog.tools.fuse import fuse
from fieldlog.tools.sim.simulate import simulate

pytest.importorskip("foxglove")
websockets = pytest.importorskip("websockets")
ROOT = Path(__file__).resolve().parents[1]
WANT = ("/imu", "/fusion/kf/fix")
# foxglove-sdk 0.30 speaks the Foxglove WebSocket protocol under this name (the successor of
# foxglove.websocket.v1: the same advertise / subscribe / message data framing)
SUBPROTOCOL = "foxglove.sdk.v1"


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> tuple[Path, list[tuple[int, bytes]]]:
    d = tmp_path_factory.mktemp("fox")
    path = d / "drive.mcap"
    simulate("figure8", 90, 1, path)
    fuse(path, "kf", d / "kf.mcap")
    with open(d / "kf.mcap", "rb") as f:
        ref = [(m.log_time, m.data) for _s, _c, m in make_reader(f).iter_messages(topics=["/fusion/kf/fix"])]
    return path, ref


async def client(url: str, stop_after: int | None = None, delay_s: float = 0.0) -> dict:
    """Subscribe to WANT as they are advertised; collect (log_time, payload) per topic until the server closes
    (or, with ``stop_after``, drop the connection after that many messages)."""
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
        assert p.wait(60) == 0, p.stderr.read()
    finally:
        if p.poll() is None:
            p.kill()
    assert sum(len(v) for v in dropped["got"].values()) == 200
    decode = {}
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
        for topic in WANT:
            ch = c["channels"][topic]
            assert ch["encoding"] == "cdr" and ch["schemaEncoding"] == "ros2msg"
            schema = Schema(id=len(decode), name=ch["schemaName"], encoding="ros2msg", data=ch["schema"].encode())
            decode[topic] = DecoderFactory().decoder_for("cdr", schema)
        m = decode["/imu"](imu[-1][1])
        assert m.header.frame_id == "imu" and abs(m.linear_acceleration.z - 9.8) < 0.5
        for (_, got), (_, want) in zip(fixes, ref[i:]):
            f, w = decode["/fusion/kf/fix"](got), decode["/fusion/kf/fix"](want)
            assert f.header.frame_id == w.header.frame_id == "imu"
            assert abs(f.latitude - w.latitude) < 1e-9 and abs(f.longitude - w.longitude) < 1e-9
            assert abs(f.altitude - w.altitude) < 1e-6
