"""The GPS receiver read through a running gpsd (``--gps gpsd://HOST[:PORT][/DEVICE]``), raw first.

gpsd may own the receiver (for chrony, for other programs); fieldlog then connects to gpsd's TCP port and asks
for the receiver's own bytes: ``?WATCH={"enable":true,"raw":2}`` (gpsd_json(5): raw 1 copies NMEA and other
text sentences as they came but hex-dumps binary packets; raw 2 copies every packet, UBX and NovAtel binary
included, verbatim). gpsd's packet lexer forwards whole packets, so what reaches ``/raw/gps`` is the receiver's
packets byte for byte (bytes gpsd could not frame as a packet are gpsd's to drop), and the framers, decoders,
time sync and ``rebuild`` see what a serial port would have given. The PPS still comes in through the DAQ board.

gpsd also writes its own JSON reports on the same connection (VERSION on connect, DEVICES and WATCH in reply,
DEVICE when a receiver comes or goes, ERROR). Each is one write of one line, ``{"class":"...", ...}`` up to a
newline, between packets: ``GpsdStream`` takes them out of the byte stream (and keeps them for the log) and
passes everything else on unchanged. A marker that does not start a valid JSON line within ``MAX_REPORT``
bytes is receiver data and passes on.

``GpsdLink`` is the connection: a non-blocking socket the daemon's port reader waits on with ``select`` like a
serial port; end of file (gpsd stopped or restarted) is a lost port, reconnected with backoff.
"""
from __future__ import annotations

import json
import logging
import socket

from fieldlog.acquire.config import GpsdAddress

MARKER = b'{"class":"'
MAX_REPORT = 1 << 16            # gpsd's longest JSON report (a DEVICES or SKY object) is a few kB
CONNECT_TIMEOUT_S = 2.0
log = logging.getLogger("fieldlog.acquire.gpsd")
HOLD_S = 0.005                  # longest wait for the rest of a possible report start at the end of a read
BACKOFF_MAX_S = 4.0             # longest wait between reconnection attempts (doubling from [daemon] reconnect_s)


def watch_command(device: str = "") -> bytes:
    """The WATCH that turns on raw passthrough (of ``device`` only when given)."""
    w: dict[str, object] = {"enable": True, "raw": 2}
    if device:
        w["device"] = device
    return b"?WATCH=" + json.dumps(w, separators=(",", ":")).encode() + b"\n"


class GpsdStream:
    """gpsd's raw-mode output in, the receiver's bytes out; gpsd's JSON reports collected in ``reports``.

    ``feed`` keeps back at most a started report (a marker and no newline yet, up to MAX_REPORT bytes) or a
    read's last bytes that could begin a marker (``{``, ``{"``, ...), so memory is bounded. Those last bytes are
    usually a packet's own (a UBX checksum of 0x7B): the reader ``release``s them when nothing follows within
    HOLD_S, so a packet is never held back until the next one; ``reports_seen`` counts reports.
    gpsd's ERROR reports (e.g. a WATCH of a device it does not know) are logged.
    """

    def __init__(self) -> None:
        self._held = b""
        self._prefix = False          # what is held is a possible marker start, not a started report
        self.reports: list[dict] = []
        self.reports_seen = 0

    @property
    def holds_prefix(self) -> bool:
        """The last read ended in bytes that may begin a report: call ``release`` if nothing follows."""
        return self._prefix

    def release(self) -> bytes:
        """The held possible marker start, as receiver bytes (nothing followed it)."""
        if not self._prefix:
            return b""
        out, self._held, self._prefix = self._held, b"", False
        return out

    def feed(self, data: bytes) -> bytes:
        buf = self._held + data
        out = bytearray()
        i = 0
        n = len(buf)
        while True:
            j = buf.find(MARKER, i)
            if j < 0:
                keep = _marker_prefix_at_end(buf, i)
                out += buf[i:n - keep]
                self._held, self._prefix = buf[n - keep:], keep > 0
                break
            out += buf[i:j]
            k = buf.find(b"\n", j, j + MAX_REPORT)
            if k < 0:
                if n - j < MAX_REPORT:
                    self._held, self._prefix = buf[j:], False
                    break
                out += buf[j:j + 1]           # no report: receiver bytes that happen to look like one
                i = j + 1
                continue
            report = _report(buf[j:k + 1])
            if report is None:
                out += buf[j:j + 1]
                i = j + 1
                continue
            self.reports_seen += 1
            if report["class"] == "ERROR":
                log.warning(f"gpsd: {report.get('message', report)}")
            self.reports.append(report)
            del self.reports[:-16]            # the latest few, for the log
            i = k + 1
        return bytes(out)


def _marker_prefix_at_end(buf: bytes, start: int) -> int:
    """Length (0 if none) of the longest tail of ``buf[start:]`` that is a proper prefix of MARKER."""
    for m in range(min(len(MARKER) - 1, len(buf) - start), 0, -1):
        if buf.endswith(MARKER[:m]):
            return m
    return 0


def _report(line: bytes) -> dict | None:
    try:
        obj = json.loads(line)
    except (ValueError, UnicodeDecodeError):
        return None
    return obj if isinstance(obj, dict) and isinstance(obj.get("class"), str) else None


class GpsdLink:
    """A connection to gpsd in raw mode, with the interface the daemon's port reader uses for a serial port:
    ``fileno``, ``close`` and ``decode`` (the bytes read -> the receiver's bytes)."""

    def __init__(self, address: GpsdAddress) -> None:
        self.address = address
        self.stream = GpsdStream()
        self.sock = socket.create_connection((address.host, address.port), timeout=CONNECT_TIMEOUT_S)
        try:
            self.sock.sendall(watch_command(address.device))
        except OSError:
            self.sock.close()
            raise
        self.sock.setblocking(False)

    def fileno(self) -> int:
        return self.sock.fileno()

    def close(self) -> None:
        self.sock.close()

    def decode(self, data: bytes) -> bytes:
        return self.stream.feed(data)

    def hold_s(self) -> float | None:
        """How long to wait for more bytes before ``release`` (None: nothing held that needs it)."""
        return HOLD_S if self.stream.holds_prefix else None

    def release(self) -> bytes:
        return self.stream.release()

    def describe(self) -> str:
        """What gpsd said about itself and the device so far (for the port's ``back`` event)."""
        version = next((r for r in self.stream.reports if r["class"] == "VERSION"), None)
        devices = [d.get("path", "") for r in self.stream.reports if r["class"] == "DEVICES"
                   for d in r.get("devices", []) if isinstance(d, dict)]
        parts = [str(self.address)]
        if version:
            parts.append(f"gpsd {version.get('release', '?')}")
        if devices:
            parts.append("devices " + ",".join(devices))
        return " ".join(parts)
