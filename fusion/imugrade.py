"""IMU grades and datasheet figures, and what they become in the 15-state filter's settings.

A grade (``GRADES``) is a datasheet: angle and velocity random walk, bias instability with its correlation
time, turn-on (run-to-run) bias, scale-factor and misalignment residuals. The simulator draws its IMU errors
from the same figures (``tools.sim.sensors.ImuErrorConfig``, ``[imu] grade = NAME``); the filter takes them as
``[fusion] imu = NAME``, or as the datasheet keys below, one by one (``DATASHEET_KEYS``, and the scale-factor and
misalignment keys, which are FusionConfig keys of the same name): the two give the same settings. A grade gives
the sensor's own figures, never figures inflated to cover an error the filter does not model.

Datasheet units and their conversion into ``FusionConfig`` (``settings``):

==============================  =========================  ===========================================
key                             unit                       FusionConfig
==============================  =========================  ===========================================
gyro_arw_deg_rth                deg/sqrt(h)                gyro_noise_dps_rthz = ARW / 60
accel_vrw_mps_rth               m/s/sqrt(h)                accel_noise_ug_rthz = VRW / 60 / 1 ug
gyro_bias_instability_dph       deg/h, with                gyro_bias_rw_dps_rts = q(B, T),
gyro_bias_corr_time_s           T in s                     init_gyro_bias_sigma_dps = B (the floor of
                                                           the bias after a static mean)
accel_bias_instability_ug       ug, with                   accel_bias_rw_ug_rts = q(B, T)
accel_bias_corr_time_s          T in s
gyro_turn_on_bias_dph           deg/h                      gyro_bias_prior_sigma_dps = hypot(turn-on, s(B, T))
accel_turn_on_bias_ug           ug                         init_accel_bias_sigma_ug = hypot(turn-on, s(B, T))
gyro_scale_factor_ppm,          ppm, mrad                  the same keys, with scale_factor_model =
gyro_misalignment_mrad,                                    "bias-steps" (below); any datasheet key sets
accel_scale_factor_ppm,                                    that model
accel_misalignment_mrad
==============================  =========================  ===========================================

Bias instability B is the flicker floor of the Allan deviation (0.664 B, IEEE 952), which the simulator draws
as flicker noise (``tools.sim.sensors``): variance B^2 / pi per e-fold of correlation time. A datasheet's T is
read two ways, and the filter takes the more conservative (``flicker_bias``):

- a first-order Gauss-Markov bias of standard deviation B and correlation time T (driving noise PSD 2 B^2 / T);
- flicker with correlation times from 1 s (faster ones are in the ARW and VRW: below) to
  T_f = max(T, 1e4 s) (the floor holds over a drive's hours, as in the simulator), whose standard deviation is
  s = B sqrt(ln(T_f / 1 s) / pi) (1.7 B) and whose change over a time tau has the variance
  D(tau) = (2 B^2 / pi) integral over ln T' in [0, ln T_f] of (1 - exp(-tau / T')).

The bias instability stays a bias process, never white noise: the datasheet's white noise densities are the
ARW and VRW alone. Components of the flicker faster than 1 s are below the averaging times at which a datasheet
reads B off the Allan deviation's floor, where the Allan curve is the white noise the ARW and VRW already give;
counting them again as white noise would turn a large B (a phone's 2000 ug) into a white density of 0.8 B per
sqrt(Hz), far above the sensor's own (test_a_large_bias_instability_stays_a_bias_process).

The 15-state model (``fusion.errmodel``) carries random-walk biases, so B and T become **an equivalent random
walk**: q(B, T) = max(B sqrt(2 / T), sqrt(D(60 s) / 60 s)), the Gauss-Markov driving noise or the random walk
that changes the bias over a minute (the time over which the filter leans on its bias estimate: a tilt or a
heading drift shows in the GPS within it) as much as the flicker does; over longer times the random walk is
the more conservative (its variance grows with the time, the flicker's with its logarithm). The Gauss-Markov
reading alone (walk B sqrt(2 / T), prior B) is well below the change and the spread of the flicker the
simulator draws (test_bias_instability_covers_the_simulated_flicker).

**Scale factors and misalignments** are not states of the filter, nor white noise. A triad measures
(I + S)(I + M) x + b for the true rate or specific force x, so its error (S + M) x is, to the filter, a bias
that moves with the signal: when x changes by dx over a cycle, the effective bias steps by (S + M) dx, of
variance s^2 dx_i^2 + m^2 (|dx|^2 - dx_i^2) per axis i, from the grade's 1-sigma s and m and the cycle's own
measured rate and specific force (``scale_factor_model = "bias-steps"``: ``fusion.errmodel.scale_factor_steps``
and ``BiasSteps``, which add it to the bias states' process noise; the first step, from 0, is the (S + M) x of
the start: mostly M g and s_z g on the accelerometers). This is the error's physical form: its size is known
each cycle (a straight drive adds nothing; a turn opens the gyro bias by s times the turn rate, which turns the
solution for as long as the turn lasts), while inflated white noise adds the same uncertainty whether the car
turns or not. The filter does not keep s and m, so it does not know that the bias comes back when the signal
does: the steps' variance adds up over the drive where the true bias stays within (S + M) x, which is
conservative; the GPS re-estimates the bias after each turn. The consider analysis (``fusion.consider``) is the
other model (``scale_factor_model = "consider"``, FusionConfig's default): the noise is inflated to absorb the
scale factors and misalignments, and their consider variance joins the printed accelerometer-bias sigma; it is
kept for the defaults, the figures this project was tuned on, and is not used with a grade. Figures:
docs/results.md, "IMU grades".
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

DATASHEET_KEYS = ("gyro_arw_deg_rth", "gyro_bias_instability_dph", "gyro_bias_corr_time_s", "gyro_turn_on_bias_dph",
                  "accel_vrw_mps_rth", "accel_bias_instability_ug", "accel_bias_corr_time_s", "accel_turn_on_bias_ug")
_G0 = 9.80665
_UG = _G0 * 1e-6


@dataclass(frozen=True)
class ImuGrade:
    """A datasheet, per axis and 1-sigma (units in the names: deg/sqrt(h), deg/h, m/s/sqrt(h), ug, s, ppm, mrad)."""

    description: str
    gyro_arw_deg_rth: float
    gyro_bias_instability_dph: float
    gyro_bias_corr_time_s: float
    gyro_turn_on_bias_dph: float
    gyro_scale_factor_ppm: float
    gyro_misalignment_mrad: float
    accel_vrw_mps_rth: float
    accel_bias_instability_ug: float
    accel_bias_corr_time_s: float
    accel_turn_on_bias_ug: float
    accel_scale_factor_ppm: float
    accel_misalignment_mrad: float

    def simulator(self) -> dict[str, float]:
        """The grade as the simulator's ``[imu]`` keys (``tools.sim.sensors.ImuErrorConfig``).

        Returns
        -------
        dict of str to float
            Key -> value in the unit its name says (deg/s/sqrt(Hz), deg/s, ug/sqrt(Hz), ug, ppm, mrad).
        """
        return dict(gyro_noise_density_dps_rthz=self.gyro_arw_deg_rth / 60.0,
                    gyro_bias_instability_dps=self.gyro_bias_instability_dph / 3600.0,
                    gyro_turn_on_bias_dps=self.gyro_turn_on_bias_dph / 3600.0,
                    gyro_scale_factor_ppm=self.gyro_scale_factor_ppm,
                    gyro_misalignment_mrad=self.gyro_misalignment_mrad,
                    accel_noise_density_ug_rthz=self.accel_vrw_mps_rth / 60.0 / _UG,
                    accel_bias_instability_ug=self.accel_bias_instability_ug,
                    accel_turn_on_bias_ug=self.accel_turn_on_bias_ug,
                    accel_scale_factor_ppm=self.accel_scale_factor_ppm,
                    accel_misalignment_mrad=self.accel_misalignment_mrad)

    def filter_settings(self) -> dict[str, float]:
        """The datasheet converted into FusionConfig keys (module docstring).

        Returns
        -------
        dict
            Flat FusionConfig key -> value in the unit its name says: the white noise and bias random walk
            densities, the initial bias sigmas, the scale factors and misalignments, and ``scale_factor_model``
            "bias-steps".
        """
        s_g, q_g = flicker_bias(self.gyro_bias_instability_dph / 3600.0, self.gyro_bias_corr_time_s)
        s_a, q_a = flicker_bias(self.accel_bias_instability_ug, self.accel_bias_corr_time_s)
        out = dict(gyro_noise_dps_rthz=self.gyro_arw_deg_rth / 60.0,
                   accel_noise_ug_rthz=self.accel_vrw_mps_rth / 60.0 / _UG,
                   gyro_bias_rw_dps_rts=q_g, accel_bias_rw_ug_rts=q_a,
                   init_gyro_bias_sigma_dps=self.gyro_bias_instability_dph / 3600.0,
                   gyro_bias_prior_sigma_dps=math.hypot(self.gyro_turn_on_bias_dph / 3600.0, s_g),
                   init_accel_bias_sigma_ug=math.hypot(self.accel_turn_on_bias_ug, s_a),
                   gyro_scale_factor_ppm=self.gyro_scale_factor_ppm,
                   gyro_misalignment_mrad=self.gyro_misalignment_mrad,
                   accel_scale_factor_ppm=self.accel_scale_factor_ppm,
                   accel_misalignment_mrad=self.accel_misalignment_mrad,
                   scale_factor_model="bias-steps")
        return out


FLICKER_FROM_S = 1.0  # s: bias-instability components faster than this are in the datasheet's ARW/VRW
FLICKER_TO_S = 1.0e4  # s: ... and slower than this (or the datasheet's T) constant over a drive
BIAS_LEAN_S = 60.0  # s: the time over which the filter leans on its bias estimate


def flicker_bias(b: float, t_corr: float) -> tuple[float, float]:
    """The bias process of a bias instability: the more conservative of the Gauss-Markov and the flicker readings
    (module docstring).

    Parameters
    ----------
    b : float
        The bias instability B, per axis, 1 sigma, in the sensor's bias unit (deg/s or ug).
    t_corr : float
        Its correlation time T, s.

    Returns
    -------
    tuple of float
        (max(b, s), max(b sqrt(2 / T), sqrt(D(BIAS_LEAN_S) / BIAS_LEAN_S))): the bias's standard deviation, in
        b's unit, and its equivalent random walk, in b's unit per sqrt(s).
    """
    span = math.log(max(t_corr, FLICKER_TO_S) / FLICKER_FROM_S)
    n = 200  # midpoint rule in ln T': the integrand is smooth
    change = sum(1.0 - math.exp(-BIAS_LEAN_S / (FLICKER_FROM_S * math.exp((k + 0.5) * span / n)))
                 for k in range(n)) * span / n
    return (max(b, b * math.sqrt(span / math.pi)),
            max(b * math.sqrt(2.0 / t_corr), b * math.sqrt(2.0 * change / math.pi / BIAS_LEAN_S)))


GRADES: dict[str, ImuGrade] = {
    # The distributed-KF paper's Table 2 MEMS (gyro 0.01 deg/s/sqrt(Hz) = 0.6 deg/sqrt(h), bias stability
    # 0.02 deg/s; accel 5 ug/sqrt(Hz)); the rest are our choices (tools.sim.sensors). FusionConfig's defaults are
    # this IMU with its noise inflated to absorb the 1000 ppm and 1 mrad residuals (scale_factor_model =
    # "consider"); the preset models them instead (module docstring; docs/results.md, "IMU grades").
    "table2-mems": ImuGrade(
        "distributed-KF paper, Table 2 MEMS (the simulator's default IMU)",
        gyro_arw_deg_rth=0.6, gyro_bias_instability_dph=72.0, gyro_bias_corr_time_s=1000.0,
        gyro_turn_on_bias_dph=180.0, gyro_scale_factor_ppm=1000.0, gyro_misalignment_mrad=1.0,
        accel_vrw_mps_rth=5.0 * _UG * 60.0, accel_bias_instability_ug=20.0, accel_bias_corr_time_s=1000.0,
        accel_turn_on_bias_ug=1000.0, accel_scale_factor_ppm=1000.0, accel_misalignment_mrad=1.0),
    # An industrial MEMS unit (our figures for the grade, not a named unit): 0.2 deg/sqrt(h),
    # 5 deg/h, 300 ppm, 0.5 mrad.
    "s000-mems": ImuGrade(
        "industrial MEMS: 0.2 deg/sqrt(h), 5 deg/h; 0.05 m/s/sqrt(h), 20 ug",
        gyro_arw_deg_rth=0.2, gyro_bias_instability_dph=5.0, gyro_bias_corr_time_s=600.0,
        gyro_turn_on_bias_dph=20.0, gyro_scale_factor_ppm=300.0, gyro_misalignment_mrad=0.5,
        accel_vrw_mps_rth=0.05, accel_bias_instability_ug=20.0, accel_bias_corr_time_s=600.0,
        accel_turn_on_bias_ug=500.0, accel_scale_factor_ppm=300.0, accel_misalignment_mrad=0.5),
    # A Leador-A15-class FOG unit: ARW 0.003 deg/sqrt(h), VRW 0.03 m/s/sqrt(h), gyro
    # bias 0.027 deg/h, accel bias 15 mGal (15 ug); turn-on biases and T are our choices; calibrated, so the
    # scale-factor and misalignment residuals are taken as 0 (the truth IMU plus the datasheet's errors).
    "tactical": ImuGrade(
        "tactical FOG (Leador A15 class): 0.003 deg/sqrt(h), 0.027 deg/h; 0.03 m/s/sqrt(h), 15 ug",
        gyro_arw_deg_rth=0.003, gyro_bias_instability_dph=0.027, gyro_bias_corr_time_s=3600.0,
        gyro_turn_on_bias_dph=0.05, gyro_scale_factor_ppm=0.0, gyro_misalignment_mrad=0.0,
        accel_vrw_mps_rth=0.03, accel_bias_instability_ug=15.0, accel_bias_corr_time_s=3600.0,
        accel_turn_on_bias_ug=50.0, accel_scale_factor_ppm=0.0, accel_misalignment_mrad=0.0),
    # A navigation-grade (ring-laser) unit, typical figures: 0.001 deg/sqrt(h), 0.003 deg/h, 5 ug.
    "navigation": ImuGrade(
        "navigation grade: 0.001 deg/sqrt(h), 0.003 deg/h; 0.005 m/s/sqrt(h), 5 ug",
        gyro_arw_deg_rth=0.001, gyro_bias_instability_dph=0.003, gyro_bias_corr_time_s=3600.0,
        gyro_turn_on_bias_dph=0.005, gyro_scale_factor_ppm=0.0, gyro_misalignment_mrad=0.0,
        accel_vrw_mps_rth=0.005, accel_bias_instability_ug=5.0, accel_bias_corr_time_s=3600.0,
        accel_turn_on_bias_ug=10.0, accel_scale_factor_ppm=0.0, accel_misalignment_mrad=0.0),
}


def grade(name: str) -> ImuGrade:
    """A grade by name.

    Parameters
    ----------
    name : str
        A key of ``GRADES``.

    Returns
    -------
    ImuGrade
        The grade called ``name``; ValueError listing the known ones.
    """
    if name not in GRADES:
        raise ValueError(f"unknown IMU grade {name!r}; one of {', '.join(GRADES)}")
    return GRADES[name]


def settings(table: dict) -> dict:
    """A ``[fusion]`` table with ``imu = NAME`` and the datasheet keys resolved into FusionConfig keys.

    Order: the grade's settings (none without ``imu``: FusionConfig's defaults), then the FusionConfig keys
    that the given datasheet keys set (their companions, e.g. the correlation time of a bias instability given
    alone, from the grade's datasheet or table2-mems'), then the explicit FusionConfig keys of the table. A
    datasheet key and the FusionConfig key it sets may not both be given.

    Parameters
    ----------
    table : dict
        The ``[fusion]`` table: flat keys with ``imu`` (a grade's name), datasheet keys (``DATASHEET_KEYS``, units
        in their names) and FusionConfig keys.

    Returns
    -------
    dict
        The table as FusionConfig keys (units in their names); ValueError names the problem.
    """
    sheet = {k: table[k] for k in DATASHEET_KEYS if k in table}
    name = table.get("imu", "")
    if not isinstance(name, str):
        raise ValueError(f"imu: expected a grade name, one of {', '.join(GRADES)}")
    if not name and not sheet:
        return dict(table)
    for k, v in sheet.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{k}: expected a finite number >= 0, got {v!r}")
        if k.endswith("corr_time_s") and not v > 0:
            raise ValueError(f"{k}: must be > 0")
    out = grade(name).filter_settings() if name else {}
    if sheet:
        derived = _derived(sheet)
        both = sorted(k for k in derived if k in table)
        if both:
            raise ValueError(f"{', '.join(both)}: also set by the datasheet key(s) given; give one or the other")
        g = replace(grade(name or "table2-mems"), **{k: float(v) for k, v in sheet.items()})
        conv = g.filter_settings()
        out.update({k: conv[k] for k in derived}, scale_factor_model=conv["scale_factor_model"])
    return {**out, **{k: v for k, v in table.items() if k not in sheet}}


def sources(table: dict) -> dict[str, str]:
    """Where the settings of ``settings(table)`` came from.

    Parameters
    ----------
    table : dict
        The ``[fusion]`` table, as ``settings`` takes it.

    Returns
    -------
    dict of str to str
        For each FusionConfig key ``settings(table)`` sets from the grade or the datasheet keys (not the table's
        own FusionConfig keys): ``"grade NAME"`` or ``"datasheet KEY[, KEY]"``.
    """
    sheet = [k for k in DATASHEET_KEYS if k in table]
    name = table.get("imu", "")
    out = {k: f"grade {name}" for k in grade(name).filter_settings()} if isinstance(name, str) and name else {}
    by_key: dict[str, list[str]] = {}
    for k in sheet:
        for derived in _derived({k: table[k]}):
            by_key.setdefault(derived, []).append(k)
    out.update({k: "datasheet " + ", ".join(keys) for k, keys in by_key.items()})
    return {k: v for k, v in out.items() if k not in table}


def _derived(sheet: dict) -> set[str]:
    """The FusionConfig keys the given datasheet keys set."""
    probe = ImuGrade(**asdict(GRADES["tactical"]))
    base = probe.filter_settings()
    out = set()
    for k in sheet:
        bumped = replace(probe, **{k: getattr(probe, k) * 2.0 + 1.0}).filter_settings()
        out |= {key for key in base if bumped[key] != base[key]}
    return out
