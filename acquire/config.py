"""``fieldlog acquire`` configuration: a TOML file, overridden by the command line.

Every section and key is optional except the two ports (from the file or ``--daq``/``--gps``). A bad file
raises ``ConfigError`` with one line that names the offending key, e.g. ``[gps] baud: 12345 is not a
standard baud rate``.

    [daq]                       # the DAQ board
    port = "/dev/ttyUSB0"
    baud = 921600
    [gps]                       # the GPS receiver
    port = "/dev/ttyUSB1"       # or "gpsd://HOST[:PORT][/DEVICE]": through a running gpsd (acquire/gpsd.py)
    baud = 115200
    protocol = "auto"           # NMEA, u-blox UBX, NovAtel OEM and Septentrio SBF, mixed, found by themselves;
                                # or one of "nmea", "ubx", "novatel", "septentrio" (with NMEA) to ignore the others
    use_hnr = false             # u-blox HNR-PVT (the receiver's own IMU-fused solution) as the fixes
    [can]                       # optional: the vehicle bus (acquire/can.py, acquire/canbus.py)
    url = "slcan:///dev/ttyACM0@500000"   # or socketcan://can0; --can URL
    baud = 115200               # the SLCAN adapter's serial rate (USB adapters ignore it)
    dbc = "car.dbc"             # decode through this DBC ("" : record the frames only)
    latency_s = 0.0             # adapter and bus delay, subtracted from the read time
    forward = ""                # wheels of the forward speed: rear, front, all, vehicle ("" : rear if named)
    [can.signals]               # MESSAGE.SIGNAL (or SIGNAL) of the DBC for each that the car has
    wheel_rl = "WHEEL_SPEEDS.WHEEL_SPEED_RL"
    wheel_rr = "WHEEL_SPEEDS.WHEEL_SPEED_RR"
    gear = "GEARBOX.GEAR"       # reverse when its choice is named [can] reverse_gear ("R")
    [calibration]
    file = "cal.toml"           # acquire/calib.py layout; omitted: the built-in defaults
    [timesync]                  # acquire/timesync.py TimeSyncConfig keys, e.g. pps_mode = "latch"
                                # (host_time_scale / --time-scale X: for `sim --serve --speed X` playback only)
    [output]
    dir = "drives"              # a session is the rosbag2 directory DIR/<session start UTC>/ (metadata.yaml) of
                                # files <session start UTC>_<NNNN>.mcap, e.g. 2026-11-22T10-15-00Z_0001.mcap
    [rotation]
    max_duration_s = 3600.0     # start the next file after this much host time (0: never)
    max_size_mb = 2048.0        # ... or once the file is this big (0: never)
    [recorder]
    chunk_size = 4194304        # uncompressed bytes per MCAP chunk
    flush_interval_s = 1.0      # a power cut loses at most this much (<= 1 s)
    compression = "zstd"        # "zstd", "lz4" or ""
    fsync = true
    [daemon]
    queue_reads = 4096          # bounded queue per port, in reads
    derived_queue_mb = 64.0     # bytes of reads recorded and waiting for the derived path; beyond, not processed
    merge_wait_s = 0.25         # longest wait for the other port before a read is processed anyway
    reconnect_s = 0.5           # retry period of a port that disappeared
    status_interval_s = 1.0
    bus = ""                    # live bus Unix socket path ("" = none)
"""
from __future__ import annotations

import datetime as _dt
import os
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fieldlog.acquire import timesync
from fieldlog.drive.tables import ConfigError, read_toml, typed_value

if TYPE_CHECKING:
    from fieldlog.acquire import canbus


# termios rates pyserial can set on Linux; anything else is a typo.
STANDARD_BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
                  1000000, 1152000, 1500000, 2000000, 2500000, 3000000, 3500000, 4000000)
NAME_FORMAT = "%Y-%m-%dT%H-%M-%SZ"


GPS_PROTOCOLS = ("auto", "nmea", "ubx", "novatel", "septentrio")   # the keys of acquire.gpsport.ACCEPTS (kept equal by a test)


@dataclass
class PortConfig:
    port: str = ""
    baud: int = 115200


GPSD_SCHEME = "gpsd://"
GPSD_DEFAULT_PORT = 2947


@dataclass(frozen=True)
class GpsdAddress:
    """A gpsd to read the receiver through: TCP ``host``:``port``; ``device`` the receiver's path in gpsd
    ("" = every device gpsd has)."""

    host: str
    port: int = GPSD_DEFAULT_PORT
    device: str = ""

    def __str__(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{GPSD_SCHEME}{host}:{self.port}{self.device}"


def parse_gpsd_url(text: str) -> GpsdAddress | None:
    """``gpsd://HOST[:PORT][/DEVICE]`` (an IPv6 host in brackets) -> GpsdAddress; None when ``text`` is not a
    gpsd URL (a serial port path). ConfigError naming ``[gps] port`` when it is one but malformed.
    ``gpsd://localhost/dev/ttyACM0`` reads /dev/ttyACM0 through the gpsd on localhost:2947."""
    if not text.startswith(GPSD_SCHEME):
        return None
    rest = text[len(GPSD_SCHEME):]
    slash = rest.find("/")
    netloc, device = (rest, "") if slash < 0 else (rest[:slash], rest[slash:])

    def bad(why: str) -> ConfigError:
        return ConfigError(f"[gps] port: {text!r} is not gpsd://HOST[:PORT][/DEVICE]: {why}")

    if netloc.startswith("["):
        close = netloc.find("]")
        if close < 0:
            raise bad("unclosed '[' around an IPv6 host")
        host, tail = netloc[1:close], netloc[close + 1:]
        if tail and not tail.startswith(":"):
            raise bad(f"unexpected {tail!r} after the host")
        port_text = tail[1:] if tail else None
    else:
        host, sep, port_text = netloc.partition(":")
        port_text = port_text if sep else None
    if not host:
        raise bad("no host")
    port = GPSD_DEFAULT_PORT
    if port_text is not None:
        if not port_text.isdigit() or not 0 < int(port_text) < 65536:
            raise bad(f"port {port_text!r} is not a number in 1..65535")
        port = int(port_text)
    return GpsdAddress(host, port, "" if device == "/" else device)


@dataclass
class GpsPortConfig(PortConfig):
    protocol: str = "auto"      # 'auto' (every protocol, mixed), 'nmea', 'ubx', 'novatel', 'septentrio' (+ NMEA)
    use_hnr: bool = False       # u-blox HNR-PVT as the fix stream (acquire/ubx.py): not independent of its IMU

    @property
    def gpsd(self) -> GpsdAddress | None:
        """The gpsd the receiver is read through, or None (a serial port); ConfigError if malformed."""
        return parse_gpsd_url(self.port)


@dataclass
class CanConfig:
    """``[can]``: the vehicle bus (``url`` empty: none). Keys as in acquire/canbus.BusConfig."""

    url: str = ""
    baud: int = 115200
    dbc: str = ""
    latency_s: float = 0.0
    forward: str = ""
    reverse_gear: str = "R"
    speed_unit: str = ""
    signals: dict[str, str] = field(default_factory=dict)

    @property
    def port(self) -> str:
        """The adapter's serial port or the SocketCAN interface the URL names (for the daemon's log)."""
        from fieldlog.acquire import can

        try:
            return can.parse_url(self.url).channel
        except ValueError:
            return self.url


@dataclass
class RotationConfig:
    max_duration_s: float = 3600.0
    max_size_mb: float = 2048.0


@dataclass
class RecorderConfig:
    chunk_size: int = 4 * 1024 * 1024
    flush_interval_s: float = 1.0
    compression: str = "zstd"
    fsync: bool = True


@dataclass
class DaemonConfig:
    queue_reads: int = 4096
    derived_queue_mb: float = 64.0      # bytes (MB) of reads recorded and waiting for the derived path, at most
    merge_wait_s: float = 0.25
    reconnect_s: float = 0.5
    status_interval_s: float = 1.0
    bus: str = ""


@dataclass
class AcquireConfig:
    daq: PortConfig = field(default_factory=lambda: PortConfig(baud=921600))
    gps: GpsPortConfig = field(default_factory=lambda: GpsPortConfig(baud=115200))
    can: CanConfig = field(default_factory=CanConfig)
    calibration_file: str = ""
    timesync: dict[str, Any] = field(default_factory=dict)
    out_dir: str = "drives"
    rotation: RotationConfig = field(default_factory=RotationConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    daemon: DaemonConfig = field(default_factory=DaemonConfig)

    def can_bus(self) -> "canbus.BusConfig | None":
        """How the pipeline decodes /raw/can (None: no [can] url); ConfigError naming the key or the DBC file."""
        from fieldlog.acquire import can

        c = self.can
        if not c.url:
            if c.dbc or c.signals:
                raise ConfigError("[can] url: a DBC or signals without a bus (--can URL or [can] url)")
            return None
        try:
            url = can.parse_url(c.url)
        except ValueError as e:
            raise ConfigError(f"[can] url: {e}") from None
        if url.kind == "slcan" and c.baud not in STANDARD_BAUDS:
            raise ConfigError(f"[can] baud: {c.baud} is not a standard baud rate")
        return bus_config(c, url.wire)

    def sync_config(self) -> timesync.TimeSyncConfig:
        return timesync.TimeSyncConfig.from_dict(self.timesync)


def bus_config(c: CanConfig, wire: str) -> "canbus.BusConfig":
    """The pipeline's decoding of a bus recorded as ``wire`` ('slcan', 'frames') from ``[can]``: the DBC read and
    checked against the signals; ConfigError with one line naming the key or the DBC file."""
    from fieldlog.acquire import canbus

    bad = [k for k, v in c.signals.items() if not isinstance(v, str)]
    if bad:
        raise ConfigError(f"[can.signals] {bad[0]}: expected MESSAGE.SIGNAL as a string")
    if c.signals and not c.dbc:
        raise ConfigError("[can] dbc: signals need the DBC that defines them (--dbc FILE or [can] dbc)")
    try:
        bus = canbus.BusConfig(wire=wire, dbc=canbus.read_dbc(c.dbc) if c.dbc else "", dbc_name=c.dbc,
                               signals=dict(c.signals), forward=c.forward, reverse_gear=c.reverse_gear,
                               speed_unit=c.speed_unit, latency_s=c.latency_s)
        canbus.VehicleDecoder(bus)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    return bus


def _section(d: dict[str, Any], name: str, obj: Any) -> None:
    """Copy table ``name`` of ``d`` onto dataclass ``obj`` with type checks; unknown keys are errors."""
    table = d.get(name, {})
    if not isinstance(table, dict):
        raise ConfigError(f"[{name}]: expected a table, got {table!r}")
    known = {f.name for f in fields(obj)}
    for key, value in table.items():
        if key not in known:
            raise ConfigError(f"[{name}] {key}: unknown key; known keys: {', '.join(sorted(known))}")
        setattr(obj, key, typed_value(name, key, value, getattr(obj, key)))


def from_dict(d: dict[str, Any]) -> AcquireConfig:
    """An AcquireConfig from parsed TOML; raises ConfigError naming the key."""
    known = {"daq", "gps", "can", "calibration", "timesync", "output", "rotation", "recorder", "daemon"}
    for key in d:
        if key not in known:
            raise ConfigError(f"[{key}]: unknown section; known sections: {', '.join(sorted(known))}")
    c = AcquireConfig()
    _section(d, "daq", c.daq)
    _section(d, "gps", c.gps)
    _section(d, "can", c.can)
    _section(d, "rotation", c.rotation)
    _section(d, "recorder", c.recorder)
    _section(d, "daemon", c.daemon)
    cal = d.get("calibration", {})
    if not isinstance(cal, dict) or set(cal) - {"file"}:
        raise ConfigError("[calibration]: only the key 'file' is allowed")
    c.calibration_file = typed_value("calibration", "file", cal.get("file", ""), "")
    out = d.get("output", {})
    if not isinstance(out, dict) or set(out) - {"dir"}:
        raise ConfigError("[output]: only the key 'dir' is allowed")
    c.out_dir = typed_value("output", "dir", out.get("dir", c.out_dir), "")
    ts = d.get("timesync", {})
    if not isinstance(ts, dict):
        raise ConfigError("[timesync]: expected a table")
    c.timesync = dict(ts)
    return c


def from_file(path: str | os.PathLike[str]) -> AcquireConfig:
    """``from_dict`` of the TOML file ``path``; a ConfigError names the file and the key."""
    d = read_toml(path)
    try:
        return from_dict(d)
    except ConfigError as e:
        raise ConfigError(f"config file {path}: {e}") from None


def load(path: str | Path | None, overrides: dict[str, Any] | None = None) -> AcquireConfig:
    """Read the TOML file (None: defaults), apply ``overrides`` (``daq``, ``gps``: port paths; ``out``: output
    directory; ``time_scale``: ``[timesync] host_time_scale``, for simulator playback only) and validate.
    Raises ConfigError with a one-line message naming the key."""
    c = from_file(path) if path is not None else from_dict({})
    o = overrides or {}
    if o.get("daq"):
        c.daq.port = o["daq"]
    if o.get("gps"):
        c.gps.port = o["gps"]
    if o.get("can"):
        c.can.url = o["can"]
    if o.get("dbc"):
        c.can.dbc = o["dbc"]
    if o.get("out"):
        c.out_dir = o["out"]
    if o.get("time_scale") is not None:
        c.timesync["host_time_scale"] = float(o["time_scale"])
    validate(c)
    return c


def validate(c: AcquireConfig) -> None:
    """Raise ConfigError naming the first bad key."""
    for name, p in (("daq", c.daq), ("gps", c.gps)):
        if not p.port:
            raise ConfigError(f"[{name}] port: no {name} port given (--{name} PORT or [{name}] port in the config)")
        if p.baud not in STANDARD_BAUDS:
            raise ConfigError(f"[{name}] baud: {p.baud} is not a standard baud rate")
    if parse_gpsd_url(c.daq.port) is not None:
        raise ConfigError(f"[daq] port: {c.daq.port} is a gpsd URL; only the GPS receiver can be read through gpsd")
    c.gps.gpsd    # raises on a malformed gpsd URL
    if c.gps.protocol not in GPS_PROTOCOLS:
        raise ConfigError(f"[gps] protocol: {c.gps.protocol!r} is not one of {', '.join(GPS_PROTOCOLS)}")
    if c.can.url and c.can.port in (c.daq.port, c.gps.port):
        raise ConfigError(f"[can] url: same device as a [daq] or [gps] port ({c.can.port})")
    if c.daq.port == c.gps.port:
        raise ConfigError(f"[gps] port: same device as [daq] port ({c.gps.port})")
    if c.can.url or c.can.dbc or c.can.signals:
        c.can_bus()
    if c.calibration_file and not Path(c.calibration_file).is_file():
        raise ConfigError(f"[calibration] file: {c.calibration_file} does not exist")
    if c.rotation.max_duration_s < 0:
        raise ConfigError("[rotation] max_duration_s: must be >= 0 (0 = no rotation by duration)")
    if c.rotation.max_size_mb < 0:
        raise ConfigError("[rotation] max_size_mb: must be >= 0 (0 = no rotation by size)")
    r = c.recorder
    if r.chunk_size < 1024:
        raise ConfigError(f"[recorder] chunk_size: {r.chunk_size} is below 1024 bytes")
    if not 0 < r.flush_interval_s <= 1.0:
        raise ConfigError(f"[recorder] flush_interval_s: {r.flush_interval_s} is not in (0, 1] s")
    if r.compression not in ("zstd", "lz4", ""):
        raise ConfigError(f"[recorder] compression: {r.compression!r} is not 'zstd', 'lz4' or ''")
    dm = c.daemon
    if dm.queue_reads < 16:
        raise ConfigError(f"[daemon] queue_reads: {dm.queue_reads} is below 16")
    for key in ("merge_wait_s", "reconnect_s", "status_interval_s", "derived_queue_mb"):
        if not getattr(dm, key) > 0:
            raise ConfigError(f"[daemon] {key}: must be > 0")
    try:
        c.sync_config()
    except (TypeError, ValueError) as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("[timesync]") else f"[timesync]: {msg}") from None


def session_name(session_start_wall_ns: int) -> str:
    """``2026-11-22T10-15-00Z``: the session's start (host wall clock, UTC); the session's directory."""
    t = _dt.datetime.fromtimestamp(session_start_wall_ns / 1e9, _dt.timezone.utc)
    return t.strftime(NAME_FORMAT)


def file_name(session_start_wall_ns: int, index: int) -> str:
    """``2026-11-22T10-15-00Z_0001.mcap``: the session's start and the file's number in the session (1, 2, ...
    as files rotate), so a session's files sort together and in order."""
    return f"{session_name(session_start_wall_ns)}_{index:04d}.mcap"
