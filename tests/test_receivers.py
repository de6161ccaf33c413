"""Real receivers: a u-blox log written with pyubx2 (NAV-PVT + TIM-TP with GGA interleaved) and a NovAtel OEM
ASCII log written here (BESTPOSA + BESTVELA, CRCs computed by the manual's bitwise algorithm, not ours) go
through ``fieldlog import --gps`` (auto-detected); the GPS-port framer on mixed, cut and corrupted streams."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest
from mcap.reader import make_reader
from pyubx2 import UBXMessage

from fieldlog.acquire import gpsport, nmea, novatel, sbf, ubx
from fieldlog.drive import reader
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.info import drive_info

NS = 1_000_000_000
N_EPOCHS = 40
T0 = dt.datetime(2026, 3, 14, 23, 59, 40, tzinfo=dt.timezone.utc)   # crosses midnight
LEAP = 18


def _truth(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = N_EPOCHS
    return dict(lat=48.1 + rng.uniform(-1, 1, n), lon=11.5 + rng.uniform(-1, 1, n),
                h=rng.uniform(-50, 3000, n), und=rng.uniform(-40, 60, n),
                v=rng.normal(0, 10, (n, 3)), hacc=rng.uniform(0.3, 8, n), vacc=rng.uniform(0.5, 15, n),
                sacc=rng.uniform(0.02, 0.8, n), sd=rng.uniform(0.2, 5, (n, 3)),
                qerr=rng.integers(-10_000, 10_000, n))


def _gps_week_tow(t: dt.datetime) -> tuple[int, float]:
    s = (t - dt.datetime(1980, 1, 6, tzinfo=dt.timezone.utc)).total_seconds() + LEAP
    return int(s // 604800), s % 604800


def _ublox_log(tr) -> bytes:
    """What a u-blox port sends each second: GGA, NAV-PVT, TIM-TP of the next pulse (as pyubx2 writes them)."""
    out = [b"\x00\xffnoise before the receiver started\r\n"]
    for i in range(N_EPOCHS):
        t = T0 + dt.timedelta(seconds=i)
        week, tow = _gps_week_tow(t)
        tod = t.hour * 3600 + t.minute * 60 + t.second
        out.append(nmea.format_gga("GN", tod, tr["lat"][i], tr["lon"][i], 1, 14, 0.9, tr["h"][i] - tr["und"][i],
                                   tr["und"][i]))
        vE, vN, vU = tr["v"][i]
        out.append(UBXMessage("NAV", "NAV-PVT", 0, iTOW=int(round(tow * 1000)), year=t.year, month=t.month,
                              day=t.day, hour=t.hour, min=t.minute, second=t.second, validDate=1, validTime=1,
                              fullyResolved=1, nano=-412, fixType=3, gnssFixOk=1, numSV=14,
                              lat=float(tr["lat"][i]), lon=float(tr["lon"][i]), height=int(round(tr["h"][i] * 1000)),
                              hMSL=int(round((tr["h"][i] - tr["und"][i]) * 1000)),
                              hAcc=int(round(tr["hacc"][i] * 1000)), vAcc=int(round(tr["vacc"][i] * 1000)),
                              velN=int(round(vN * 1000)), velE=int(round(vE * 1000)), velD=int(round(-vU * 1000)),
                              sAcc=int(round(tr["sacc"][i] * 1000))).serialize())
        out.append(UBXMessage("TIM", "TIM-TP", 0, towMS=int(round(tow + 1)) * 1000, towSubMS=0,
                              qErr=int(tr["qerr"][i]), week=week, timeBase=0, utc=1).serialize())
    return b"".join(out)


def _crc32_manual(data: bytes) -> int:
    """CRC32Value / CalculateBlockCRC32 of the OEM7 manual, bit by bit."""
    crc = 0
    for byte in data:
        t = (crc >> 8) & 0x00FFFFFF
        v = (crc ^ byte) & 0xFF
        for _ in range(8):
            v = (v >> 1) ^ 0xEDB88320 if v & 1 else v >> 1
        crc = t ^ v
    return crc


def _oem_line(name: str, week: int, tow: float, body: str) -> bytes:
    text = f"{name},COM2,0,72.5,FINESTEERING,{week},{tow:.3f},02000020,cdba,16809;{body}".encode()
    return b"#" + text + b"*%08x\r\n" % _crc32_manual(text)


def _novatel_log(tr) -> bytes:
    out = [b"[COM2]"]
    for i in range(N_EPOCHS):
        t = T0 + dt.timedelta(seconds=i)
        week, tow = _gps_week_tow(t)
        sd_e, sd_n, sd_u = tr["sd"][i]
        out.append(_oem_line("BESTPOSA", week, tow,
                             f"SOL_COMPUTED,PSRDIFF,{tr['lat'][i]:.11f},{tr['lon'][i]:.11f},"
                             f"{tr['h'][i] - tr['und'][i]:.4f},{tr['und'][i]:.4f},WGS84,{sd_n:.4f},{sd_e:.4f},"
                             f"{sd_u:.4f},\"131\",7.000,0.000,18,16,16,16,00,0b,11,33"))
        vE, vN, vU = tr["v"][i]
        trk = math.degrees(math.atan2(vE, vN)) % 360
        out.append(_oem_line("BESTVELA", week, tow, f"SOL_COMPUTED,PSRDIFF,0.250,7.000,{math.hypot(vE, vN):.6f},"
                                                    f"{trk:.9f},{vU:.6f},0.0"))
    return b"".join(out)


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("receivers")
    out = {}
    for name, make, seed in (("ublox", _ublox_log, 1), ("novatel", _novatel_log, 2)):
        tr = _truth(seed)
        (tmp / f"{name}.log").write_bytes(make(tr))
        path = tmp / f"{name}.mcap"
        assert fieldlog(["import", "--gps", str(tmp / f"{name}.log"), "--out", str(path)]) == 0
        out[name] = (path, tr)
    return out


@pytest.mark.parametrize("name", ["ublox", "novatel"])
def test_import_gives_one_fix_per_epoch_at_the_receivers_utc(imported, name):
    path, tr = imported[name]
    fix = reader.read_topic(path, "/gps/fix")
    t_expect = np.array([int((T0 + dt.timedelta(seconds=i)).timestamp()) * NS for i in range(N_EPOCHS)])
    np.testing.assert_array_equal(fix["log_time_ns"], t_expect)
    np.testing.assert_array_equal(fix["stamp_ns"], t_expect)
    assert np.all(fix["status"] >= 0)
    assert np.max(np.abs(fix["lat_deg"] - tr["lat"])) <= 1e-7
    assert np.max(np.abs(fix["lon_deg"] - tr["lon"])) <= 1e-7
    assert np.max(np.abs(fix["alt_m"] - tr["h"])) <= 1e-3
    cov = fix["position_covariance"].reshape(-1, 3, 3)
    var = np.stack([cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]], 1)
    if name == "ublox":     # UBX sends mm
        h, v = np.round(tr["hacc"], 3), np.round(tr["vacc"], 3)
        expect = np.stack([h ** 2, h ** 2, v ** 2], 1)
    else:
        expect = tr["sd"] ** 2
    np.testing.assert_allclose(var, expect, rtol=1e-3)
    assert np.all(fix["covariance_type"] == 2)


@pytest.mark.parametrize("name", ["ublox", "novatel"])
def test_import_gives_3d_velocity_with_a_usable_vertical_sigma(imported, name):
    path, tr = imported[name]
    vel = reader.read_topic(path, "/gps/vel")
    assert len(vel["log_time_ns"]) == N_EPOCHS
    np.testing.assert_allclose(vel["v_n"], tr["v"], atol=1e-3 if name == "ublox" else 1e-5)
    var = vel["covariance"][:, [0, 7, 14]]
    if name == "ublox":
        np.testing.assert_allclose(var, np.repeat(np.round(tr["sacc"], 3)[:, None] ** 2, 3, 1), rtol=1e-12)
    else:   # BESTVEL has no accuracy: the configured defaults, vertical included
        np.testing.assert_allclose(var, [[0.1 ** 2, 0.1 ** 2, 0.2 ** 2]] * N_EPOCHS)
    assert np.all(var[:, 2] < 100.0)        # fusion feeds the vertical (vel_var_max)


def test_ublox_import_keeps_nmea_and_binary_records(imported):
    path, _ = imported["ublox"]
    counts = {t.topic: t.count for t in reader.topics(path)}
    assert counts["/gps/nmea"] == N_EPOCHS
    assert counts["/gps/receiver"] == 2 * N_EPOCHS
    raw = reader.read_topic(path, "/gps/receiver")
    ports = {m.port for m in raw["msgs"]}
    assert ports == {"ubx:NAV-PVT", "ubx:TIM-TP"}
    info = drive_info(path)
    assert int(info.counters["nmea_superseded"]) == N_EPOCHS
    assert int(info.counters["ubx.NAV-PVT"]) == N_EPOCHS


@pytest.mark.parametrize("name", ["ublox", "novatel"])
def test_rebuild_of_an_imported_receiver_log_is_bit_for_bit(imported, name, tmp_path):
    path, _ = imported[name]
    out = tmp_path / "rebuilt.mcap"
    assert fieldlog(["rebuild", str(path), "--out", str(out)]) == 0
    for topic in ("/gps/fix", "/gps/vel", "/gps/receiver", "/raw/gps"):
        with open(path, "rb") as f, open(out, "rb") as g:
            a = [(m.log_time, m.data) for _s, _c, m in make_reader(f).iter_messages(topics=[topic])]
            b = [(m.log_time, m.data) for _s, _c, m in make_reader(g).iter_messages(topics=[topic])]
        assert a == b and len(a) > 0, topic


# ---------------------------------------------------------------------------------------------- framer

def _mixed_stream(seed: int) -> tuple[bytes, list[tuple[str, bytes]]]:
    tr = _truth(seed)
    parts = [_ublox_log(tr), _novatel_log(tr)]
    framer = gpsport.Framer()
    frames = framer.feed(b"".join(parts))
    return b"".join(parts), frames


def test_framer_demultiplexes_and_is_split_invariant():
    data, whole = _mixed_stream(3)
    kinds = [k for k, _ in whole]
    assert kinds.count("ubx") == 2 * N_EPOCHS and kinds.count("nmea") == N_EPOCHS
    assert kinds.count("novatel") == 2 * N_EPOCHS
    rng = np.random.default_rng(4)
    f = gpsport.Framer()
    got = []
    i = 0
    while i < len(data):
        n = int(rng.integers(1, 40))
        got += f.feed(data[i:i + n])
        i += n
    assert got == whole


def test_framer_resynchronises_on_garbage_and_never_raises():
    data, whole = _mixed_stream(5)
    rng = np.random.default_rng(6)
    noisy = bytearray(data)
    # garbage bursts that contain every sync pattern, and flipped bits
    for pos in sorted(rng.integers(0, len(noisy), 30).tolist(), reverse=True):
        noisy[pos:pos] = b"\xb5\x62\x01\x07\xff\xff$GP#BEST\xaa\x44\x12\x1c" + rng.bytes(20)
    for pos in rng.integers(0, len(noisy), 20).tolist():
        noisy[pos] ^= 1 << int(rng.integers(0, 8))
    f = gpsport.Framer()
    got = []
    for i in range(0, len(noisy), 97):
        got += f.feed(bytes(noisy[i:i + 97]))
        assert f.pending <= gpsport.MAX_FRAME
    good = set(whole)
    # every frame we output passed its check; at most 2 frames lost per corruption (flips + bursts)
    assert all((k, fr) in good for k, fr in got if k != "nmea")      # NMEA is checked later, by its decoder
    assert len([g for g in got if g in good]) >= len(whole) - 2 * 50
    dec_u, dec_o = ubx.UbxDecoder(), novatel.NovatelDecoder()
    for k, fr in got:
        if k == "ubx":
            dec_u.decode(fr, 0)
        elif k != "nmea":
            dec_o.decode(k, fr, 0)


def test_decoders_never_raise_on_random_frames():
    """Frames with valid checksums around random payloads (what the framer lets through) decode or are
    counted, never raise; memory stays bounded on a stream of pure noise."""
    rng = np.random.default_rng(7)
    dec_u, dec_o = ubx.UbxDecoder(), novatel.NovatelDecoder()
    for _ in range(2000):
        cls, mid = rng.choice([(1, 7), (0x0D, 1), (1, 0x21), (int(rng.integers(0, 256)), int(rng.integers(0, 256)))])
        payload = rng.bytes(int(rng.choice([92, 16, 20, int(rng.integers(0, 120))])))
        body = bytes([cls, mid]) + len(payload).to_bytes(2, "little") + payload
        dec_u.decode(b"\xb5\x62" + body + gpsport.ubx_checksum(body), 0)
        text = b"BESTPOSA,COM1,0,1,FINESTEERING," + rng.bytes(int(rng.integers(0, 80))).replace(b"*", b"")
        dec_o.decode("novatel", b"#" + text + b"*%08x" % gpsport.crc32(text), 0)
        hdr = bytearray(28)
        hdr[0:3] = gpsport.OEM_SYNC
        hdr[3] = 28
        hdr[4:6] = int(rng.choice([42, 99, 101])).to_bytes(2, "little")
        hdr[13] = 180
        hdr[14:20] = rng.bytes(6)
        msg = rng.bytes(int(rng.integers(0, 80)))
        hdr[8:10] = len(msg).to_bytes(2, "little")
        frame = bytes(hdr) + msg
        dec_o.decode("novatel_bin", frame + gpsport.crc32(frame).to_bytes(4, "little"), 0)
    dec_o.flush()
    f = gpsport.Framer()
    for _ in range(200):
        f.feed(rng.bytes(1000))
        assert f.pending <= gpsport.MAX_FRAME
    assert dec_u.stats.undecodable + sum(dec_u.stats.by_type.values()) >= 2000
    assert len(dec_u.stats.by_type) < 40 and len(dec_o.stats.by_type) <= 4    # bounded counters


def test_novatel_binary_logs_match_ascii():
    """Binary BESTPOS/BESTVEL (OEM7 layouts, packed here) give the same solution as their ASCII twins."""
    import struct
    week, ms = 2410, 345_600_000
    lat, lon, hgt, und = 51.0, -114.0, 1000.25, -16.5

    def frame(msg_id: int, body: bytes) -> bytes:
        hdr = bytearray(28)
        hdr[0:3], hdr[3] = gpsport.OEM_SYNC, 28
        hdr[4:6] = msg_id.to_bytes(2, "little")
        hdr[8:10] = len(body).to_bytes(2, "little")
        hdr[13] = 180
        hdr[14:20] = struct.pack("<HI", week, ms)
        f = bytes(hdr) + body
        return f + gpsport.crc32(f).to_bytes(4, "little")

    pos = struct.pack("<IIdddfIfff4sffBBBBBBBB", 0, 16, lat, lon, hgt, und, 61, 1.5, 1.25, 3.0, b"0\0\0\0",
                      0, 0, 12, 11, 11, 11, 0, 0, 0, 0)
    vel = struct.pack("<IIffdddf", 0, 8, 0.0, 0.0, 5.0, 90.0, -0.25, 0)
    stream = frame(novatel.BESTPOS_ID, pos) + frame(novatel.BESTVEL_ID, vel)
    frames = gpsport.Framer().feed(stream)
    assert [k for k, _ in frames] == ["novatel_bin", "novatel_bin"]
    dec = novatel.NovatelDecoder()
    sols = [s for k, fr in frames for s in dec.decode(k, fr, 0)[1] if isinstance(s, gpsport.Solution)]
    assert len(sols) == 1
    s = sols[0]
    assert s.fix and s.lat_deg == lat and s.lon_deg == lon and abs(s.h_m - (hgt + und)) < 1e-6
    np.testing.assert_allclose(s.pos_var, (1.25 ** 2, 1.5 ** 2, 9.0))
    np.testing.assert_allclose(s.vel_enu, (5.0, 0.0, -0.25), atol=1e-12)
    assert s.utc_ns == (gpsport.GPS_EPOCH_S + week * 604800 - 18) * NS + ms * 1_000_000


def test_nmea_gns_gsa_gsv_hdt_gst_of_any_talker(tmp_path):
    """A multi-constellation receiver without GGA: GNS gives the fix, GST (talker GA) the sigmas; GSA, GSV and
    HDT are decoded and kept."""
    s = nmea.sentence
    log = b"".join([
        s("GNGNS,092750.00,5321.6802,N,00630.3372,W,AAN,14,0.9,61.7,55.2,,,V"),
        s("GNRMC,092750.00,A,5321.6802,N,00630.3372,W,0.02,31.66,280511,,,A"),
        s("GAGST,092750.00,1.2,1.0,0.8,12.0,0.9,0.7,1.6"),
        s("GNGSA,A,3,05,12,15,19,24,,,,,,,,1.6,0.9,1.3,1"),
        s("GPGSV,2,1,07,05,60,120,45,12,35,045,41,15,20,300,38,19,10,200,"),
        s("HEHDT,123.40,T"),
        s("GNGNS,092751.00,5321.6803,N,00630.3370,W,DDN,14,0.9,61.8,55.2,,,V"),
        s("GNRMC,092751.00,A,5321.6803,N,00630.3370,W,0.06,31.66,280511,,,A"),
        s("GBGST,092751.00,1.2,1.0,0.8,12.0,1.1,0.6,1.9"),
    ])
    (tmp_path / "gns.nmea").write_bytes(log)
    out = tmp_path / "gns.mcap"
    assert fieldlog(["import", "--gps", str(tmp_path / "gns.nmea"), "--out", str(out)]) == 0
    fix = reader.read_topic(out, "/gps/fix")
    assert len(fix["log_time_ns"]) == 2 and np.all(fix["status"] >= 0)
    np.testing.assert_allclose(fix["lat_deg"], [53 + 21.6802 / 60, 53 + 21.6803 / 60], atol=1e-9)
    np.testing.assert_allclose(fix["alt_m"], [61.7 + 55.2, 61.8 + 55.2], atol=1e-6)
    cov = fix["position_covariance"].reshape(-1, 3, 3)
    np.testing.assert_allclose(cov[:, [0, 1, 2], [0, 1, 2]], [[0.7 ** 2, 0.9 ** 2, 1.6 ** 2],
                                                               [0.6 ** 2, 1.1 ** 2, 1.9 ** 2]])
    assert fix["status"][1] == 1                     # GNS mode D: differential (SBAS)
    dec = nmea.NmeaDecoder()
    kinds = [type(x).__name__ for x in dec.feed(log)]
    assert kinds == ["Gns", "Rmc", "Gst", "Gsa", "Gsv", "Hdt", "Gns", "Rmc", "Gst"]
    assert dec.stats.unknown == 0 and dec.stats.bad_fields == 0


def test_new_nmea_decoders_never_raise_on_garbage_fields():
    rng = np.random.default_rng(11)
    alphabet = np.frombuffer(b"0123456789.,-+ENSWTAVDRFM*$_x\xff", np.uint8)
    dec = nmea.NmeaDecoder()
    for i in range(3000):
        kind = ["GNS", "GSA", "GSV", "HDT", "GST"][i % 5]
        body = b"GN" + kind.encode() + b"," + rng.choice(alphabet, int(rng.integers(0, 90))).tobytes()
        dec.decode_line(b"$" + body + b"*%02X" % nmea.checksum(body))
    assert sum(dec.stats.by_type.values()) == 3000


class _Count:
    def __init__(self) -> None:
        self.n: dict[str, int] = {}

    def write(self, topic: str, *_: object) -> None:
        self.n[topic] = self.n.get(topic, 0) + 1

    def write_batch(self, topic: str, t: np.ndarray, _: object) -> None:
        self.n[topic] = self.n.get(topic, 0) + len(t)


@pytest.mark.parametrize("receiver", ["ublox", "novatel", "septentrio"])
def test_every_scenario_plays_in_every_receiver_protocol(receiver):
    """20 s of each scenario through the pipeline: one fix per epoch sent, the edges labelled from the
    receiver's own messages (as many accepted as with NMEA)."""
    from fieldlog.acquire.pipeline import Pipeline
    from fieldlog.acquire.timesync import TimeSyncConfig
    from fieldlog.tools.sim import simulate, trajectory
    from fieldlog.tools.sim.emit import GpsConfig

    for name in ("figure8", "static", "urban", "aircraft", "flight600", "flight600-noisy", "coloured"):
        sc = trajectory.load_scenario(name)
        accepted = {}
        for rcv in ("nmea", receiver):
            reads, _, _, ccfg, cal = simulate.make_reads(sc, 20.0, 3, None, rcv)
            sink = _Count()
            pipe = Pipeline(sink, cal, TimeSyncConfig(pps_mode=ccfg.pps_mode, fs_hz=ccfg.fs_hz))
            for r in reads:
                pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
            pipe.finish()
            c = pipe.counters
            accepted[rcv] = c.pps_edges - c.pps_rejected
            if rcv == receiver:
                sent = sum(1 for k, fr in gpsport.Framer().feed(b"".join(r.data for r in reads if r.port == "gps"))
                           if (k == "ubx" and fr[2:4] == b"\x01\x07") or (k == "novatel" and b"BESTPOSA" in fr[:9])
                           or (k == "sbf" and sbf.block_name(fr) == "PVTGeodetic"))
                assert c.gps_epochs == sent == sink.n["/gps/fix"], name
                rate = GpsConfig.from_dict(dict(sc.gps)).rate_hz
                assert sent >= 19 * rate - 6, name
                assert (c.nmea_superseded >= 19 * rate - 6) if receiver == "ublox" else c.nmea_superseded == 0
        assert accepted[receiver] >= accepted["nmea"] - 2, (name, accepted)


@pytest.mark.parametrize("name", ["ublox", "novatel"])
def test_fusion_takes_the_receivers_accuracy_and_the_vertical_velocity(imported, name):
    """The engine's GPS epochs carry the receiver's per-epoch covariances, and the velocity update keeps the
    vertical row (NMEA's unobserved vertical is left out)."""
    from fieldlog.fusion import measurements
    from fieldlog.fusion.config import FusionConfig
    from fieldlog.fusion.ins import NavState

    path, tr = imported[name]
    g = reader.gps_block(reader.read_topic(path, "/gps/fix"), reader.read_topic(path, "/gps/vel"))
    np.testing.assert_allclose(g.pos_cov[:, 2, 2], (np.round(tr["vacc"], 3) if name == "ublox" else tr["sd"][:, 2]) ** 2,
                               rtol=1e-3)
    nav = NavState(0.0, math.radians(tr["lat"][0]), math.radians(tr["lon"][0]), tr["h"][0], tr["v"][0],
                   np.array([0.0, 0.0, 0.0, 1.0]))
    z, H, R = measurements.velocity_measurement(nav, g.v_n[0], g.vel_cov[0], np.zeros(3), np.zeros(3),
                                      FusionConfig().gps.vel_var_max)
    assert len(z) == 3 and abs(z[2]) < 1e-3
    np.testing.assert_allclose(np.diag(R), np.diag(g.vel_cov[0]))
    z_p, _, R_p = measurements.position_measurement(nav, 0.0, nav.lat, nav.lon, nav.h, g.pos_cov[0], np.zeros(3))
    np.testing.assert_allclose(R_p, g.pos_cov[0])


def test_config_protocols_are_the_pipelines():
    from fieldlog.acquire.config import GPS_PROTOCOLS

    assert GPS_PROTOCOLS == tuple(gpsport.ACCEPTS)


@pytest.mark.parametrize("protocol, fixes_from", [("auto", "ubx"), ("ubx", "ubx"), ("nmea", "nmea"),
                                                  ("novatel", "nmea")])
def test_gps_protocol_setting_selects_what_is_decoded(protocol, fixes_from):
    from fieldlog.acquire.pipeline import Pipeline, PipelineConfig

    data = _ublox_log(_truth(1))
    sink = _Count()
    pipe = Pipeline(sink, cfg=PipelineConfig(gps_protocol=protocol))
    t = int(T0.timestamp()) * NS
    for i in range(0, len(data), 500):
        pipe.feed("gps", t + i * 1000, t + i * 1000, data[i:i + 500])
    pipe.finish()
    c = pipe.counters
    assert c.gps_epochs == N_EPOCHS and sink.n["/gps/nmea"] == N_EPOCHS
    assert sink.n.get("/gps/receiver", 0) == (2 * N_EPOCHS if fixes_from == "ubx" else 0)
    assert c.gps_ignored == (0 if fixes_from == "ubx" else 2 * N_EPOCHS)
    assert c.nmea_superseded == (N_EPOCHS if fixes_from == "ubx" else 0)
