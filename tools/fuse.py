"""``fieldlog fuse DRIVE --method ins|kf|dkf|rbfn|tdln|dkf-rbfn [--outage START:LEN ...] --out FUSED.mcap``.

Streams the drive in blocks (``drive.reader.iter_blocks``: vectorised decode, no per-message Python on the
IMU path) through ``fusion.engine.Engine`` in the loop of every front end (``replay.loop.run``) and writes,
following docs/data-model.md (``replay.solutions``):

- ``/fusion/<method>/fix`` NavSatFix: position, covariance ENU m^2 (diagonal known); 10 Hz by default
  (``[fusion] output_hz``), stamped with the IMU sample time of the state;
- ``/fusion/<method>/vel`` TwistWithCovarianceStamped: ENU velocity, its variances in the covariance;
- ``/fusion/<method>/attitude`` QuaternionStamped: C_bn (body RFU -> ENU), x, y, z, w;
- ``/fusion/<method>/std`` Vector3Stamped: position sigma E, N, U in m;
- ``/fusion/<method>/kf1/{fix,vel}``, ``/fusion/<method>/kf2/{fix,vel}`` (``dkf``, ``rbfn``, ``tdln``, ``dkf-rbfn``):
  the local solutions, the INS corrected by KF_I's (velocity) or KF_II's (position) estimate alone, with
  that local filter's variances (the paper's Fig. 5);
- ``/fusion/<method>/attitude_std`` Vector3Stamped: attitude sigma (phi E, N, U: ~pitch, roll, heading), rad;
- ``/fusion/<method>/odom`` nav_msgs/Odometry (odom -> base_link), ``/tf`` map -> odom -> base_link,
  ``/tf_static`` (earth -> map, base_link -> imu -> gps_antenna) and ``/fusion/<method>/datum`` (map's origin)
  (REP-105, ``replay.solutions.Odometry``): the same rows for ROS tools, with the vehicle frame of the drive's
  mounting;
- ``/fusion/outage`` Outage: injected and detected outage windows.

With ``smooth`` (``--smooth``) the solution rows are written after the drive, smoothed by the RTS backward
pass (``fusion.smoother``) under the same topics; the filter's records (5.5 kB per 0.1 s), the forward rows and
the smoothed errors go to temporary files and the rows are smoothed and written back a block at a time
(``fusion.smoother.smoothed_blocks``).

The ``fuse`` command decodes the drive once, in its own process: the first pass keeps its input blocks in an
anonymous temporary file (``replay.inputs.InputStream(..., keep=True)``; about 100 MB per hour of a 500 Hz IMU)
that the installation pass's second read and the fusion read back.

Settings: ``tools.fuse_settings`` (``--config FILE``, the drive's own record, the defaults); the writing:
``tools.fuse_output``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.drive import outputs, reader
from fieldlog.drive.files import DriveSpec, label
from fieldlog.drive.recorder import Recorder
from fieldlog.acquire import calib
from fieldlog.fusion import adaptive, earth, hinf, installation, measurements, odometer
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.methods import KF
from fieldlog.fusion.predictors import OutagePredictor, PredictorConfig
from fieldlog.fusion.smoother import SmootherLog, smoothed_blocks
from fieldlog.fusion.types import Solution
from fieldlog.replay import inputs as inputs_mod
from fieldlog.replay.ahead import Remote
from fieldlog.replay.inputs import InputMap, InputStream
from fieldlog.replay.loop import Pace, run
from fieldlog.tools.fuse_output import FusedOutput, RowSpill
from fieldlog.tools.fuse_settings import BLOCK_S, Settings, drive_config, drive_mounting

NO_ALIGNMENT = ("no solution: the filter never aligned, which needs a GPS speed of align_speed_mps ([fusion]) for "
                "the heading; a drive that never moves cannot be aligned with a MEMS IMU")


@dataclass
class FuseResult:
    path: Path
    method: str
    rows: int
    updates: int
    outages: int
    imu_samples: int
    predicted: int = 0  # outage epochs bridged by a predictor (rbfn, tdln, dkf-rbfn)
    imu_rate_hz: float = float("nan")
    imu_gaps: int = 0  # IMU steps longer than 1.5 sample periods, bridged by the INS
    imu_missing: int = 0  # samples those gaps lack
    gamma_raised: int = 0  # hinf: epochs where the existence bound raised gamma
    still_ns: tuple[int, ...] = ()  # GPS epoch times (UTC ns) with a stationary (ZUPT + ZARU) update
    alignment: str = ""  # how the heading was aligned (fusion.align.Alignment.note)
    hinf: dict[str, str] | None = None  # hinf: which gamma ran, whether it equalled kf (fusion.hinf.summary)
    zaru_skipped_ns: tuple[int, ...] = ()  # still_ns epochs whose ZARU failed its chi^2 test (ZUPT alone)
    odometer: dict[str, float] | None = None  # the wheel odometer's scale, its sigma, epochs used and slip-skipped
    solution: Solution | None = None  # the rows written (smoothed with smooth), when fuse was asked to keep them
    alignment_summary: dict | None = None  # which alignment ran on which interval (fusion.align.Alignment.summary)
    imu_warnings: tuple[str, ...] = ()  # what is wrong with the IMU's timing (replay.inputs.InputStream.warnings)
    virtual_odometer: dict | None = None  # dkf-rbfn, predictor_mode "pseudo": its held-out score and whether it ran
    noise: dict[str, tuple[float, str]] | None = None  # adapt_noise: the figures the drive set (Adaptation.figures)


def estimate_installation(drive: DriveSpec, config: FusionConfig, inputs: InputMap,
                          stream: InputStream | None = None) -> tuple[FusionConfig, dict]:
    """``fusion.installation``'s first pass over ``drive`` and the settings that apply it.

    Two reads: the IMU's time offset from its rate integral (stamps less the configured start value ``[fusion]
    imu_time_offset_s``) and the receiver's velocities; then ``kf`` without the vehicle aids and the forced
    outages (they would pull the attitude onto the nominal mounting), its IMU on the GPS's time, smoothed (RTS),
    and the mounting from its rows. The mounting used is the estimate and the configured one (``[fusion]
    mounting_rpy_deg``, else the drive's calibration record) weighted by their inverse variances, the configured
    sigma ``mounting_sigma_deg`` (all 0: a mounting nobody measured, the estimate alone); where the drive does not
    show one, the configured value and sigma stay. The rate integral (50 Hz, ``installation.GyroTrack``), the
    forward rows (``tools.fuse_output.RowSpill``) and the smoother's records go to temporary files, and the rows
    are smoothed and reduced to the mounting a block at a time, so memory does not grow with the drive but for the
    receiver's epochs (32 bytes each) and the mounting's 10 s block means (24 bytes each).

    Parameters
    ----------
    drive : the drive.
    config : the settings of the run (its aids, noise, start values).
    inputs : the drive's topics.
    stream : the drive's input blocks over ``inputs`` (``BLOCK_S``), read as given; None: an ``InputStream`` of
        its own that keeps them (``keep``), so they are decoded once for both passes, over the first ``[fusion]
        installation_span_s`` of the drive when that is set. Given one that keeps them, :func:`fuse` of the same
        stream reads them back too.

    Returns
    -------
    (config with ``imu_time_offset_s``, ``mounting_rpy_deg`` and ``mounting_sigma_deg`` replaced by what is used,
    the ``fuse --json`` keys: ``installation_read_s`` (s, from the first IMU sample the estimates read to the
    last), ``imu_time_offset_s``, ``imu_time_offset_sigma_s`` (s, the IMU's stamps late against the GPS's; the
    sigma None when not estimated), ``mounting_rpy_deg``, ``mounting_sigma_deg`` (IMU -> base_link, deg, the
    values used) and ``mounting_estimate_rpy_deg``, ``mounting_estimate_sigma_deg`` (the drive's own estimate,
    None when it shows none)).
    """
    with contextlib.ExitStack() as own:
        if stream is None:
            stream = own.enter_context(contextlib.closing(
                InputStream(drive, inputs, BLOCK_S, keep=True, span_s=config.aids.installation_span_s)))
        late, late_sigma = _estimated_offset(stream, config.sensor.imu_time_offset_s)
        config = config.replace(imu_time_offset_s=late)
        mount = _estimated_mounting(stream, config)
        read_s = stream.imu_span_s
    prior = np.array(config.aids.mounting_rpy_deg, float)
    if not prior.any():
        prior = calibration_mounting_rpy(drive_mounting(drive))
    prior_sigma = np.array(config.aids.mounting_sigma_deg, float)
    used, used_sigma = prior, prior_sigma
    if mount is not None:
        used, used_sigma = installation.combine(prior, prior_sigma if prior_sigma.any() else np.full(3, np.inf), *mount)
    config = config.replace(mounting_rpy_deg=tuple(float(x) for x in used),
                            mounting_sigma_deg=tuple(float(x) for x in used_sigma))

    def rounded(a) -> list[float] | None:
        return None if a is None else [round(float(x), 4) for x in a]

    return config, {"installation_read_s": round(read_s, 3),
                    "imu_time_offset_s": late, "imu_time_offset_sigma_s": late_sigma,
                    "mounting_rpy_deg": rounded(used), "mounting_sigma_deg": rounded(used_sigma),
                    "mounting_estimate_rpy_deg": rounded(mount and mount[0]),
                    "mounting_estimate_sigma_deg": rounded(mount and mount[1])}


def _estimated_offset(stream: InputStream, start: float) -> tuple[float, float | None]:
    """The IMU's time offset (s, late against the GPS) from ``stream``'s rate integral against its course, the
    configured ``start`` added, and its sigma (s); (start, None) where the drive does not show one."""
    late_ns = int(round(start * 1e9))
    gyro = installation.GyroTrack()
    t_gps, v_gps = [], []
    try:
        for block in stream:
            gyro.add(block.imu.t_ns - late_ns, block.imu.omega_ib_b, block.imu.f_b)
            t_gps.append(block.gps.t_ns)
            v_gps.append(block.gps.v_n)
        offset = installation.time_offset(gyro, np.concatenate(t_gps), np.concatenate(v_gps).reshape(-1, 3))
    finally:
        gyro.close()
    return (start + offset[0], offset[1]) if offset is not None else (start, None)


def _estimated_mounting(stream: InputStream, config: FusionConfig) -> tuple[np.ndarray, np.ndarray] | None:
    """``installation.mounting`` of ``kf`` over ``stream`` without the vehicle aids and the forced outages (nor the
    gyro's consider analysis, whose sigma the mounting does not read), smoothed (deg, their sigmas): the forward
    rows spilled as they come (``RowSpill``), smoothed and reduced a block at a time."""
    log, spill = SmootherLog(), RowSpill()
    off = {"nhc": False, "zupt": False, "odometer": False, "outages": ()}
    if config.sensor.scale_factor_model == "consider":  # its analysis adds to the accelerometer-bias sigma alone,
        off.update(gyro_scale_factor_ppm=0.0, gyro_misalignment_mrad=0.0)  # which the mounting does not read
    try:
        engine = Engine(KF.name, config.replace(**off), log=log)
        for block in stream:
            spill.add(engine.process(block.imu, block.gps)[0])
        spill.add(engine.finish()[0])
        return installation.mounting(smoothed_blocks(spill.blocks(), log),
                                     np.asarray(config.aids.odometer_lever_b, float))
    finally:
        log.close()
        spill.close()


def calibration_mounting_rpy(mounting: calib.Mounting) -> np.ndarray:
    """The calibration's IMU mounting (``[mounting] imu_rpy_deg``: fixed-axis roll, pitch, yaw, REP-103) as
    ``[fusion] mounting_rpy_deg`` (C_bm = ``fusion.earth.euler_to_dcm(yaw, pitch, roll)``), deg (3,)."""
    if not any(mounting.imu_rpy_deg):
        return np.zeros(3)
    C_bm = earth.rpy_to_dcm(np.radians(mounting.imu_rpy_deg))
    yaw, pitch, roll = earth.dcm_to_euler(C_bm)
    return np.degrees([roll, pitch, yaw])


def fused_mounting(mounting: calib.Mounting, config: FusionConfig) -> calib.Mounting:
    """The mounting the fused file's ``/tf_static`` gives: the drive's, its IMU angles replaced by the ones the
    NHC and the odometer used (``[fusion] mounting_rpy_deg``) when those are not zero."""
    rpy = config.aids.mounting_rpy_deg
    if not any(rpy):
        return mounting
    roll, pitch, yaw = np.radians(rpy)
    C_bm = earth.euler_to_dcm(yaw, pitch, roll)
    return dataclasses.replace(mounting, imu_rpy_deg=np.degrees(earth.dcm_to_rpy(C_bm)))


class RemotePredictor:
    """An outage predictor trained in a worker on the second core (``replay.ahead.Remote``), beside the fusion
    loop: ``train`` is sent without waiting, ``predict`` waits for an answer that reflects every epoch trained
    before it, so the solution is the one an ``OutagePredictor`` in the loop gives, to the bit."""

    def __init__(self, remote: Remote) -> None:
        self.remote = remote

    def train(self, t_s: float, u: np.ndarray, y: np.ndarray) -> None:
        self.remote.send("train", t_s, u, y)

    def predict(self, u: np.ndarray) -> np.ndarray:
        return self.remote.ask("predict", u)


def worker_predictors(workers: contextlib.ExitStack) -> Callable[[str, PredictorConfig], RemotePredictor]:
    """The engine's ``make_predictor``: each outage predictor trained in a worker of its own (``RemotePredictor``)
    that lives as long as ``workers``."""

    def predictor(network: str, config: PredictorConfig) -> RemotePredictor:
        return RemotePredictor(workers.enter_context(Remote(lambda: OutagePredictor(network, config))))

    return predictor


def fuse(drive: DriveSpec, method: str, out: str | os.PathLike[str],
         config: FusionConfig | None = None, progress: Callable[[float], None] | None = None,
         smooth: bool = False, inputs: InputMap | None = None, force: bool = False, keep: bool = False,
         installation: dict[str, object] | None = None, stream: InputStream | None = None) -> FuseResult:
    """Fuse ``drive`` with ``method`` into ``out`` (MCAP); streaming, memory bounded by one block unless
    ``smooth`` (RTS backward pass after the drive). ``config`` None: ``drive_config(drive)``; ``inputs`` None:
    ``replay.inputs.resolve(drive)``. A drive of several files (``drive.files``) is fused once, across the file
    boundaries. Raises ``replay.solutions.Diverged`` (nothing past the first bad row written) when the
    solution turns NaN or inf. ``out`` must be new, unless ``force`` (``drive.outputs``). ``keep``: the rows
    written are also returned (``FuseResult.solution``), for a caller that scores them without reading ``out``
    back (``replay.solutions.read``); memory then grows by the rows, as with ``smooth``. ``installation``: the
    keys of :func:`estimate_installation`, written as the ``fusion.installation`` record (JSON values).
    ``stream``: the drive's input blocks over ``inputs`` (``BLOCK_S``), e.g. the one ``estimate_installation``
    kept; None: read from the drive."""
    outputs.check_new(out, force)
    cfg = config or drive_config(drive)
    imap = inputs or inputs_mod.resolve(drive)
    pace = Pace(0.0, reader.span(drive, imap.topics), progress)
    log = SmootherLog() if smooth else None
    mounting = fused_mounting(drive_mounting(drive), cfg)
    stream = stream or InputStream(drive, imap, BLOCK_S)
    with contextlib.ExitStack() as workers:  # the predictor's worker, if the method has one; then the file
        engine = Engine(method, cfg, log=log, make_predictor=worker_predictors(workers))
        rec = workers.enter_context(Recorder(out, flush_interval_s=None, fsync=False, force=force, behind=True))
        rec.add_metadata("fusion", run_record(drive, method, cfg, imap, smooth))
        if installation:
            rec.add_metadata("fusion.installation", {k: json.dumps(v) for k, v in installation.items()})
        written = FusedOutput(rec, method, mounting, log, keep)
        run(stream, engine, [written], pace)
        hinf_note = hinf.summary(engine.filter) if isinstance(engine.filter, hinf.HInfinityFilter) else {}
        if hinf_note:
            rec.add_metadata("fusion.hinf", hinf_note)
        written.close()
    if progress:
        progress(1.0)
    return FuseResult(Path(out), method, written.rows, engine.updates, written.outages, stream.samples,
                      engine.predicted, stream.rate_hz, stream.gaps, stream.missing,
                      getattr(engine.filter, "raised", 0), engine.used("Stationary"), engine.alignment.note,
                      hinf_note or None, engine.used("Stationary", "zaru_skipped"),
                      odometer_summary(engine), written.solution,
                      dict(engine.alignment.summary), tuple(stream.warnings()),
                      next((m.summary() for m in engine.measurements if hasattr(m, "summary")), None),
                      engine.adapt.figures() if engine.adapt is not None else None)


NOISE_KEYS = ("gyro_noise_dps_rthz", "accel_noise_ug_rthz", "gyro_bias_rw_dps_rts", "accel_bias_rw_ug_rts")


def noise_sources(st: Settings, res: FuseResult) -> dict[str, dict[str, object]]:
    """Each noise figure the run used: key -> {"value", "source"}: the settings' source (default, the config,
    its grade or datasheet key) unless the drive set it (``adapt_noise``: estimated from the still start,
    adapted; ``fusion.adaptive``)."""
    out: dict[str, dict[str, object]] = {k: {"value": st.config.get(k), "source": st.sources[k]} for k in NOISE_KEYS}
    for k, (value, src) in (res.noise or {}).items():
        if src != adaptive.CONFIGURED:
            out[k] = {"value": value, "source": src}
    return out


def run_record(drive: DriveSpec, method: str, config: FusionConfig, inputs: InputMap, smooth: bool
               ) -> dict[str, str]:
    """The fused file's ``fusion`` metadata record: the drive, the method, the settings and the input map."""
    return {"source": label(drive), "method": method, "config": repr(config.flat()),
            "smooth": "rts" if smooth else "no",
            "inputs": ", ".join(f"{k}={getattr(inputs, k)}" for k in ("imu_topic", "fix_topic", "vel_topic",
                                                                        "imu_frame", "odom_topic"))}


def odometer_summary(engine: Engine) -> dict[str, float] | None:
    """The wheel odometer's fitted scale factor and its sigma (``fusion.odometer.ScaleEstimator``), the epochs it
    updated at, those among them skipped as slip, those the four wheels were tested at and those each wheel (FL,
    FR, RL, RR) was skipped at (``fusion.odometer.WheelSlip``); None when the run had no odometer or no wheel speed."""
    odo = [p for m in engine.measurements for p in getattr(m, "parts", (m,)) if isinstance(p, measurements.Odometer)]
    if not odo or not odo[0].times:
        return None
    return {"scale": odo[0].scale.scale, "scale_sigma": odo[0].scale.sigma, "epochs": len(odo[0].times),
            "slip_skipped": len(odo[0].slip_skipped),
            "wheel_epochs": odo[0].wheels.tested,
            "wheels_skipped": dict(zip(odometer.WHEELS, odo[0].wheels.skipped.tolist()))}
