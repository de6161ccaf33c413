"""``fieldlog fuse DRIVE --method ins|kf|dkf|rbfn|tdln|dkf-rbfn [--outage START:LEN ...] --out FUSED.mcap``.

Streams the drive in blocks (``drive.reader.iter_blocks``: vectorised decode, no per-message Python on the
IMU path) through ``fusion.engine.Engine`` and writes, following docs/data-model.md (``replay.solutions``):

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

Settings (``FusionConfig``): ``--config FILE`` reads the ``[fusion]`` table of a TOML file (other tables are
ignored, so a scenario file works too), e.g.::

    [fusion]
    gyro_noise_dps_rthz = 0.0097     # any FusionConfig field; lists for tuples
    lever_arm_b = [0.0, 0.5, 1.2]
    imu = "tactical"                 # an IMU grade of fusion.imugrade, and/or its datasheet keys:
    gyro_arw_deg_rth = 0.003         # deg/sqrt(h), gyro_bias_instability_dph with gyro_bias_corr_time_s, ...
    [fusion.predictor]               # fusion.predictors.PredictorConfig
    centres = 12

Without it, the drive's own ``fusion.config`` metadata record (what ``fieldlog sim`` stored from the scenario's
[fusion] table), else the defaults (``drive_config``). An explicit ``--config`` replaces the drive's record as
a whole; ``--outage`` replaces the outages of either.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from fieldlog.acquire import calib
from fieldlog.drive import messages, metavalue, outputs
from fieldlog.acquire.config import ConfigError, TomlFile, from_table, typed_value
from fieldlog.drive.recorder import Recorder
from fieldlog.fusion import earth, hinf, imugrade, installation, measurements
from fieldlog.fusion.config import FLAT_KEYS, FusionConfig, known_keys
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.methods import KF
from fieldlog.fusion.predictors import OutagePredictor, PredictorConfig
from fieldlog.fusion.types import Solution
from fieldlog.fusion.smoother import SmootherLog, rts, smooth_rows, smooth_solution
from fieldlog.replay import inputs as inputs_mod
from fieldlog.replay.ahead import Remote
from fieldlog.drive.files import DriveSpec, label
from fieldlog.replay.inputs import InputMap, InputSpec, InputStream
from fieldlog.drive.reader import read_metadata
from fieldlog.drive.reader import topics as reader_topics
from fieldlog.replay.solutions import OUTAGE, Odometry, write_solution, write_status

BLOCK_S = 10.0


class _RowSpill:
    """The forward solution rows of a smoothed run, spilled block by block to an anonymous temporary file as they
    come and read back in the same blocks (``Solution`` without ``local``, which smoothing drops, and ``status``,
    written as it comes)."""

    _FIELDS = [f.name for f in fields(Solution) if f.name not in ("local", "status")]

    def __init__(self) -> None:
        self._file = tempfile.TemporaryFile()  # noqa: SIM115 (lives as long as the spill; close())
        self._blocks = 0

    def add(self, sol: Solution) -> None:
        if len(sol.t_ns):
            for name in self._FIELDS:
                np.save(self._file, getattr(sol, name), allow_pickle=False)
            self._blocks += 1

    def blocks(self) -> Iterator[Solution]:
        """The blocks added, in order."""
        self._file.seek(0)
        for _ in range(self._blocks):
            yield Solution(*(np.load(self._file, allow_pickle=False) for _ in self._FIELDS))

    def close(self) -> None:
        self._file.close()


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


def parse_outage(text: str) -> tuple[float, float]:
    """``START:LEN`` in seconds from the drive's first IMU sample -> (start_s, length_s)."""
    try:
        a, b = text.split(":")
        start, length = float(a), float(b)
    except ValueError:
        raise ValueError(f"--outage expects START:LEN in seconds, got {text!r}") from None
    if not (math.isfinite(start) and math.isfinite(length) and start >= 0.0 and length > 0.0):
        raise ValueError(f"--outage {text!r}: need START >= 0 and LEN > 0")
    return start, length


def fusion_config(table: dict[str, Any]) -> FusionConfig:
    """``FusionConfig`` from a ``[fusion]`` table of flat keys (``fusion.config``), each value converted by
    ``acquire.config.typed_value`` and the whole checked by ``FusionConfig.validate``; a bad key or value raises
    ConfigError naming it, e.g. ``[fusion] gyro_nosie_dps_rthz: unknown key; known keys: ...``."""
    try:
        table = imugrade.settings(table)
    except ValueError as e:
        raise ConfigError(f"[fusion] {e}") from None
    bad = sorted(set(table) - set(known_keys()))
    if bad:
        raise ConfigError(f"[fusion] {', '.join(bad)}: unknown key; known keys: {', '.join(sorted(known_keys()))}")
    defaults = FusionConfig()
    try:
        return FusionConfig.from_flat(**{k: typed_value("fusion", k, v, defaults.get(k))
                                         for k, v in table.items()}).validate()
    except ValueError as e:
        raise ConfigError(str(e)) from None


def load_fusion_config(config: TomlFile) -> FusionConfig:
    """``--config FILE``: the ``[fusion]`` table of a TOML file; ConfigError with one line naming the problem."""
    if not isinstance(config.tables.get("fusion"), dict):
        raise ConfigError(f"config file {config}: no [fusion] table")
    return fusion_config(config.tables["fusion"])


def load_input_spec(config: TomlFile | None) -> InputSpec:
    """The ``[input]`` table of a config file (``replay.inputs.InputSpec``: imu_topic, fix_topic, vel_topic,
    imu_frame); an empty spec without a file or table."""
    if config is None:
        return InputSpec()
    table = config.tables.get("input", {})
    if not isinstance(table, dict):
        raise ConfigError(f"config file {config}: [input] must be a table")
    for k, v in table.items():
        if not isinstance(v, str):
            raise ConfigError(f"[input] {k}: expected a string, got {v!r}")
    spec = from_table(InputSpec, "input", table)
    if spec.imu_frame is not None and spec.imu_frame.lower() not in ("rfu", "flu", "frd"):
        raise ConfigError(f"[input] imu_frame: one of rfu, flu, frd, got {spec.imu_frame!r}")
    return spec


def input_map(drive: DriveSpec, config: TomlFile | None, spec: InputSpec | None) -> InputMap:
    """``replay.inputs.resolve`` of the config's ``[input]`` table overridden by ``spec`` (the options), each
    input's source naming where it was given."""
    table, spec = load_input_spec(config), spec or InputSpec()
    given = {k: f"[input] of {config}" for k in table.given() if k not in spec.given()}
    return inputs_mod.resolve(drive, table.merged(spec), given)


@dataclass
class Settings:
    """What a fusion run uses: the FusionConfig, the input map, and where each setting came from."""

    config: FusionConfig
    inputs: InputMap
    sources: dict[str, str]  # FusionConfig field -> "--config FILE", "the drive's record", "/tf_static", "default"

    def lines(self, drive: DriveSpec) -> list[str]:
        """The settings grouped by where they came from; a warning when another logger's drive runs on the
        default sensor figures or lever arm."""
        out = [self.inputs.describe()]
        groups: dict[str, list[str]] = {}
        for k, src in self.sources.items():
            groups.setdefault(src, []).append(f"{k}={_show(self.config.get(k))}")
        for src in sorted(groups, key=lambda x: x == "default"):
            out.append(f"fusion settings ({src}): " + ", ".join(groups[src]))
        defaulted = [k for k in SENSOR_KEYS if self.sources[k] == "default"]
        if not self.inputs.native and defaulted:
            out.append(f"warning: {label(drive)} is from another logger and runs on default {', '.join(defaulted)}: "
                       "give its own figures in the [fusion] table of --config")
        return out


# the figures of a particular car and IMU: a default is a guess
SENSOR_KEYS = ("lever_arm_b", "gyro_noise_dps_rthz", "accel_noise_ug_rthz", "gyro_bias_rw_dps_rts",
               "accel_bias_rw_ug_rts", "gyro_scale_factor_ppm", "gyro_misalignment_mrad")


def _show(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, tuple):
        return "(" + ", ".join(_show(x) for x in v) + ")"
    return str(v) if v != "" else "none"


def settings(drive: DriveSpec, config: TomlFile | None = None,
             spec: InputSpec | None = None, outages: tuple[tuple[float, float], ...] | None = None) -> Settings:
    """The settings of a fusion run and their sources: the input map (``replay.inputs.resolve`` of the config's
    [input] table overridden by ``spec``), the FusionConfig from ``--config``'s [fusion] table (replacing the
    drive's record as a whole), else the drive's ``fusion.config`` record, else the defaults; the lever arm from
    the drive's /tf_static when neither gives it; ``outages`` (``--outage``) replace the config's."""
    imap = input_map(drive, config, spec)
    table = config.tables.get("fusion") if config else None
    if table is None:
        table = drive_table(drive)
        where = "the drive's record"
    else:
        where = f"--config {config}"
    try:
        cfg = fusion_config(table)
    except (ValueError, TypeError) as e:
        if config:
            raise
        raise ValueError(f"{label(drive)}: its fusion.config record: {e}") from None
    given = set(imugrade.settings(table))  # an IMU grade's or datasheet keys' settings count as given
    derived = imugrade.sources(table)
    sources = {f: (f"{where}, {derived[f]}" if f in derived else where if f in given else "default")
               for f in FLAT_KEYS}
    sources["predictor"] = where if "predictor" in given else "default"
    if "lever_arm_b" not in given and imap.lever_arm_b is not None:
        cfg = cfg.replace(lever_arm_b=tuple(float(x) for x in imap.lever_arm_b), lever_arm_frame="rfu")
        sources["lever_arm_b"] = sources["lever_arm_frame"] = inputs_mod.TF_STATIC
    if outages:
        cfg = cfg.replace(outages=tuple(outages))
        sources["outages"] = "--outage"
    return Settings(cfg, imap, sources)


def drive_config(drive: DriveSpec) -> FusionConfig:
    """The drive's ``fusion.config`` metadata record (a simulated drive's scenario [fusion] table) as a
    FusionConfig; the defaults when the drive has none."""
    table = drive_table(drive)
    try:
        return fusion_config(table)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{label(drive)}: its fusion.config record: {e}") from None


def drive_table(drive: DriveSpec) -> dict[str, Any]:
    """The drive's ``fusion.config`` metadata record as a [fusion] table; ValueError naming the drive when a
    value is not one (damaged metadata)."""
    out = {}
    for k, v in read_metadata(drive).get("fusion.config", {}).items():
        try:
            out[k] = metavalue.load(v)
        except ValueError as e:
            raise ValueError(f"{label(drive)}: its fusion.config record, {k}: {e}") from None
    return out


def drive_mounting(drive: DriveSpec) -> calib.Mounting:
    """The mounting in the drive's calibration record (zeros when the drive has none, e.g. a foreign bag)."""
    toml = read_metadata(drive).get("calibration", {}).get("toml")
    return calib.Calibration.from_toml(toml).mounting if toml else calib.Mounting()


def estimate_installation(drive: DriveSpec, config: FusionConfig, inputs: InputMap) -> tuple[FusionConfig, dict]:
    """``fusion.installation``'s first pass over ``drive`` and the settings that apply it.

    Two reads: the IMU's time offset from its rate integral (stamps less the configured start value ``[fusion]
    imu_time_offset_s``) and the receiver's velocities; then ``kf`` without the vehicle aids and the forced
    outages (they would pull the attitude onto the nominal mounting), its IMU on the GPS's time, smoothed (RTS),
    and the mounting from its rows. The mounting used is the estimate and the configured one (``[fusion]
    mounting_rpy_deg``, else the drive's calibration record) weighted by their inverse variances, the configured
    sigma ``mounting_sigma_deg`` (all 0: a mounting nobody measured, the estimate alone); where the drive does not
    show one, the configured value and sigma stay. Memory grows by the rows (10 Hz) and the rate integral (50 Hz);
    the smoother's records go to a temporary file (5.5 kB per 0.1 s).

    Parameters
    ----------
    drive : the drive.
    config : the settings of the run (its aids, noise, start values).
    inputs : the drive's topics.

    Returns
    -------
    (config with ``imu_time_offset_s``, ``mounting_rpy_deg`` and ``mounting_sigma_deg`` replaced by what is used,
    the ``fuse --json`` keys: ``imu_time_offset_s``, ``imu_time_offset_sigma_s`` (s, the IMU's stamps late against
    the GPS's; the sigma None when not estimated), ``mounting_rpy_deg``, ``mounting_sigma_deg`` (IMU -> base_link,
    deg, the values used) and ``mounting_estimate_rpy_deg``, ``mounting_estimate_sigma_deg`` (the drive's own
    estimate, None when it shows none)).
    """
    start = config.sensor.imu_time_offset_s
    late_ns = int(round(start * 1e9))
    gyro = installation.GyroTrack()
    t_gps, v_gps = [], []
    for block in InputStream(drive, inputs, BLOCK_S):
        gyro.add(block.imu.t_ns - late_ns, block.imu.omega_ib_b, block.imu.f_b)
        t_gps.append(block.gps.t_ns)
        v_gps.append(block.gps.v_n)
    offset = installation.time_offset(gyro, np.concatenate(t_gps), np.concatenate(v_gps).reshape(-1, 3))
    late, late_sigma = (start + offset[0], offset[1]) if offset is not None else (start, None)
    config = config.replace(imu_time_offset_s=late)
    log = SmootherLog()
    engine = Engine(KF.name, config.replace(nhc=False, zupt=False, odometer=False, outages=()), log=log)
    parts = [engine.process(block.imu, block.gps)[0] for block in InputStream(drive, inputs, BLOCK_S)]
    parts.append(engine.finish()[0])
    mount = installation.mounting(smooth_solution(Solution.concat(parts), log),
                                  np.asarray(config.aids.odometer_lever_b, float))
    log.close()
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

    return config, {"imu_time_offset_s": late, "imu_time_offset_sigma_s": late_sigma,
                    "mounting_rpy_deg": rounded(used), "mounting_sigma_deg": rounded(used_sigma),
                    "mounting_estimate_rpy_deg": rounded(mount and mount[0]),
                    "mounting_estimate_sigma_deg": rounded(mount and mount[1])}


def calibration_mounting_rpy(mounting: calib.Mounting) -> np.ndarray:
    """The calibration's IMU mounting (``[mounting] imu_rpy_deg``: fixed-axis roll, pitch, yaw, REP-103) as
    ``[fusion] mounting_rpy_deg`` (C_bm = ``fusion.earth.euler_to_dcm(yaw, pitch, roll)``), deg (3,)."""
    if not any(mounting.imu_rpy_deg):
        return np.zeros(3)
    from scipy.spatial.transform import Rotation

    C_bm = Rotation.from_euler("xyz", mounting.imu_rpy_deg, degrees=True).as_matrix()
    yaw, pitch, roll = earth.dcm_to_euler(C_bm)
    return np.degrees([roll, pitch, yaw])


def fused_mounting(mounting: calib.Mounting, config: FusionConfig) -> calib.Mounting:
    """The mounting the fused file's ``/tf_static`` gives: the drive's, its IMU angles replaced by the ones the
    NHC and the odometer used (``[fusion] mounting_rpy_deg``) when those are not zero."""
    rpy = config.aids.mounting_rpy_deg
    if not any(rpy):
        return mounting
    from scipy.spatial.transform import Rotation

    roll, pitch, yaw = np.radians(rpy)
    C_bm = earth.euler_to_dcm(yaw, pitch, roll)
    return dataclasses.replace(mounting, imu_rpy_deg=Rotation.from_matrix(C_bm).as_euler("xyz", degrees=True))


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


def fuse(drive: DriveSpec, method: str, out: str | os.PathLike[str],
         config: FusionConfig | None = None, progress: Callable[[float], None] | None = None,
         smooth: bool = False, inputs: InputMap | None = None, force: bool = False, keep: bool = False,
         installation: dict[str, object] | None = None) -> FuseResult:
    """Fuse ``drive`` with ``method`` into ``out`` (MCAP); streaming, memory bounded by one block unless
    ``smooth`` (RTS backward pass after the drive). ``config`` None: ``drive_config(drive)``; ``inputs`` None:
    ``replay.inputs.resolve(drive)``. A drive of several files (``drive.files``) is fused once, across the file
    boundaries. Raises ``replay.solutions.Diverged`` (nothing past the first bad row written) when the
    solution turns NaN or inf. ``out`` must be new, unless ``force`` (``drive.outputs``). ``keep``: the rows
    written are also returned (``FuseResult.solution``), for a caller that scores them without reading ``out``
    back (``replay.solutions.read``); memory then grows by the rows, as with ``smooth``. ``installation``: the
    keys of :func:`estimate_installation`, written as the ``fusion.installation`` record (JSON values)."""
    outputs.check_new(out, force)
    cfg = config or drive_config(drive)
    imap = inputs or inputs_mod.resolve(drive)
    log = SmootherLog() if smooth else None
    spill = _RowSpill() if smooth else None
    odom = Odometry(method, fused_mounting(drive_mounting(drive), cfg))
    kept: list[Solution] = []
    span = [t for t in reader_topics(drive) if t.topic in imap.topics and t.count]
    t_first = min(t.first_ns for t in span)
    t_last = max(t.last_ns for t in span)
    rows = outages = 0
    stream = InputStream(drive, imap, BLOCK_S)
    hinf_note: dict[str, str] = {}
    meta = {"source": label(drive), "method": method, "config": repr(cfg.flat()), "smooth": "rts" if smooth else "no",
            "inputs": ", ".join(f"{k}={getattr(imap, k)}" for k in ("imu_topic", "fix_topic", "vel_topic",
                                                                      "imu_frame", "odom_topic"))}
    with contextlib.ExitStack() as workers:  # the predictor's worker, if the method has one; then the file

        def predictor(network: str, config: PredictorConfig) -> RemotePredictor:
            return RemotePredictor(workers.enter_context(Remote(lambda: OutagePredictor(network, config))))

        engine = Engine(method, cfg, log=log, make_predictor=predictor)  # its outage predictor trained in a worker
        rec = workers.enter_context(Recorder(out, flush_interval_s=None, fsync=False, force=force))
        rec.add_metadata("fusion", meta)
        if installation:
            rec.add_metadata("fusion.installation", {k: json.dumps(v) for k, v in installation.items()})

        def write_outages(items) -> None:
            nonlocal outages
            for o in items:
                rec.write(OUTAGE, max(o.start_ns, 1), messages.encode_outage(
                    o.start_ns, o.start_ns, o.end_ns, o.reason))
                outages += 1

        def take(sol: Solution, done) -> None:
            nonlocal rows
            if smooth:
                spill.add(sol)
                write_status(rec, method, sol)  # the forward pass's: what the filter knew at the row
            else:
                if keep:
                    kept.append(sol)
                write_solution(rec, method, sol)
                odom.write(rec, sol)
            write_outages(done)
            rows += len(sol.t_ns)

        for block in stream:
            take(*engine.process(block.imu, block.gps, block.odom))
            if progress:
                progress(min((block.t1_ns - t_first) / max(t_last - t_first, 1), 1.0))
        take(*engine.finish())
        if isinstance(engine.filter, hinf.HInfinityFilter):
            hinf_note = hinf.summary(engine.filter)
            rec.add_metadata("fusion.hinf", hinf_note)
        if smooth:
            sm = rts(log)
            for block in spill.blocks():
                smoothed = smooth_rows(block, sm, log)
                if keep:
                    kept.append(smoothed)
                write_solution(rec, method, smoothed)
                odom.write(rec, smoothed)
            log.close()
            spill.close()
        if odom.origin is not None:
            rec.add_metadata("fusion.map", odom.metadata())
    if progress:
        progress(1.0)
    return FuseResult(Path(out), method, rows, engine.updates, outages, stream.samples, engine.predicted,
                      stream.rate_hz, stream.gaps, stream.missing,
                      getattr(engine.filter, "raised", 0), engine.used("Stationary"), engine.alignment.note,
                      hinf_note or None, engine.used("Stationary", "zaru_skipped"),
                      odometer_summary(engine), Solution.concat(kept) if keep else None,
                      dict(engine.alignment.summary), tuple(stream.warnings()),
                      next((m.summary() for m in engine.measurements if hasattr(m, "summary")), None))


def odometer_summary(engine: Engine) -> dict[str, float] | None:
    """The wheel odometer's fitted scale factor and its sigma (``fusion.odometer.ScaleEstimator``), the epochs it
    updated at and those among them skipped as slip; None when the run had no odometer or no wheel speed."""
    odo = [p for m in engine.measurements for p in getattr(m, "parts", (m,)) if isinstance(p, measurements.Odometer)]
    if not odo or not odo[0].times:
        return None
    return {"scale": odo[0].scale.scale, "scale_sigma": odo[0].scale.sigma, "epochs": len(odo[0].times),
            "slip_skipped": len(odo[0].slip_skipped)}
