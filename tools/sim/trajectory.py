"""True vehicle kinematics on WGS-84 and the error-free IMU output derived from them.

A scenario (``tools/sim/scenarios/NAME.toml``) describes a drive (or a flight) as data: a static start, then
segments of (duration, target speed, turn angle, target grade or pitch). Speed, yaw rate and grade change with
the septic "smootherstep" S(x) = 35x^4 - 84x^5 + 70x^6 - 20x^7, which is C3: acceleration, angular rate and
angular acceleration are continuous. Pitch equals the road grade angle (the flight-path angle: the velocity is
along the body forward axis). Roll follows the lateral acceleration a_lat = v * yaw rate: a car rolls out of
the turn, roll = -``roll_per_g_deg`` * a_lat / g; with ``coordinated_turns`` an aircraft banks into it,
roll = atan(a_lat / g), so the specific force has no lateral component in a level turn.

Scenario file format (TOML):

    name, description, duration_s          default drive length, s
    extends = "NAME"                       optional: start from scenario NAME (or a .toml path) and
                                           override it table by table (key by key; arrays replace)
    [origin]  lat_deg, lon_deg, h_m        start position (ellipsoidal height)
    [motion]  initial_heading_deg, static_s, max_accel_mps2, turn_ramp_s, grade_ramp_s, roll_per_g_deg,
              coordinated_turns (bool, default false),
              lap_speed_jitter_pct, lap_time_jitter_pct, lap_turn_jitter_deg (default 0: laps repeat exactly)
    [motion.idle]                          optional: how the car stands while stopped (engine running), below
    [[motion.segments]]                    driven once, in order, after static_s
    [[motion.lap]]                         then repeated until the drive ends (optional)
        each: one of duration_s | distance_m | radius_m (with turn_deg), and optionally
              speed_mps (target, default: unchanged), turn_deg (+ = right), grade_pct or pitch_deg (target
              grade or pitch, default: unchanged), accel_mps2 (peak acceleration of this speed change,
              default max_accel_mps2), ramp_s (duration of this segment's speed and pitch changes instead
              of accel_mps2 and grade_ramp_s)
    [imu], [clock], [gps]                  passed through as dicts for the sensor and clock models; [imu] also
                                           says how the IMU sits in the car (``sensors.Installation``)
    [vibration]                            optional: the car's vibration at the IMU (``vibration``; absent: none)
    [vehicle]                              optional: the car on the CAN bus (``vehicle.from_scenario``: ``can =
                                           true`` puts the bus in the drive, ``tyre_scale`` its scale error)
    [fusion]                               passed through: the spec-sheet figures of fusion.engine.FusionConfig
                                           that ``fieldlog sim`` stores in the drive (``tools.fuse_settings.drive_config``)

Laps that vary: with the ``lap_*_jitter`` keys each lap is drawn afresh from the drive's seed (``generate``'s
``seed``): all its speeds scaled by one factor k = 1 + N(0, lap_speed_jitter_pct %) and its durations by 1 / k
(the same road at another speed, so the lap's period changes), each segment's duration then by its own
1 + N(0, lap_time_jitter_pct %) (straights longer or shorter, loops wider or tighter: the line moves),
each turn's angle changed by N(0, lap_turn_jitter_deg) less the lap's mean change (the lap's net heading change
is kept, so the track does not rotate away). Factors are clipped to [0.7, 1.3]; a segment is lengthened to its
speed change where that needs it. A predictor that learns the lap as a pattern of time cannot replay it.

A car that stands (``[motion.idle]``): while the speed is zero (the static start, every stop) the body rocks on
its springs, roll and pitch rates of sines at ``rock_hz`` (list, Hz) with rate amplitude ``rock_rate_dps``
each; the engine shakes it at ``engine_hz`` with ``engine_rate_dps``; and ``bumps_per_min`` times a minute on
average (Poisson, from the seed) someone moves: a Gabor pulse of ``bump_rate_dps`` at ``bump_hz``, width
``bump_s``. Phases are drawn from the seed. The motion is a perturbation of the true roll and pitch angles
(analytic, so the true attitude carries it and the error-free IMU sees its rates and the tilted gravity),
faded in and out over ``fade_s`` inside each stop, so the moving car is untouched.

Kinematics are exact in a fixed local tangent frame t (ENU at the origin, Earth-fixed): speed, heading, grade
and their derivatives are analytic; position is integrated with 8-point Gauss-Legendre on a grid (<= 0.1 s,
every profile knot a grid node) and interpolated in between with quintic Hermite on (position, velocity,
acceleration). Level roads are level in the t frame, so they rise above the ellipsoid by d^2 / 2R (8 cm at
1 km from the origin). The t frame maps linearly into ECEF, so for ECEF position r_e:

    f_n = C_en a_e + 2 omega_ie_n x v_n - g_n(lat, h)     (g_n = fusion.earth.gravity_n)
    omega_ib_b = omega_tb_b + C_bt^T omega_ie_t
    C_bn = C_en(lat, lon) C_te C_bt

These are the INS equations of ``fusion.ins``; a perfect INS fed ``f_b``, ``omega_ib_b`` reproduces the drive.
Times are seconds since the drive start (t = 0 at the start of the static period).
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from fieldlog.acquire import rows
from fieldlog.drive import tables
from fieldlog.fusion import earth

SCENARIO_DIR = Path(__file__).parent / "scenarios"
GRID_STEP_S = 0.1
MARGIN_S = 10.0  # the truth is defined this far before 0 and after the drive's duration
EVAL_BLOCK = 8192  # sample times a Truth evaluates at a time: its temporaries stay small and are reused
_G_ROLL = 9.80665  # g used only to scale the roll: the car's gradient, the aircraft's bank angle
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)


@dataclass(frozen=True)
class Segment:
    """One piece of a drive, resolved to a duration.

    At the segment start the speed moves smoothly to ``speed_mps`` (peak acceleration ``accel_mps2``) and the
    grade to ``grade_pct`` (over the motion's ``grade_ramp_s``); the heading changes by ``turn_deg`` over the
    whole segment (+ = right, clockwise), yaw rate ramping up and down over ``turn_ramp_s`` at each end.
    ``ramp_s`` > 0 sets the duration of the speed and grade changes instead.
    """

    duration_s: float
    speed_mps: float
    turn_deg: float = 0.0
    grade_pct: float = 0.0
    accel_mps2: float = 1.5
    ramp_s: float = 0.0  # > 0: duration of the speed and grade changes (instead of accel_mps2, grade_ramp_s)


@dataclass(frozen=True)
class Idle:
    """The [motion.idle] table: a standing car's motion (module docstring). Rates in deg/s, frequencies in Hz."""

    rock_hz: tuple[float, ...] = (0.7, 1.9)
    rock_rate_dps: float = 0.03
    engine_hz: float = 25.0
    engine_rate_dps: float = 0.01
    bumps_per_min: float = 1.0
    bump_rate_dps: float = 0.3
    bump_hz: float = 1.5
    bump_s: float = 0.6
    fade_s: float = 1.0

    @classmethod
    def from_dict(cls, d: dict) -> "Idle":
        bad = set(d) - set(cls.__dataclass_fields__)
        if bad:
            raise ValueError(f"[motion.idle]: unknown keys {sorted(bad)}")
        kw = {k: (tuple(float(x) for x in v) if k == "rock_hz" else float(v)) for k, v in d.items()}
        out = cls(**kw)
        if min((out.rock_rate_dps, out.engine_rate_dps, out.bumps_per_min, out.bump_rate_dps)) < 0.0 or \
                min((out.engine_hz, out.bump_hz, out.bump_s, out.fade_s, *out.rock_hz)) <= 0.0:
            raise ValueError("[motion.idle]: rates must be >= 0, frequencies and durations > 0")
        return out


@dataclass(frozen=True)
class Motion:
    """The [motion] table: static start, then ``segments`` once, then ``lap`` repeated to the drive's end.

    After the last segment (and with no lap) the vehicle keeps its final speed, heading and grade.
    """

    initial_heading_deg: float = 0.0
    static_s: float = 0.0
    max_accel_mps2: float = 1.5
    turn_ramp_s: float = 2.0
    grade_ramp_s: float = 4.0
    roll_per_g_deg: float = 4.0
    coordinated_turns: bool = False
    segments: tuple[Segment, ...] = ()
    lap: tuple[Segment, ...] = ()
    lap_speed_jitter_pct: float = 0.0  # sd of the per-lap speed factor, %
    lap_time_jitter_pct: float = 0.0  # sd of each lap segment's duration factor, %
    lap_turn_jitter_deg: float = 0.0  # sd of each lap turn's angle change (zero-sum within the lap), deg
    idle: "Idle | None" = None  # how the car stands while stopped; None: perfectly still

    def jittered(self) -> bool:
        return bool(self.lap) and (self.lap_speed_jitter_pct > 0.0 or self.lap_time_jitter_pct > 0.0
                                   or self.lap_turn_jitter_deg > 0.0)


@dataclass(frozen=True)
class Origin:
    """Start position of the drive: geodetic latitude, longitude (deg) and ellipsoidal height (m)."""

    lat_deg: float
    lon_deg: float
    h_m: float


@dataclass(frozen=True)
class Scenario:
    """A scenario file. ``imu``, ``clock``, ``gps``, ``fusion``, ``vibration`` (None: no table), ``vehicle`` are
    the raw [imu], [clock], [gps], [fusion], [vibration], [vehicle] tables."""

    name: str
    description: str
    duration_s: float
    origin: Origin
    motion: Motion
    imu: dict = field(default_factory=dict)
    clock: dict = field(default_factory=dict)
    gps: dict = field(default_factory=dict)
    fusion: dict = field(default_factory=dict)
    vibration: dict | None = None
    vehicle: dict = field(default_factory=dict)


@dataclass(frozen=True)
class TruthSample:
    """True state at times t (n,), s. lat, lon in rad; h in m; v_n ENU m/s; r_e ECEF m;
    q = [x, y, z, w] of C_bn (body RFU -> ENU); heading/pitch/roll rad (fusion.earth conventions);
    f_b specific force m/s^2 and omega_ib_b angular rate rad/s, body RFU: the error-free IMU. The attitude's
    other forms (q, heading, pitch, roll) are computed from C_bn when first asked for."""

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    h: np.ndarray
    v_n: np.ndarray
    r_e: np.ndarray
    C_bn: np.ndarray
    f_b: np.ndarray
    omega_ib_b: np.ndarray

    @cached_property
    def q(self) -> np.ndarray:
        return earth.dcm_to_quat(self.C_bn)

    @cached_property
    def _euler(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return earth.dcm_to_euler(self.C_bn)

    @property
    def heading(self) -> np.ndarray:
        return self._euler[0]

    @property
    def pitch(self) -> np.ndarray:
        return self._euler[1]

    @property
    def roll(self) -> np.ndarray:
        return self._euler[2]


# ---------------------------------------------------------------------------------------------- loading

_SEGMENT_KEYS = {"duration_s", "distance_m", "radius_m", "speed_mps", "turn_deg", "grade_pct", "pitch_deg",
                 "accel_mps2", "ramp_s"}
_MOTION_KEYS = {"initial_heading_deg", "static_s", "max_accel_mps2", "turn_ramp_s", "grade_ramp_s",
                "roll_per_g_deg", "coordinated_turns", "segments", "lap", "lap_speed_jitter_pct",
                "lap_time_jitter_pct", "lap_turn_jitter_deg", "idle"}
_TOP_KEYS = {"name", "description", "duration_s", "extends", "origin", "motion", "imu", "clock", "gps", "fusion",
             "vibration", "vehicle"}


def _ramp_time(dv: float, accel: float) -> float:
    """Duration of a smootherstep speed change of dv with peak acceleration accel (S' peaks at 35/16)."""
    return 35.0 / 16.0 * abs(dv) / accel


def _resolve_segments(raw: list[dict], speed: float, grade: float, motion: dict, where: str
                      ) -> tuple[list[Segment], float, float]:
    """Turn segment tables into Segments. A segment gives exactly one of duration_s, distance_m
    (along-road distance at the target speed, the speed ramp included) or radius_m (with turn_deg: the
    radius of the constant-rate part of the turn)."""
    out = []
    for i, s in enumerate(raw):
        bad = set(s) - _SEGMENT_KEYS
        if bad:
            raise ValueError(f"{where}[{i}]: unknown keys {sorted(bad)}")
        v1 = float(s.get("speed_mps", speed))
        accel = float(s.get("accel_mps2", motion["max_accel_mps2"]))
        turn = float(s.get("turn_deg", 0.0))
        ramp = float(s.get("ramp_s", 0.0))
        given = [k for k in ("duration_s", "distance_m", "radius_m") if k in s]
        if len(given) != 1:
            raise ValueError(f"{where}[{i}]: give exactly one of duration_s, distance_m, radius_m")
        if "grade_pct" in s and "pitch_deg" in s:
            raise ValueError(f"{where}[{i}]: give grade_pct or pitch_deg, not both")
        if ramp < 0.0 or (ramp > 0.0 and "accel_mps2" in s):
            raise ValueError(f"{where}[{i}]: ramp_s must be > 0 and replaces accel_mps2")
        t_ramp = (ramp if v1 != speed else 0.0) if ramp else _ramp_time(v1 - speed, accel)
        if "duration_s" in s:
            dur = float(s["duration_s"])
        elif "distance_m" in s:
            d_ramp = t_ramp * 0.5 * (speed + v1)
            if v1 <= 0.0 or float(s["distance_m"]) < d_ramp:
                raise ValueError(f"{where}[{i}]: distance_m needs speed > 0 and >= the ramp's {d_ramp:.1f} m")
            dur = t_ramp + (float(s["distance_m"]) - d_ramp) / v1
        else:
            if v1 <= 0.0 or turn == 0.0 or v1 != speed:
                raise ValueError(f"{where}[{i}]: radius_m needs a turn at constant non-zero speed")
            dur = float(np.radians(abs(turn))) * float(s["radius_m"]) / v1 + motion["turn_ramp_s"]
        if dur <= 0.0 or t_ramp > dur + 1e-9:
            raise ValueError(f"{where}[{i}]: duration {dur:.2f} s shorter than its speed change ({t_ramp:.2f} s)")
        g1 = float(s.get("grade_pct", grade))
        if "pitch_deg" in s:
            if not abs(float(s["pitch_deg"])) < 80.0:
                raise ValueError(f"{where}[{i}]: pitch_deg must be within +-80 deg")
            g1 = 100.0 * float(np.tan(np.radians(float(s["pitch_deg"]))))
        if g1 != grade and (ramp or motion["grade_ramp_s"]) > dur:
            raise ValueError(f"{where}[{i}]: duration {dur:.2f} s shorter than its grade ramp")
        out.append(Segment(duration_s=dur, speed_mps=v1, turn_deg=turn, grade_pct=g1, accel_mps2=accel, ramp_s=ramp))
        speed, grade = v1, g1
    return out, speed, grade


def _parse_motion(raw: dict) -> Motion:
    bad = set(raw) - _MOTION_KEYS
    if bad:
        raise ValueError(f"[motion]: unknown keys {sorted(bad)}")
    defaults = Motion()
    m = {k: float(raw.get(k, getattr(defaults, k))) for k in _MOTION_KEYS - {"segments", "lap", "coordinated_turns",
                                                                            "idle"}}
    if min(m["lap_speed_jitter_pct"], m["lap_time_jitter_pct"], m["lap_turn_jitter_deg"]) < 0.0:
        raise ValueError("[motion] lap_*_jitter: must be >= 0")
    coordinated = raw.get("coordinated_turns", False)
    if not isinstance(coordinated, bool):
        raise ValueError(f"[motion] coordinated_turns: expected true or false, got {coordinated!r}")
    segs, speed, grade = _resolve_segments(raw.get("segments", []), 0.0, 0.0, m, "motion.segments")
    lap, speed_end, grade_end = _resolve_segments(raw.get("lap", []), speed, grade, m, "motion.lap")
    if lap and (speed_end != speed or grade_end != grade):
        raise ValueError("motion.lap must end at the speed and grade it starts with")
    idle = Idle.from_dict(raw["idle"]) if "idle" in raw else None
    return Motion(**m, coordinated_turns=coordinated, segments=tuple(segs), lap=tuple(lap), idle=idle)


def _scenario_path(name_or_path: str | Path) -> Path:
    path = Path(name_or_path)
    return path if path.suffix == ".toml" else SCENARIO_DIR / f"{name_or_path}.toml"


def _merge(base: dict, over: dict) -> dict:
    """``over`` on top of ``base``: tables merge key by key, anything else (arrays included) replaces."""
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _read_raw(path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """The scenario's TOML with its ``extends`` chain resolved (relative paths from the file's folder)."""
    if path.resolve() in seen:
        raise ValueError(f"{path}: circular extends")
    raw = tables.load_toml(tables.read_text(path, "scenario file"), f"scenario file {path}")
    bad = set(raw) - _TOP_KEYS
    if bad:
        raise ValueError(f"{path}: unknown top-level keys {sorted(bad)}")
    parent = raw.pop("extends", None)
    if parent is None:
        return raw
    ppath = _scenario_path(parent)
    if ppath.suffix == ".toml" and not ppath.is_absolute() and not ppath.exists():
        ppath = path.parent / ppath
    base = _read_raw(ppath, seen + (path.resolve(),))
    base.pop("name", None)
    base.pop("description", None)
    return _merge(base, raw)


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load a scenario by name (``tools/sim/scenarios/NAME.toml``) or by path to a TOML file."""
    path = _scenario_path(name_or_path)
    raw = _read_raw(path)
    o = raw["origin"]
    return Scenario(
        name=str(raw.get("name", path.stem)),
        description=str(raw.get("description", "")),
        duration_s=float(raw["duration_s"]),
        origin=Origin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["h_m"])),
        motion=_parse_motion(raw.get("motion", {})),
        imu=dict(raw.get("imu", {})),
        clock=dict(raw.get("clock", {})),
        gps=dict(raw.get("gps", {})),
        fusion=dict(raw.get("fusion", {})),
        vibration=dict(raw["vibration"]) if "vibration" in raw else None,
        vehicle=dict(raw.get("vehicle", {})),
    )


# ---------------------------------------------------------------------------------------------- profiles

def _smootherstep(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S(x) on [0, 1] (clipped outside), its derivative and its integral from 0."""
    x = np.clip(x, 0.0, 1.0)
    x2 = x * x
    s0 = x2 * x2 * (35.0 + x * (-84.0 + x * (70.0 - 20.0 * x)))
    s1 = 140.0 * x2 * x * (1.0 - x) ** 3
    si = x2 * x2 * x * (7.0 + x * (-14.0 + x * (10.0 - 2.5 * x)))
    return s0, s1, si


@dataclass(frozen=True)
class _Profile:
    """Piecewise-constant value with non-overlapping smootherstep ramps [a_i, b_i]: y0_i -> y1_i."""

    y_init: float
    a: np.ndarray
    b: np.ndarray
    y0: np.ndarray
    y1: np.ndarray
    F_a: np.ndarray  # integral of y from 0 to a_i

    @classmethod
    def build(cls, y_init: float, ramps: list[tuple[float, float, float, float]]) -> "_Profile":
        r = np.array(sorted(ramps), dtype=float).reshape(-1, 4)
        a, b, y0, y1 = r.T
        if np.any(a[1:] < b[:-1] - 1e-9):
            raise ValueError("overlapping ramps")
        F_a = np.empty_like(a)
        F, t_prev, y_prev = 0.0, 0.0, y_init
        for i in range(len(a)):
            F += y_prev * (a[i] - t_prev)
            F_a[i] = F
            F += 0.5 * (y0[i] + y1[i]) * (b[i] - a[i])
            t_prev, y_prev = b[i], y1[i]
        return cls(y_init, a, b, y0, y1, F_a)

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """(y, dy/dt, integral of y from 0 to t) at times t."""
        if len(self.a) == 0:
            z = np.zeros_like(t)
            return z + self.y_init, z, self.y_init * t
        i = np.searchsorted(self.a, t, side="right") - 1
        before = i < 0
        i = np.maximum(i, 0)
        a, b, y0, dy = self.a[i], self.b[i], self.y0[i], self.y1[i] - self.y0[i]
        T = b - a
        s0, s1, si = _smootherstep((t - a) / T)
        y = np.where(before, self.y_init, y0 + dy * s0)
        d1 = np.where(before, 0.0, dy * s1 / T)
        F = self.F_a[i] + y0 * (t - a) + dy * (T * si + np.maximum(t - b, 0.0))
        return y, d1, np.where(before, self.y_init * t, F)


@dataclass(frozen=True)
class _Profiles:
    speed: _Profile
    yaw_rate: _Profile  # d(heading)/dt, rad/s
    grade: _Profile  # grade angle, rad
    heading0: float
    roll_k: float  # roll = -roll_k * v * yaw_rate
    coordinated: bool = False  # roll = atan(v * yaw_rate / g) instead
    stand: "_Stand | None" = None  # the standing car's roll and pitch perturbation

    def knots(self) -> np.ndarray:
        return np.concatenate([np.concatenate([p.a, p.b]) for p in (self.speed, self.yaw_rate, self.grade)])


@dataclass(frozen=True)
class _Stand:
    """Roll and pitch perturbation of a standing car (``Idle``): sines and Gabor pulses, each gated to the stops."""

    stops: np.ndarray  # (k, 2) s: intervals of zero speed (-inf start allowed)
    fade_s: float
    freq: np.ndarray  # (m,) Hz of the sines
    amp: np.ndarray  # (m, 2) rad/s rate amplitudes, roll and pitch
    phase: np.ndarray  # (m, 2) rad
    bump_t: np.ndarray  # (b,) s, pulse centres
    bump_amp: np.ndarray  # (b, 2) rad/s
    bump_hz: float
    bump_s: float

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(angles (n, 2) rad, their rates (n, 2) rad/s): roll and pitch added to the moving car's."""
        g, dg = self._gate(t)
        w = 2.0 * np.pi * self.freq
        arg = w[None, :, None] * t[:, None, None] + self.phase[None]
        a = np.sum(self.amp[None] / w[None, :, None] * np.sin(arg), axis=1)
        da = np.sum(self.amp[None] * np.cos(arg), axis=1)
        if len(self.bump_t):
            x = t[:, None] - self.bump_t[None, :]
            env = np.exp(-(x / self.bump_s) ** 2)
            wb = 2.0 * np.pi * self.bump_hz
            sb, cb = np.sin(wb * x), np.cos(wb * x)
            a = a + rows.dot(env * sb / wb, self.bump_amp)
            da = da + rows.dot(env * (cb - 2.0 * x / self.bump_s ** 2 * sb / wb), self.bump_amp)
        return g[:, None] * a, dg[:, None] * a + g[:, None] * da

    def _gate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """1 inside a stop (smootherstep fades of fade_s at its ends), 0 outside; and its time derivative."""
        g, dg = np.zeros_like(t), np.zeros_like(t)
        T = self.fade_s
        for a, b in self.stops:
            up, dup, _ = _smootherstep((t - a) / T) if np.isfinite(a) else (np.ones_like(t), np.zeros_like(t), None)
            dn, ddn, _ = _smootherstep((b - t) / T)
            g += up * dn
            dg += dup / T * dn - up * ddn / T
        return g, dg


def _stand(idle: Idle, speed_r: list[tuple[float, float, float, float]], t_end: float, seed: int) -> _Stand:
    """The stops of the speed profile (ramps ending at 0 to the next ramp; the start to the first ramp) longer
    than two fades, and the idle motion's draws for them."""
    rng = np.random.default_rng([seed, 13])
    r = sorted(speed_r)
    stops, start = [], -np.inf
    for a, b, y0, y1 in r:
        if start is not None and y0 == 0.0:
            stops.append((start, a))
        start = b if y1 == 0.0 else None
    if start is not None:
        stops.append((start, t_end + 1.0))
    stops = [(a, b) for a, b in stops if b - a > 2.0 * idle.fade_s]
    freq = np.array([*idle.rock_hz, idle.engine_hz])
    amp = np.radians(np.array([[idle.rock_rate_dps] * 2] * len(idle.rock_hz) + [[idle.engine_rate_dps] * 2]))
    phase = rng.uniform(0.0, 2.0 * np.pi, amp.shape)
    bumps = []
    for a, b in stops:
        a = max(a, -MARGIN_S)
        n = rng.poisson(idle.bumps_per_min * (b - a) / 60.0)
        bumps += list(rng.uniform(a + idle.fade_s + 2 * idle.bump_s, max(b - idle.fade_s - 2 * idle.bump_s,
                                                                          a + idle.fade_s + 2 * idle.bump_s), n))
    bump_amp = np.radians(idle.bump_rate_dps) * rng.choice([-1.0, 1.0], (len(bumps), 2)) * \
        rng.uniform(0.5, 1.0, (len(bumps), 2))
    return _Stand(np.array(stops, float).reshape(-1, 2), idle.fade_s, freq, amp, phase, np.array(bumps, float),
                  bump_amp, idle.bump_hz, idle.bump_s)


JITTER_CLIP = (0.7, 1.3)


def _varied_lap(lap: tuple[Segment, ...], motion: Motion, v_prev: float, rng: np.random.Generator) -> list[Segment]:
    """One lap drawn with the motion's lap jitter (module docstring), entered at speed v_prev (m/s)."""
    lo, hi = JITTER_CLIP
    k_v = float(np.clip(1.0 + rng.normal(0.0, motion.lap_speed_jitter_pct / 100.0), lo, hi))
    k_t = np.clip(1.0 + rng.normal(0.0, motion.lap_time_jitter_pct / 100.0, len(lap)), lo, hi)
    turns = np.array([s.turn_deg != 0.0 for s in lap])
    d_turn = np.zeros(len(lap))
    if turns.sum() > 1:
        d = rng.normal(0.0, motion.lap_turn_jitter_deg, int(turns.sum()))
        d_turn[turns] = d - d.mean()
    out, v, g = [], v_prev, lap[-1].grade_pct
    for s, kt, dt in zip(lap, k_t, d_turn):
        v1 = s.speed_mps * k_v
        need = (s.ramp_s if v1 != v else 0.0) if s.ramp_s else _ramp_time(v1 - v, s.accel_mps2)
        if s.grade_pct != g:
            need = max(need, s.ramp_s or motion.grade_ramp_s)
        dur = max(s.duration_s * float(kt) / k_v, 1.2 * need, 2.0 * motion.turn_ramp_s if s.turn_deg else 0.0)
        out.append(replace(s, duration_s=dur, speed_mps=v1, turn_deg=s.turn_deg + float(dt)))
        v, g = v1, s.grade_pct
    return out


def _build_profiles(motion: Motion, t_end: float, seed: int = 0) -> _Profiles:
    speed_r, yaw_r, grade_r = [], [], []
    t, v, g = motion.static_s, 0.0, 0.0
    segs = list(motion.segments)
    if motion.lap:
        lap_s = sum(s.duration_s for s in motion.lap)
        n_laps = int(np.ceil((t_end - t - sum(s.duration_s for s in segs)) / (lap_s * JITTER_CLIP[0]) + 1))
        if motion.jittered():
            rng = np.random.default_rng([seed, 11])
            for _ in range(n_laps):
                segs += _varied_lap(motion.lap, motion, segs[-1].speed_mps if segs else 0.0, rng)
        else:
            segs += list(motion.lap) * n_laps
    for s in segs:
        if t >= t_end:
            break
        if s.speed_mps != v:
            speed_r.append((t, t + (s.ramp_s or _ramp_time(s.speed_mps - v, s.accel_mps2)), v, s.speed_mps))
        g1 = np.arctan(s.grade_pct / 100.0)
        if g1 != g:
            grade_r.append((t, t + (s.ramp_s or motion.grade_ramp_s), g, g1))
        if s.turn_deg != 0.0:
            tau = min(motion.turn_ramp_s, 0.5 * s.duration_s)
            r = np.radians(s.turn_deg) / (s.duration_s - tau)
            yaw_r += [(t, t + tau, 0.0, r), (t + s.duration_s - tau, t + s.duration_s, r, 0.0)]
        t, v, g = t + s.duration_s, s.speed_mps, g1
    stand = _stand(motion.idle, speed_r, t_end, seed) if motion.idle is not None else None
    return _Profiles(_Profile.build(0.0, speed_r), _Profile.build(0.0, yaw_r), _Profile.build(0.0, grade_r),
                     np.radians(motion.initial_heading_deg), np.radians(motion.roll_per_g_deg) / _G_ROLL,
                     motion.coordinated_turns, stand)


# ---------------------------------------------------------------------------------------------- truth

def _kinematics_t(pr: _Profiles, t: np.ndarray) -> dict[str, np.ndarray]:
    """Velocity, acceleration (t frame), Euler angles and body rates relative to the t frame."""
    v, dv, _ = pr.speed(t)
    r, dr, psi_int = pr.yaw_rate(t)
    gam, dgam, _ = pr.grade(t)
    psi = pr.heading0 + psi_int
    sp, cp, sg, cg = np.sin(psi), np.cos(psi), np.sin(gam), np.cos(gam)
    u = np.stack([cg * sp, cg * cp, sg], axis=-1)
    du = np.stack([-sg * dgam * sp + cg * cp * r, -sg * dgam * cp - cg * sp * r, cg * dgam], axis=-1)
    if pr.coordinated:
        x = v * r / _G_ROLL
        roll = np.arctan(x)
        droll = (dv * r + v * dr) / _G_ROLL / (1.0 + x * x)
    else:
        roll = -pr.roll_k * v * r
        droll = -pr.roll_k * (dv * r + v * dr)
    if pr.stand is not None:  # the standing car rocks: only while v = 0, so the velocity direction u is moot
        ang, rate = pr.stand(t)
        roll, droll = roll + ang[:, 0], droll + rate[:, 0]
        gam, dgam = gam + ang[:, 1], dgam + rate[:, 1]
        sg, cg = np.sin(gam), np.cos(gam)
    sr, cr = np.sin(roll), np.cos(roll)
    omega_tb_b = np.stack([r * sr * cg + dgam * cr, -r * sg + droll, -r * cr * cg + dgam * sr], axis=-1)
    return {"v_t": v[:, None] * u, "a_t": dv[:, None] * u + v[:, None] * du, "psi": psi, "pitch": gam,
            "roll": roll, "omega_tb_b": omega_tb_b}


def _hermite5(h, x, p0, v0, a0, p1, v1, a1):
    """Quintic Hermite interpolation on [0, h] at x = (t - t0)/h in [0, 1]."""
    x = x[:, None]
    h = h[:, None]
    x2, x3 = x * x, x * x * x
    h01 = x3 * (10.0 - 15.0 * x + 6.0 * x2)
    h10 = x - x3 * (6.0 - 8.0 * x + 3.0 * x2)
    h20 = 0.5 * x2 * (1.0 - x) ** 3
    h11 = x3 * (-4.0 + 7.0 * x - 3.0 * x2)
    h21 = 0.5 * x3 * (1.0 - x) ** 2
    return p0 + h01 * (p1 - p0) + h * (h10 * v0 + h11 * v1) + h * h * (h20 * a0 + h21 * a1)


@dataclass(frozen=True)
class Truth:
    """True trajectory of a drive; ``evaluate`` works at any times in [t_min, t_max] s."""

    scenario: Scenario
    t_min: float
    t_max: float
    _pr: _Profiles = field(repr=False)
    _nodes: np.ndarray = field(repr=False)
    _p: np.ndarray = field(repr=False)  # grid positions, velocities, accelerations in the tangent frame
    _v: np.ndarray = field(repr=False)
    _a: np.ndarray = field(repr=False)
    _r0_e: np.ndarray = field(repr=False)
    _C_et: np.ndarray = field(repr=False)  # ECEF -> tangent frame at the origin

    def evaluate(self, t_s: np.ndarray, beside: Executor | None = None) -> TruthSample:
        """True state and error-free IMU output at times t_s (n,) in s since the drive start, ``EVAL_BLOCK``
        times at a time into arrays of all n (``rows.blocks``: each time's state depends on that time alone and
        no block is a lone time, so the values are the same however the times are split). ``beside``: an
        executor whose thread takes blocks too while the caller's does (numpy releases the GIL in its loops), so
        that a thread of it which comes free shares the work (None: the caller's thread alone)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if t.size and (t.min() < self.t_min or t.max() > self.t_max):
            raise ValueError(f"times outside the truth's span [{self.t_min}, {self.t_max}] s")
        if len(t) <= EVAL_BLOCK:
            return self._evaluate(t)
        ranges = iter(rows.blocks(len(t), EVAL_BLOCK))   # a list's iterator: each range taken by one thread
        i, j = next(ranges)
        first = self._evaluate(t[i:j])
        names = [f.name for f in fields(TruthSample) if f.name != "t"]
        out = {"t": t}
        for name in names:
            x = getattr(first, name)
            out[name] = np.empty((len(t),) + x.shape[1:], x.dtype)

        def fill(block: TruthSample, i: int, j: int) -> None:
            for name in names:
                out[name][i:j] = getattr(block, name)

        def take_ranges() -> None:
            for i, j in ranges:
                fill(self._evaluate(t[i:j]), i, j)

        fill(first, i, j)
        helper = beside.submit(take_ranges) if beside is not None else None
        take_ranges()
        if helper is not None:
            helper.result()
        return TruthSample(**out)

    def _evaluate(self, t: np.ndarray) -> TruthSample:
        """``evaluate`` at the times t (n,), s, in the truth's span."""
        k = _kinematics_t(self._pr, t)
        r_e = self._r0_e + rows.dot(self.local_position(t), self._C_et)
        lat, lon, h = earth.ecef_to_lla(r_e)
        C_tn = earth.C_en(lat, lon) @ self._C_et.T
        v_n = np.einsum("nij,nj->ni", C_tn, k["v_t"])
        a_n = np.einsum("nij,nj->ni", C_tn, k["a_t"])  # = C_en a_e
        C_bt = earth.euler_to_dcm(k["psi"], k["pitch"], k["roll"])
        C_bn = C_tn @ C_bt
        f_n = a_n + 2.0 * np.cross(earth.omega_ie_n(lat), v_n) - earth.gravity_n(lat, h)
        f_b = np.einsum("nji,nj->ni", C_bn, f_n)
        omega_ie_t = self._C_et @ np.array([0.0, 0.0, earth.OMEGA_IE])
        omega_ib_b = k["omega_tb_b"] + np.einsum("nji,j->ni", C_bt, omega_ie_t)
        return TruthSample(t=t, lat=lat, lon=lon, h=h, v_n=v_n, r_e=r_e, C_bn=C_bn, f_b=f_b, omega_ib_b=omega_ib_b)

    def local_position(self, t_s: np.ndarray) -> np.ndarray:
        """Position (n, 3) in m in the tangent ENU frame at the origin (quintic Hermite on the grid)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        j = np.clip(np.searchsorted(self._nodes, t, side="right") - 1, 0, len(self._nodes) - 2)
        hj = self._nodes[j + 1] - self._nodes[j]
        return _hermite5(hj, (t - self._nodes[j]) / hj, self._p[j], self._v[j], self._a[j],
                         self._p[j + 1], self._v[j + 1], self._a[j + 1])


def generate(scenario: Scenario, duration_s: float | None = None, seed: int = 0) -> Truth:
    """Build the true trajectory of ``scenario`` for ``duration_s`` (default: the scenario's) seconds; ``seed``
    draws the laps of a scenario whose laps vary (``[motion] lap_*_jitter``), and is unused otherwise.

    The result is defined on [-MARGIN_S, duration_s + MARGIN_S] (the vehicle stands still before t = 0).
    """
    duration = scenario.duration_s if duration_s is None else float(duration_s)
    t_min, t_max = -MARGIN_S, duration + MARGIN_S
    pr = _build_profiles(scenario.motion, t_max, seed)
    fixed = np.unique(np.concatenate([[t_min, 0.0, t_max], pr.knots()]))
    fixed = fixed[(fixed >= t_min) & (fixed <= t_max)]
    uniform = GRID_STEP_S * np.arange(np.ceil(t_min / GRID_STEP_S), np.floor(t_max / GRID_STEP_S) + 1)
    # drop uniform nodes crowding a knot so that no grid interval is degenerate
    j = np.clip(np.searchsorted(fixed, uniform), 1, len(fixed) - 1)
    crowded = np.minimum(np.abs(uniform - fixed[j - 1]), np.abs(uniform - fixed[j])) < 1e-3
    nodes = np.union1d(fixed, uniform[~crowded])
    h = np.diff(nodes)
    tq = nodes[:-1, None] + 0.5 * h[:, None] * (1.0 + _GL_X[None, :])
    v_q = _kinematics_t(pr, tq.ravel())["v_t"].reshape(tq.shape + (3,))
    dp = 0.5 * h[:, None] * np.einsum("q,nqi->ni", _GL_W, v_q)
    p = np.concatenate([np.zeros((1, 3)), np.cumsum(dp, axis=0)])
    p -= p[np.searchsorted(nodes, 0.0)]
    k = _kinematics_t(pr, nodes)
    o = scenario.origin
    lat0, lon0 = np.radians(o.lat_deg), np.radians(o.lon_deg)
    return Truth(scenario, t_min, t_max, pr, nodes, p, k["v_t"], k["a_t"],
                 earth.lla_to_ecef(lat0, lon0, o.h_m), earth.C_en(lat0, lon0))
