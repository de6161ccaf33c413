"""The simulated car's CAN bus (``fieldlog sim --can``): wheel speeds, steering, gear and unrelated traffic as an
SLCAN adapter puts them on its serial line.

The car is the demo DBC's (``data/sim-car.dbc``). The IMU sits at the centre of the rear axle (the drive's
calibration has no ``[mounting] imu_position_m``, so base_link is there too), the body frame is RFU. Each
wheel's hub moves with v_w = v_b + omega_nb_b x r_w (r_w: the hub from the IMU, RFU: rear at (-+track/2, 0, 0),
front at (-+track/2, wheelbase, 0)); its speed is the horizontal magnitude of v_w (the wheel rolls along its
own heading; front wheels are steered) and it reports that times (1 + its tyre-radius scale error: a common
part, drawn in +-``tyre_scale_max`` or set by ``tyre_scale``, plus each wheel's own) times (1 + its slip),
quantised by the DBC signal's resolution. Slip: the driven front wheels spin up by ``traction_slip`` x (a / g)^2
under acceleration a > 0, every wheel locks up by ``brake_slip`` x (a / g)^2 when braking; a scenario's
``[vehicle] spin_wheel`` makes one wheel spin by ``spin_ratio`` for ``spin_s`` from ``spin_start_s`` (a slip event
the odometer's per-wheel test must find). The road wheel angle is the bicycle model's atan(wheelbase x yaw rate / speed).

Timing: each ECU samples at its own rate with a random phase; a frame reaches the bus ``latency_s`` plus a
uniform jitter in [0, ``jitter_s``) after its sample; the adapter stamps the frame's end with its own ms clock
(its offset to UTC is random, its rate ``adapter_ppm`` off) and sends the SLCAN record over its serial line (``emit.serial_reads``).
``/truth/vehicle/twist`` has the true forward speed of the rear axle's centre at every wheel-speed sample
instant (UTC), so the stamps of ``/vehicle/twist`` and its speeds can be scored.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fieldlog.acquire import can, canbus
from fieldlog.acquire.pipeline import RawRead
from fieldlog.drive.tables import ConfigError, from_table
from fieldlog.fusion import earth
from fieldlog.fusion.odometer import WHEELS
from fieldlog.tools.sim.emit import HostClock, serial_reads

NS = 1_000_000_000
G = 9.80665
DBC_PATH = Path(__file__).resolve().parent / "scenarios" / "sim-car.dbc"    # data/sim-car.dbc links to it
SIGNALS = {"wheel_fl": "WHEEL_SPEEDS.WHEEL_SPEED_FL", "wheel_fr": "WHEEL_SPEEDS.WHEEL_SPEED_FR",
           "wheel_rl": "WHEEL_SPEEDS.WHEEL_SPEED_RL", "wheel_rr": "WHEEL_SPEEDS.WHEEL_SPEED_RR",
           "gear": "GEARBOX.GEAR", "steering": "STEERING.STEER_ANGLE"}
UNKNOWN_IDS = ((0x5F0, False, 20.0), (0x18FEF100, True, 10.0))     # traffic the DBC does not describe


@dataclass(frozen=True)
class CanSimConfig:
    """The simulated car and bus; SI units."""

    wheel_rate_hz: float = 50.0
    steering_rate_hz: float = 50.0
    gear_rate_hz: float = 10.0
    engine_rate_hz: float = 100.0
    wheelbase_m: float = 2.7
    track_m: float = 1.6
    tyre_scale_max: float = 0.005       # common tyre-radius scale error, uniform in +-this
    tyre_scale_wheel: float = 0.0005    # and each wheel's own, 1 sigma
    tyre_scale: float | None = None     # the common scale error instead of the draw (the draw is made still)
    traction_slip: float = 0.2          # slip ratio per (a/g)^2 of the driven (front) wheels accelerating
    brake_slip: float = 0.1             # ... of every wheel braking
    spin_wheel: str = ""                # a wheel (FL, FR, RL, RR) that spins: its speed x (1 + spin_ratio) ...
    spin_start_s: float = 0.0           # ... from this time, s from the drive's start, ...
    spin_s: float = 2.0                 # ... for this long (none: "")
    spin_ratio: float = 0.2
    latency_s: float = 0.004            # sample -> bus (ECU processing)
    jitter_s: float = 0.002
    adapter_ppm: float = 30.0           # the adapter's ms clock runs this fast
    serial_baud: int = 1_000_000        # the adapter's serial line (USB CDC)
    read_period_s: tuple[float, float] = (0.001, 0.004)


def engine_rpm(speed_mps: np.ndarray) -> np.ndarray:
    """The engine speed, rpm, at the forward speed (m/s): idle at 800 rpm, one gear above it."""
    return 800 + 110 * np.abs(speed_mps)


def from_scenario(table: dict) -> tuple[bool, CanSimConfig]:
    """A scenario's [vehicle] table: (``can``: the drive has the CAN bus without ``--can``, the car's
    ``CanSimConfig`` from the other keys, e.g. ``tyre_scale = 0.008``); unknown keys raise ConfigError."""
    d = dict(table)
    can_on = d.pop("can", False)
    if not isinstance(can_on, bool):
        raise ConfigError(f"[vehicle] can: expected true or false, got {can_on!r}")
    cfg = from_table(CanSimConfig, "vehicle", d)
    if cfg.spin_wheel not in ("", *WHEELS):
        raise ConfigError(f"[vehicle] spin_wheel: expected one of {', '.join(WHEELS)}, got {cfg.spin_wheel!r}")
    return can_on, cfg


def bus_config(cfg: CanSimConfig | None = None) -> canbus.BusConfig:
    """How a simulated drive's /raw/can is decoded: SLCAN, the demo DBC, its wheel, gear and steering signals,
    ``[can] latency_s`` = the bus's mean delay (as one would set it from the car's measured latency)."""
    cfg = cfg or CanSimConfig()
    return canbus.BusConfig(wire="slcan", dbc=DBC_PATH.read_text(), dbc_name=DBC_PATH.name, signals=dict(SIGNALS),
                            latency_s=cfg.latency_s + cfg.jitter_s / 2)


def _sample_times(rate_hz: float, duration_s: float, rng: np.random.Generator) -> np.ndarray:
    return (rng.uniform(0, 1) + np.arange(int(duration_s * rate_hz))) / rate_hz


def wheel_speeds(truth, t_s: np.ndarray, cfg: CanSimConfig) -> dict[str, np.ndarray]:
    """True speeds at ``t_s``: ``wheels`` (n, 4) FL, FR, RL, RR hub speeds m/s, ``forward`` (n,) the rear axle
    centre's forward speed m/s, ``accel`` (n,) m/s^2 along it, ``steer`` (n,) road wheel angle rad, left +."""
    ts = truth.evaluate(t_s)
    v_b = np.einsum("nji,nj->ni", ts.C_bn, ts.v_n)
    omega_nb_b = ts.omega_ib_b - np.einsum("nji,nj->ni", ts.C_bn, earth.omega_ie_n(ts.lat))
    half, wb = cfg.track_m / 2, cfg.wheelbase_m
    r_w = np.array([[-half, wb, 0.0], [half, wb, 0.0], [-half, 0.0, 0.0], [half, 0.0, 0.0]])
    v_w = v_b[:, None, :] + np.cross(omega_nb_b[:, None, :], r_w[None, :, :])
    speed = np.hypot(v_w[..., 0], v_w[..., 1]) * np.sign(v_w[..., 1])
    f_b = ts.f_b + np.einsum("nji,nj->ni", ts.C_bn, earth.gravity_n(ts.lat, ts.h))   # a_b, Coriolis neglected
    forward = v_b[:, 1]
    moving = np.abs(forward) > 0.5
    steer = np.where(moving, np.arctan(wb * omega_nb_b[:, 2] / np.where(moving, forward, 1.0)), 0.0)
    return {"wheels": speed, "forward": forward, "accel": f_b[:, 1], "steer": steer}


def can_frames(truth, duration_s: float, cfg: CanSimConfig, rng: np.random.Generator
               ) -> tuple[np.ndarray, list[can.CanFrame], dict]:
    """The frames on the bus (sorted by their end time on the bus, s since the drive start) and the truth."""
    import cantools

    db = cantools.database.load_file(str(DBC_PATH))
    m_ws, m_st = db.get_message_by_name("WHEEL_SPEEDS"), db.get_message_by_name("STEERING")
    m_gear, m_eng = db.get_message_by_name("GEARBOX"), db.get_message_by_name("ENGINE")
    common = rng.uniform(-cfg.tyre_scale_max, cfg.tyre_scale_max)
    scale = (common if cfg.tyre_scale is None else cfg.tyre_scale) + rng.normal(0, cfg.tyre_scale_wheel, 4)
    out: list[tuple[float, can.CanFrame]] = []

    def sent(t_sample: np.ndarray) -> np.ndarray:
        return t_sample + cfg.latency_s + rng.uniform(0, cfg.jitter_s, len(t_sample))

    t_ws = _sample_times(cfg.wheel_rate_hz, duration_s, rng)
    w = wheel_speeds(truth, t_ws, cfg)
    a_g = w["accel"] / G
    slip = np.zeros((len(t_ws), 4))
    slip[:, :2] += np.where(a_g > 0, cfg.traction_slip * a_g ** 2, 0.0)[:, None]
    slip -= np.where(a_g < 0, cfg.brake_slip * a_g ** 2, 0.0)[:, None]
    if cfg.spin_wheel:
        spinning = (t_ws >= cfg.spin_start_s) & (t_ws < cfg.spin_start_s + cfg.spin_s)
        slip[spinning, WHEELS.index(cfg.spin_wheel)] += cfg.spin_ratio
    reported = np.abs(w["wheels"]) * (1 + scale) * (1 + slip)
    res = [s.scale for s in m_ws.signals]
    raw = np.clip(np.round(reported * 3.6 / np.array(res)), 0, 65535).astype(int)
    names = [s.name for s in m_ws.signals]
    for t, row in zip(sent(t_ws).tolist(), raw.tolist()):
        out.append((t, can.CanFrame(m_ws.frame_id, m_ws.encode(dict(zip(names, row)), scaling=False))))
    t_st = _sample_times(cfg.steering_rate_hz, duration_s, rng)
    steer_deg = np.degrees(wheel_speeds(truth, t_st, cfg)["steer"])
    for i, (t, a) in enumerate(zip(sent(t_st).tolist(), steer_deg.tolist())):
        out.append((t, can.CanFrame(m_st.frame_id, m_st.encode({"STEER_ANGLE": a, "STEER_COUNTER": i % 16}))))
    t_g = _sample_times(cfg.gear_rate_hz, duration_s, rng)
    fwd = wheel_speeds(truth, t_g, cfg)["forward"]
    for t, v in zip(sent(t_g).tolist(), fwd.tolist()):
        out.append((t, can.CanFrame(m_gear.frame_id, m_gear.encode({"GEAR": 1 if v < -0.05 else 3}, scaling=False))))
    t_e = _sample_times(cfg.engine_rate_hz, duration_s, rng)
    rpm = engine_rpm(wheel_speeds(truth, t_e, cfg)["forward"])
    for t, r in zip(sent(t_e).tolist(), rpm.tolist()):
        out.append((t, can.CanFrame(m_eng.frame_id, m_eng.encode({"ENGINE_RPM": r, "PEDAL": 20.0}))))
    for can_id, ext, rate in UNKNOWN_IDS:
        for t in sent(_sample_times(rate, duration_s, rng)).tolist():
            out.append((t, can.CanFrame(can_id, rng.bytes(8), extended=ext)))
    out.sort(key=lambda x: x[0])
    t_bus = np.array([t for t, _ in out])
    truth_out = {"t_s": t_ws, "forward": w["forward"], "wheels": w["wheels"], "scale": scale}
    return t_bus, [f for _, f in out], truth_out


def can_reads(truth, duration_s: float, host: HostClock, t0_ns: int, rng: np.random.Generator,
              cfg: CanSimConfig | None = None) -> tuple[list[RawRead], dict]:
    """The SLCAN adapter's serial reads (port ``can``) and the truth for ``/truth/vehicle/twist``."""
    cfg = cfg or CanSimConfig()
    t_bus, frames, truth_out = can_frames(truth, duration_s, cfg, rng)
    if not frames:
        return [], truth_out
    adapter_offset_s = rng.uniform(0, 60)
    ms = np.floor((t_bus * (1 + cfg.adapter_ppm * 1e-6) + adapter_offset_s) * 1000).astype(np.int64)
    records = [can.slcan_record(f, int(m)) for f, m in zip(frames, ms.tolist())]
    byte_s = 10.0 / cfg.serial_baud
    start = np.empty(len(records))
    free = -np.inf
    for i, (t, r) in enumerate(zip(t_bus.tolist(), records)):
        start[i] = max(t, free)
        free = start[i] + len(r) * byte_s
    keep = start < duration_s
    records = [r for r, k in zip(records, keep.tolist()) if k]
    reads = serial_reads("can", start[keep], records, None, cfg.serial_baud, cfg.read_period_s, host, t0_ns, rng)
    return reads, truth_out
