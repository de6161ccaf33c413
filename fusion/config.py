"""Fusion settings: :class:`FusionConfig` in sections, its flat keys and its validation.

A ``[fusion]`` TOML table (``fieldlog fuse --config``, a scenario's table, the ``fusion.config`` record of a
drive, the ``fusion`` record of a fused file) names every setting by its flat key, e.g. ``nhc_sigma_mps``; each
flat key is a field of exactly one section (``FLAT_KEYS``), so :meth:`FusionConfig.from_flat` and
:meth:`FusionConfig.flat` map between the two. ``predictor`` is the one key whose value is a table
(``[fusion.predictor]``, ``fusion.predictors.PredictorConfig``).

Sensor figures default to the distributed-KF paper's Table 2 class of MEMS IMU (gyro 0.01 deg/s/sqrt(Hz), bias
stability 0.02 deg/s; accel 5 ug/sqrt(Hz)), the noise densities inflated to absorb the scale-factor and
misalignment errors the 15-state model does not carry (``scale_factor_model = "consider"``); the gyro bias random
walk is Table 2's bias stability as a random walk over a minute (``fusion.imugrade``). An IMU grade
(``imu = NAME``) or datasheet keys give the sensor's own figures instead, with ``scale_factor_model =
"bias-steps"``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fieldlog.fusion import earth, errmodel
from fieldlog.fusion.dkf import FUSIONS
from fieldlog.fusion.predictors import PredictorConfig

GPS_ERROR_MODELS = ("consider", "gm-states")
SCALE_FACTOR_MODELS = ("consider", "bias-steps")
PREDICTOR_MODES = ("paper", "pseudo")
_DEG = math.pi / 180.0
_UG = 9.80665e-6


@dataclass
class SensorConfig:
    """The IMU's error figures (body RFU, every axis alike)."""

    imu: str = ""  # the IMU grade whose figures were taken (fusion.imugrade); "" = the figures below as given
    gyro_noise_dps_rthz: float = 0.03
    accel_noise_ug_rthz: float = 300.0
    gyro_bias_rw_dps_rts: float = 0.02 * math.sqrt(2.0 / 60.0)  # deg/s/sqrt(s): B sqrt(2 / 60 s) (fusion.imugrade)
    accel_bias_rw_ug_rts: float = 10.0  # ug/sqrt(s)
    gyro_scale_factor_ppm: float = 1000.0  # 1-sigma per axis, not a state (scale_factor_model says how it counts);
    gyro_misalignment_mrad: float = 1.0  # 0 and 0: none
    accel_scale_factor_ppm: float = 1000.0  # the same for the accelerometers (bias-steps only: the consider
    accel_misalignment_mrad: float = 1.0  # analysis leaves them to the bias states, fusion.consider)
    scale_factor_model: str = "consider"  # "consider": the noise figures are inflated to absorb the scale factors
    # and misalignments, whose consider variance joins the printed accel-bias sigma (fusion.consider);
    # "bias-steps": the noise figures are the sensor's own, and the scale factors and misalignments are the bias
    # steps (S + M) dx of each cycle's change of rate and specific force (fusion.errmodel.scale_factor_steps)
    gyro_range_dps: float = 20.0  # a gyro flat at this rate (or beyond) is clipped (Table 2: +-20 deg/s)
    clip_rate_sigma_dps: float = 0.5  # 1-sigma of a clipped yaw rate rebuilt from the lateral acceleration
    adapt_noise: bool = False  # the white noise from the still start and Q and R by covariance matching
    # (fusion.adaptive); false: the figures as given
    imu_time_offset_s: float = 0.0  # how late the IMU's stamps are against the GPS's, s: the engine takes it off
    # every IMU stamp; `fuse` estimates it from the drive (fusion.installation) with this as its start value

    def noise_psd(self) -> np.ndarray:
        """The filter's noise PSD (12, 12) (``fusion.errmodel.noise_psd``) in SI units.

        Returns
        -------
        np.ndarray
            (12, 12) diagonal: gyro and accelerometer white noise, (rad/s)^2/Hz and (m/s^2)^2/Hz, then the gyro
            and accelerometer bias random walks, (rad/s)^2/s and (m/s^2)^2/s, three axes each.
        """
        return errmodel.noise_psd(self.gyro_noise_dps_rthz * _DEG, self.accel_noise_ug_rthz * _UG,
                                  self.gyro_bias_rw_dps_rts * _DEG, self.accel_bias_rw_ug_rts * _UG)


@dataclass
class GpsConfig:
    """The receiver: antenna lever arm, which epochs are used, outages forced, the correlated error."""

    lever_arm_b: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU -> GPS antenna, m, in lever_arm_frame
    lever_arm_frame: str = "rfu"  # body frame of lever_arm_b: rfu, flu (REP-103) or frd (earth.BODY_FRAMES)
    vel_var_max: float = 100.0  # velocity components with a larger variance are not fed, (m/s)^2
    max_fix_sigma_m: float = 30.0
    outages: tuple[tuple[float, float], ...] = ()  # forced (start_s, length_s) from the first IMU sample
    gps_error_tau_s: float = 300.0  # correlation time of the GPS position error (multipath, atmosphere); 0: white
    gps_error_model: str = "consider"  # "consider": added to the printed sigma (fusion.output); "gm-states": kf
    # (unsmoothed) carries it as Gauss-Markov states (fusion.gpserror), the other methods keep "consider"
    gps_error_white_share: float = 0.15  # gm-states: share of the fix's variance that is white (the rest correlated)

    def lever_rfu(self) -> np.ndarray:
        """The lever arm IMU -> antenna (3,) in body RFU, m.

        Returns
        -------
        np.ndarray
            (3,) ``lever_arm_b`` rotated from ``lever_arm_frame`` into body RFU, m.
        """
        return earth.C_rfu_from(self.lever_arm_frame) @ np.asarray(self.lever_arm_b, dtype=float)


@dataclass
class InitConfig:
    """The initial state's sigmas, and an optional configured start (``fusion.align``)."""

    init_vel_sigma_mps: float = 0.2  # sigma of the initial velocity (the alignment epoch's or init_velocity_enu), m/s
    init_level_sigma_deg: float = 0.5  # roll/pitch allowance added to the levelling's own sigma (fusion.align)
    init_heading_sigma_deg: float = 3.0  # sigma of init_attitude_deg's heading
    init_attitude_deg: tuple[float, ...] = ()  # optional [roll, pitch, heading] at the drive's start, deg
    init_position_llh: tuple[float, ...] = ()  # optional [lat deg, lon deg, h m (ellipsoidal)] of the IMU at the
    # first IMU sample: with init_attitude_deg, the INS starts there from the config (fusion.align)
    init_position_sigma_m: float = 1.0  # sigma of init_position_llh per axis (E, N, U), m
    init_velocity_enu: tuple[float, ...] = ()  # optional [E, N, U] velocity at the first IMU sample, m/s (default 0)
    init_gyro_bias_sigma_dps: float = 0.02  # floor after the static gyro mean: the bias instability
    gyro_bias_prior_sigma_dps: float = 0.1  # before any static mean: turn-on and instability
    init_accel_bias_sigma_ug: float = 2000.0


@dataclass
class AlignConfig:
    """Alignment and re-alignment (``fusion.align``)."""

    align_speed_mps: float = 3.0  # the GPS course gives the heading from this speed
    align_sideslip_deg: float = 2.0  # course - heading allowance (sideslip, IMU mounting yaw)
    gyrocompass_max_deg: float = 5.0  # gyrocompass only when its heading sigma is below this (and the course's)
    realign_window_s: float = 120.0  # chi-square test of the heading on the GPS innovations this long (0: off)
    realign_epochs: int = 10  # ... summed over this many epochs
    still_trim_s: float = 2.0  # the static start loses this much at an end where the vehicle moved


@dataclass
class StillConfig:
    """The still detector (``fusion.still``), shared by the alignment and the stationary update."""

    still_speed_mps: float = 0.5  # still: INS speed below this without GPS velocity, ...
    still_gps_speed_mps: float = 0.1  # ... or the mean GPS velocity of the last second below this (or 1.5 of its
    # sigmas from the reported velocity covariance, fusion.still.GpsSpeed), ...
    still_accel_std_mps2: float = 0.1  # ... specific force and rate varying less than these over the interval,
    still_gyro_std_dps: float = 0.5
    still_rate_tol_dps: float = 0.01  # ... and their means within 3 sigma plus these of standing still
    still_accel_tol_mps2: float = 0.02


@dataclass
class AidConfig:
    """The vehicle aids of a car (``fusion.measurements``): they need no GPS and act in outages too."""

    nhc: bool = True  # non-holonomic constraint of a car (body lateral, vertical velocity 0) at every epoch;
    # with the odometer on, its lateral and vertical rows (false: the odometer's forward row alone)
    nhc_sigma_mps: float = 0.1
    zupt: bool = True  # zero-velocity and zero-angular-rate update when the vehicle stands still
    zupt_sigma_mps: float = 0.02
    static_speed_mps: float = 0.3  # below this GPS speed the car is slow: no non-holonomic constraint
    odometer: bool = True  # the wheel speeds (/vehicle/twist or --odom-topic) with the NHC, when the drive has them
    # (false: the NHC alone; fusion.odometer, "With the NHC and without")
    odometer_lever_b: tuple[float, float, float] = (0.0, 0.0, 0.0)  # IMU -> rear axle centre, body RFU, m
    odometer_sigma_mps: float = 0.02  # the wheel speed's sigma when the topic gives no variance
    mounting_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the IMU's axes from the car's (base_link),
    # [roll, pitch, yaw] deg, C_bm = fusion.earth.euler_to_dcm(yaw, pitch, roll) maps IMU axes to the car's: the NHC
    # and the odometer constrain the car's velocity, C_bm C_nb v_n; `fuse` estimates it from the drive
    # (fusion.installation) with this as its initial value
    mounting_sigma_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # its 1-sigma, deg, added to the NHC's and the
    # odometer's lateral (yaw) and vertical (pitch) variance; all 0 to `fuse`: nobody measured it (the estimate alone)
    estimate_installation: bool = True  # `fuse` estimates the mounting and the IMU time offset from the drive
    # first and uses them, with a car aid on (the NHC, or the odometer with wheel speeds: its estimators assume a
    # car, heading = course; tools.fuse_settings.installation_applies);
    # false: the configured values as they are
    installation_span_s: float = 0.0  # s: estimate it from the drive's first this many seconds (whole 60 s reading
    # blocks) and fuse the whole drive with it, the estimate's passes a fraction of a long drive's time and
    # its sigmas those of the span; 0: from the whole drive
    odometer_track_m: float = 1.6  # the car's track (left to right wheel centres) and wheelbase, m: the per-wheel
    odometer_wheelbase_m: float = 2.7  # slip test's kinematics (fusion.odometer, "Per-wheel slip")


@dataclass
class FilterConfig:
    """The filter cycle, the output rate, and the settings of particular methods."""

    output_hz: float = 10.0
    cov_step_s: float = 0.1  # covariance propagation cycle, s
    dkf_fusion: str = "paper"  # dkf and the predictors' filter: "paper" (eqs. 3-4, lossy) or "federated" (= kf)
    predictor_mode: str = "paper"  # dkf-rbfn: "paper" (networks predict the local filters' innovations, eq. 7) or
    # "pseudo" (a network learns the forward speed from the IMU: a virtual odometer, fusion.pseudo)
    hinf_gamma: float = 100.0  # H-infinity bound, position (m) / velocity (m/s) errors; must exceed their sigma
    hinf_min_ratio: float = 1.5  # gamma_k = max(hinf_gamma, ratio x existence bound); 0: fixed gamma (may raise)
    status_max_sigma_m: float = 10.0  # the status is "degraded" above this horizontal position sigma, m
    status_diverged_nis: float = 25.0  # ... "diverged" above this mean NIS per degree of freedom (fusion.output)


SECTIONS = {"sensor": SensorConfig, "gps": GpsConfig, "init": InitConfig, "align": AlignConfig,
            "still": StillConfig, "aids": AidConfig, "filter": FilterConfig}
FLAT_KEYS = {f.name: s for s, cls in SECTIONS.items() for f in dataclasses.fields(cls)}  # flat key -> section


@dataclass
class FusionConfig:
    """Every fusion setting, in sections (module docstring)."""

    sensor: SensorConfig = field(default_factory=SensorConfig)
    gps: GpsConfig = field(default_factory=GpsConfig)
    init: InitConfig = field(default_factory=InitConfig)
    align: AlignConfig = field(default_factory=AlignConfig)
    still: StillConfig = field(default_factory=StillConfig)
    aids: AidConfig = field(default_factory=AidConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    predictor: PredictorConfig = field(default_factory=PredictorConfig)

    @classmethod
    def from_flat(cls, **keys: Any) -> FusionConfig:
        """The defaults with the given flat keys (values already of the field's type); KeyError names an
        unknown key.

        Parameters
        ----------
        **keys : flat keys (``known_keys``) and their values, in the units the fields name

        Returns
        -------
        FusionConfig
        """
        return cls().replace(**keys)

    def replace(self, **keys: Any) -> FusionConfig:
        """A copy with the given flat keys (and ``predictor``) replaced.

        Parameters
        ----------
        **keys : flat keys (``known_keys``) and their values, in the units the fields name

        Returns
        -------
        FusionConfig
            A new config; self is unchanged.

        Raises
        ------
        KeyError
            Naming the unknown keys.
        """
        bad = sorted(k for k in keys if k not in FLAT_KEYS and k != "predictor")
        if bad:
            raise KeyError(f"{', '.join(bad)}: unknown key; known keys: {', '.join(sorted(known_keys()))}")
        parts = {s: dataclasses.replace(getattr(self, s), **{k: v for k, v in keys.items() if FLAT_KEYS.get(k) == s})
                 for s in SECTIONS}
        return FusionConfig(**parts, predictor=keys.get("predictor", self.predictor))

    def get(self, key: str) -> Any:
        """The value of a flat key (or ``predictor``); KeyError for an unknown one.

        Parameters
        ----------
        key : str, a flat key (``known_keys``)

        Returns
        -------
        Any
            The value, in the unit its field names.
        """
        return self.predictor if key == "predictor" else getattr(getattr(self, FLAT_KEYS[key]), key)

    def flat(self) -> dict[str, Any]:
        """Every setting by its flat key (``predictor`` as a dict), in section order.

        Returns
        -------
        dict
            Flat key -> value, in the unit its field names; ``predictor`` -> the ``PredictorConfig`` as a dict.
        """
        out: dict[str, Any] = {}
        for s in SECTIONS:
            out.update(dataclasses.asdict(getattr(self, s)))
        out["predictor"] = dataclasses.asdict(self.predictor)
        return out

    def validate(self) -> FusionConfig:
        """Self, when every value is in range; else ValueError naming the key, ``[fusion] KEY: ...``.

        Returns
        -------
        FusionConfig
            Self, unchanged (for chaining).
        """
        g, i, f = self.gps, self.init, self.filter
        if g.lever_arm_frame.lower() not in ("rfu", "flu", "frd"):
            raise ValueError(f"[fusion] lever_arm_frame: one of rfu, flu, frd, got {g.lever_arm_frame!r}")
        for key in ("output_hz", "cov_step_s", "status_max_sigma_m", "status_diverged_nis"):
            if not getattr(f, key) > 0:
                raise ValueError(f"[fusion] {key}: must be > 0")
        if f.dkf_fusion not in FUSIONS:
            raise ValueError(f"[fusion] dkf_fusion: {f.dkf_fusion!r}; one of {', '.join(FUSIONS)}")
        for key in ("init_attitude_deg", "init_position_llh", "init_velocity_enu"):
            v = getattr(i, key)
            if v and (len(v) != 3 or not all(math.isfinite(x) for x in v)):
                raise ValueError(f"[fusion] {key}: expected 3 finite numbers, got {list(v)!r}")
        if i.init_position_llh and not i.init_attitude_deg:
            raise ValueError("[fusion] init_position_llh: a configured start needs init_attitude_deg too")
        if i.init_velocity_enu and not i.init_position_llh:
            raise ValueError("[fusion] init_velocity_enu: only with init_position_llh (the configured start)")
        for key in ("init_position_sigma_m", "init_vel_sigma_mps", "init_level_sigma_deg", "init_heading_sigma_deg"):
            if not getattr(i, key) > 0:
                raise ValueError(f"[fusion] {key}: must be > 0")
        if f.predictor_mode not in PREDICTOR_MODES:
            raise ValueError(f"[fusion] predictor_mode: {f.predictor_mode!r}; one of {', '.join(PREDICTOR_MODES)}")
        if self.sensor.scale_factor_model not in SCALE_FACTOR_MODELS:
            raise ValueError(f"[fusion] scale_factor_model: {self.sensor.scale_factor_model!r}; one of "
                             f"{', '.join(SCALE_FACTOR_MODELS)}")
        for key in ("gyro_scale_factor_ppm", "gyro_misalignment_mrad", "accel_scale_factor_ppm",
                    "accel_misalignment_mrad"):
            if not getattr(self.sensor, key) >= 0:
                raise ValueError(f"[fusion] {key}: must be >= 0")
        if g.gps_error_model not in GPS_ERROR_MODELS:
            raise ValueError(f"[fusion] gps_error_model: {g.gps_error_model!r}; one of {', '.join(GPS_ERROR_MODELS)}")
        a = self.aids
        for key in ("mounting_rpy_deg", "mounting_sigma_deg"):
            v = getattr(a, key)
            if len(v) != 3 or not all(math.isfinite(x) for x in v) or (key == "mounting_sigma_deg" and min(v) < 0):
                raise ValueError(f"[fusion] {key}: expected 3 finite numbers (sigmas >= 0), got {list(v)!r}")
        for key in ("odometer_track_m", "odometer_wheelbase_m"):
            if not getattr(a, key) > 0:
                raise ValueError(f"[fusion] {key}: must be > 0")
        if not (math.isfinite(a.installation_span_s) and a.installation_span_s >= 0):
            raise ValueError("[fusion] installation_span_s: must be >= 0 (0: the whole drive)")
        if not abs(self.sensor.imu_time_offset_s) < 10.0:
            raise ValueError("[fusion] imu_time_offset_s: must be within +-10 s")
        for n, o in enumerate(g.outages):
            if len(o) != 2 or not (o[0] >= 0 and o[1] > 0):
                raise ValueError(f"[fusion] outages[{n}]: expected [start_s >= 0, length_s > 0], got {list(o)!r}")
        return self


def known_keys() -> list[str]:
    """The flat keys of a ``[fusion]`` table.

    Returns
    -------
    list of str
        Every section's field names in section order, then ``predictor``.
    """
    return [*FLAT_KEYS, "predictor"]
