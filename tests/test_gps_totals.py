"""Every GPS decoder is total: hostile numbers in checksum-valid NMEA sentences and CRC-valid NovAtel logs give
NaN/None for that field (counted), and every other field, sentence and epoch of the read is kept, in the
daemon's pipeline and in ``fieldlog import``."""
from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import gpsport, nmea, novatel, numbers, ubx
from fieldlog.drive import recorder
from fieldlog.acquire.pipeline import Pipeline, RawRead
from fieldlog.drive import reader
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim import simulate, trajectory

HUGE = "9" * 20
HOSTILE_NMEA = [f"GPZDA,{{t}},{HUGE},05,2026,00,00", f"GPZDA,{{t}},04,{HUGE},2026,00,00",
                f"GPZDA,{{t}},04,05,{HUGE},00,00", f"GPZDA,{{t}},inf,nan,1e999,00,00",
                f"GPGGA,{{t}},{HUGE}.0,N,{HUGE}.0,E,{HUGE},{HUGE},inf,nan,M,1e999,M,,",
                "GPGST,{t},1e999,inf,-inf,nan,1e308,1e308,1e308", f"GPRMC,{{t}},A,{HUGE}.0,N,01131.000,E,{HUGE},"
                f"{HUGE},{HUGE[:6]},,,A", f"GPGSV,{HUGE},{HUGE},{HUGE},{HUGE},{HUGE},{HUGE},{HUGE}"]


def hostile_novatel(week: int, sec: float) -> list[bytes]:
    pos = ("SOL_COMPUTED,SINGLE,inf,nan,1e999,1e308,WGS84,inf,nan,-1,\"\",0.000,0.000,"
           f"{HUGE},{HUGE},{HUGE},{HUGE},00,06,00,33")
    vel = "SOL_COMPUTED,DOPPLER_VELOCITY,0.000,0.000,inf,1e308,nan,0.0"
    return [novatel.ascii_log("BESTPOS", week, math.inf, pos.replace("inf,nan", "48.1,11.5")),
            novatel.ascii_log("BESTVEL", week, math.nan, vel),
            novatel.ascii_log("BESTPOS", 10**20, sec, pos),
            novatel.ascii_log("TIME", week, sec, f"VALID,0.0,0.0,{HUGE}{HUGE},2026,5,4,9,30,0,VALID"),
            novatel.ascii_log("TIME", week, sec, "VALID,0.0,0.0,-1e300,2026,5,4,9,30,0,VALID"),
            novatel.ascii_log("TIME", week, sec, "VALID,0.0,0.0,inf,2026,5,4,9,30,0,VALID")]


def drive_reads(receiver: str, seed: int = 4, duration: float = 20.0) -> list[RawRead]:
    return simulate.make_reads(trajectory.load_scenario("figure8"), duration, seed, receiver=receiver)[0]


LINE_TIME = {"nmea": re.compile(rb"\$G[PN][A-Z]{3},(\d{6})"),
             "novatel": re.compile(rb"#BEST(?:POS|VEL)A,[^,;]*,[^,;]*,[^,;]*,[^,;]*,(\d+),([\d.]+)")}


def with_hostile_lines(reads: list[RawRead], receiver: str) -> tuple[list[RawRead], int]:
    """The reads with hostile lines (valid checksums) just before the first line of every epoch, so valid
    sentences follow them in the same read. Their times (NMEA) are half a second after the epoch before, so
    they change no valid epoch."""
    stream = b"".join(r.data for r in reads if r.port == "gps")
    at: dict[int, list[bytes]] = {}
    last = None
    for m in LINE_TIME[receiver].finditer(stream):
        t = m.groups()
        if last is not None and t != last:
            at[m.start()] = ([nmea.sentence(x.format(t=last[0].decode() + ".50")) for x in HOSTILE_NMEA]
                             if receiver == "nmea" else hostile_novatel(int(last[0]), float(last[1])))
        last = t
    out, pos, n = [], 0, 0
    for r in reads:
        if r.port == "gps":
            cuts = [p for p in at if pos <= p < pos + len(r.data)]
            data, prev = b"", 0
            for p in sorted(cuts):
                data += r.data[prev:p - pos] + b"".join(at[p])
                prev = p - pos
                n += len(at[p])
            r = RawRead(r.port, r.mono_ns, r.wall_ns, data + r.data[prev:])
            pos += len(r.data) - sum(len(b"".join(at[p])) for p in cuts)
        out.append(r)
    return out, n


def run_pipeline(reads: list[RawRead], out: Path) -> dict[str, str]:
    """The daemon's processing path over the reads, into a drive; returns its counters."""
    with recorder.Recorder(out, flush_interval_s=None, fsync=False) as rec:
        pipe = Pipeline(rec)
        for r in reads:
            pipe.feed(r.port, r.mono_ns, r.wall_ns, r.data)
        pipe.finish()
        rec.add_metadata("acquire.counters", pipe.counters_metadata())
    return read_metadata(out)["acquire.counters"]


def fixes(path: Path) -> np.ndarray:
    fix = reader.read_topic(path, "/gps/fix")
    return fix["log_time_ns"][fix["status"] >= 0]


@pytest.mark.parametrize("receiver", ["nmea", "novatel"])
def test_pipeline_keeps_every_valid_sentence_of_a_read_with_hostile_numbers(tmp_path: Path, receiver: str) -> None:
    clean = drive_reads(receiver)
    bad, n_bad = with_hostile_lines(clean, receiver)
    assert n_bad > 50
    c0 = run_pipeline(clean, tmp_path / "clean.mcap")
    c1 = run_pipeline(bad, tmp_path / "hostile.mcap")
    assert int(c1["processing_errors"]) == 0
    want = fixes(tmp_path / "clean.mcap")
    assert len(want) >= 15
    np.testing.assert_array_equal(fixes(tmp_path / "hostile.mcap"), want)
    np.testing.assert_array_equal(reader.read_topic(tmp_path / "hostile.mcap", "/imu")["log_time_ns"],
                                  reader.read_topic(tmp_path / "clean.mcap", "/imu")["log_time_ns"])
    key = "nmea.bad_fields" if receiver == "nmea" else "novatel.bad_fields"
    assert int(c1[key]) >= n_bad > int(c0[key])


@pytest.mark.parametrize("receiver", ["nmea", "novatel"])
def test_import_of_a_log_with_hostile_numbers_exits_0_and_keeps_every_valid_epoch(tmp_path: Path,
                                                                                    receiver: str) -> None:
    clean = drive_reads(receiver)
    bad, _ = with_hostile_lines(clean, receiver)
    drives = {}
    for name, reads in (("clean", clean), ("hostile", bad)):
        log = tmp_path / f"{name}.log"
        log.write_bytes(b"".join(r.data for r in reads if r.port == "gps"))
        out = tmp_path / f"{name}.mcap"
        p = subprocess.run([sys.executable, "-m", "fieldlog", "import", "--gps", str(log), "--out", str(out)],
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        drives[name] = fixes(out)
    assert len(drives["clean"]) >= 15
    np.testing.assert_array_equal(drives["hostile"], drives["clean"])


def test_checked_numbers_never_raise_and_refuse_what_is_out_of_range() -> None:
    t = numbers.Tally()
    for v in ["inf", "-inf", "nan", "1e999", HUGE, "9" * 5000, "1_0", "0x10", "ü", "", None, b"\xff", 10**400,
              math.inf, math.nan, object()]:
        assert math.isnan(t.real(v, -1e6, 1e6))
        assert t.whole(v, -10**6, 10**6) is None
        assert t.day(v, v, v, 1980, 2200) is None
    assert t.bad == 3 * 14                              # '' and None are missing, not bad
    assert (numbers.real(" 12.5 ", 0, 20), numbers.whole("-7", -10, 0)) == (12.5, -7)
    assert numbers.day("2024", "02", "29", 1980, 2200).isoformat() == "2024-02-29"
    assert numbers.day(2023, 2, 29, 1980, 2200) is None and numbers.whole(np.int64(5), 0, 9) == 5


def test_ubx_nav_pvt_with_hostile_values_gives_no_epoch_and_no_error() -> None:
    from pyubx2 import UBXMessage

    dec = ubx.UbxDecoder()
    for day in (0, 31, 255):
        msg = UBXMessage("NAV", "NAV-PVT", 0, year=2026, month=2, day=day, hour=25, min=99, second=99,
                         validDate=1, validTime=1, nano=-2**31, fixType=3, numSV=255, lat=0, lon=0)
        name, recs = dec.decode(msg.serialize(), 0)
        assert name == "NAV-PVT" and recs == []
    assert dec.stats.no_time == 3 and dec.stats.undecodable == 0
    assert isinstance(gpsport.Solution, type)
