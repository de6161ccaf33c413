"""Fuzzing that gets past the checks: mutated inputs whose checksums and CRCs are rewritten after mutating, so
that they reach the field decoders, the counter judge, the time sync and the MCAP reader's record parsing.

    python -m fieldlog.tools.dev.fuzz --target nmea --runs 1000000            # one decoder
    python -m fieldlog.tools.dev.fuzz --target all --runs 1000000 --crashes out/fuzz-crashes
    python -m fieldlog.tools.dev.fuzz --target ubx --atheris -max_total_time=3600 out/corpus   # coverage-guided

Targets: ``nmea``, ``ubx``, ``novatel`` (ASCII and binary), ``sbf`` (Septentrio) through the pipeline's GPS path
(framer, decoders, epochs, /gps/fix); ``daq`` through its DAQ path (decoder, counter judge, time sync, /imu), one
read per input of a continuous simulated stream with valid GPS beside it; ``mcap`` through the reader (summary,
chunks, metadata, every topic). Inputs start from valid bytes of the simulator's encoders (and mcap's own Writer),
are mutated (bit flips, interesting bytes, hostile numbers in text fields, spans inserted, deleted, duplicated,
spliced) and re-checksummed: NMEA ``*HH``, UBX Fletcher, NovAtel CRC-32 (ASCII and binary), SBF CRC-16, DAQ
CRC-16, MCAP chunk CRC-32 (data section and summary CRCs set to 0, "not computed"). A *crash* is any exception
escaping the target: for the pipeline, any processing error it would have counted; for the reader, any exception
but the ValueError that commands report as bad input. Each crash is written to ``--crashes`` as
``TARGET-KIND-HASH.bin`` (tests/test_fuzz.py replays the ones kept in tests/data/fuzz/). Without atheris the loop
is a plain seeded random one (reproducible from ``--seed``).
"""
from __future__ import annotations

import argparse
import hashlib
import io
import logging
import re
import struct
import sys
import tempfile
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

NS = 1_000_000_000
TARGETS = ("nmea", "ubx", "novatel", "daq", "mcap")
CAN_TARGETS = ("slcan", "candump", "asc", "blf", "dbc")
HOSTILE = [b"inf", b"-inf", b"nan", b"1e999", b"9" * 20, b"9" * 400, b"-1", b"", b"1_0", b"0x10", b"999999",
           b"240000", b"-0", b"4294967296", b"\xff"]
INTERESTING = [0x00, 0xFF, 0x7F, 0x80, 0x01, 0xA5, 0x5A, 0x2C, 0x2A, 0x24, 0x23, 0x0A, 0x0D, 0x39, 0x2E, 0x2D]
_SENTENCE = re.compile(rb"\$([^*$\r\n]{0,160})\*[0-9A-Fa-f]{0,2}")
_NOVATEL_ASCII = re.compile(rb"#([^*#\r\n]{0,600})\*[0-9A-Fa-f]{0,8}")
_FIELD = re.compile(rb"[^,;*$#\r\n]+")


# ------------------------------------------------------------------------------------------ checksums

def fix_nmea(data: bytes) -> bytes:
    from fieldlog.acquire import nmea

    return _SENTENCE.sub(lambda m: b"$" + m.group(1) + b"*%02X" % nmea.checksum(m.group(1)), data)


def fix_novatel(data: bytes) -> bytes:
    """NovAtel ASCII '*crc' and binary CRC-32s (frames found by their sync and lengths) rewritten."""
    from fieldlog.acquire import gpsport

    data = bytearray(_NOVATEL_ASCII.sub(lambda m: b"#" + m.group(1) + b"*%08x" % gpsport.crc32(m.group(1)), data))
    for m in re.finditer(rb"\xaa\x44\x12", bytes(data)):
        p = m.start()
        if p + 10 > len(data):
            break
        total = data[p + 3] + int.from_bytes(data[p + 8:p + 10], "little") + 4
        if data[p + 3] >= 28 and p + total <= len(data):
            data[p + total - 4:p + total] = gpsport.crc32(bytes(data[p:p + total - 4])).to_bytes(4, "little")
    return bytes(data)


def fix_ubx(data: bytes) -> bytes:
    from fieldlog.acquire import gpsport

    data = bytearray(data)
    for m in re.finditer(rb"\xb5\x62", bytes(data)):
        p = m.start()
        if p + 6 > len(data):
            break
        ln = int.from_bytes(data[p + 4:p + 6], "little")
        if p + 8 + ln <= len(data):
            data[p + 6 + ln:p + 8 + ln] = gpsport.ubx_checksum(bytes(data[p + 2:p + 6 + ln]))
    return bytes(data)


def fix_daq(data: bytes) -> bytes:
    """Every 38 bytes that start with the sync pair get the CRC-16 of their bytes 2..35."""
    from fieldlog.acquire import daq

    b = np.frombuffer(data, np.uint8).copy()
    at = np.flatnonzero((b[:-1] == daq.SYNC0) & (b[1:] == daq.SYNC1))
    at = at[at + daq.FRAME_SIZE <= b.size]
    if at.size:
        rows = b[at[:, None] + np.arange(daq.FRAME_SIZE)]
        crc = daq.crc16_frames(rows[:, 2:36])
        b[at + 36], b[at + 37] = crc & 0xFF, crc >> 8
    return b.tobytes()


def fix_mcap(data: bytes) -> bytes:
    """Uncompressed chunks' CRC-32 recomputed, compressed ones' set to 0; the Data End and Footer CRCs set to 0
    (MCAP: not computed). Records found by walking the lengths from the magic."""
    data = bytearray(data)
    pos = 8
    while pos + 9 <= len(data):
        op, n = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        body = pos + 9
        if n > len(data) - body:
            break
        if op == 0x06 and n >= 40:      # Chunk: start, end, uncompressed size, CRC, compression, records
            comp_len = int.from_bytes(data[body + 28:body + 32], "little")
            rec_at = body + 32 + comp_len
            if rec_at + 8 <= body + n:
                rec_len = int.from_bytes(data[rec_at:rec_at + 8], "little")
                recs = bytes(data[rec_at + 8:min(rec_at + 8 + rec_len, body + n)])
                crc = zlib.crc32(recs) if comp_len == 0 else 0
                data[body + 24:body + 28] = crc.to_bytes(4, "little")
        elif op == 0x0F and n >= 4:                                  # Data End
            data[body:body + 4] = b"\0\0\0\0"
        elif op == 0x02 and n >= 20:                                 # Footer
            data[body + 16:body + 20] = b"\0\0\0\0"
        pos = body + n
    return bytes(data)


FIXES: dict[str, Callable[[bytes], bytes]] = {
    "nmea": fix_nmea, "ubx": lambda d: fix_nmea(fix_ubx(d)), "novatel": lambda d: fix_nmea(fix_novatel(d)),
    "daq": fix_daq, "mcap": fix_mcap}


# ------------------------------------------------------------------------------------------ mutation

def mutate(data: bytes, rng: np.random.Generator, other: bytes = b"") -> bytes:
    """1..8 random edits of ``data``; ``other`` (another seed) for splices."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        op = int(rng.integers(0, 9))
        n = len(b)
        p = int(rng.integers(0, n)) if n else 0
        if op == 0 and n:
            b[p] ^= 1 << int(rng.integers(0, 8))
        elif op == 1 and n:
            b[p] = INTERESTING[int(rng.integers(0, len(INTERESTING)))]
        elif op == 2 and n:
            b[p] = int(rng.integers(0, 256))
        elif op == 3:                                   # a text field replaced by a hostile number
            fields = list(_FIELD.finditer(bytes(b)))
            if fields:
                m = fields[int(rng.integers(0, len(fields)))]
                b[m.start():m.end()] = HOSTILE[int(rng.integers(0, len(HOSTILE)))]
        elif op == 4 and n:
            del b[p:p + int(rng.integers(1, 40))]
        elif op == 5 and n:
            q = int(rng.integers(0, n))
            b[p:p] = b[q:q + int(rng.integers(1, 80))]
        elif op == 6 and other:
            q = int(rng.integers(0, len(other)))
            b[p:p] = other[q:q + int(rng.integers(1, 200))]
        elif op == 7 and n >= 4:                        # a little-endian integer field set to an extreme
            v = int(rng.choice([0, 1, 2**31 - 1, 2**31, 2**32 - 1, 2**16 - 1, int(rng.integers(0, 2**32))]))
            b[p:p + 4] = v.to_bytes(4, "little")
        elif op == 8 and n >= 8:                        # a double set to inf / nan / huge
            b[p:p + 8] = struct.pack("<d", float(rng.choice([np.inf, -np.inf, np.nan, 1e308, -1e308, 0.0])))
    return bytes(b)


# ------------------------------------------------------------------------------------------ targets

class _Drop:
    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        pass

    def write_batch(self, topic: str, log_time_ns, data) -> None:
        pass


def _strict_pipeline():
    """A Pipeline whose processing errors raise (the daemon would count them; here they are crashes)."""
    from fieldlog.acquire.pipeline import Pipeline

    class Strict(Pipeline):
        def _processing_error(self, e: Exception, port: str, mono_ns: int, wall_ns: int) -> None:
            raise e

    return Strict(_Drop())


@dataclass
class Target:
    """A target's seeds and its state between inputs (a pipeline lives for many inputs, as in a drive; without
    ``pipe`` in ``state`` the next input starts a new one)."""

    name: str
    seeds: list[bytes]
    run: Callable[["Target", bytes], None]
    state: dict = field(default_factory=dict)


def _gps_run(t: Target, data: bytes) -> None:
    st = t.state
    if "pipe" not in st or st["n"] >= 200:
        if "pipe" in st:
            st["pipe"].finish()
        st["pipe"], st["mono"], st["n"] = _strict_pipeline(), 10 * NS, 0
    st["n"] += 1
    st["mono"] += NS // 50
    st["pipe"].feed("gps", st["mono"], 1_700_000_000 * NS + st["mono"], data)


def _daq_run(t: Target, data: bytes) -> None:
    """One mutated DAQ read of a continuous simulated drive (its GPS reads fed in between, valid)."""
    st = t.state
    reads = st["reads"]
    if "pipe" not in st or st["i"] >= len(reads):
        if "pipe" in st:
            st["pipe"].finish()
        st["pipe"], st["i"] = _strict_pipeline(), 0
    while st["i"] < len(reads) and reads[st["i"]].port != "daq":
        r = reads[st["i"]]
        st["pipe"].feed(r.port, r.mono_ns, r.wall_ns, r.data)
        st["i"] += 1
    if st["i"] < len(reads):
        r = reads[st["i"]]
        st["pipe"].feed("daq", r.mono_ns, r.wall_ns, data)
        st["i"] += 1


def _gps_decoders_run(t: Target, data: bytes) -> None:
    """The GPS decoders alone (framer, NMEA with epochs, UBX, NovAtel, SBF): the fast loop of the CI tests."""
    from fieldlog.acquire import gpsport, nmea, novatel, sbf, ubx

    st = t.state
    if "framer" not in st or st["n"] >= 200:
        st.update(framer=gpsport.Framer(), nmea=nmea.NmeaDecoder(), epochs=nmea.EpochAssembler(),
                  ubx=ubx.UbxDecoder(), oem=novatel.NovatelDecoder(), sbf=sbf.SbfDecoder(), n=0)
    st["n"] += 1
    for kind, frame in st["framer"].feed(data):
        if kind == "nmea":
            s = st["nmea"].decode_line(frame)
            if s is not None:
                for ep in st["epochs"].add(s, st["n"]):
                    ep.utc_ns
        elif kind == "ubx":
            st["ubx"].decode(frame, st["n"])
        elif kind == "sbf":
            st["sbf"].decode(frame, st["n"])
        else:
            st["oem"].decode(kind, frame, st["n"])


def _daq_decoder_run(t: Target, data: bytes) -> None:
    """The DAQ decoder and the counter judge alone, checking the judge's contract: k strictly increases."""
    from fieldlog.acquire import counterjudge, daq

    st = t.state
    if "dec" not in st or st["n"] >= 200:
        dec = daq.DaqDecoder()
        st.update(dec=dec, judge=counterjudge.CounterJudge(dec.stats), n=0, last=None)
    st["n"] += 1
    base = st["dec"].stats.bytes_in
    k = st["judge"].judge(st["dec"].feed(data), base, st["n"] * NS // 10).k
    if k.size:
        if np.any(np.diff(k) < 1) or (st["last"] is not None and k[0] <= st["last"]):
            raise AssertionError("judged k does not increase")
        st["last"] = int(k[-1])


def _mcap_run(t: Target, data: bytes) -> None:
    from fieldlog.drive import reader

    path = t.state["path"]
    path.write_bytes(data)
    try:
        for topic in reader.topics(path):
            reader.read_topic(path, topic.topic)
        reader.read_metadata_records(path)
    except ValueError:
        pass                                          # bad input, reported in one line by every command


def _sim_reads(receiver: str, duration: float = 12.0):
    from fieldlog.tools.sim import simulate, trajectory

    return simulate.make_reads(trajectory.load_scenario("figure8"), duration, 5, receiver=receiver)[0]


def _novatel_binary(week: int, ms: int) -> bytes:
    """A binary BESTPOS and TIME (OEM7 layouts) with their CRC-32s."""
    from fieldlog.acquire import gpsport, novatel

    def log(msg_id: int, body: bytes) -> bytes:
        head = struct.pack("<3sBHbBHHBBHIIHH", b"\xaa\x44\x12", 28, msg_id, 0, 32, len(body), 0, 0, 180, week, ms,
                           0, 0, 0)
        return head + body + gpsport.crc32(head + body).to_bytes(4, "little")

    pos = struct.pack("<IIdddfIfff", 0, 16, 48.1, 11.5, 500.0, 47.0, 61, 1.0, 1.0, 2.0) + bytes(72 - 48)
    pos = pos[:65] + bytes([12]) + pos[66:]
    return log(novatel.BESTPOS_ID, pos) + log(novatel.TIME_ID, struct.pack("<Iddd", 0, 0.0, 0.0, -18.0) +
                                              struct.pack("<I", 1) + bytes(4))


def _ubx_older(itow: int) -> bytes:
    """An epoch of a receiver without NAV-PVT (NAV-POSLLH, NAV-SOL, NAV-VELNED, NAV-TIMEUTC, NAV-EOE), a
    time-only NAV-PVT and an HNR-PVT, as pyubx2 writes them."""
    from pyubx2 import UBXMessage

    t = dict(year=2026, month=3, day=14, hour=12, min=0, validDate=1, validTime=1, nano=0, lat=48.1, lon=11.5,
             height=500_000, hAcc=1500, vAcc=2500, sAcc=80)
    return b"".join(m.serialize() for m in (
        UBXMessage("NAV", "NAV-POSLLH", 0, iTOW=itow, lat=48.1, lon=11.5, height=500_000, hAcc=1500, vAcc=2500),
        UBXMessage("NAV", "NAV-SOL", 0, iTOW=itow, week=2410, gpsFix=3, gpsfixOK=1, wknSet=1, towSet=1, numSV=9,
                   sAcc=8),
        UBXMessage("NAV", "NAV-VELNED", 0, iTOW=itow, velN=120, velE=-40, velD=3, sAcc=8),
        UBXMessage("NAV", "NAV-TIMEUTC", 0, iTOW=itow, year=2026, month=3, day=14, hour=12, min=0,
                   sec=itow // 1000 % 60, validTOW=1, validWKN=1, validUTC=1),
        UBXMessage("NAV", "NAV-EOE", 0, iTOW=itow),
        UBXMessage("NAV", "NAV-PVT", 0, iTOW=itow, **t, second=itow // 1000 % 60, fixType=5, gnssFixOk=1),
        UBXMessage("HNR", "HNR-PVT", 0, iTOW=itow, **t, second=itow // 1000 % 60, gpsFix=4, GPSfixOK=1)))


def _mcap_seed() -> bytes:
    """A small drive written by mcap's own Writer, uncompressed chunks of a few messages, with metadata."""
    from fieldlog.drive.records import CompressionType, Writer

    from fieldlog.drive import messages

    buf = io.BytesIO()
    w = Writer(buf, chunk_size=600, compression=CompressionType.NONE)
    w.start(profile="ros2", library="mcap writer")
    sid = w.register_schema("sensor_msgs/msg/Imu", "ros2msg", messages.schema_text("sensor_msgs/msg/Imu").encode())
    cid = w.register_channel("/imu", "cdr", sid)
    t = np.arange(40, dtype=np.int64) * 2_000_000 + 1_700_000_000 * NS
    payloads = messages.encode_imu(t, np.zeros((40, 3)), np.tile([0, 0, 9.8], (40, 1)), np.zeros(9), np.zeros(9))
    for i, p in enumerate(payloads.to_list()):
        w.add_message(cid, int(t[i]), bytes(p), int(t[i]))
    w.add_metadata("fieldlog.info", {"span./imu": f"[{t[0]}, {t[-1]}]", "rate_ppm": "NaN"})
    w.add_metadata("timesync", {"window_s": "120.0"})
    w.finish()
    return buf.getvalue()


# ------------------------------------------------------------------------------------------ SBF

def fix_sbf(data: bytes) -> bytes:
    """Septentrio SBF CRC-16s rewritten: each '$@' whose length field is a block length gets the CRC of its id,
    length and body."""
    from fieldlog.acquire import gpsport

    data = bytearray(data)
    for m in re.finditer(rb"\$@", bytes(data)):
        p = m.start()
        if p + 8 > len(data):
            break
        ln = int.from_bytes(data[p + 6:p + 8], "little")
        if ln >= 8 and ln % 4 == 0 and p + ln <= len(data):
            data[p + 2:p + 4] = gpsport.sbf_crc(bytes(data[p + 4:p + ln])).to_bytes(2, "little")
    return bytes(data)


def make_sbf_target(fast: bool = False) -> Target:
    """Target ``sbf``: a simulated Septentrio receiver's blocks (PVTGeodetic, PosCovGeodetic, VelCovGeodetic,
    ReceiverTime, xPPSOffset), five to an input, through the pipeline's GPS path (``fast``: the decoders)."""
    from fieldlog.acquire import gpsport

    gps = b"".join(r.data for r in _sim_reads("septentrio") if r.port == "gps")
    frames = [f for _, f in gpsport.Framer().feed(gps)]
    group = 1 if fast else 5
    seeds = [b"".join(frames[i:i + group]) for i in range(0, len(frames), group)]
    return Target("sbf", seeds, _gps_decoders_run if fast else _gps_run)


TARGETS = (*TARGETS, "sbf")
FIXES["sbf"] = fix_sbf


# ------------------------------------------------------------------------------------------ CAN targets

_SLCAN_RECORD = re.compile(rb"([tTxrR])([0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})([0-9])([0-9A-Fa-f]*)\r")
_ASC_FRAME = re.compile(rb"(\s[0-9A-Fa-f]+x?\s+[RT]x\s+d\s+)([0-9A-Fa-f])((?:\s+[0-9A-Fa-f]{2})*)")


def fix_slcan(data: bytes) -> bytes:
    """Each classic data frame record's DLC digit set to its number of data bytes (at most 8) when it matches
    neither the data alone nor the data and a 4-digit adapter time; the time is taken to be there (adapters that
    stamp, as the simulated one does) when the digits allow it."""
    def dlc(m: re.Match) -> bytes:
        hexdata, d = m.group(4), int(m.group(3))
        digits = len(hexdata)
        if m.group(1) in b"rR" or digits % 2 or digits in (2 * d, 2 * d + 4):
            return m.group(0)
        n = (digits - 4) // 2 if 4 <= digits <= 20 else min(digits // 2, 8)
        return m.group(1) + m.group(2) + b"%d" % n + hexdata + b"\r"

    return _SLCAN_RECORD.sub(dlc, data)


def fix_asc(data: bytes) -> bytes:
    """Each Vector ASC data frame's DLC set to the number of data bytes that follow it."""
    return _ASC_FRAME.sub(lambda m: m.group(1) + b"%X" % min(len(m.group(3).split()), 15) + m.group(3), data)


def fix_blf(data: bytes) -> bytes:
    """BLF object sizes rewritten from where the objects lie: each ``LOBJ`` object ends where the next one of its
    level starts (log containers at the top level, stored uncompressed; the frames inside them), and a
    container's uncompressed size is its data's length."""
    b = bytearray(data)
    at = [m.start() for m in re.finditer(b"LOBJ", data)]
    outer = [p for p in at if p + 32 <= len(b) and int.from_bytes(b[p + 12:p + 16], "little") == 10]
    for p, e in zip(outer, [*outer[1:], len(b)]):
        size = e - p - (e - p) % 4
        b[p + 8:p + 12] = size.to_bytes(4, "little")
        b[p + 16:p + 18] = b"\0\0"                     # stored, not compressed
        b[p + 24:p + 28] = max(size - 32, 0).to_bytes(4, "little")
        inner = [q - p - 32 for q in at if p + 32 <= q < p + size]
        for q, f in zip(inner, [*inner[1:], size - 32]):
            b[p + 32 + q + 8:p + 32 + q + 12] = (f - q).to_bytes(4, "little")
    return bytes(b)


FIXES.update(slcan=fix_slcan, candump=lambda d: d, asc=fix_asc, blf=fix_blf, dbc=lambda d: d)


def _dbc_seeds() -> list[bytes]:
    """The simulated car's DBC and variants with what real DBCs hold: 64-bit and float signals, multiplexed
    signals (simple and extended multiplexing), the largest ids, each also cut short at a few places."""
    from fieldlog.tools.sim import vehicle

    base = vehicle.DBC_PATH.read_bytes()
    extra = [
        b'BO_ 1024 BIG64: 8 ECM\n SG_ COUNT64 : 0|64@1+ (1,0) [0|18446744073709551615] "" LOGGER\n'
        b' SG_ WHEEL64 : 63|64@0- (0.001,0) [-9.2e15|9.2e15] "m/s" LOGGER\n',
        b'BO_ 1040 FLOATS: 8 ECM\n SG_ F32 : 0|32@1- (1,0) [0|0] "km/h" LOGGER\n SG_ F64B : 32|32@1- (1,0) [0|0] ""'
        b' LOGGER\nSIG_VALTYPE_ 1040 F32 : 1;\n',
        b'BO_ 1056 MUXED: 8 ABS\n SG_ MUX M : 0|8@1+ (1,0) [0|255] "" LOGGER\n SG_ SPEED_A m0 : 8|16@1+ (0.01,0)'
        b' [0|655.35] "km/h" LOGGER\n SG_ SPEED_B m1 : 8|16@1+ (0.01,0) [0|655.35] "km/h" LOGGER\n'
        b' SG_ SUB m2M : 8|8@1+ (1,0) [0|255] "" LOGGER\n SG_ DEEP m3 : 16|16@1+ (1,0) [0|65535] "" LOGGER\n'
        b'SG_MUL_VAL_ 1056 DEEP SUB 3-3;\nSG_MUL_VAL_ 1056 SUB MUX 2-2;\n',
        b'BO_ 2147483648 ZERO_EXT: 0 ECM\n',
        b'BO_ 2684354559 MAX_EXT: 64 ECM\n SG_ WHEEL_X : 0|16@1+ (1e308,0) [0|0] "km/h" LOGGER\n'
        b' SG_ LAST : 504|8@1+ (1,0) [0|255] "" LOGGER\n',
    ]
    whole = base + b"\n" + b"".join(extra)
    huge = whole + b'BO_ 4294967295 HUGE_EXT: 8 ECM\n SG_ H : 0|8@1+ (1,0) [0|255] "" LOGGER\n'
    return [whole] * 4 + [huge] + [whole[:n] for n in (len(whole) // 5, len(whole) // 2, len(whole) - 40)]


DBC_SIGNALS = {"wheel_fl": "WHEEL_SPEEDS.WHEEL_SPEED_FL", "wheel_fr": "BIG64.WHEEL64",
               "wheel_rl": "MUXED.SPEED_A", "wheel_rr": "MUXED.SPEED_B", "vehicle_speed": "FLOATS.F32",
               "gear": "GEARBOX.GEAR", "steering": "STEERING.STEER_ANGLE"}


def _can_frames(rng: np.random.Generator) -> bytes:
    """``frames`` records of every id the DBC seeds name, of every length up to 64, random data."""
    from fieldlog.acquire import can

    ids = [(464, False), (480, False), (928, False), (192, False), (1024, False), (1040, False), (1056, False),
           (0x1FFFFFFF, True), (0x0, True), (0x1FFFFFFF & 2684354559, True)]
    frames = []
    for cid, ext in ids:
        for n in (0, 1, 2, 4, 7, 8, 12, 64):
            data = bytearray(rng.bytes(n))
            if cid == 1056 and n:
                data[0] = int(rng.integers(0, 5))                 # every multiplexer value, and one unknown
            frames.append(can.CanFrame(cid, bytes(data), ext, fd=n > 8, adapter_ns=int(rng.integers(-1, 10**12))))
    return can.encode_records(frames)


def _vehicle(dbc: bytes, signals: dict[str, str], wire: str):
    from fieldlog.acquire import canbus

    return canbus.VehicleDecoder(canbus.BusConfig(wire=wire, dbc=dbc.decode("utf-8", "replace"),
                                                  dbc_name="fuzz.dbc", signals=dict(signals)))


def _one_line(e: ValueError) -> None:
    """A ValueError is a command's one-line report: more than one line is a finding too."""
    if "\n" in str(e):
        raise AssertionError(f"a bad-input message of more than one line: {str(e)[:200]!r}")


def _slcan_run(t: Target, data: bytes) -> None:
    """SLCAN bytes through the daemon's CAN path: the framer and the DBC decoder (a new one every 200 reads)."""
    from fieldlog.tools.sim import vehicle

    st = t.state
    if "dec" not in st or st["n"] >= 200:
        st.update(dec=_vehicle(vehicle.DBC_PATH.read_bytes(), vehicle.SIGNALS, "slcan"), n=0)
    st["n"] += 1
    st["dec"].feed(data, 1_700_000_000 * NS + st["n"] * NS // 100, _Drop())


def _can_log_run(t: Target, data: bytes) -> None:
    """A CAN log file through ``fieldlog import --can``'s reading (python-can's reader for the suffix) and the DBC
    decoder; a ValueError (the one-line report of a bad log) is not a crash."""
    from fieldlog.tools import importer
    from fieldlog.tools.sim import vehicle

    st = t.state
    path = st["path"]
    path.write_bytes(data)
    try:
        reads = importer.can_reads(path, 1_700_000_000 * NS)
    except ValueError as e:
        _one_line(e)
        return
    dec = st.get("dec") or st.setdefault("dec", _vehicle(vehicle.DBC_PATH.read_bytes(), vehicle.SIGNALS, "frames"))
    for r in reads:
        dec.feed(r.data, r.wall_ns, _Drop())


def _dbc_run(t: Target, data: bytes) -> None:
    """A DBC file as ``[can] dbc`` or ``import --dbc`` loads it, the signals set up, then frames of every id and
    length decoded; a ValueError (CanConfigError: the one-line report of a bad DBC or signal) is not a crash."""
    try:
        dec = _vehicle(data, DBC_SIGNALS, "frames")
    except ValueError as e:
        _one_line(e)
        return
    dec.feed(t.state["frames"], 1_700_000_000 * NS, _Drop())


def _can_log_seeds(fmt: str) -> list[bytes]:
    """Logs of the simulated car's bus (4 s) and a few odd frames (CAN FD, remote, error), 20 frames to a log,
    written by python-can's own writers (BLF stored uncompressed, so that mutations reach the frames)."""
    import can as pycan

    from fieldlog.acquire import can
    from fieldlog.tools.sim import simulate, trajectory

    reads = simulate.make_reads(trajectory.load_scenario("figure8"), 4.0, 5, can=True)[0]
    framer = can.SlcanFramer()
    frames = [f for r in reads if r.port == "can" for f in framer.feed(r.data)]
    frames += [can.CanFrame(0x1FFFFFFF, bytes(range(64)), True, fd=True, brs=True),
               can.CanFrame(0x7FF, b"", remote=True), can.CanFrame(0, b"\0" * 8, error=True)]
    path = Path(tempfile.mkdtemp(prefix="fieldlog-fuzz-")) / f"seed.{fmt}"
    seeds = []
    for start in range(0, len(frames), 20):
        with pycan.Logger(str(path), **({"compression_level": 0} if fmt == "blf" else {})) as w:
            for i, f in enumerate(frames[start:start + 20], start):
                w.on_message_received(pycan.Message(
                    timestamp=1_700_000_000 + i / 100, arbitration_id=f.can_id, is_extended_id=f.extended,
                    is_remote_frame=f.remote, is_error_frame=f.error, is_fd=f.fd, bitrate_switch=f.brs,
                    data=f.data, dlc=len(f.data), channel=0 if fmt == "blf" else "can0"))
        seeds.append(path.read_bytes())
        path.unlink()
    return seeds


def _can_target(name: str) -> Target:
    if name == "slcan":
        from fieldlog.tools.sim import simulate, trajectory

        reads = simulate.make_reads(trajectory.load_scenario("figure8"), 4.0, 5, can=True)[0]
        return Target(name, [r.data for r in reads if r.port == "can"][:400], _slcan_run)
    if name == "dbc":
        return Target(name, _dbc_seeds(), _dbc_run, {"frames": _can_frames(np.random.default_rng(0))})
    fmt = {"candump": "log", "asc": "asc", "blf": "blf"}[name]
    import can.io.player

    can.io.player._update_reader_plugins()          # python-can looks its plugins up on every LogReader: once here
    can.io.player._update_reader_plugins = lambda: None
    work = Path(tempfile.mkdtemp(prefix="fieldlog-fuzz-", dir="/dev/shm" if Path("/dev/shm").is_dir() else None))
    return Target(name, _can_log_seeds(fmt), _can_log_run, {"path": work / f"input.{fmt}"})


def make_target(name: str, fast: bool = False) -> Target:
    """Target ``name``; ``fast``: the decoders without the pipeline (nmea, ubx, novatel, sbf), the decoder and the
    counter judge without the time sync (daq)."""
    if name == "sbf":
        return make_sbf_target(fast)
    if name in ("nmea", "ubx", "novatel"):
        from fieldlog.acquire import gpsport

        gps = b"".join(r.data for r in _sim_reads({"ubx": "ublox"}.get(name, name)) if r.port == "gps")
        frames = [f if k in ("ubx", "novatel_bin") else f.rstrip(b"\r\n") + b"\r\n" for k, f in gpsport.Framer().feed(gps)]
        group = 1 if fast else 4                        # whole frames: a UBX NAV-PVT is 100 bytes
        seeds = [b"".join(frames[i:i + group]) for i in range(0, len(frames), group)]
        if name == "novatel":
            seeds += [_novatel_binary(2300, 1000 * k) for k in range(4)]
        if name == "ubx":
            seeds += [_ubx_older(1000 * k) for k in range(4)]
        return Target(name, seeds, _gps_decoders_run if fast else _gps_run)
    if name == "daq":
        reads = _sim_reads("nmea", 20.0)
        seeds = [r.data for r in reads if r.port == "daq"][:200]
        return Target(name, seeds, _daq_decoder_run) if fast else Target(name, seeds, _daq_run, {"reads": reads})
    if name == "mcap":
        tmp = Path(tempfile.mkdtemp(prefix="fieldlog-fuzz-"))
        return Target(name, [_mcap_seed()], _mcap_run, {"path": tmp / "input.mcap"})
    if name in CAN_TARGETS:
        return _can_target(name)
    raise ValueError(f"unknown target {name!r}; one of {', '.join(TARGETS + CAN_TARGETS)}")


def one_input(target: Target, data: bytes) -> None:
    """Re-checksum ``data`` and run it through ``target``; raises on a crash."""
    target.run(target, FIXES[target.name](data))


def replay(name: str, data: bytes, fast: bool = False) -> None:
    """Run one saved input (already mutated) through a fresh target; raises on a crash."""
    one_input(make_target(name, fast), data)


# ------------------------------------------------------------------------------------------ the loop

@dataclass
class Campaign:
    inputs: int = 0
    crashes: Counter = field(default_factory=Counter)     # kind -> count
    seconds: float = 0.0


def kind_of(e: BaseException) -> str:
    tb = e.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    where = f"{Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno}" if tb is not None else "?"
    return f"{type(e).__name__}@{where}"


def campaign(name: str, runs: int, seed: int = 1, crashes: Path | None = None,
             progress: Callable[[Campaign], None] | None = None, fast: bool = False) -> Campaign:
    """``runs`` mutated, re-checksummed inputs through target ``name`` (``make_target``); crashes counted by kind
    and (one file per kind) saved to ``crashes``."""
    rng = np.random.default_rng([seed, (TARGETS + CAN_TARGETS).index(name)])
    t = make_target(name, fast)
    res = Campaign()
    t0 = time.monotonic()
    for i in range(runs):
        a, b = (t.seeds[int(j)] for j in rng.integers(0, len(t.seeds), 2))
        data = mutate(a, rng, b)
        try:
            one_input(t, data)
        except Exception as e:  # noqa: BLE001 - every exception is a finding
            kind = kind_of(e)
            if res.crashes[kind] == 0 and crashes is not None:
                crashes.mkdir(parents=True, exist_ok=True)
                tag = hashlib.sha1(data).hexdigest()[:10]
                (crashes / f"{name}-{re.sub(r'[^A-Za-z0-9_.]+', '_', kind)}-{tag}.bin").write_bytes(
                    FIXES[name](data))
            res.crashes[kind] += 1
            for key in ("pipe", "framer", "dec"):      # fresh decoders after a crash
                t.state.pop(key, None)
        res.inputs = i + 1
        if progress and (i + 1) % 10_000 == 0:
            res.seconds = time.monotonic() - t0
            progress(res)
    res.seconds = time.monotonic() - t0
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fieldlog.tools.dev.fuzz", description=__doc__.splitlines()[0])
    p.add_argument("--target", choices=[*TARGETS, *CAN_TARGETS, "all", "can"], required=True)
    p.add_argument("--runs", type=int, default=1_000_000, help="inputs per target (default 10^6)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--crashes", type=Path, default=Path("out/fuzz-crashes"), help="one input per crash kind")
    p.add_argument("--atheris", action="store_true", help="coverage-guided (pip install atheris); libFuzzer "
                                                          "flags follow")
    a, rest = p.parse_known_args(argv)
    logging.disable(logging.WARNING)                  # the decoders' warnings about bad input: what is fed here
    names = {"all": TARGETS, "can": CAN_TARGETS}.get(a.target, (a.target,))
    if a.atheris:
        return _atheris(names[0], rest)
    for name in names:
        def show(r: Campaign, name: str = name) -> None:
            print(f"{name}: {r.inputs} inputs, {sum(r.crashes.values())} crashes in {len(r.crashes)} kinds, "
                  f"{r.seconds:.0f} s", file=sys.stderr, flush=True)

        r = campaign(name, a.runs, a.seed, a.crashes, show)
        show(r)
        for kind, n in r.crashes.most_common():
            print(f"  {n:8d}  {kind}")
    return 0


def _atheris(name: str, flags: list[str]) -> int:
    try:
        import atheris
    except ImportError:
        sys.exit("fieldlog fuzz: atheris is not installed: pip install atheris (or run without --atheris)")
    t = make_target(name)
    rng = np.random.default_rng(0)

    def custom_mutator(data: bytes, max_size: int, seed: int) -> bytes:
        return FIXES[name](mutate(data or t.seeds[seed % len(t.seeds)], np.random.default_rng(seed),
                                  t.seeds[int(rng.integers(0, len(t.seeds)))]))[:max_size]

    atheris.Setup([sys.argv[0], *flags], lambda d: t.run(t, d), custom_mutator=custom_mutator)
    atheris.Fuzz()
    return 0


if __name__ == "__main__":
    sys.exit(main())
