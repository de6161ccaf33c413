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
pass (``fusion.smoother``) under the same topics; the filter's records (5.5 kB per 0.1 s) and the forward rows
go to temporary files and the rows are smoothed and written back a block at a time, so memory grows only by
the smoothed errors (about 15 MB per hour).

Settings: ``tools.fuse_settings`` (``--config FILE``, the drive's own record, the defaults); the writing:
``tools.fuse_output``.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from fieldlog.drive import outputs
from fieldlog.drive.files import DriveSpec, label
from fieldlog.drive.reader import topics as reader_topics
from fieldlog.drive.recorder import Recorder
from fieldlog.fusion import adaptive, hinf, installation, measurements, odometer
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.methods import KF
from fieldlog.fusion.predictors import OutagePredictor, PredictorConfig
from fieldlog.fusion.smoother import SmootherLog
from fieldlog.fusion.types import Solution
from fieldlog.replay import inputs as inputs_mod
from fieldlog.replay.ahead import Remote
from fieldlog.replay.inputs import InputMap, InputStream
from fieldlog.replay.loop import Pace, run
from fieldlog.tools.fuse_output import FusedOutput
from fieldlog.tools.fuse_settings import Settings, drive_config, drive_mounting

BLOCK_S = 10.0

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


def estimate_installation(drive: DriveSpec, config: FusionConfig, inputs: InputMap) -> dict[str, object]:
    """``fusion.installation``'s first pass over ``drive``, in two reads: the IMU's time offset from its rate
    integral and the receiver's velocities; then ``kf`` without the vehicle aids and the forced outages (they would
    pull the attitude onto the nominal mounting) on the IMU stamps less that offset (a late IMU tilts the INS in
    the turns), and the mounting from its rows. The ``fuse --json`` keys ``imu_time_offset_s``,
    ``imu_time_offset_sigma_s`` (s, the IMU's stamps late against the GPS's), ``mounting_rpy_deg`` and
    ``mounting_sigma_deg`` (IMU -> base_link, deg), None where the drive does not show them. Reported, not yet
    applied: the run's NHC and odometer take the IMU's axes for the car's. Memory grows by the rows (10 Hz) and
    the rate integral (50 Hz)."""
    out: dict[str, object] = dict.fromkeys(("imu_time_offset_s", "imu_time_offset_sigma_s", "mounting_rpy_deg",
                                            "mounting_sigma_deg"))
    gyro = installation.GyroTrack()
    t_gps, v_gps = [], []
    for block in InputStream(drive, inputs, BLOCK_S):
        gyro.add(block.imu.t_ns, block.imu.omega_ib_b, block.imu.f_b)
        t_gps.append(block.gps.t_ns)
        v_gps.append(block.gps.v_n)
    offset = installation.time_offset(gyro, np.concatenate(t_gps), np.concatenate(v_gps).reshape(-1, 3))
    if offset is not None:
        out["imu_time_offset_s"], out["imu_time_offset_sigma_s"] = offset
    shift = int(round(offset[0] * 1e9)) if offset is not None else 0
    engine = Engine(KF.name, config.replace(nhc=False, zupt=False, odometer=False, outages=()))
    parts = []
    for block in InputStream(drive, inputs, BLOCK_S):
        imu = block.imu
        parts.append(engine.process(type(imu)(imu.t_ns - shift, imu.omega_ib_b, imu.f_b), block.gps)[0])
    parts.append(engine.finish()[0])
    mount = installation.mounting(Solution.concat(parts))
    if mount is not None:
        out["mounting_rpy_deg"], out["mounting_sigma_deg"] = ([round(float(x), 4) for x in a] for a in mount)
    return out


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
         smooth: bool = False, inputs: InputMap | None = None, force: bool = False, keep: bool = False
         ) -> FuseResult:
    """Fuse ``drive`` with ``method`` into ``out`` (MCAP); streaming, memory bounded by one block unless
    ``smooth`` (RTS backward pass after the drive). ``config`` None: ``drive_config(drive)``; ``inputs`` None:
    ``replay.inputs.resolve(drive)``. A drive of several files (``drive.files``) is fused once, across the file
    boundaries. Raises ``replay.solutions.Diverged`` (nothing past the first bad row written) when the
    solution turns NaN or inf. ``out`` must be new, unless ``force`` (``drive.outputs``). ``keep``: the rows
    written are also returned (``FuseResult.solution``), for a caller that scores them without reading ``out``
    back (``replay.solutions.read``); memory then grows by the rows, as with ``smooth``."""
    outputs.check_new(out, force)
    cfg = config or drive_config(drive)
    imap = inputs or inputs_mod.resolve(drive)
    span = [t for t in reader_topics(drive) if t.topic in imap.topics and t.count]
    pace = Pace(0.0, (min(t.first_ns for t in span), max(t.last_ns for t in span)), progress)
    log = SmootherLog() if smooth else None
    mounting = drive_mounting(drive)
    stream = InputStream(drive, imap, BLOCK_S)
    with contextlib.ExitStack() as workers:  # the predictor's worker, if the method has one; then the file
        engine = Engine(method, cfg, log=log, make_predictor=worker_predictors(workers))
        rec = workers.enter_context(Recorder(out, flush_interval_s=None, fsync=False, force=force))
        rec.add_metadata("fusion", run_record(drive, method, cfg, imap, smooth))
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
