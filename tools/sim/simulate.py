"""``fieldlog sim``: make a drive the way the hardware would.

Truth -> sensor errors -> ADC counts -> DAQ frames and NMEA sentences -> serial reads with host clocks ->
the real acquisition pipeline -> MCAP, with ``/truth/*`` added from the simulator's side.

Rates: the DAQ runs at ``[clock] fs_hz`` (default: ``[imu] rate_hz``; the two must agree), the receiver at
``[gps] rate_hz`` (epochs at whole UTC seconds plus multiples of its period). The ``drive`` metadata records
both (``imu_rate_hz``, ``gps_rate_hz``), the ``timesync`` record the DAQ rate the pipeline used, and a
scenario's ``[fusion]`` table goes into the ``fusion.config`` record (one key each, Python literals), which
``fieldlog fuse`` and ``evaluate`` use when no ``--config`` is given (``tools.fuse_settings.drive_config``).
"""
from __future__ import annotations

import datetime as _dt
import gc
from contextlib import contextmanager
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from fieldlog.acquire import calib, daq, rows, timesync
from fieldlog.drive import messages, metavalue, outputs, recorder
from fieldlog.acquire.pipeline import Pipeline, PipelineConfig, RawRead, in_read_order
from fieldlog.tools.sim import clock as simclock
from fieldlog.tools.sim import sensors, trajectory, vehicle, vibration
from fieldlog.tools.sim.emit import GpsConfig, HostClock, gps_solution, nmea_bursts, pulse_errors, serial_reads

NS = 1_000_000_000
DAQ_BAUD = 921_600
FRAME_DELAY_S = 150e-6      # ADC conversion and framing before the frame starts on the wire
TRUTH_NAV_HZ = 100.0
TRUTH_BLOCK = 8192          # /truth/* messages encoded and written at a time (_write_blocks)
YOUNG_COLLECT = 10_000      # allocations between collections of the youngest generation (_collector_eased)
START_UTC = _dt.datetime(2026, 5, 4, 9, 30, 0, tzinfo=_dt.timezone.utc)


@dataclass
class SimResult:
    path: Path
    imu_samples: int
    gps_epochs: int
    reads: int
    counters: object


def drive_start_ns(seed: int) -> int:
    """Drive start in UTC ns: a fixed day, a seed-dependent sub-second offset (never on a whole second)."""
    frac = 0.137 + 0.7 * np.random.default_rng([seed, 7]).random()
    return int(START_UTC.timestamp()) * NS + int(frac * NS)


class _InTurn(Executor):
    """An executor that runs each call at once, on the caller's thread (``_beside`` on one CPU)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        out: Future = Future()
        try:
            out.set_result(fn(*args, **kwargs))
        except BaseException as e:  # noqa: BLE001 - raised by result(), as a thread pool's future does
            out.set_exception(e)
        return out


def _beside() -> Executor:
    """Where ``make_reads`` runs what needs no IMU truth: threads beside the caller when the process may use more
    than one CPU (numpy and the compiled kernels release the GIL, so they run at once), else in turn on the
    caller's thread (threads taking turns on one CPU only add their switches)."""
    from fieldlog.drive import reader

    return ThreadPoolExecutor(3) if reader.cpus() > 1 else _InTurn()


def make_reads(scenario: trajectory.Scenario, duration_s: float, seed: int, pps_mode: str | None = None,
               receiver: str | None = None, can: bool = False) -> tuple[list[RawRead], dict, int,
                                                                        simclock.ClockConfig, calib.Calibration]:
    """All raw reads of a simulated drive, sorted in host-monotonic order, plus the truth needed to score it
    and to write ``/truth/*`` (``write_truth``: ``nav`` is the truth at the times ``t_nav``, TRUTH_NAV_HZ).
    ``receiver`` ('nmea', 'ublox', 'novatel') overrides the scenario's ``[gps] receiver``; ``can``: the car's
    CAN bus on an SLCAN adapter too (port ``can``, ``sim.vehicle``)."""
    seeds = np.random.SeedSequence(seed).spawn(9)     # spawn(n)'s first children do not depend on n
    rng_clock, rng_imu, rng_gps, rng_nmea, rng_daq_reads, rng_gps_reads, rng_pulse, rng_can, rng_vib = (
        np.random.default_rng(s) for s in seeds)
    install, imu_table = sensors.Installation.split(scenario.imu)
    imu_cfg = sensors.ImuErrorConfig.from_dict(imu_table)
    can_on, car = vehicle.from_scenario(scenario.vehicle)
    can = can or can_on
    clock_d = dict(scenario.clock)
    if pps_mode:
        clock_d["pps_mode"] = pps_mode
    clock_d.setdefault("start_utc_ns", drive_start_ns(seed))
    clock_d.setdefault("fs_hz", imu_cfg.rate_hz)
    ccfg = simclock.ClockConfig.from_dict(clock_d)
    if ccfg.fs_hz != imu_cfg.rate_hz:
        raise ValueError(f"[clock] fs_hz = {ccfg.fs_hz:g} differs from [imu] rate_hz = {imu_cfg.rate_hz:g}")
    gps_cfg = GpsConfig.from_dict({**scenario.gps, **({"receiver": receiver} if receiver else {})})
    cal = calib.load_calibration(None)
    host = HostClock()
    t0_ns = ccfg.start_utc_ns
    truth = trajectory.generate(scenario, duration_s, seed)

    n = int(round(duration_s * ccfg.fs_hz))
    t_k = simclock.sample_times(n, ccfg, rng_clock)
    qerr_s = pulse_errors(int(duration_s) + 2, gps_cfg, rng_pulse)
    t_nav = np.arange(0.0, duration_s, 1.0 / TRUTH_NAV_HZ)
    with _beside() as pool:   # the sensor errors' draws, the nav truth, the GPS and CAN reads need no IMU truth
        draws = pool.submit(sensors.draw_errors, t_k, imu_cfg, rng_imu)
        nav = pool.submit(truth.evaluate, t_nav)
        gps_rngs = (rng_gps, rng_nmea, rng_gps_reads)
        gps = pool.submit(_gps_reads, truth, duration_s, ccfg, gps_cfg, qerr_s, host, gps_rngs)
        bus = pool.submit(vehicle.can_reads, truth, duration_s, host, t0_ns, rng_can, car) if can else None
        ts = truth.evaluate(t_k, pool)
        w_sensed, f_sensed = sensed(truth, t_k, ts, install, scenario.vibration, ccfg.fs_hz, rng_vib)
        counts, realised = sensors.apply_errors(draws.result(), w_sensed, f_sensed, imu_cfg, cal)
        pps, latch, latch_valid, edges_truth = simclock.pps_frames(t_k, ccfg, rng_clock, pulse_late_s=qerr_s)
        if not gps_cfg.pps_in_outage:
            valid, _ = gps_cfg.windows(t_k)
            pps &= valid
        k = np.arange(n, dtype=np.int64)
        temp_c = 25.0 + 3.0 * t_k / max(duration_s, 1.0)
        frames = daq.encode_frames(k, counts, pps, latch if ccfg.pps_mode == "latch" else None, temp_c)
        reads = serial_reads("daq", t_k + FRAME_DELAY_S, frames, daq.FRAME_SIZE, DAQ_BAUD, (0.002, 0.012), host,
                             t0_ns, rng_daq_reads)
        gps_reads, sol, utc_ns = gps.result()
        can_reads, vehicle_truth = bus.result() if bus is not None else ([], None)
    reads += gps_reads + can_reads
    reads = in_read_order(reads)
    truth_data = dict(truth=truth, t_k=t_k, ts=ts, t0_ns=t0_ns, realised=realised, edges=edges_truth,
                      gps=sol, gps_utc_ns=utc_ns, counts=counts, pps=pps, latch=latch,
                      temp_c=temp_c, vehicle=vehicle_truth, sensed=(w_sensed, f_sensed), install=install,
                      t_nav=t_nav, nav=nav.result())
    return reads, truth_data, t0_ns, ccfg, cal


def _gps_reads(truth: trajectory.Truth, duration_s: float, ccfg: simclock.ClockConfig, gps_cfg: GpsConfig,
               qerr_s: np.ndarray, host: HostClock,
               rngs: tuple[np.random.Generator, ...]) -> tuple[list[RawRead], dict | None, np.ndarray]:
    """The GPS port's reads of a drive of ``duration_s`` s (``make_reads``), the receiver's solutions at its
    epochs (``gps_solution``; None without an epoch) and the epochs' UTC times (ns). ``qerr_s``: the pulses'
    quantisation errors (s, ``pulse_errors``); ``rngs``: the solutions', the sentences' and the reads' draws."""
    rng_gps, rng_nmea, rng_reads = rngs
    t0_ns, period_ns = ccfg.start_utc_ns, gps_cfg.epoch_period_ns()
    first_ns = ccfg.first_utc_s() * NS
    n_epochs = max(int((t0_ns + duration_s * NS - first_ns) // period_ns) + 1, 0)
    utc_ns = first_ns + period_ns * np.arange(n_epochs, dtype=np.int64)
    rel_s = (utc_ns // NS - t0_ns / NS) + (utc_ns % NS) / NS
    if not len(utc_ns):
        return [], None, utc_ns
    sol = gps_solution(truth, rel_s, gps_cfg, rng_gps)
    starts, sentences = nmea_bursts(sol, utc_ns, gps_cfg, rng_nmea, qerr_s, utc_ns + gps_cfg.clock_offset_ns(rel_s))
    starts = starts + rel_s[0]
    keep = starts < duration_s
    sentences = [s for s, kk in zip(sentences, keep) if kk]
    if not sentences:
        return [], sol, utc_ns
    return serial_reads("gps", starts[keep], sentences, None, gps_cfg.baud, (0.001, 0.004), host, t0_ns,
                        rng_reads), sol, utc_ns


def sensed(truth: trajectory.Truth, t_k: np.ndarray, ts: trajectory.TruthSample, install: sensors.Installation,
           vibration_table: dict | None, rate_hz: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The rate (rad/s) and specific force (m/s^2), (n, 3), the IMU senses at its sample times t_k (s): the car's
    (``ts``, body RFU) delayed, shaken by the ``[vibration]`` table's vibration (None: none), in the IMU's axes
    through its filter (``sensors.Installation``); ``ts``'s own without either."""
    if not install.active and vibration_table is None:
        return ts.omega_ib_b, ts.f_b
    t_s = t_k - install.transport_s(rate_hz)
    at = truth.evaluate(t_s) if install.delay_s > 0.0 else ts
    w, f = at.omega_ib_b, at.f_b
    if vibration_table is not None:
        dw, df = vibration.vibration(t_s, np.linalg.norm(at.v_n, axis=1),
                                     vibration.VibrationConfig.from_dict(vibration_table), rng)
        w, f = w + dw, f + df
    return install.sense(w, f, rate_hz)


def truth_metadata(truth_data: dict, scenario: trajectory.Scenario) -> dict[str, str]:
    """The ``sim.truth`` record of a drive with the car's imperfections (``sensors.Installation``, ``[vibration]``,
    ``[vehicle]``): the true IMU mounting [roll, pitch, yaw] deg to ``base_link`` (the drive's /tf_static keeps
    the nominal zero), the IMU delay s and filter corner Hz, the vibration table's figures, each wheel's true
    speed scale (FL, FR, RL, RR: reported / true - 1, slip aside); empty for a drive without them."""
    install = truth_data["install"]
    if not install.active and scenario.vibration is None and not scenario.vehicle:
        return {}
    vt = truth_data.get("vehicle")
    vib = scenario.vibration
    out = {"imu_mounting_rpy_deg": list(install.mounting_rpy_deg), "imu_delay_s": install.delay_s,
           "imu_filter_hz": install.filter_hz,
           "vibration": None if vib is None else vibration.VibrationConfig.from_dict(vib).__dict__,
           "wheel_speed_scale": None if vt is None else [float(x) for x in vt["scale"]]}
    return {k: metavalue.dump(v) for k, v in out.items()}


def write_truth(rec: recorder.Recorder, truth_data: dict) -> None:
    """``/truth/imu`` at every true sample time, and the true trajectory at TRUTH_NAV_HZ, of ``make_reads``'
    truth."""
    t0_ns, t_k, ts = truth_data["t0_ns"], truth_data["t_k"], truth_data["ts"]
    t_ns = t0_ns + np.round(t_k * NS).astype(np.int64)
    _write_imu(rec, "/truth/imu", t_ns, ts.omega_ib_b, ts.f_b)
    t_nav, nav = truth_data["t_nav"], truth_data["nav"]
    tn_ns = t0_ns + np.round(t_nav * NS).astype(np.int64)
    lat_deg, lon_deg = np.degrees(nav.lat), np.degrees(nav.lon)
    _write_blocks(rec, "/truth/fix", tn_ns, lambda s: messages.encode_navsatfix(
        tn_ns[s], lat_deg[s], lon_deg[s], nav.h[s], frame_id="imu"))
    # ENU vectors in a drive: the frame of the point they belong to (local ENU axes), as ROS GPS drivers do
    _write_blocks(rec, "/truth/vel", tn_ns, lambda s: messages.encode_twist(tn_ns[s], nav.v_n[s], frame_id="imu"))
    _write_blocks(rec, "/truth/attitude", tn_ns, lambda s: messages.encode_quaternion(
        tn_ns[s], nav.q[s], frame_id="imu"))
    r = truth_data["realised"]  # the sensor error less its white noise, at the nav rate (sim.sensors.imu_counts)
    k = np.clip(np.searchsorted(t_k, t_nav), 0, len(t_k) - 1)
    bias = {}
    for x, true in zip(("gyro", "accel"), truth_data["sensed"]):
        coloured = r[f"{x}_coloured"][k] if f"{x}_coloured" in r else 0.0
        bias[x] = r[f"{x}_bias"][k] + coloured + rows.dot(true[k], (sensors.gain(r, x) - np.eye(3)).T)
    _write_imu(rec, "/truth/imu_bias", tn_ns, bias["gyro"], bias["accel"])
    vt = truth_data.get("vehicle")
    if vt is not None:   # the rear axle centre's forward speed at each wheel-speed sample instant
        tv_ns = t0_ns + np.round(vt["t_s"] * NS).astype(np.int64)
        lin = np.zeros((len(tv_ns), 3))
        lin[:, 0] = vt["forward"]
        _write_blocks(rec, "/truth/vehicle/twist", tv_ns, lambda s: messages.encode_twist(
            tv_ns[s], lin[s], frame_id="base_link"))


def _write_imu(rec: recorder.Recorder, topic: str, t_ns: np.ndarray, omega_b: np.ndarray, f_b: np.ndarray) -> None:
    """Imu messages of rates ``omega_b`` (rad/s) and specific forces ``f_b`` (m/s^2), (n, 3), at ``t_ns`` (UTC ns),
    no covariances, to ``topic`` (``_write_blocks``)."""
    zero = np.zeros(9)
    _write_blocks(rec, topic, t_ns, lambda s: messages.encode_imu(t_ns[s], omega_b[s], f_b[s], zero, zero,
                                                                  frame_id="imu"))


def _write_blocks(rec: recorder.Recorder, topic: str, t_ns: np.ndarray,
                  encode: Callable[[slice], messages.Packed]) -> None:
    """Messages of ``topic`` at ``t_ns`` (UTC ns), ``encode(s)`` the payloads of ``t_ns[s]``: encoded and written
    ``TRUTH_BLOCK`` at a time, so the encoder fills memory the allocator hands back rather than a fresh array of
    all of them; ``write_batch`` fills the chunks the same however its messages come."""
    for i in range(0, len(t_ns), TRUTH_BLOCK):
        s = slice(i, i + TRUTH_BLOCK)
        rec.write_batch(topic, t_ns[s], encode(s))


def fusion_metadata(table: dict) -> dict[str, str]:
    """A scenario's [fusion] table as the ``fusion.config`` metadata record (checked: a bad key raises
    ConfigError naming it)."""
    if not table:
        return {}
    from fieldlog.tools.fuse_settings import fusion_config

    fusion_config(table)
    return {k: metavalue.dump(v) for k, v in table.items()}


@contextmanager
def _collector_eased() -> Iterator[None]:
    """Until exit, the objects alive on entry (the modules' functions, classes and tables) moved into the
    collector's permanent generation (``gc.freeze``), and the youngest generation collected after
    ``YOUNG_COLLECT`` allocations rather than the default's few hundred. A simulation allocates enough objects
    to set off full collections, which would walk all of those every time and find no garbage among them: each
    collection walks only the objects made since. And most of what it allocates lives to the end (its reads,
    hundreds of thousands of tuples), so each young collection finds little to free and moves the rest on,
    whose walks set off the older generations'. On exit the thresholds are the caller's again, and the frozen
    objects collectable, unless the caller froze objects itself (``gc.unfreeze`` cannot tell its objects from
    ours)."""
    caller_froze = gc.get_freeze_count() > 0
    thresholds = gc.get_threshold()
    gc.freeze()
    gc.set_threshold(max(YOUNG_COLLECT, thresholds[0]), *thresholds[1:])
    try:
        yield
    finally:
        gc.set_threshold(*thresholds)
        if not caller_froze:
            gc.unfreeze()


def simulate(scenario_name: str, duration_s: float | None, seed: int, out: str | Path,
             pps_mode: str | None = None, progress: Callable[[float], None] | None = None,
             receiver: str | None = None, sync_settings: dict | None = None, can: bool = False,
             force: bool = False, mounting_rpy_deg: tuple[float, float, float] | None = None,
             imu_delay_s: float | None = None) -> SimResult:
    """Simulate a drive into ``out`` (MCAP). ``duration_s=None`` takes the scenario's default; ``sync_settings``:
    more TimeSyncConfig settings for the pipeline (e.g. ``{"pulse_error": False}``); ``can``: with the car's CAN
    bus (``/raw/can``, ``/vehicle/*``, ``/truth/vehicle/twist``; also when the scenario's ``[vehicle] can``);
    ``mounting_rpy_deg`` (deg) and ``imu_delay_s`` (s) replace the scenario's ``[imu]`` ones. ``out`` must be new,
    unless ``force`` (``drive.outputs``)."""
    with _collector_eased():
        outputs.check_new(out, force)
        scenario = trajectory.load_scenario(scenario_name)
        over = {k: v for k, v in (("mounting_rpy_deg", mounting_rpy_deg), ("delay_s", imu_delay_s)) if v is not None}
        if over:
            scenario = replace(scenario, imu={**scenario.imu, **over})
        can = can or vehicle.from_scenario(scenario.vehicle)[0]
        duration_s = float(duration_s or scenario.duration_s)
        fusion_meta = fusion_metadata(scenario.fusion)
        reads, truth_data, t0_ns, ccfg, cal = make_reads(scenario, duration_s, seed, pps_mode, receiver, can)
        gps_cfg = GpsConfig.from_dict({**scenario.gps, **({"receiver": receiver} if receiver else {})})
        meta = {"source": "fieldlog sim", "scenario": scenario.name, "seed": str(seed),
                "duration_s": repr(duration_s), "pps_mode": ccfg.pps_mode,
                "drive_start_utc_ns": str(t0_ns), "imu_rate_hz": repr(float(ccfg.fs_hz)),
                "gps_rate_hz": repr(float(gps_cfg.rate_hz)), "gps_receiver": gps_cfg.receiver}
        sync_cfg = timesync.TimeSyncConfig.from_dict({"pps_mode": ccfg.pps_mode, "fs_hz": ccfg.fs_hz,
                                                      **(sync_settings or {})})
        with recorder.Recorder(out, flush_interval_s=None, fsync=False, metadata=meta, force=force,
                               behind=True) as rec:
            pipe = Pipeline(rec, cal, sync_cfg, PipelineConfig(can=vehicle.bus_config() if can else None))
            for name, d in pipe.metadata().items():
                rec.add_metadata(name, d)
            if fusion_meta:
                rec.add_metadata("fusion.config", fusion_meta)
            sim_truth = truth_metadata(truth_data, scenario)
            if sim_truth:
                rec.add_metadata("sim.truth", sim_truth)
            write_truth(rec, truth_data)   # before /imu: drivestats pairs /imu with it as /imu comes
            pipe.feed_reads(reads, (lambda i: progress(i / len(reads))) if progress else None)
            pipe.finish()
            rec.add_metadata("acquire.counters", pipe.counters_metadata())
        if progress:
            progress(1.0)
        return SimResult(Path(out), pipe.counters.imu_samples, pipe.counters.gps_epochs, len(reads), pipe.counters)
