"""Alignment and initial uncertainty for every IMU grade, the still detector (creeping and stops) and
the datasheet units of the IMU grades.

Drives: ``figure8-tactical`` (tactical IMU, RTK, the car creeps 1 m with a 3-degree turn as it leaves the
parking spot), figure8 variants with the MEMS grades, and ``creep`` (creeping through slow turns, real stops).
The outage drift is held against an INS error budget computed from the grade's figures (``_budget``)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire.config import ConfigError
from fieldlog.fusion import earth, imugrade
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.errmodel import BG
from fieldlog.drive import reader
from fieldlog.replay.inputs import InputSpec, InputStream, resolve
from fieldlog.tools.evaluation.evaluate import (attitude_errors, attitudes, heading_at_starts, outage_error_series,
                                                rms_columns)
from fieldlog.tools.fuse import BLOCK_S, fuse
from fieldlog.tools.fuse_settings import drive_config, fusion_config
from fieldlog.tools.sim.emit import GpsConfig
from fieldlog.tools.sim.sensors import ImuErrorConfig, flicker_noise
from fieldlog.tools.sim.simulate import simulate

NS = 1_000_000_000
G = 9.80665
TACTICAL_OUTAGES = ((630.0, 60.0), (720.0, 60.0))  # 60 s, after 10 minutes of driving (the car leaves at 30 s)
MEMS_S = 300.0
MEMS_OUTAGE = ((200.0, 60.0),)
SHORT_S, SHORT_SEEDS, SHORT_OUTAGE = 300.0, (1, 2, 3), ((170.0, 60.0),)


def _scenario(tmp: Path, name: str, body: str) -> Path:
    p = tmp / f"{name}.toml"
    p.write_text(f'extends = "figure8"\nname = "{name}"\n{body}')
    return p


@pytest.fixture(scope="module")
def tactical(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("tactical") / "tactical.mcap"
    simulate("figure8-tactical", None, 1, path)
    return path


@pytest.fixture(scope="module")
def tactical_short(tmp_path_factory) -> list[Path]:
    """figure8-tactical cut to SHORT_S, seeds 1-3 (the configured start against the aligned one)."""
    tmp = tmp_path_factory.mktemp("tactical_short")
    paths = [tmp / f"s{seed}.mcap" for seed in SHORT_SEEDS]
    for seed, path in zip(SHORT_SEEDS, paths):
        simulate("figure8-tactical", SHORT_S, seed, path)
    return paths


@pytest.fixture(scope="module")
def creep(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("creep") / "creep.mcap"
    simulate("creep", None, 1, path)
    return path


@pytest.fixture(scope="module", params=["table2-mems", "s000-mems"])
def mems(request, tmp_path_factory) -> tuple[str, Path]:
    tmp = tmp_path_factory.mktemp(request.param)
    sc = _scenario(tmp, request.param, f'[imu]\ngrade = "{request.param}"\n'
                   f'[fusion]\nimu = "{request.param}"\nnhc = false\nzupt = false\n')
    path = tmp / "drive.mcap"
    simulate(str(sc), MEMS_S, 2, path)
    return request.param, path


def _t0(drive: Path) -> int:
    return min(t.first_ns for t in reader.topics(drive) if t.topic == "/imu")


def _windows(drive: Path, outages) -> list[tuple[int, int]]:
    t0 = _t0(drive)
    return [(t0 + int(s * NS), t0 + int((s + n) * NS)) for s, n in outages]


def _budget(grade: str, fused: Path, method: str, w0: int, t: float) -> float:
    """1-sigma horizontal position error per axis (m) of the free INS t s after w0, from the grade's figures
    (fusion.imugrade: what the filter is given) and the filter's own sigmas at w0, in quadrature:
    position sigma; velocity sigma x t; level sigma: g phi t^2/2; heading sigma x speed x t; accel bias (the
    instability plus its random walk over t) t^2/2; VRW t^1.5/sqrt(3); gyro bias (the instability) g b t^3/6
    and v b t^2/2; ARW g N t^2.5/sqrt(20). Uncorrelated terms: a budget, not a bound."""
    s = imugrade.grade(grade).filter_settings()
    f = {k: reader.read_topic(fused, f"/fusion/{method}/{k}") for k in ("std", "attitude_std", "vel")}
    j = int(np.searchsorted(f["std"]["log_time_ns"], w0))
    sd_p = float(np.max(f["std"]["xyz"][j, :2]))
    sd_v = math.sqrt(float(np.max(f["vel"]["covariance"][j].reshape(6, 6)[[0, 1], [0, 1]])))
    sd_level, sd_head = float(np.max(f["attitude_std"]["xyz"][j, :2])), float(f["attitude_std"]["xyz"][j, 2])
    speed = float(np.hypot(*f["vel"]["v_n"][j, :2]))
    ba = (s["accel_bias_rw_ug_rts"] * math.sqrt(t) + imugrade.grade(grade).accel_bias_instability_ug) * 1e-6 * G
    bg = math.radians(s["init_gyro_bias_sigma_dps"])
    vrw = s["accel_noise_ug_rthz"] * 1e-6 * G
    arw = math.radians(s["gyro_noise_dps_rthz"])
    terms = [sd_p, sd_v * t, G * sd_level * t * t / 2, sd_head * speed * t, ba * t * t / 2,
             vrw * t ** 1.5 / math.sqrt(3), G * bg * t ** 3 / 6, speed * bg * t * t / 2, G * arw * t ** 2.5 / math.sqrt(20)]
    return math.sqrt(sum(x * x for x in terms))


def _attitudes(drive: Path, fused: Path, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """evaluate.attitudes with the time in s from the first IMU sample."""
    t, C_s, C_t, sd = attitudes(drive, fused, method)
    return (t - _t0(drive)) * 1e-9, C_s, C_t, sd


def _heading_series(drive: Path, fused: Path, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s from the first IMU sample, heading error deg, heading sigma deg) of every solution row."""
    t, C_s, C_t, sd = _attitudes(drive, fused, method)
    h_s, h_t = earth.dcm_to_euler(C_s)[0], earth.dcm_to_euler(C_t)[0]
    err = np.degrees((h_s - h_t + np.pi) % (2 * np.pi) - np.pi)
    return t, err, np.degrees(sd[:, 2])


def _phi_z(drive: Path, fused: Path, method: str) -> tuple[np.ndarray, np.ndarray]:
    """(t_s from the first IMU sample, attitude error phi E, N, U over its sigma (n, 3))."""
    t, phi, sd = attitude_errors(drive, fused, method)
    return (t - _t0(drive)) * 1e-9, phi / np.maximum(sd, 1e-12)


def _outage_check(drive: Path, fused: Path, grade: str, outages) -> tuple[float, list[float], list[float]]:
    """2D RMS in the outages, per window the max 2D drift and its budget (2D: sqrt(2) x the per-axis budget)."""
    win = _windows(drive, outages)
    t, e = outage_error_series(drive, fused, "kf", win)
    rms = rms_columns(e)
    h = np.hypot(e[:, 0], e[:, 1])
    drift = [float(h[(t >= a) & (t < b)].max()) for a, b in win]
    budget = [math.sqrt(2.0) * _budget(grade, fused, "kf", a, n) for (a, _), (_, n) in zip(win, outages)]
    return math.hypot(rms[0], rms[1]), drift, budget


def test_tactical_rtk_creeping_pullaway(tactical, tmp_path):
    """Tactical IMU + RTK, the car creeps and turns as it pulls away, kf with the
    grade's figures only and aids off: under 0.5 m 2D RMS in 60 s outages after 10 minutes; the heading sigma
    covers the heading error at every outage start (3 sigma); each outage's drift within 3x the budget. The
    heading is gyrocompassed from the trimmed static start (the creep is not in it)."""
    cfg = drive_config(tactical).replace(outages=TACTICAL_OUTAGES)
    assert cfg.sensor.imu == "tactical" and not cfg.aids.nhc and not cfg.aids.zupt
    out = tmp_path / "kf.mcap"
    r = fuse(tactical, "kf", out, cfg)
    assert r.alignment.startswith("heading by gyrocompassing"), r.alignment
    rms2d, drift, budget = _outage_check(tactical, out, "tactical", TACTICAL_OUTAGES)
    assert rms2d < 0.5, rms2d
    for d, b in zip(drift, budget):
        assert d < 3.0 * b, (drift, budget)
    err, sig = heading_at_starts(tactical, out, "kf", _windows(tactical, TACTICAL_OUTAGES))
    assert np.all(np.abs(err) <= 3.0 * sig), (err, sig)
    t, e, s = _heading_series(tactical, out, "kf")
    assert np.mean(np.abs(e) <= 3.0 * s) > 0.95  # throughout the drive, not only at the starts


def test_mems_grades(mems, tmp_path):
    """The same for the MEMS grades on a 300 s figure8 (aids off, one 60 s outage at 200 s): heading within 3
    sigma at the outage start, drift within 3x the budget."""
    grade, drive = mems
    cfg = drive_config(drive).replace(outages=MEMS_OUTAGE)
    assert cfg.sensor.imu == grade
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, cfg)
    assert r.alignment.startswith("heading from the GPS course"), r.alignment  # MEMS cannot see the Earth rate
    _, drift, budget = _outage_check(drive, out, grade, MEMS_OUTAGE)
    assert drift[0] < 3.0 * budget[0], (drift, budget)
    err, sig = heading_at_starts(drive, out, "kf", _windows(drive, MEMS_OUTAGE))
    assert abs(err[0]) <= 3.0 * sig[0], (err, sig)


def test_mems_attitude_sigma_covers_the_error(mems, tmp_path):
    """Honest attitude sigma on the MEMS grades (aids off, GPS only, one 60 s outage): from 100 s on, the tilt
    (phi E, N) and heading (phi U) errors are within 3 sigma at >= 95 % of the rows and within 1 sigma at 40-97 %
    (68 % if honest; one 300 s drive holds a few independent samples of a heading error). With the gyro bias
    random walk the flicker bias instability needs (fusion.imugrade, matched over 60 s) rather than the 2e-4
    deg/s/sqrt(s) before, figure8 seeds 1-5 went from 62-86 % to 100 % of the heading within 3 sigma."""
    grade, drive = mems
    out = tmp_path / "kf.mcap"
    fuse(drive, "kf", out, drive_config(drive).replace(outages=MEMS_OUTAGE))
    t, z = _phi_z(drive, out, "kf")
    z = np.abs(z[t > 100.0])
    in1, in3 = np.mean(z <= 1.0, axis=0), np.mean(z <= 3.0, axis=0)
    assert np.all(in3 >= 0.95), (grade, in1, in3)
    assert np.all((in1 >= 0.4) & (in1 <= 0.97)), (grade, in1, in3)


@pytest.mark.parametrize("offset_deg", [2.0, 10.0, 30.0])
def test_initial_heading_error_converges_and_sigma_covers_it(mems, offset_deg, tmp_path):
    """Initial-error sweep: the config's initial attitude with the heading off by 2, 10, 30 deg and that offset
    as its sigma. From 60 s after the alignment the heading error is as small as with the normal alignment (the
    GPS course): its largest value at most 1.5x that run's plus 0.25 deg; the sigma covers the error (3 sigma)
    at 95 % of the rows throughout."""
    grade, drive = mems
    if grade != "table2-mems":
        pytest.skip("one grade is enough for the sweep")
    base = drive_config(drive)
    fuse(drive, "kf", tmp_path / "ref.mcap", base)
    t, e_ref, _ = _heading_series(drive, tmp_path / "ref.mcap", "kf")
    ref = float(np.abs(e_ref[t > t[0] + 60.0]).max())
    cfg = base.replace(init_attitude_deg=(0.0, 0.0, 45.0 + offset_deg),  # figure8 parks at 45 deg, level
                  init_heading_sigma_deg=offset_deg)
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, cfg)
    assert "init_attitude_deg" in r.alignment
    t, e, s = _heading_series(drive, out, "kf")
    assert abs(e[0] - offset_deg) < 1.0  # the offset is there at the start ...
    late = float(np.abs(e[t > t[0] + 60.0]).max())
    assert late < 1.5 * ref + 0.25, (late, ref)  # ... and gone a minute later
    assert np.mean(np.abs(e) <= 3.0 * s) > 0.95


def _true_start(drive: Path) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """The true position (lat deg, lon deg, h m), velocity ENU (m/s) and attitude (roll, pitch, heading deg) at the
    drive's first IMU sample (the truth's rows are 100 Hz; the drive starts standing)."""
    t0 = _t0(drive)
    fx, tv, ta = (reader.read_topic(drive, f"/truth/{k}") for k in ("fix", "vel", "attitude"))
    j = int(np.searchsorted(fx["log_time_ns"], t0))
    h, p, r = np.degrees(earth.dcm_to_euler(earth.quat_to_dcm(ta["q_xyzw"][j])))
    return ((float(fx["lat_deg"][j]), float(fx["lon_deg"][j]), float(fx["alt_m"][j])), tuple(map(float, tv["v_n"][j])),
            (float(r), float(p), float(h)))


def test_configured_start_tactical(tactical_short, tmp_path):
    """The initial state from the config (position, velocity, attitude and
    their sigmas) starts the INS at the first IMU sample. Given the truth plus a draw within the sigmas, on the
    tactical RTK drive (300 s, seeds 1-3; the car stands 30 s, creeps and turns, pulls away): the heading sigma
    covers the error (3 sigma) at 99 % of the rows of all seeds and at 98 % of each seed's, and at least 40 %
    within 1 sigma; the 2D RMS in a 60 s outage is no worse than the aligned start's, within twice the standard
    error of the per-seed differences plus a tenth of the aligned start's spread over the seeds."""
    sd_pos, sd_vel, sd_level, sd_head = 0.05, 0.01, 0.05, 0.1  # m, m/s, deg: a surveyed spot, the last heading
    rng = np.random.default_rng(18)
    within1, within3, rms = [], [], {"aligned": [], "configured": []}
    for drive in tactical_short:
        base = drive_config(drive).replace(outages=SHORT_OUTAGE)
        (lat, lon, h), v, (roll, pitch, head) = _true_start(drive)
        e = rng.standard_normal(6)
        de, dn = e[0] * sd_pos, e[1] * sd_pos  # m east, north
        cfg = base.replace(init_position_llh=(lat + math.degrees(dn / 6.378e6),
                                               lon + math.degrees(de / (6.378e6 * math.cos(math.radians(lat)))),
                                               h + e[2] * sd_pos),
                      init_position_sigma_m=sd_pos, init_velocity_enu=v, init_vel_sigma_mps=sd_vel,
                      init_attitude_deg=(roll + e[3] * sd_level, pitch + e[4] * sd_level, head + e[5] * sd_head),
                      init_level_sigma_deg=sd_level, init_heading_sigma_deg=sd_head)
        for name, c in (("aligned", base), ("configured", cfg)):
            out = tmp_path / f"{drive.stem}_{name}.mcap"
            r = fuse(drive, "kf", out, c)
            assert ("initial state from the config" in r.alignment) == (name == "configured"), r.alignment
            win = _windows(drive, SHORT_OUTAGE)
            _, err = outage_error_series(drive, out, "kf", win)
            rms[name].append(float(np.hypot(*rms_columns(err)[:2])))
            if name == "configured":
                _, e_h, s_h = _heading_series(drive, out, "kf")
                within1.append(np.abs(e_h) <= s_h)
                within3.append(np.abs(e_h) <= 3.0 * s_h)
    share3 = [float(np.mean(w)) for w in within3]
    pooled3, pooled1 = float(np.mean(np.concatenate(within3))), float(np.mean(np.concatenate(within1)))
    assert pooled3 >= 0.99 and min(share3) >= 0.98, (pooled3, share3)
    assert pooled1 >= 0.4, pooled1  # 68 % if Gaussian; lower: minutes near 1-2 sigma after the pull-away
    d = np.array(rms["configured"]) - np.array(rms["aligned"])
    margin = 2.0 * d.std(ddof=1) / math.sqrt(len(d)) + 0.1 * float(np.std(rms["aligned"], ddof=1))
    assert d.mean() <= margin, rms


def test_perfect_imu_initial_bias_and_heading_sigma(tactical_short, tmp_path):
    """The tactical RTK drives (300 s, seeds 1-3: the car stands 30 s, creeps 1 m with a 3-degree turn, pulls away)
    fused from the perfect IMU (/truth/imu): only the GPS errs, so the filter's sigmas must hold. The initial gyro
    bias is the static mean minus the Earth rate through the static interval's attitude: 0 here, within a tenth of
    its sigma (through the aligned attitude, 3 deg further on, the Earth rate leaks into the bias by several
    sigma, and the heading then sits off by over 2 sigma for minutes). From 60 s after the
    alignment, the heading error is within 3 sigma at 99 % of the rows of every seed and within 1 sigma at
    half of all rows (68 % if Gaussian)."""
    within1, within3 = [], []
    for drive in tactical_short:
        inputs = resolve(drive, InputSpec(imu_topic="/truth/imu"))
        eng = Engine("kf", drive_config(drive))
        for block in InputStream(drive, inputs, BLOCK_S):
            eng.process(block.imu, block.gps)
            if eng.filter is not None:
                break
        sd_bg = np.sqrt(np.diag(eng.filter.covariance)[BG])
        assert np.all(np.abs(eng.bg) <= 0.1 * sd_bg), (drive.stem, np.degrees(eng.bg) * 3600, np.degrees(sd_bg) * 3600)
        out = tmp_path / f"{drive.stem}_truth_imu.mcap"
        fuse(drive, "kf", out, drive_config(drive), inputs=inputs)
        t, e, s = _heading_series(drive, out, "kf")
        late = t > t[0] + 60.0  # solutions start at the alignment
        within1.append(np.abs(e[late]) <= s[late])
        within3.append(np.abs(e[late]) <= 3.0 * s[late])
    share3 = [float(np.mean(w)) for w in within3]
    share1 = [float(np.mean(w)) for w in within1]
    assert min(share3) >= 0.99, share3
    assert float(np.mean(np.concatenate(within1))) >= 0.5, share1


def _no_static_run(tmp: Path, scenario: str, seconds: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simulate the scenario (TOML text) and fuse it with kf: it has no static start; its heading series."""
    sc = tmp / "nostatic.toml"
    sc.write_text(scenario)
    drive = tmp / "drive.mcap"
    simulate(str(sc), seconds, seed, drive)
    out = tmp / "kf.mcap"
    r = fuse(drive, "kf", out, drive_config(drive))
    assert r.alignment.endswith("no static start)"), r.alignment
    return _heading_series(drive, out, "kf")


@pytest.fixture(scope="module")
def tactical_reference(tactical_short, tmp_path_factory) -> tuple[Path, float, float]:
    """The aligned start on the first short tactical drive: (drive, its largest heading error from 60 s after the
    alignment on, deg; 3x its median heading sigma there, deg: the margin of the sweep)."""
    drive = tactical_short[0]
    out = tmp_path_factory.mktemp("tactical_ref") / "kf.mcap"
    fuse(drive, "kf", out, drive_config(drive))
    t, e, s = _heading_series(drive, out, "kf")
    late = t > t[0] + 60.0
    return drive, float(np.abs(e[late]).max()), 3.0 * float(np.median(s[late]))


@pytest.mark.parametrize("offset_deg", [2.0, 10.0, 30.0])
def test_tactical_initial_heading_error_converges_and_sigma_covers_it(tactical_reference, offset_deg, tmp_path):
    """Initial-error sweep on the tactical IMU with RTK: the config's initial attitude with the
    heading off by 2, 10, 30 deg and that offset as its sigma, on a drive that stands 30 s, creeps 1 m with a
    3-degree turn and pulls away. From 60 s after the alignment the heading error is as small as the aligned
    start's (gyrocompassing): its largest value at most 1.5x that run's plus 3 of that run's sigmas; the sigma
    covers the error (3 sigma) at 99 % of the rows throughout."""
    drive, ref, margin = tactical_reference
    cfg = drive_config(drive).replace(init_attitude_deg=(0.0, 0.0, 45.0 + offset_deg),
                  init_heading_sigma_deg=offset_deg)
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, cfg)
    assert "init_attitude_deg" in r.alignment
    t, e, s = _heading_series(drive, out, "kf")
    assert abs(e[0] - offset_deg) < 0.1 * offset_deg  # the offset is there at the start (3 deg turned since) ...
    late = float(np.abs(e[t > t[0] + 60.0]).max())
    assert late < 1.5 * ref + margin, (late, ref, margin)  # ... and gone a minute later
    assert np.mean(np.abs(e) <= 3.0 * s) >= 0.99


def test_tactical_no_static_start(tactical_reference, tmp_path):
    """The tactical RTK drive with no static start (it creeps and turns from the first sample, then pulls
    away): no levelling, no static gyro mean, no gyrocompassing; the heading from the course with its sigma.
    The sigma covers the heading error (3 sigma) at 99 % of the rows; from 60 s after the alignment the error is
    at most 1.5x the aligned start's (30 s static) plus 3 of its sigmas."""
    _, ref, margin = tactical_reference
    t, e, s = _no_static_run(tmp_path, 'extends = "figure8-tactical"\nname = "nostatic"\n[motion]\nstatic_s = 0.0\n',
                             200.0, 1)
    assert np.mean(np.abs(e) <= 3.0 * s) >= 0.99
    late = float(np.abs(e[t > t[0] + 60.0]).max())
    assert late < 1.5 * ref + margin, (late, ref, margin)


def test_no_static_start(tmp_path):
    """A drive that moves off at once: no static interval, so no levelling and no gyro bias from it; the
    heading from the course with its sigma, which covers the error over the first 120 s (alignment and
    convergence). Later, in the loops, the Table 2 MEMS's 1000 ppm scale factor (not a filter state) can take
    the heading error past 3 sigma (1.3 deg against 0.34 deg at 140 s on this seed): not the alignment's."""
    t, e, s = _no_static_run(tmp_path, 'extends = "figure8"\nname = "nostatic"\n[motion]\nstatic_s = 0.0\n'
                             '[fusion]\nnhc = false\nzupt = false\n', 150.0, 3)
    first = t < t[0] + 120.0
    assert np.mean(np.abs(e[first]) <= 3.0 * s[first]) > 0.95
    assert np.all(np.abs(e[t > t[0] + 60.0]) < 1.5)


def test_still_detector_creep_and_stops(creep, tmp_path):
    """On a drive that creeps at 0.2 m/s through slow turns (slow enough to pass a GPS speed test alone),
    no stationary update while the car moves (over 2 cm/s anywhere in the interval); every real stop after the
    alignment gets them; the static start before it is found (levelling, bias) without the creep."""
    r = fuse(creep, "kf", tmp_path / "kf.mcap", drive_config(creep))
    assert "no static start" not in r.alignment, r.alignment
    tv = reader.read_topic(creep, "/truth/vel")
    speed = np.hypot(tv["v_n"][:, 0], tv["v_n"][:, 1])
    t0 = _t0(creep)
    moving = [t for t in r.still_ns if speed[(tv["log_time_ns"] > t - NS) & (tv["log_time_ns"] <= t)].max() > 0.02]
    assert moving == [], [(t - t0) * 1e-9 for t in moving]
    stills_s = (np.array(r.still_ns) - t0) * 1e-9
    for a, b in ((84.7, 98.6), (130.3, 149.1)):  # the stops (tools/sim/scenarios/creep.toml)
        assert np.sum((stills_s > a) & (stills_s <= b)) >= 5, (a, b, stills_s)


def test_datasheet_units_and_grades():
    """ARW deg/sqrt(h) / 60 = deg/s/sqrt(Hz); VRW m/s/sqrt(h) / 60 = m/s^2/sqrt(Hz) (the bias instability adds no
    white noise: test_a_large_bias_instability_stays_a_bias_process); bias instability
    B with correlation time T -> the random walk B sqrt(2/T); table2-mems is the simulator's defaults, and as the
    filter's preset the datasheet given key by key (the defaults keep the inflated figures); a datasheet key and
    the setting it derives cannot both be given; an unknown grade is named."""
    c = fusion_config({"gyro_arw_deg_rth": 0.6, "accel_vrw_mps_rth": 0.06, "gyro_bias_instability_dph": 36.0,
                       "gyro_bias_corr_time_s": 200.0})
    assert c.sensor.gyro_noise_dps_rthz == pytest.approx(0.01)
    assert c.sensor.accel_noise_ug_rthz == pytest.approx(0.001 / (G * 1e-6))
    assert c.sensor.scale_factor_model == "bias-steps" and fusion_config({}).sensor.scale_factor_model == "consider"
    assert c.sensor.gyro_bias_rw_dps_rts >= 0.01 * math.sqrt(2.0 / 200.0)  # the Gauss-Markov reading, or the flicker's
    assert c.init.init_gyro_bias_sigma_dps == pytest.approx(0.01)
    assert c.sensor.accel_bias_rw_ug_rts == fusion_config({}).sensor.accel_bias_rw_ug_rts  # not given: the default stays
    table2, g = fusion_config({"imu": "table2-mems"}), imugrade.grade("table2-mems")
    keys = ("gyro_scale_factor_ppm", "gyro_misalignment_mrad", "accel_scale_factor_ppm", "accel_misalignment_mrad")
    assert table2.replace(imu="") == fusion_config({k: getattr(g, k) for k in (*imugrade.DATASHEET_KEYS, *keys)})
    assert table2.sensor.gyro_noise_dps_rthz < fusion_config({}).sensor.gyro_noise_dps_rthz  # not inflated
    assert ImuErrorConfig.from_dict({"grade": "table2-mems"}) == ImuErrorConfig()
    tac = ImuErrorConfig.from_dict({"grade": "tactical", "rate_hz": 200})
    assert tac.gyro_noise_density_dps_rthz == pytest.approx(0.003 / 60) and tac.rate_hz == 200.0
    assert fusion_config({"imu": "tactical"}).sensor.gyro_noise_dps_rthz == pytest.approx(
        tac.gyro_noise_density_dps_rthz)
    rtk = GpsConfig.from_dict({"quality": "rtk"})
    assert (rtk.white_h_m, rtk.gm_h_m, rtk.vel_noise_mps) == (0.02, 0.0, 0.01)
    assert GpsConfig.from_dict({"quality": "standalone"}) == GpsConfig()
    with pytest.raises(ConfigError, match="gyro_noise_dps_rthz: also set by the datasheet"):
        fusion_config({"gyro_arw_deg_rth": 0.6, "gyro_noise_dps_rthz": 0.01})
    with pytest.raises(ConfigError, match="unknown IMU grade 'fog'"):
        fusion_config({"imu": "fog"})
    with pytest.raises(ConfigError, match=r"\[gps\] quality"):
        GpsConfig.from_dict({"quality": "dgps"})


def test_a_large_bias_instability_stays_a_bias_process():
    """A phone's datasheet (VRW 0.1 m/s/sqrt(h), accelerometer bias instability 2000 ug; ARW 0.3 deg/sqrt(h), gyro
    bias instability 50 deg/h): the white noise densities are the datasheet's VRW and ARW, whatever the bias
    instability, while the bias random walk and prior grow with it (a bias process); ten times the instability
    moves the bias process and leaves the white noise where it was; each setting's source is the datasheet key or
    the grade that set it (``imugrade.sources``, shown by ``fuse -v``)."""
    sheet = {"accel_vrw_mps_rth": 0.1, "accel_bias_instability_ug": 2000.0, "accel_bias_corr_time_s": 100.0,
             "gyro_arw_deg_rth": 0.3, "gyro_bias_instability_dph": 50.0, "gyro_bias_corr_time_s": 100.0}
    small = {**sheet, "accel_bias_instability_ug": 200.0, "gyro_bias_instability_dph": 5.0}
    big, little = fusion_config(sheet), fusion_config(small)
    assert big.sensor.accel_noise_ug_rthz == pytest.approx(0.1 / 60.0 / (G * 1e-6), rel=1e-3)
    assert big.sensor.gyro_noise_dps_rthz == pytest.approx(0.3 / 60.0)
    for k in ("accel_noise_ug_rthz", "gyro_noise_dps_rthz"):
        assert getattr(big.sensor, k) == getattr(little.sensor, k), k
    for k in ("accel_bias_rw_ug_rts", "gyro_bias_rw_dps_rts"):
        assert getattr(big.sensor, k) == pytest.approx(10.0 * getattr(little.sensor, k)), k
    assert big.init.init_accel_bias_sigma_ug > 2000.0 > little.init.init_accel_bias_sigma_ug
    src = imugrade.sources({**sheet, "imu": "s000-mems", "gyro_noise_dps_rthz": 0.02})   # what fuse -v names
    assert src["accel_noise_ug_rthz"] == "datasheet accel_vrw_mps_rth"
    assert "accel_bias_instability_ug" in src["accel_bias_rw_ug_rts"] and "gyro_noise_dps_rthz" not in src
    assert src["gyro_scale_factor_ppm"] == "grade s000-mems"


@pytest.mark.parametrize("grade", ["tactical", "navigation", "s000-mems"])
def test_bias_instability_covers_the_simulated_flicker(grade):
    """The filter's reading of a bias instability (fusion.imugrade.flicker_bias) against the simulator's draw of
    it (tools.sim.sensors: turn-on bias + flicker noise with the Allan floor 0.664 B), 400 draws per axis: the
    prior gyro_bias_prior_sigma_dps covers the spread of the bias a 30 s static start sees (its mean), and the
    random walk covers the change of the bias (10 s means) over the minute the filter leans on it; both within
    the draws' sampling error (10 %). The old reading (prior hypot(turn-on, B), walk B sqrt(2 / T)) does not."""
    g, s = imugrade.grade(grade), imugrade.grade(grade).filter_settings()
    sim = ImuErrorConfig.from_dict({"grade": grade})
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 100.0, 0.1)
    flick = flicker_noise(t, 400, sim.bias_corr_time_min_s, sim.bias_corr_time_max_s, rng)
    bias = rng.normal(0.0, sim.gyro_turn_on_bias_dps, (400, 1)) + sim.gyro_bias_instability_dps * flick.T  # deg/s
    spread = float(np.std(bias[:, :300].mean(axis=1)))
    lean = imugrade.BIAS_LEAN_S
    k = int(lean / 0.1)
    change = float(np.sqrt(np.mean((bias[:, k:k + 100].mean(axis=1) - bias[:, :100].mean(axis=1)) ** 2)))
    assert s["gyro_bias_prior_sigma_dps"] >= spread / 1.1, (s["gyro_bias_prior_sigma_dps"], spread)
    assert s["gyro_bias_rw_dps_rts"] * math.sqrt(lean) >= change / 1.1, (s["gyro_bias_rw_dps_rts"], change)
    old_prior = math.hypot(g.gyro_turn_on_bias_dph, g.gyro_bias_instability_dph) / 3600.0
    old_walk = g.gyro_bias_instability_dph / 3600.0 * math.sqrt(2.0 / g.gyro_bias_corr_time_s)
    assert old_prior < spread / 1.1 or old_walk * math.sqrt(lean) < change / 1.1


def test_realignment_by_chi_square(mems, tmp_path):
    """A config that claims a heading 30 deg off with a 1 deg sigma: the chi-square test on the GPS velocity
    innovations of the first minutes re-aligns from the course, after which the sigma covers the error (3 sigma)
    over the first two minutes; without the test (realign_window_s = 0) it does not."""
    grade, drive = mems
    if grade != "table2-mems":
        pytest.skip("one grade is enough")
    cover = {}
    for window in (120.0, 0.0):
        cfg = drive_config(drive).replace(init_attitude_deg=(0.0, 0.0, 75.0), init_heading_sigma_deg=1.0,
                      realign_window_s=window)
        out = tmp_path / f"kf_{window:g}.mcap"
        r = fuse(drive, "kf", out, cfg)
        assert ("re-aligned" in r.alignment) == (window > 0), r.alignment
        t, e, s = _heading_series(drive, out, "kf")
        first = (t > t[0] + 10.0) & (t < t[0] + 120.0)
        cover[window] = float(np.mean(np.abs(e[first]) <= 3.0 * s[first]))
    assert cover[120.0] > 0.95 and cover[0.0] < cover[120.0], cover


def test_fuse_says_how_it_aligned(creep, tmp_path, capsys):
    """`fieldlog fuse` prints how the heading was found, and why not by gyrocompassing (a MEMS gyro)."""
    from fieldlog.tools.cli import main as fieldlog

    assert fieldlog(["fuse", str(creep), "--method", "kf", "--out", str(tmp_path / "kf.mcap")]) == 0
    line = [x for x in capsys.readouterr().out.splitlines() if x.startswith("alignment: ")]
    assert len(line) == 1 and "heading from the GPS course" in line[0] and "cannot see the Earth rate" in line[0], line
