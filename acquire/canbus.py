"""The vehicle bus decoded: CAN frames through a DBC (cantools) into ``/vehicle/twist`` and ``/vehicle/wheel_speeds``.

``[can.signals]`` names the signals (``MESSAGE.SIGNAL``, or a signal name the DBC has once): ``wheel_fl``,
``wheel_fr``, ``wheel_rl``, ``wheel_rr`` (wheel speeds), ``vehicle_speed``, ``gear`` (reverse when its value is
the choice named ``[can] reverse_gear``, default ``R``, or equals it as a number), ``reverse`` (reverse when
non-zero), ``steering`` (steering wheel or road wheel angle). Speeds are converted to m/s from the DBC's unit
(km/h, kph, m/s, mph; ``[can] speed_unit`` overrides a missing or other one), angles to rad (deg, rad).

``/vehicle/twist`` (``geometry_msgs/msg/TwistWithCovarianceStamped``, ``base_link``, REP-103 forward-left-up):
linear.x = the forward speed, the mean of the wheels ``[can] forward`` names (``rear``: rear left and right,
the speed of the rear axle's centre, which does not slip sideways and is not steered; ``front``, ``all``, or
``vehicle``: the vehicle speed signal). Default: ``rear`` when both rear wheels are named, else ``vehicle``,
else every wheel named. Its sign is negative in reverse (the speed's magnitude: wheel speed sensors do not see
the direction). Variance: the quantisation of the signals averaged, sum(q_i^2 / 12) / n^2 with q_i the
signal's resolution in m/s; lateral and vertical speed and the angular velocity are not measured (variance
``messages.UNKNOWN_VARIANCE``). One message per frame that carries a forward-speed signal,
once every one of them has been seen.

Stamps (both topics): the host read time of the frame mapped to UTC through the daemon's GPS clock fit
(``TimeSync.mono_to_utc``: the PPS edges' least host latency), less ``[can] latency_s`` (the delay from the ECU's sample to
the adapter's stamp, configured). Frames with adapter time stamps (SLCAN: ms within the minute; SocketCAN: the
kernel's receive time) are stamped on the adapter's clock mapped to that time by ``AdapterClock``.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fieldlog.acquire import can
from fieldlog.drive import messages, metavalue

NS = 1_000_000_000
SIGNAL_KEYS = ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr", "vehicle_speed", "gear", "reverse", "steering")
WHEELS = ("wheel_fl", "wheel_fr", "wheel_rl", "wheel_rr")
FORWARD = {"rear": ("wheel_rl", "wheel_rr"), "front": ("wheel_fl", "wheel_fr"), "all": WHEELS,
           "vehicle": ("vehicle_speed",)}
SPEED_UNITS = {"km/h": 1 / 3.6, "kph": 1 / 3.6, "kmh": 1 / 3.6, "m/s": 1.0, "mps": 1.0, "mph": 0.44704}
ANGLE_UNITS = {"deg": math.pi / 180, "°": math.pi / 180, "degree": math.pi / 180, "rad": 1.0}
MAX_IDS = 256               # frames are counted per id for this many ids (the rest together)
CLOCK_WINDOW_NS = NS        # the adapter clock's offset: the least delay over this much adapter time


class CanConfigError(ValueError):
    """A DBC or ``[can.signals]`` problem; the message is one line naming the file or key."""


@dataclass
class BusConfig:
    """How /raw/can is decoded (the ``can`` metadata record: a rebuild re-derives with it, DBC text included)."""

    wire: str = "slcan"                  # acquire.can: 'slcan' (serial bytes) or 'frames' (records)
    dbc: str = ""                        # the DBC text ('' : frames are recorded and counted, not decoded)
    dbc_name: str = ""                   # where it came from (for messages)
    signals: dict[str, str] = field(default_factory=dict)
    forward: str = ""                    # see the module docstring ('' : the default)
    reverse_gear: str = "R"
    speed_unit: str = ""                 # '' : the DBC's
    latency_s: float = 0.0               # subtracted from the read time (adapter and bus delay)

    def metadata(self) -> dict[str, str]:
        return {"wire": self.wire, "dbc": self.dbc, "dbc_name": self.dbc_name,
                "signals": metavalue.dump(self.signals), "forward": self.forward, "reverse_gear": self.reverse_gear,
                "speed_unit": self.speed_unit, "latency_s": metavalue.dump(self.latency_s)}

    @classmethod
    def from_metadata(cls, d: dict[str, str]) -> "BusConfig":
        """The inverse of ``metadata`` (also of older drives' Python literals); ValueError when damaged."""
        signals = metavalue.load(d.get("signals", "{}"))
        if not isinstance(signals, dict) or not all(isinstance(v, str) for v in signals.values()):
            raise ValueError("metadata can.signals: not a table of signal names")
        return cls(wire=d.get("wire", "slcan"), dbc=d.get("dbc", ""), dbc_name=d.get("dbc_name", ""),
                   signals={str(k): v for k, v in signals.items()}, forward=d.get("forward", ""),
                   reverse_gear=d.get("reverse_gear", "R"), speed_unit=d.get("speed_unit", ""),
                   latency_s=metavalue.number(metavalue.load(d.get("latency_s", "0.0")), "metadata can.latency_s"))


def load_dbc(text: str, name: str) -> Any:
    """A cantools database from DBC text; CanConfigError naming ``name`` when it does not parse."""
    import cantools

    try:
        db = cantools.database.load_string(text, database_format="dbc", strict=False)
    except Exception as e:  # noqa: BLE001 - cantools raises many kinds (ParseError, ValueError, ...)
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CanConfigError(f"{name}: not a DBC file cantools can read ({first}): give a DBC file") from None
    if not db.messages:
        raise CanConfigError(f"{name}: the DBC has no messages: give the car's DBC file")
    return db


def read_dbc(path: str) -> str:
    """The text of a DBC file; CanConfigError with one line when it cannot be read."""
    try:
        with open(path, "rb") as f:
            raw = f.read(64 << 20)
    except OSError as e:
        raise CanConfigError(f"{path}: cannot read the DBC file ({e.strerror or e}): give a DBC file") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("cp1252", "replace")     # DBC files from Windows tools


@dataclass(frozen=True)
class _Signal:
    key: str
    message: str
    name: str
    scale: float             # physical value -> SI (m/s, rad); 1 for gear/reverse
    resolution: float        # the signal's step in SI units


def _find(db: Any, key: str, ref: str, dbc_name: str) -> tuple[Any, Any]:
    msg_name, dot, sig_name = ref.rpartition(".")
    if dot:
        try:
            m = db.get_message_by_name(msg_name)
        except KeyError:
            raise CanConfigError(f"[can.signals] {key}: no message {msg_name!r} in {dbc_name}") from None
        for s in m.signals:
            if s.name == sig_name:
                return m, s
        raise CanConfigError(f"[can.signals] {key}: message {msg_name} in {dbc_name} has no signal {sig_name!r} "
                             f"(it has {', '.join(s.name for s in m.signals)})")
    hits = [(m, s) for m in db.messages for s in m.signals if s.name == ref]
    if len(hits) != 1:
        what = "no signal" if not hits else f"{len(hits)} signals named"
        raise CanConfigError(f"[can.signals] {key}: {what} {ref!r} in {dbc_name}: give MESSAGE.SIGNAL")
    return hits[0]


def _unit_scale(key: str, unit: str, override: str, sig: str) -> float:
    if key in ("gear", "reverse"):
        return 1.0
    table = ANGLE_UNITS if key == "steering" else SPEED_UNITS
    u = (override if key != "steering" and override else unit or "").strip()
    if u.lower() in {k.lower() for k in table}:
        return next(v for k, v in table.items() if k.lower() == u.lower())
    fix = "" if key == "steering" else "; set [can] speed_unit"
    raise CanConfigError(f"[can.signals] {key}: signal {sig} has unit {u!r}, not one of {', '.join(table)}{fix}")


class AdapterClock:
    """Adapter time stamps -> UTC: adapter time + the least (read time - adapter time) of the frames of the last
    CLOCK_WINDOW_NS of adapter time (the frame read with the least delay), so the USB and host read jitter drops
    out and what is left is the adapter's stamp resolution. SLCAN's ms within the minute are unwrapped (``wrap_ns``);
    an adapter whose clock restarts (replugged) is followed within the window. Deterministic in the reads."""

    def __init__(self, wrap_ns: int | None) -> None:
        self.wrap_ns = wrap_ns
        self._prev = -1                  # the last adapter stamp as given
        self._a = 0                      # ... unwrapped
        self._win: deque[tuple[int, int]] = deque()   # (unwrapped adapter time, read - adapter), offsets rising

    def stamp(self, adapter_ns: int, read_ns: int) -> int:
        if self.wrap_ns is None or self._prev < 0:
            a = adapter_ns
        else:
            a = self._a + (adapter_ns - self._prev) % self.wrap_ns
        self._prev, self._a = adapter_ns, a
        off = read_ns - a
        win = self._win
        while win and win[-1][1] >= off:
            win.pop()
        win.append((a, off))
        while win[0][0] < a - CLOCK_WINDOW_NS or win[0][0] > a:
            win.popleft()
        return a + win[0][1]


class VehicleDecoder:
    """Frames in, the derived vehicle topics out (``sink.write`` / ``write_batch``), with counters."""

    def __init__(self, cfg: BusConfig) -> None:
        self.cfg = cfg
        self.stats = can.CanStats()
        self.framer = can.framer(cfg.wire, self.stats)
        self.clock = AdapterClock(can.SLCAN_TIME_WRAP_MS * 1_000_000 if cfg.wire == "slcan" else None)
        self.by_id: dict[int, int] = {}
        self.other_ids = 0
        self.decode_errors = 0
        self.twists = 0
        self.wheel_messages = 0
        self._wanted: dict[tuple[int, bool], tuple[Any, list[_Signal]]] = {}
        self._value: dict[str, float] = {}
        self._reverse: bool | None = None
        self.forward: tuple[str, ...] = ()
        self.variance = 0.0
        if cfg.dbc:
            db = load_dbc(cfg.dbc, cfg.dbc_name or "the DBC")
            if cfg.signals:
                self._setup(db)

    def _setup(self, db: Any) -> None:
        c = self.cfg
        bad = sorted(set(c.signals) - set(SIGNAL_KEYS))
        if bad:
            raise CanConfigError(f"[can.signals] {', '.join(bad)}: unknown key; known keys: {', '.join(SIGNAL_KEYS)}")
        name = c.dbc_name or "the DBC"
        sigs: dict[str, _Signal] = {}
        for key, ref in c.signals.items():
            m, s = _find(db, key, str(ref), name)
            k = _unit_scale(key, s.unit, c.speed_unit, f"{m.name}.{s.name}")
            sigs[key] = _Signal(key, m.name, s.name, k, abs(float(s.scale)) * k)
            entry = self._wanted.setdefault((m.frame_id, bool(m.is_extended_frame)), (m, []))
            entry[1].append(sigs[key])
        forward = c.forward or ("rear" if {"wheel_rl", "wheel_rr"} <= set(sigs) else
                                "vehicle" if "vehicle_speed" in sigs else "all")
        if forward not in FORWARD:
            raise CanConfigError(f"[can] forward: {forward!r} is not one of {', '.join(FORWARD)}")
        self.forward = tuple(k for k in FORWARD[forward] if k in sigs) if forward == "all" else FORWARD[forward]
        missing = [k for k in self.forward if k not in sigs]
        if missing or not self.forward:
            raise CanConfigError(f"[can] forward = {forward!r} needs [can.signals] {', '.join(missing or WHEELS)}")
        n = len(self.forward)
        self.variance = sum(sigs[k].resolution ** 2 / 12.0 for k in self.forward) / n ** 2

    # -- input ---------------------------------------------------------------------------------------
    def feed(self, data: bytes, stamp_ns: int, sink: Any) -> None:
        """One read's bytes, read at UTC ``stamp_ns`` (the GPS-disciplined host read time)."""
        frames = self.framer.feed(data)
        if not frames:
            return
        for f in frames:
            key = f.can_id | (can.CAN_EFF_FLAG if f.extended else 0)
            if key in self.by_id or len(self.by_id) < MAX_IDS:
                self.by_id[key] = self.by_id.get(key, 0) + 1
            else:
                self.other_ids += 1
        if not self._wanted:
            return
        base = stamp_ns - int(round(self.cfg.latency_s * NS))
        for f in frames:
            entry = self._wanted.get((f.can_id, f.extended))
            if entry is None or f.remote:
                continue
            t_ns = base if f.adapter_ns < 0 else self.clock.stamp(f.adapter_ns, base)
            self._decode(f, entry, t_ns, sink)

    def _decode(self, f: can.CanFrame, entry: tuple[Any, list[_Signal]], t_ns: int, sink: Any) -> None:
        m, sigs = entry
        try:
            vals = m.decode(f.data, decode_choices=True, scaling=True)
        except Exception:  # noqa: BLE001 - cantools' DecodeError and friends: a frame of the wrong length
            self.decode_errors += 1
            return
        names, values = [], []
        for s in sigs:
            v = vals.get(s.name)
            if v is None:
                continue
            if s.key == "gear":
                self._reverse = _is_reverse(v, self.cfg.reverse_gear)
                num = float(v.value) if hasattr(v, "value") else float(v)
            else:
                num = float(v.value if hasattr(v, "value") else v)
                if s.key == "reverse":
                    self._reverse = num != 0
            names.append(f"{s.message}.{s.name}")
            values.append(num)
            self._value[s.key] = num * s.scale
        if names:
            self.wheel_messages += 1
            wheels = [self._value.get(k, math.nan) for k in WHEELS]
            sink.write("/vehicle/wheel_speeds", t_ns, messages.encode_wheel_speeds(
                t_ns, f.can_id, wheels, self._value.get("vehicle_speed", math.nan),
                self._value.get("steering", math.nan), -1 if self._reverse is None else int(self._reverse),
                names, values))
        if any(s.key in self.forward for s in sigs) and all(k in self._value for k in self.forward):
            v = sum(self._value[k] for k in self.forward) / len(self.forward)
            if self._reverse:
                v = -abs(v)
            self.twists += 1
            cov = np.zeros((1, 36))
            cov[0, [7, 14, 21, 28, 35]] = messages.UNKNOWN_VARIANCE
            cov[0, 0] = self.variance
            t = np.array([t_ns], np.int64)
            sink.write_batch("/vehicle/twist", t, messages.encode_twist(t, np.array([[v, 0.0, 0.0]]), None, cov,
                                                                        frame_id="base_link"))

    def counters(self) -> dict[str, str]:
        st = self.stats
        out = {f"can.{k}": str(v) for k, v in vars(st).items() if k != "by_kind"}
        out.update({f"can.kind.{k}": str(v) for k, v in st.by_kind.items()})
        out.update({"can.ids": str(len(self.by_id)), "can.other_id_frames": str(self.other_ids),
                    "can.decode_errors": str(self.decode_errors), "can.twists": str(self.twists),
                    "can.wheel_speed_messages": str(self.wheel_messages)})
        out.update({f"can.id.{_id_name(k)}": str(v) for k, v in sorted(self.by_id.items())})
        return out


def _id_name(key: int) -> str:
    return f"{key & can.CAN_EFF_MASK:08X}x" if key & can.CAN_EFF_FLAG else f"{key:03X}"


def _is_reverse(v: Any, reverse_gear: str) -> bool:
    name = getattr(v, "name", None)
    if name is not None and str(name).upper() == reverse_gear.upper():
        return True
    try:
        return float(getattr(v, "value", v)) == float(reverse_gear)
    except ValueError:
        return False

