"""The daemon's link to the vehicle bus (``[can] url``): what its port reader selects on and reads.

* ``slcan://PORT[@BITRATE]``: the adapter's serial port through pyserial, raw and non-blocking like the DAQ and
  GPS ports; on opening it is sent close, the bit rate (when the URL gives one), time stamps on and open
  (``can.slcan_open_commands``). The reader takes the serial bytes as they come (``/raw/can`` wire ``slcan``).
  SLCAN is read here rather than through python-can's ``slcan`` interface, which parses the line itself and
  keeps no bytes: raw first.
* ``socketcan://IFACE``: python-can's SocketCAN bus, error frames on (``CAN_RAW_ERR_FILTER``); each ready read
  drains the frames received into ``frames`` records with the kernel's receive time (``/raw/can`` wire
  ``frames``). The interface going down (bus-off with restart off, the adapter pulled) ends the link as an
  unplugged serial port does, and the reader reopens it.
"""
from __future__ import annotations

import socket
from typing import Any

import serial

from fieldlog.acquire import can

NS = 1_000_000_000
CAN_ERR_MASK = 0x1FFFFFFF


class SlcanLink:
    """An SLCAN adapter on a serial port; ``fileno`` for select and os.read."""

    def __init__(self, port: str, baud: int, bitrate: int) -> None:
        self.ser = serial.Serial(port, baud, timeout=0, write_timeout=1.0, exclusive=True)
        try:
            self.ser.write(can.slcan_open_commands(bitrate))
        except (serial.SerialException, OSError):
            self.ser.close()
            raise

    def fileno(self) -> int:
        return self.ser.fileno()

    def close(self) -> None:
        self.ser.close()


class SocketcanLink:
    """A SocketCAN interface through python-can; ``read_ready`` gives the frames received as records."""

    def __init__(self, channel: str) -> None:
        try:
            import can as pycan

            self.bus: Any = pycan.Bus(interface="socketcan", channel=channel, receive_own_messages=False)
        except Exception as e:  # noqa: BLE001 - python-can raises CanError, OSError, ImportError
            raise OSError(f"socketcan {channel}: {e}") from None
        sock = getattr(self.bus, "socket", None)
        if sock is not None and hasattr(socket, "SOL_CAN_RAW"):
            sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_ERR_FILTER, CAN_ERR_MASK)

    def fileno(self) -> int:
        return self.bus.fileno()

    def read_ready(self) -> bytes:
        """The frames waiting (at least the one select saw) as ``frames`` records; OSError when the bus is gone."""
        frames = []
        try:
            m = self.bus.recv(0)
            while m is not None:
                frames.append(can.CanFrame(int(m.arbitration_id), b"" if m.is_remote_frame else bytes(m.data),
                                           bool(m.is_extended_id), bool(m.is_remote_frame), bool(m.is_error_frame),
                                           bool(m.is_fd), bool(m.bitrate_switch), int(round(m.timestamp * NS))))
                m = self.bus.recv(0)
        except Exception as e:  # noqa: BLE001 - python-can's CanOperationError on a downed interface
            if not frames:
                raise OSError(str(e) or type(e).__name__) from None
        return can.encode_records(frames)

    def close(self) -> None:
        self.bus.shutdown()


def open_link(url: str, baud: int) -> SlcanLink | SocketcanLink:
    """The link of a ``[can] url`` (checked by the config already)."""
    u = can.parse_url(url)
    if u.kind == "slcan":
        return SlcanLink(u.channel, baud, u.bitrate)
    return SocketcanLink(u.channel)
