"""The vehicle bus at the byte level: the ``--can`` URL, the SLCAN serial framer and the frame-record codec.

Two wire formats reach ``/raw/can`` (``RawBytes``, port ``can``; the ``can`` metadata record says which):

* ``slcan``: the serial bytes of an SLCAN (Lawicel) adapter exactly as read (CANable, USBtin, Lawicel CANUSB):
  ASCII records ending in CR. ``tiiiL<data>[tttt]`` standard and ``Tiiiiiiii L<data>[tttt]`` extended data
  frames (``x`` for ``T``: CANDapter), ``r``/``R`` remote frames, ``d``/``D``/``b``/``B`` CAN FD (DLC code
  0-F; ``b``/``B`` with bit-rate switch), the optional 4 hex-digit adapter time stamp (ms, 0..59999, wrapping
  each minute) after the data, ``Fxx`` status flags (bus errors, overrun, error passive), BEL for a
  refused command, ``z``/``Z``/``V``/``N`` replies. Anything else up to the next CR is garbage: counted, skipped.
* ``frames``: one record per frame, from python-can (SocketCAN) or a log file (``import``): little-endian i64
  adapter time in ns (-1: none), u32 ``can_id`` with the SocketCAN flag bits (EFF 0x80000000, RTR 0x40000000,
  ERR 0x20000000), u8 data length, u8 FD flags (0x01 bit-rate switch, 0x02 error state, 0x04 FD frame), 2
  reserved bytes, the data bytes. A read holds whole records.

The framer holds at most ``MAX_RECORD`` bytes between reads, never raises and counts what it skips.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import NamedTuple

CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CAN_EFF_MASK = 0x1FFFFFFF
CAN_ERR_BUSOFF = 0x40            # error class bits of an error frame's id (linux/can/error.h)
CAN_ERR_CRTL = 0x04
FD_BRS, FD_ESI, FD_FRAME = 0x01, 0x02, 0x04
FD_DLC = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
# SLCAN 'S' commands by CAN bit rate (Lawicel; python-can's slcan interface uses the same table)
SLCAN_BITRATES = {10000: "S0", 20000: "S1", 50000: "S2", 100000: "S3", 125000: "S4", 250000: "S5",
                  500000: "S6", 750000: "S7", 1000000: "S8", 83300: "S9"}
MAX_RECORD = 1 + 8 + 1 + 128 + 4          # the longest SLCAN record: 'D', 29-bit id, DLC, 64 bytes, time
SLCAN_TIME_WRAP_MS = 60000
_RECORD = struct.Struct("<qIBBxx")
_HEX = frozenset(b"0123456789ABCDEFabcdef")


class CanFrame(NamedTuple):
    """One frame as the adapter gave it. ``can_id`` without flag bits; ``adapter_ns``: the adapter's own time
    stamp in ns (SLCAN: ms within the minute; SocketCAN: the kernel's receive time), -1 when it has none."""

    can_id: int
    data: bytes
    extended: bool = False
    remote: bool = False
    error: bool = False
    fd: bool = False
    brs: bool = False
    adapter_ns: int = -1


@dataclass(frozen=True)
class CanUrl:
    """A parsed ``--can`` URL: ``socketcan://IFACE`` or ``slcan://PORT[@BITRATE]`` (CAN bit rate, bit/s)."""

    kind: str
    channel: str
    bitrate: int = 0

    @property
    def wire(self) -> str:
        """The /raw/can format this interface records: 'slcan' (serial bytes) or 'frames' (records)."""
        return "slcan" if self.kind == "slcan" else "frames"


def parse_url(url: str) -> CanUrl:
    """``socketcan://can0``, ``slcan:///dev/ttyACM0@500000``; ValueError with one line otherwise."""
    kind, sep, rest = url.partition("://")
    if not sep or kind not in ("socketcan", "slcan") or not rest:
        raise ValueError(f"--can {url!r}: expected socketcan://IFACE or slcan://PORT[@BITRATE]")
    if kind == "socketcan":
        return CanUrl(kind, rest)
    port, at, rate = rest.rpartition("@") if "@" in rest else (rest, "", "")
    bitrate = 0
    if at:
        try:
            bitrate = int(rate)
        except ValueError:
            bitrate = -1
        if bitrate not in SLCAN_BITRATES:
            raise ValueError(f"--can {url!r}: bit rate {rate!r} is not one of "
                             f"{', '.join(str(b) for b in sorted(SLCAN_BITRATES))}")
    return CanUrl(kind, port, bitrate)


def slcan_open_commands(bitrate: int) -> bytes:
    """What the daemon sends an SLCAN adapter on opening: close, the bit rate (if given), time stamps on, open."""
    return b"C\r" + (SLCAN_BITRATES[bitrate].encode() + b"\r" if bitrate else b"") + b"Z1\r" + b"O\r"


def slcan_record(f: CanFrame, time_ms: int | None = None) -> bytes:
    """The SLCAN record of a frame (what an adapter sends), with the adapter time stamp if ``time_ms``."""
    if f.fd:
        kind = ("B" if f.extended else "b") if f.brs else ("D" if f.extended else "d")
        dlc = "%X" % FD_DLC.index(len(f.data))
    else:
        kind = ("R" if f.extended else "r") if f.remote else ("T" if f.extended else "t")
        dlc = "%d" % len(f.data)
    ident = "%08X" % f.can_id if f.extended else "%03X" % f.can_id
    data = "" if f.remote else f.data.hex().upper()
    stamp = "" if time_ms is None else "%04X" % (time_ms % SLCAN_TIME_WRAP_MS)
    return f"{kind}{ident}{dlc}{data}{stamp}\r".encode()


@dataclass
class CanStats:
    """What the bus and the adapter delivered besides good frames; every field is a count."""

    frames: int = 0
    by_kind: dict[str, int] = field(default_factory=dict)    # std, ext, remote, fd
    error_frames: int = 0          # SocketCAN error frames
    bus_off: int = 0               # ... of class bus-off
    status_errors: int = 0         # SLCAN 'F' replies with an error flag set
    overruns: int = 0              # SLCAN 'F' data overrun / receive FIFO full
    refused: int = 0               # SLCAN BEL: the adapter refused a command
    bad_records: int = 0           # records that start like a frame but do not parse
    overlong: int = 0              # more than MAX_RECORD bytes without a CR
    bytes_discarded: int = 0       # bytes of no record (garbage on the line)


_IDLEN = {ord("t"): 3, ord("r"): 3, ord("d"): 3, ord("b"): 3, ord("T"): 8, ord("x"): 8, ord("R"): 8,
          ord("D"): 8, ord("B"): 8}


class SlcanFramer:
    """SLCAN bytes in, ``CanFrame``s out, in stream order; see the module docstring."""

    def __init__(self, stats: CanStats | None = None) -> None:
        self.stats = stats or CanStats()
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[CanFrame]:
        st = self.stats
        if 7 in data:                      # BEL: a refused command, a reply of its own without CR
            st.refused += data.count(7)
            data = data.replace(b"\x07", b"")
        buf = self._buf
        buf += data
        out: list[CanFrame] = []
        pos = 0
        while True:
            end = buf.find(b"\r", pos)
            if end < 0:
                if len(buf) - pos > MAX_RECORD:
                    st.overlong += 1
                    st.bytes_discarded += len(buf) - pos
                    pos = len(buf)
                break
            rec = bytes(buf[pos:end])
            pos = end + 1
            if len(rec) > MAX_RECORD:
                st.overlong += 1
                st.bytes_discarded += len(rec) + 1
                continue
            self._record(rec.lstrip(b"\n"), out)
        del buf[:pos]
        return out

    def _record(self, rec: bytes, out: list[CanFrame]) -> None:
        st = self.stats
        if not rec:
            return
        c = rec[0]
        if c in _IDLEN:
            f = _parse_frame(rec, _IDLEN[c])
            if f is None:
                st.bad_records += 1
                st.bytes_discarded += len(rec) + 1
                return
            st.frames += 1
            kind = "fd" if f.fd else "remote" if f.remote else "ext" if f.extended else "std"
            st.by_kind[kind] = st.by_kind.get(kind, 0) + 1
            out.append(f)
        elif c == ord("F") and len(rec) == 3 and all(x in _HEX for x in rec[1:]):
            flags = int(rec[1:], 16)
            st.overruns += bool(flags & 0x09)
            st.status_errors += bool(flags & 0xF4)
        elif c in b"zZ" and len(rec) == 1 or c in b"VvN" and 1 < len(rec) <= 5:
            return
        else:
            st.bytes_discarded += len(rec) + 1


def _parse_frame(rec: bytes, idlen: int) -> CanFrame | None:
    """One SLCAN frame record (no CR), or None when it does not parse."""
    c = chr(rec[0])
    head = 1 + idlen + 1
    if len(rec) < head or not all(x in _HEX for x in rec[1:]):
        return None
    can_id = int(rec[1:1 + idlen], 16)
    fd = c in "dDbB"
    code = int(rec[head - 1:head], 16)
    if fd:
        n = FD_DLC[code]
    elif code > 8:
        return None
    else:
        n = code
    remote = c in "rR"
    ndata = 0 if remote else 2 * n
    rest = len(rec) - head - ndata
    if rest not in (0, 4) or can_id > (CAN_EFF_MASK if idlen == 8 else 0x7FF):
        return None
    data = bytes.fromhex(rec[head:head + ndata].decode()) if ndata else bytes(n if remote else 0)
    t_ms = int(rec[head + ndata:], 16) if rest else -1
    if t_ms >= SLCAN_TIME_WRAP_MS:
        return None
    return CanFrame(can_id, b"" if remote else data, idlen == 8, remote, False, fd, c in "bB",
                    t_ms * 1_000_000 if t_ms >= 0 else -1)


def encode_records(frames: list[CanFrame]) -> bytes:
    """Frames as ``frames`` records (module docstring)."""
    parts = []
    for f in frames:
        cid = f.can_id | (CAN_EFF_FLAG if f.extended else 0) | (CAN_RTR_FLAG if f.remote else 0) | \
            (CAN_ERR_FLAG if f.error else 0)
        flags = (FD_FRAME if f.fd else 0) | (FD_BRS if f.brs else 0)
        parts.append(_RECORD.pack(f.adapter_ns, cid, len(f.data), flags) + f.data)
    return b"".join(parts)


class RecordDecoder:
    """``frames`` records in, ``CanFrame``s out; a record cut short or too long ends the read (counted)."""

    def __init__(self, stats: CanStats | None = None) -> None:
        self.stats = stats or CanStats()

    def feed(self, data: bytes) -> list[CanFrame]:
        out: list[CanFrame] = []
        st = self.stats
        pos, n = 0, len(data)
        while pos < n:
            if n - pos < _RECORD.size:
                st.bad_records += 1
                st.bytes_discarded += n - pos
                break
            t_ns, cid, ln, flags = _RECORD.unpack_from(data, pos)
            if ln > 64 or pos + _RECORD.size + ln > n:
                st.bad_records += 1
                st.bytes_discarded += n - pos
                break
            body = bytes(data[pos + _RECORD.size:pos + _RECORD.size + ln])
            pos += _RECORD.size + ln
            ext = bool(cid & CAN_EFF_FLAG)
            f = CanFrame(cid & (CAN_EFF_MASK if ext else 0x7FF), body, ext, bool(cid & CAN_RTR_FLAG),
                         bool(cid & CAN_ERR_FLAG), bool(flags & FD_FRAME), bool(flags & FD_BRS), t_ns)
            if f.error:
                st.error_frames += 1
                st.bus_off += bool(f.can_id & CAN_ERR_BUSOFF)
                continue
            st.frames += 1
            kind = "fd" if f.fd else "remote" if f.remote else "ext" if f.extended else "std"
            st.by_kind[kind] = st.by_kind.get(kind, 0) + 1
            out.append(f)
        return out


def framer(wire: str, stats: CanStats | None = None) -> SlcanFramer | RecordDecoder:
    """The decoder of one /raw/can wire format ('slcan' or 'frames')."""
    if wire == "slcan":
        return SlcanFramer(stats)
    if wire == "frames":
        return RecordDecoder(stats)
    raise ValueError(f"[can] wire format {wire!r} is not 'slcan' or 'frames'")
