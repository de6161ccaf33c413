"""IMU calibration: DAQ ADC counts <-> SI body-frame rates and specific forces.

ADC: signed 24-bit counts (stored in int32), full scale +-10 V, 1 LSB = 10 V / 2**23.
Channel order: 0,1,2 = gyro x,y,z; 3,4,5 = accel x,y,z (body frame right-forward-up).

Per-triad model (one for the gyros, one for the accelerometers)::

    x_SI = M @ ((volts - bias_V) / sensitivity)

- ``sensitivity`` (3,): volts per SI unit, V/(rad/s) for gyros, V/(m/s^2) for accels;
- ``bias_V`` (3,): zero-rate / zero-g output voltage, V;
- ``M`` (3,3): misalignment (and cross-axis) matrix, dimensionless, identity when the axes are ideal.

The defaults are the sensors of the distributed-KF paper's Table 2 (accel +-2 g, 2000 mV/g,
5 ug/sqrt(Hz); gyro +-20 deg/s, 500 mV/(deg/s), bias stability 0.02 deg/s) with zero biases and
identity misalignment. Note the gyro range times its sensitivity is exactly the ADC full scale.

TOML layout (all six keys required, nothing else allowed; ``default_toml()`` prints the defaults)::

    [gyro]
    sensitivity = [28.64788975654116, 28.64788975654116, 28.64788975654116]  # V/(rad/s)
    bias_V = [0.0, 0.0, 0.0]                                                    # V
    misalignment = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

    [accel]
    sensitivity = [0.20394324259558566, 0.20394324259558566, 0.20394324259558566]  # V/(m/s^2)
    bias_V = [0.0, 0.0, 0.0]
    misalignment = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]

    [mounting]                   # optional, every key optional (zeros); the drive's /tf_static (acquire/frames.py)
    imu_position_m = [0.0, 0.0, 0.0]   # IMU origin in base_link (REP-103 forward-left-up), m
    imu_rpy_deg = [0.0, 0.0, 0.0]      # IMU triad vs the vehicle's right-forward-up axes: roll, pitch, yaw about
                                       # fixed right, forward, up axes (x, y, z), deg
    antenna_m = [0.0, 0.0, 0.0]        # GPS antenna from the IMU, IMU axes (RFU), m (as [fusion] lever_arm_b)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fieldlog.acquire import rows
from fieldlog.drive import tables

G0 = 9.80665  # standard gravity, m/s^2 (used to convert g and ug)
ADC_FULL_SCALE_V = 10.0
ADC_BITS = 24
LSB_V = ADC_FULL_SCALE_V / 2 ** (ADC_BITS - 1)
COUNTS_MIN = -(2 ** (ADC_BITS - 1))
COUNTS_MAX = 2 ** (ADC_BITS - 1) - 1

# Table 2 of the distributed-KF paper.
GYRO_SENSITIVITY_V_PER_DPS = 0.5
GYRO_RANGE_DPS = 20.0
GYRO_BIAS_STABILITY_DPS = 0.02
ACCEL_SENSITIVITY_V_PER_G = 2.0
ACCEL_RANGE_G = 2.0
ACCEL_NOISE_UG_RTHZ = 5.0

GYRO_SENSITIVITY_SI = GYRO_SENSITIVITY_V_PER_DPS * 180.0 / math.pi  # V/(rad/s)
ACCEL_SENSITIVITY_SI = ACCEL_SENSITIVITY_V_PER_G / G0  # V/(m/s^2)

_TRIADS = ("gyro", "accel")
_KEYS = {"sensitivity": (3,), "bias_V": (3,), "misalignment": (3, 3)}


def _as_array(value, shape: tuple[int, ...], key: str) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"calibration key {key!r}: not numeric ({exc})") from None
    if arr.shape != shape:
        raise ValueError(f"calibration key {key!r}: expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"calibration key {key!r}: non-finite value")
    return arr


@dataclass(frozen=True, eq=False)
class SensorTriadCal:
    """Calibration of one sensor triad (see the module docstring for the model and units)."""

    sensitivity: np.ndarray  # (3,) V per SI unit
    bias_V: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) V
    misalignment: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3,3)

    def __post_init__(self) -> None:
        for key, shape in _KEYS.items():
            object.__setattr__(self, key, _as_array(getattr(self, key), shape, key))
        if np.any(self.sensitivity == 0.0):
            raise ValueError("calibration key 'sensitivity': zero sensitivity")
        if abs(np.linalg.det(self.misalignment)) < 1e-6:
            raise ValueError("calibration key 'misalignment': matrix is singular")

    def to_si(self, volts: np.ndarray) -> np.ndarray:
        """(n,3) volts -> (n,3) SI values."""
        return np.dot((volts - self.bias_V) / self.sensitivity, self.misalignment.T)

    def to_volts(self, x_si: np.ndarray) -> np.ndarray:
        """(n,3) SI values -> (n,3) volts (exact inverse of ``to_si``)."""
        out = rows.dot(x_si, np.linalg.inv(self.misalignment).T)
        out *= self.sensitivity
        out += self.bias_V
        return out


_MOUNTING_KEYS = ("imu_position_m", "imu_rpy_deg", "antenna_m")


@dataclass(frozen=True, eq=False)
class Mounting:
    """Where the IMU and the GPS antenna sit on the vehicle (the ``[mounting]`` table; units in the key names)."""

    imu_position_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    imu_rpy_deg: np.ndarray = field(default_factory=lambda: np.zeros(3))
    antenna_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        for key in _MOUNTING_KEYS:
            object.__setattr__(self, key, _as_array(getattr(self, key), (3,), f"mounting.{key}"))


@dataclass(frozen=True, eq=False)
class Calibration:
    """Gyro and accelerometer triad calibrations, and the mounting of the IMU and the antenna."""

    gyro: SensorTriadCal
    accel: SensorTriadCal
    mounting: Mounting = field(default_factory=Mounting)

    @classmethod
    def from_dict(cls, d: dict) -> Calibration:
        """Build from the parsed TOML mapping; raises ValueError naming the first bad key."""
        unknown = set(d) - set(_TRIADS) - {"mounting"}
        if unknown:
            raise ValueError(f"calibration: unknown table(s) {sorted(unknown)}; expected {list(_TRIADS)} "
                             f"and optionally [mounting]")
        triads = {}
        for name in _TRIADS:
            table = d.get(name)
            if not isinstance(table, dict):
                raise ValueError(f"calibration: missing table [{name}]")
            extra = set(table) - set(_KEYS)
            if extra:
                raise ValueError(f"calibration: unknown key(s) {sorted(extra)} in [{name}]")
            for key in _KEYS:
                if key not in table:
                    raise ValueError(f"calibration: missing key '{name}.{key}'")
            try:
                triads[name] = SensorTriadCal(**{k: table[k] for k in _KEYS})
            except ValueError as exc:
                raise ValueError(f"[{name}] {exc}") from None
        mounting = d.get("mounting", {})
        if not isinstance(mounting, dict):
            raise ValueError("calibration: [mounting] must be a table")
        extra = set(mounting) - set(_MOUNTING_KEYS)
        if extra:
            raise ValueError(f"calibration: unknown key(s) {sorted(extra)} in [mounting]; known: {list(_MOUNTING_KEYS)}")
        return cls(**triads, mounting=Mounting(**mounting))

    @classmethod
    def from_toml(cls, text: str, name: str = "calibration") -> Calibration:
        """From TOML text (bounded: ``tables.load_toml``); ValueError in one line naming ``name`` or the key."""
        return cls.from_dict(tables.load_toml(text, name))

    def to_toml(self) -> str:
        """TOML text that ``from_toml`` reads back to identical values (floats written with repr)."""

        def fmt(v: np.ndarray) -> str:
            if v.ndim == 1:
                return "[" + ", ".join(repr(float(x)) for x in v) + "]"
            return "[" + ", ".join(fmt(row) for row in v) + "]"

        units = {"gyro": "V/(rad/s)", "accel": "V/(m/s^2)"}
        lines = ["# fieldlog IMU calibration: x_SI = misalignment @ ((volts - bias_V) / sensitivity)"]
        for name in _TRIADS:
            t: SensorTriadCal = getattr(self, name)
            lines += [
                "",
                f"[{name}]",
                f"sensitivity = {fmt(t.sensitivity)}  # {units[name]}",
                f"bias_V = {fmt(t.bias_V)}  # V",
                f"misalignment = {fmt(t.misalignment)}",
            ]
        lines += ["", "[mounting]"] + [f"{k} = {fmt(getattr(self.mounting, k))}" for k in _MOUNTING_KEYS]
        return "\n".join(lines) + "\n"


def default_calibration() -> Calibration:
    """Nominal calibration from Table 2: zero biases, identity misalignment."""
    return Calibration(
        gyro=SensorTriadCal(np.full(3, GYRO_SENSITIVITY_SI)),
        accel=SensorTriadCal(np.full(3, ACCEL_SENSITIVITY_SI)),
    )


def default_toml() -> str:
    """The default calibration as a TOML file (what ``fieldlog`` dumps as a starting point)."""
    return default_calibration().to_toml()


def load_calibration(path: str | Path | None) -> Calibration:
    """Read a calibration TOML file; ``None`` gives ``default_calibration()``."""
    if path is None:
        return default_calibration()
    name = f"calibration file {path}"
    try:
        return Calibration.from_toml(tables.read_text(path, "calibration file"), name)
    except tables.ConfigError:
        raise
    except ValueError as e:
        raise ValueError(f"{name}: {e}") from None


def apply(cal: Calibration, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ADC counts (n,6) -> (omega_ib_b (n,3) rad/s, f_b (n,3) m/s^2), body frame RFU."""
    volts = np.asarray(counts).astype(np.float64) * LSB_V
    return cal.gyro.to_si(volts[:, :3]), cal.accel.to_si(volts[:, 3:])


def to_counts(cal: Calibration, omega_ib_b: np.ndarray, f_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of ``apply``: SI (n,3), (n,3) -> (counts (n,6) int32, saturated (6,) int64).

    Counts are rounded to nearest and clipped to the signed 24-bit range; ``saturated`` holds
    the number of clipped samples per channel.
    """
    counts = np.concatenate([cal.gyro.to_volts(omega_ib_b), cal.accel.to_volts(f_b)], axis=1)
    counts /= LSB_V                 # in place, as each step below: these are a whole drive's samples
    np.rint(counts, out=counts)
    saturated = np.count_nonzero((counts < COUNTS_MIN) | (counts > COUNTS_MAX), axis=0).astype(np.int64)
    return np.clip(counts, COUNTS_MIN, COUNTS_MAX, out=counts).astype(np.int32), saturated
