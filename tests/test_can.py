"""The vehicle bus: SLCAN bytes and frame records (acquire/can.py), DBC decoding (acquire/canbus.py), the
simulator's car (tools/sim/vehicle.py), rebuild and import of CAN logs written by python-can."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import can as pycan
import cantools
import numpy as np
import pytest

from fieldlog.acquire import can, canbus
from fieldlog.drive import messages
from fieldlog.drive import reader
from fieldlog.tools.rebuild import rebuild

ROOT = Path(__file__).resolve().parents[1]
DBC = ROOT / "data" / "sim-car.dbc"


class ListSink:
    """A pipeline sink keeping (topic, log_time, payload)."""

    def __init__(self) -> None:
        self.out: list[tuple[str, int, bytes]] = []

    def write(self, topic: str, t: int, data: bytes) -> None:
        self.out.append((topic, int(t), data))

    def write_batch(self, topic: str, t, data) -> None:
        for ti, d in zip(np.asarray(t).tolist(), messages.as_packed(data)):
            self.out.append((topic, ti, d))

    def topic(self, name: str) -> list[tuple[int, bytes]]:
        return [(t, d) for top, t, d in self.out if top == name]


def foreign_dbc(tmp_path: Path) -> Path:
    """A DBC another tool made (cantools' own writer): other names, ids, m/s, big-endian, a reverse flag."""
    from cantools.database.can import Database, Message, Signal

    speeds = [Signal(f"WhlSpd_{w}", start=7 + 16 * i, length=16, byte_order="big_endian", is_signed=False,
                     conversion=cantools.database.conversion.LinearConversion(0.005, 0.0, False), unit="m/s")
              for i, w in enumerate(("LF", "RF", "LR", "RR"))]
    m1 = Message(0x2A1, "ABS_WhlSpd", 8, speeds)
    m2 = Message(0x18FF1234, "Trans_Status", 1, [Signal("RevGear", start=0, length=1)], is_extended_frame=True)
    path = tmp_path / "foreign.dbc"
    path.write_text(Database(messages=[m1, m2]).as_dbc_string())
    return path


FOREIGN_SIGNALS = {"wheel_fl": "WhlSpd_LF", "wheel_fr": "WhlSpd_RF", "wheel_rl": "ABS_WhlSpd.WhlSpd_LR",
                   "wheel_rr": "ABS_WhlSpd.WhlSpd_RR", "reverse": "RevGear"}


# ---------------------------------------------------------------------------------------------- bytes


def test_slcan_bytes_written_by_python_can_decode_to_its_frames():
    master, slave = os.openpty()
    import tty

    tty.setraw(slave)
    bus = pycan.Bus(interface="slcan", channel=os.ttyname(slave), sleep_after_open=0)
    rng = np.random.default_rng(3)
    sent = []
    try:
        for i in range(200):
            ext = i % 3 == 0
            cid = int(rng.integers(0, 1 << 29 if ext else 1 << 11))
            data = rng.bytes(int(rng.integers(0, 9)))
            remote = i % 17 == 5
            msg = pycan.Message(arbitration_id=cid, is_extended_id=ext, data=b"" if remote else data,
                                is_remote_frame=remote, dlc=len(data))
            bus.send(msg)
            sent.append((cid, ext, remote, b"" if remote else data))
        time.sleep(0.05)
        os.set_blocking(master, False)
        raw = b""
        while True:
            try:
                chunk = os.read(master, 65536)
            except BlockingIOError:
                break
            if not chunk:
                break
            raw += chunk
    finally:
        bus.shutdown()
        os.close(master)
        os.close(slave)
    fr = can.SlcanFramer()
    got = []
    for i in range(0, len(raw), 7):       # cut anywhere
        got += fr.feed(raw[i:i + 7])
    assert [(f.can_id, f.extended, f.remote, f.data) for f in got] == sent
    # python-can's open commands (C, O, ...) are no frames and are not garbage frames either
    assert fr.stats.frames == len(sent) and fr.stats.bad_records == 0


def test_slcan_garbage_status_and_overlong_are_counted_and_survived():
    good = [can.CanFrame(0x123, b"\x01\x02"), can.CanFrame(0x1ABCDEF0, bytes(8), extended=True),
            can.CanFrame(0x7FF, bytes(range(12)), fd=True, brs=True)]
    stream = (b"\x00\xffnoise\r" + can.slcan_record(good[0], 59999) + b"\x07" + b"t12G1\r" + b"F0C\r" + b"z\r"
              + b"A" * (can.MAX_RECORD + 50) + b"\r" + can.slcan_record(good[1]) + b"T1234\r"
              + can.slcan_record(good[2]) + b"t8001\r")
    fr = can.SlcanFramer()
    out = fr.feed(stream)
    assert [(f.can_id, f.data, f.fd) for f in out] == [(g.can_id, g.data, g.fd) for g in good]
    assert out[0].adapter_ns == 59999 * 1_000_000 and out[1].adapter_ns == -1
    st = fr.stats
    assert st.refused == 1 and st.status_errors == 1 and st.overruns == 1
    assert st.bad_records == 3                 # t12G1 (not hex), T1234 (short), t8001 (id > 0x7FF)
    assert st.overlong == 1
    fr.feed(b"x" * 10 * can.MAX_RECORD)         # no CR ever: bounded
    assert len(fr._buf) <= can.MAX_RECORD


def test_frame_records_round_trip_and_a_cut_record_is_counted():
    frames = [can.CanFrame(0x10, b"", adapter_ns=5), can.CanFrame(0x1FFFFFFF, bytes(range(8)), extended=True),
              can.CanFrame(0x300, bytes(64), fd=True, brs=True, adapter_ns=10**18)]
    data = can.encode_records(frames)
    dec = can.RecordDecoder()
    assert dec.feed(data) == frames
    err = can.encode_records([can.CanFrame(can.CAN_ERR_BUSOFF, bytes(8), error=True)])
    assert dec.feed(err + data[:-3]) == frames[:2]
    assert dec.stats.error_frames == 1 and dec.stats.bus_off == 1 and dec.stats.bad_records == 1


def test_url_parsing():
    assert can.parse_url("slcan:///dev/ttyACM0@500000") == can.CanUrl("slcan", "/dev/ttyACM0", 500000)
    assert can.parse_url("slcan:///dev/pts/3") == can.CanUrl("slcan", "/dev/pts/3", 0)
    assert can.parse_url("socketcan://vcan0").wire == "frames"
    for bad in ("can0", "slcan://x@12345", "udp://x", "socketcan://"):
        with pytest.raises(ValueError):
            can.parse_url(bad)


# ---------------------------------------------------------------------------------------------- DBC


def test_a_foreign_dbc_decodes_the_rear_mean_reverse_and_variance(tmp_path):
    path = foreign_dbc(tmp_path)
    db = cantools.database.load_file(str(path))
    cfg = canbus.BusConfig(wire="frames", dbc=path.read_text(), dbc_name=path.name, signals=FOREIGN_SIGNALS)
    dec = canbus.VehicleDecoder(cfg)
    ws, tr = db.get_message_by_name("ABS_WhlSpd"), db.get_message_by_name("Trans_Status")
    frames = []
    speeds = [(10.0, 10.2, 9.9, 10.05), (3.0, 3.1, 2.995, 3.01), (0.0, 0.0, 0.0, 0.0)]
    for i, s in enumerate(speeds):
        if i == 1:
            frames.append(can.CanFrame(tr.frame_id, tr.encode({"RevGear": 1}), extended=True))
        frames.append(can.CanFrame(ws.frame_id, ws.encode(dict(zip([x.name for x in ws.signals], s)))))
    frames.append(can.CanFrame(0x555, b"\x00"))     # another id
    frames.append(can.CanFrame(ws.frame_id, b"\x00"))   # too short for the DBC: counted
    sink = ListSink()
    dec.feed(can.encode_records(frames), 1_000_000_000, sink)
    tw = messages.decode_twist([d for _, d in sink.topic("/vehicle/twist")])
    expect = [np.mean(s[2:]) * (-1 if i >= 1 else 1) for i, s in enumerate(speeds)]
    np.testing.assert_allclose(tw["v_n"][:, 0], expect, atol=0.0025 + 1e-12)
    assert np.all(tw["v_n"][:, 1:] == 0)
    np.testing.assert_allclose(tw["covariance"][:, 0], 2 * 0.005 ** 2 / 12 / 4)
    assert dec.decode_errors == 1 and dec.by_id[0x555] == 1
    ws_msgs = [messages.decode_message(messages.WHEELSPEEDS, d) for _, d in sink.topic("/vehicle/wheel_speeds")]
    assert [m.reverse for m in ws_msgs] == [-1, 1, 1, 1]
    np.testing.assert_allclose(ws_msgs[0].wheel_speed, speeds[0], atol=0.0025 + 1e-12)


@pytest.mark.parametrize("text,what", [('VERSION ""\nBO_ 1 X: 8 Y\n SG_ S : 0|8@1+ (1,0) [0|1 "" Y\n', "not a DBC"),
                                       ("VERSION \"\"\n", "no messages"),
                                       (None, "no signal 'WHEEL_SPEED_XX'")])
def test_bad_dbc_and_missing_signal_are_one_line(text, what):
    cfg = canbus.BusConfig(dbc=text or DBC.read_text(), dbc_name="car.dbc",
                           signals={"wheel_rl": "WHEEL_SPEED_XX", "wheel_rr": "WHEEL_SPEED_RR"})
    with pytest.raises(canbus.CanConfigError) as e:
        canbus.VehicleDecoder(cfg)
    msg = str(e.value)
    assert what in msg and "car.dbc" in msg and "\n" not in msg


# ---------------------------------------------------------------------------------------------- simulator


@pytest.fixture(scope="module")
def can_drive(tmp_path_factory):
    from fieldlog.tools.sim.simulate import simulate

    path = tmp_path_factory.mktemp("can") / "figure8-can.mcap"
    simulate("figure8", 90.0, 4, path, can=True)
    return path


def _twists(path, topic):
    t, _, p = reader.read_payloads(path, topic)
    d = messages.decode_twist(p)
    return d["stamp_ns"], d["v_n"][:, 0], d["covariance"][:, 0]


@pytest.mark.slow
def test_sim_can_twist_at_the_bus_rate_with_stamps_and_speeds_near_truth(can_drive):
    ts, v, var = _twists(can_drive, "/vehicle/twist")
    tt, vt, _ = _twists(can_drive, "/truth/vehicle/twist")
    assert len(ts) == len(tt) > 0
    rate = (len(ts) - 1) / ((ts[-1] - ts[0]) / 1e9)
    assert abs(rate - 50.0) < 0.5
    locked = slice(len(ts) // 3, None)          # after time sync has locked
    err_ms = (ts - tt)[locked] / 1e6
    # the adapter's ms stamps on its clock (AdapterClock): the bus jitter and the ms floor are left, and the
    # host clock's offset to UTC (the PPS read with the least delay is still late by about a millisecond)
    assert -3.0 < np.mean(err_ms) < 0.0 and np.std(err_ms) < 1.2, (np.mean(err_ms), np.std(err_ms))
    meta = reader.read_metadata_records(can_drive)
    assert any(name == "can" for name, _ in meta)
    moving = vt > 2.0
    ratio = v[moving] / vt[moving]
    assert abs(np.median(ratio) - 1) < 0.006          # the tyre scale error: +-0.5 %
    assert np.all(np.abs(v - vt) < 0.02 * np.abs(vt) + 0.01)


@pytest.mark.slow
def test_rebuild_reproduces_the_vehicle_topics_bit_for_bit(can_drive, tmp_path):
    out = tmp_path / "rebuilt.mcap"
    rebuild(can_drive, out)
    for topic in ("/raw/can", "/vehicle/twist", "/vehicle/wheel_speeds", "/imu"):
        a, b = reader.read_payloads(can_drive, topic), reader.read_payloads(out, topic)
        assert len(a[0]) > 0, topic
        np.testing.assert_array_equal(a[0], b[0])
        assert a[2].to_list() == b[2].to_list(), topic


# ---------------------------------------------------------------------------------------------- import


def _write_log(path: Path, dbc: Path, n: int = 500, t0: float = 1_780_000_000.25) -> list[tuple[float, float]]:
    """A CAN log written by python-can's own writer for ``path``'s suffix: the foreign car's wheel speeds at 50 Hz,
    reverse from frame 300 on, other ids, an error frame. Returns (time, written rear-mean speed) per wheel frame."""
    db = cantools.database.load_file(str(dbc))
    ws, tr = db.get_message_by_name("ABS_WhlSpd"), db.get_message_by_name("Trans_Status")
    rng = np.random.default_rng(11)
    written = []
    with pycan.Logger(str(path)) as log:
        for i in range(n):
            t = t0 + 0.02 * i
            v = 5 + 3 * np.sin(i / 40)
            vals = {s.name: round(v + rng.normal(0, 0.05), 2) for s in ws.signals}
            rev = i >= 300
            log(pycan.Message(timestamp=t - 0.001, arbitration_id=tr.frame_id, is_extended_id=True,
                              data=tr.encode({"RevGear": int(rev)})))
            log(pycan.Message(timestamp=t, arbitration_id=ws.frame_id, is_extended_id=False, data=ws.encode(vals)))
            log(pycan.Message(timestamp=t + 0.003, arbitration_id=0x7DF, data=rng.bytes(8)))
            if i == 100:
                log(pycan.Message(timestamp=t + 0.004, arbitration_id=0x1CEBFF00, is_extended_id=True,
                                  data=rng.bytes(3)))
                log(pycan.Message(timestamp=t + 0.005, is_error_frame=True, arbitration_id=0, data=b""))
            mean = (vals["WhlSpd_LR"] + vals["WhlSpd_RR"]) / 2
            written.append((t, -mean if rev else mean))
    return written


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_import_of_can_logs_written_by_python_can(tmp_path, suffix):
    from fieldlog.acquire import config
    from fieldlog.tools.importer import import_captures

    dbc = foreign_dbc(tmp_path)
    log = tmp_path / f"drive{suffix}"
    written = _write_log(log, dbc)
    bus = config.bus_config(config.CanConfig(dbc=str(dbc), signals=dict(FOREIGN_SIGNALS)), "frames")
    out = tmp_path / "imported.mcap"
    res = import_captures(None, None, out, can_log=log, can_bus=bus)
    assert res.vehicle_twists == len(written)
    ts, v, var = _twists(out, "/vehicle/twist")
    t_w, v_w = np.array(written).T
    np.testing.assert_allclose(v, v_w, atol=0.0025 + 1e-9)       # the DBC's 0.005 m/s resolution
    if suffix != ".asc":     # ASC: the header's date is local time, python-can's reading of it
        np.testing.assert_allclose(ts / 1e9, t_w, atol=2e-6)
    assert np.all(np.diff(ts) > 0)
    meta = reader.read_metadata(out)
    counters = meta["acquire.counters"]
    assert int(counters["can.ids"]) >= 3 and int(counters["can.twists"]) == len(written)
    # rebuild gives the same from /raw/can
    again = tmp_path / "rebuilt.mcap"
    rebuild(out, again)
    assert reader.read_payloads(again, "/vehicle/twist")[2].to_list() == reader.read_payloads(
        out, "/vehicle/twist")[2].to_list()


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fieldlog", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def test_import_bad_input_is_one_line_exit_2(tmp_path):
    dbc = foreign_dbc(tmp_path)
    log = tmp_path / "drive.log"
    _write_log(log, dbc, n=20)
    bad_dbc = tmp_path / "bad.dbc"
    bad_dbc.write_text('VERSION ""\nBO_ 1 X: 8 Y\n SG_ S : 0|8@1+ (1,0) [0|1 "" Y\n')
    odd = tmp_path / "drive.xyz"
    odd.write_bytes(log.read_bytes())
    garbled = tmp_path / "garbled.blf"
    garbled.write_bytes(b"LOGG" + bytes(300))
    cases = [(["--can", str(log), "--dbc", str(bad_dbc), "--signal", "wheel_rl=X"], "bad.dbc"),
             (["--can", str(log), "--dbc", str(dbc), "--signal", "wheel_rl=WhlSpd_XX", "--signal",
               "wheel_rr=WhlSpd_RR"], "WhlSpd_XX"),
             (["--can", str(odd), "--dbc", str(dbc)], "drive.xyz"),
             (["--can", str(garbled)], "garbled.blf")]
    for args, name in cases:
        r = _cli("import", *args, "--out", str(tmp_path / "x.mcap"))
        assert r.returncode == 2, r.stderr
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and name in lines[0] and "Traceback" not in r.stderr, r.stderr
    r = _cli("import", "--can", str(log), "--dbc", str(dbc), *sum((["--signal", f"{k}={v}"] for k, v in
                                                                   FOREIGN_SIGNALS.items()), []),
             "--out", str(tmp_path / "ok.mcap"))
    assert r.returncode == 0 and "20 /vehicle/twist" in r.stdout, r.stderr


def test_acquire_with_a_bad_can_config_is_one_line_exit_2(tmp_path):
    bad = tmp_path / "car.dbc"
    bad.write_text("VERSION \"\"\nBO_ 1 X: 8 Y\n SG_ S : 0|8@1+ (1,0) [0|1 \"\" Y\n")
    cfg = tmp_path / "car.toml"
    cfg.write_text('[can.signals]\nwheel_rl = "WHEEL_SPEEDS.WHEEL_SPEED_RL"\nwheel_rr = "NO_SUCH.SIGNAL"\n')
    base = ["acquire", "--daq", "/dev/null", "--gps", "/dev/zero", "--out", str(tmp_path / "d")]
    for extra, name in ((["--can", "slcan:///dev/ttyACM0", "--dbc", str(bad)], "car.dbc"),
                        (["--can", "slcan:///dev/ttyACM0", "--dbc", str(DBC), "--config", str(cfg)], "NO_SUCH"),
                        (["--can", "slcan:///dev/ttyACM0@12345"], "12345"),
                        (["--can", "udp://x"], "udp://x")):
        r = _cli(*base, *extra)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and name in lines[0], r.stderr


@pytest.mark.slow
def test_view_shows_the_wheel_speed_beside_the_fused_forward_speed(can_drive, tmp_path):
    pytest.importorskip("rerun", reason="needs the view extra (rerun-sdk)")
    from test_view_export import _rerun, _rows

    from fieldlog.tools.cli import main as cli_main

    fused, rrd = tmp_path / "kf.mcap", tmp_path / "v.rrd"
    assert cli_main(["fuse", str(can_drive), "--method", "kf", "--out", str(fused)]) == 0
    assert cli_main(["view", str(can_drive), str(fused), "--rrd", str(rrd)]) == 0
    rows = _rows(_rerun("print", str(rrd)))
    n_twist = len(reader.read_payloads(can_drive, "/vehicle/twist")[0])
    n_kf = len(reader.read_payloads(fused, "/fusion/kf/odom")[0])
    assert rows.get(("/speed/wheels", "Scalars:scalars")) == n_twist
    assert rows.get(("/speed/truth", "Scalars:scalars")) == n_twist
    assert rows.get(("/speed/kf", "Scalars:scalars")) == n_kf > 0


# ---------------------------------------------------------------------------------------------- fusion


@pytest.fixture(scope="module")
def odo_drive(tmp_path_factory):
    from fieldlog.tools.sim.simulate import simulate

    path = tmp_path_factory.mktemp("odo") / "figure8-can-240.mcap"
    simulate("figure8", 240.0, 2, path, can=True)
    return path


OUTAGE = (150.0, 60.0)


def _drift(drive, fused, method):
    """RMS over the outage of the 2-D position error's growth since the outage start, and the share of rows whose
    east and north errors are within 3 sigma."""
    f, s = reader.read_topic(fused, f"/fusion/{method}/fix"), reader.read_topic(fused, f"/fusion/{method}/std")
    tr = reader.read_topic(drive, "/truth/fix")
    t = f["log_time_ns"]
    lat, lon = (np.interp(t, tr["log_time_ns"], tr[k]) for k in ("lat_deg", "lon_deg"))
    de = np.radians(f["lon_deg"] - lon) * 6378137.0 * np.cos(np.radians(lat))
    dn = np.radians(f["lat_deg"] - lat) * 6378137.0
    t0 = reader.read_topic(drive, "/imu")["log_time_ns"][0]
    w = np.flatnonzero((t >= t0 + OUTAGE[0] * 1e9) & (t < t0 + sum(OUTAGE) * 1e9))
    growth = np.hypot(de[w] - de[w[0]], dn[w] - dn[w[0]])
    within = (np.abs(de[w]) <= 3 * s["xyz"][w, 0]) & (np.abs(dn[w]) <= 3 * s["xyz"][w, 1])
    return float(np.sqrt(np.mean(growth ** 2))), float(np.mean(within))


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kf", "dkf"])
def test_the_odometer_cuts_the_outage_drift_and_keeps_sigma_honest(odo_drive, tmp_path, method):
    from fieldlog.fusion.engine import Engine
    from fieldlog.replay import inputs
    from fieldlog.tools.fuse import BLOCK_S, fuse
    from fieldlog.tools.fuse_settings import drive_config

    base = drive_config(odo_drive).replace(outages=(OUTAGE,))
    got = {}
    for odo in (True, False):
        out = tmp_path / f"{method}-{odo}.mcap"
        fuse(odo_drive, method, out, base.replace(odometer=odo))
        got[odo] = _drift(odo_drive, out, method)
    if method == "kf":      # dkf: KF_I takes it with the NHC; its lossy fusion gains less (docs/results.md)
        assert got[True][0] < 0.85 * got[False][0], got
    assert got[True][1] >= 0.9, got
    # the engine used it at (nearly) every epoch, outage included, and fitted the tyres' scale factor
    eng = Engine(method, base)
    for b in inputs.InputStream(odo_drive, inputs.resolve(odo_drive), BLOCK_S):
        eng.process(b.imu, b.gps, b.odom)
    eng.finish()
    odo = next(p for m in eng.measurements for p in getattr(m, "parts", (m,)) if type(p).__name__ == "Odometer")
    assert len(eng.used("Odometer")) > 0.8 * 240
    t, _, p = reader.read_payloads(odo_drive, "/vehicle/twist")
    tt, _, pt = reader.read_payloads(odo_drive, "/truth/vehicle/twist")
    v, vt = messages.decode_twist(p)["v_n"][:, 0], messages.decode_twist(pt)["v_n"][:, 0]
    ratio = np.sum(v[vt > 3]) / np.sum(vt[vt > 3])            # the simulated tyre error (and slip)
    assert abs(odo.scale.scale - ratio) < 3 * odo.scale.sigma + 5e-4, (odo.scale.scale, ratio, odo.scale.sigma)


@pytest.mark.slow
@pytest.mark.parametrize("odom_type", ["nav_msgs/msg/Odometry", "geometry_msgs/msg/TwistStamped"])
def test_odometry_of_another_logger_through_odom_topic(odo_drive, tmp_path, odom_type):
    from foreign_drives import Foreign, write_foreign

    from fieldlog.replay import inputs
    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.fuse_settings import drive_config

    foreign = write_foreign(odo_drive, tmp_path / "foreign.mcap", Foreign(odom_topic="/wheel/odom",
                                                                          odom_type=odom_type))
    imap = inputs.resolve(foreign, inputs.InputSpec(odom_topic="/wheel/odom"))
    assert imap.odom_topic == "/wheel/odom" and inputs.resolve(foreign).odom_topic is None
    cfg = drive_config(odo_drive).replace(outages=(OUTAGE,))
    out = {}
    for name, im in (("odom", imap), ("none", inputs.resolve(foreign))):
        out[name] = tmp_path / f"{name}.mcap"
        fuse(foreign, "kf", out[name], cfg, inputs=im)
    a, b = _drift(odo_drive, out["odom"], "kf"), _drift(odo_drive, out["none"], "kf")
    assert a[0] < 0.85 * b[0], (a, b)
    with pytest.raises(ValueError, match="NavSatFix"):
        inputs.resolve(foreign, inputs.InputSpec(odom_topic="/sensors/gnss/fix"))


@pytest.mark.slow
def test_evaluate_gives_a_column_without_the_odometer(odo_drive, tmp_path):
    pl = pytest.importorskip("polars", reason="needs the export extra (polars)")
    from fieldlog.tools.evaluation.evaluate import evaluate

    table = evaluate([odo_drive], [60.0], ["kf"], tmp_path / "report", say=lambda s: None)
    vel = table.filter(pl.col("quantity").is_in(["vE", "vN"]))
    by = {m: vel.filter(pl.col("method") == m)["mean"].to_numpy() for m in ("kf", "kf-no-odometer")}
    assert len(by["kf"]) == len(by["kf-no-odometer"]) == 2
    assert np.hypot(*by["kf"]) < np.hypot(*by["kf-no-odometer"])      # the wheels hold the velocity in outages
