"""Alignment and initial uncertainty for every IMU grade (issue 18), the still detector (issue 13 item 4) and
the datasheet units of the IMU grades.

Drives: ``figure8-tactical`` (tactical IMU, RTK, the car creeps 1 m with a 3-degree turn as it leaves the
parking spot), figure8 variants with the MEMS grades, and ``creep`` (creeping through slow turns, real stops).
The outage drift is held against an INS error budget computed from the grade's figures (``_budget``)."""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire.config import ConfigError
from fieldlog.fusion import earth, imugrade
from fieldlog.replay import reader
from fieldlog.tools.evaluate import _quat_interp, heading_at_starts, outage_error_series, rms_columns
from fieldlog.tools.fuse import drive_config, fuse, fusion_config
from fieldlog.tools.sim.emit import GpsConfig
from fieldlog.tools.sim.sensors import ImuErrorConfig
from fieldlog.tools.sim.simulate import simulate

NS = 1_000_000_000
G = 9.80665
TACTICAL_OUTAGES = ((630.0, 60.0), (720.0, 60.0))  # 60 s, after 10 minutes of driving (the car leaves at 30 s)
MEMS_S = 300.0
MEMS_OUTAGE = ((200.0, 60.0),)


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


def _heading_series(drive: Path, fused: Path, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s from the first IMU sample, heading error deg, heading sigma deg) of every solution row."""
    a = reader.read_topic(fused, f"/fusion/{method}/attitude")
    sd = reader.read_topic(fused, f"/fusion/{method}/attitude_std")
    ta = reader.read_topic(drive, "/truth/attitude")
    ts = a["log_time_ns"]
    ok = (ts >= ta["log_time_ns"][0]) & (ts <= ta["log_time_ns"][-1])
    h_s = earth.dcm_to_euler(earth.quat_to_dcm(a["q_xyzw"][ok]))[0]
    h_t = earth.dcm_to_euler(earth.quat_to_dcm(_quat_interp(ts[ok], ta["log_time_ns"], ta["q_xyzw"])))[0]
    err = np.degrees((h_s - h_t + np.pi) % (2 * np.pi) - np.pi)
    return (ts[ok] - _t0(drive)) * 1e-9, err, np.degrees(sd["xyz"][ok, 2])


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
    """Issue 18's done criterion: tactical IMU + RTK, the car creeps and turns as it pulls away, kf with the
    grade's figures only and aids off: under 0.5 m 2D RMS in 60 s outages after 10 minutes; the heading sigma
    covers the heading error at every outage start (3 sigma); each outage's drift within 3x the budget. The
    heading is gyrocompassed from the trimmed static start (the creep is not in it)."""
    cfg = replace(drive_config(tactical), outages=TACTICAL_OUTAGES)
    assert cfg.imu == "tactical" and not cfg.nhc and not cfg.zupt
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
    cfg = replace(drive_config(drive), outages=MEMS_OUTAGE)
    assert cfg.imu == grade
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, cfg)
    assert r.alignment.startswith("heading from the GPS course"), r.alignment  # MEMS cannot see the Earth rate
    _, drift, budget = _outage_check(drive, out, grade, MEMS_OUTAGE)
    assert drift[0] < 3.0 * budget[0], (drift, budget)
    err, sig = heading_at_starts(drive, out, "kf", _windows(drive, MEMS_OUTAGE))
    assert abs(err[0]) <= 3.0 * sig[0], (err, sig)


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
    cfg = replace(base, init_attitude_deg=(0.0, 0.0, 45.0 + offset_deg),  # figure8 parks at 45 deg, level
                  init_heading_sigma_deg=offset_deg)
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, cfg)
    assert "init_attitude_deg" in r.alignment
    t, e, s = _heading_series(drive, out, "kf")
    assert abs(e[0] - offset_deg) < 1.0  # the offset is there at the start ...
    late = float(np.abs(e[t > t[0] + 60.0]).max())
    assert late < 1.5 * ref + 0.25, (late, ref)  # ... and gone a minute later
    assert np.mean(np.abs(e) <= 3.0 * s) > 0.95


def test_no_static_start(tmp_path):
    """A drive that moves off at once: no static interval, so no levelling and no gyro bias from it; the
    heading from the course with its sigma, which covers the error over the first 120 s (alignment and
    convergence). Later, in the loops, the Table 2 MEMS's 1000 ppm scale factor (not a filter state) can take
    the heading error past 3 sigma (1.3 deg against 0.34 deg at 140 s on this seed): not the alignment's."""
    sc = _scenario(tmp_path, "nostatic", "[motion]\nstatic_s = 0.0\n[fusion]\nnhc = false\nzupt = false\n")
    drive = tmp_path / "drive.mcap"
    simulate(str(sc), 150.0, 3, drive)
    out = tmp_path / "kf.mcap"
    r = fuse(drive, "kf", out, drive_config(drive))
    assert r.alignment.endswith("no static start)"), r.alignment
    t, e, s = _heading_series(drive, out, "kf")
    first = t < t[0] + 120.0
    assert np.mean(np.abs(e[first]) <= 3.0 * s[first]) > 0.95
    assert np.all(np.abs(e[t > t[0] + 60.0]) < 1.5)


def test_still_detector_creep_and_stops(creep, tmp_path):
    """Issue 13 item 4: on a drive that creeps at 0.2 m/s through slow turns (below the old 0.3 m/s speed test),
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
    """ARW deg/sqrt(h) / 60 = deg/s/sqrt(Hz); VRW m/s/sqrt(h) / 60 = m/s^2/sqrt(Hz); bias instability B with
    correlation time T -> the random walk B sqrt(2/T); table2-mems is the filter's defaults and the simulator's;
    a datasheet key and the setting it derives cannot both be given; an unknown grade is named."""
    c = fusion_config({"gyro_arw_deg_rth": 0.6, "accel_vrw_mps_rth": 0.06, "gyro_bias_instability_dph": 36.0,
                       "gyro_bias_corr_time_s": 200.0})
    assert c.gyro_noise_dps_rthz == pytest.approx(0.01)
    assert c.accel_noise_ug_rthz == pytest.approx(0.001 / (G * 1e-6))
    assert c.gyro_bias_rw_dps_rts == pytest.approx(0.01 * math.sqrt(2.0 / 200.0))
    assert c.init_gyro_bias_sigma_dps == pytest.approx(0.01)
    assert c.accel_bias_rw_ug_rts == fusion_config({}).accel_bias_rw_ug_rts  # not given: the default stays
    table2 = fusion_config({"imu": "table2-mems"})
    assert replace(table2, imu="") == fusion_config({})
    assert ImuErrorConfig.from_dict({"grade": "table2-mems"}) == ImuErrorConfig()
    tac = ImuErrorConfig.from_dict({"grade": "tactical", "rate_hz": 200})
    assert tac.gyro_noise_density_dps_rthz == pytest.approx(0.003 / 60) and tac.rate_hz == 200.0
    assert fusion_config({"imu": "tactical"}).gyro_noise_dps_rthz == pytest.approx(tac.gyro_noise_density_dps_rthz)
    rtk = GpsConfig.from_dict({"quality": "rtk"})
    assert (rtk.white_h_m, rtk.gm_h_m, rtk.vel_noise_mps) == (0.02, 0.0, 0.01)
    assert GpsConfig.from_dict({"quality": "standalone"}) == GpsConfig()
    with pytest.raises(ConfigError, match="gyro_noise_dps_rthz: also set by the datasheet"):
        fusion_config({"gyro_arw_deg_rth": 0.6, "gyro_noise_dps_rthz": 0.01})
    with pytest.raises(ConfigError, match="unknown IMU grade 'fog'"):
        fusion_config({"imu": "fog"})
    with pytest.raises(ConfigError, match=r"\[gps\] quality"):
        GpsConfig.from_dict({"quality": "dgps"})


def test_realignment_by_chi_square(mems, tmp_path):
    """A config that claims a heading 30 deg off with a 1 deg sigma: the chi-square test on the GPS velocity
    innovations of the first minutes re-aligns from the course, after which the sigma covers the error (3 sigma)
    over the first two minutes; without the test (realign_window_s = 0) it does not."""
    grade, drive = mems
    if grade != "table2-mems":
        pytest.skip("one grade is enough")
    cover = {}
    for window in (120.0, 0.0):
        cfg = replace(drive_config(drive), init_attitude_deg=(0.0, 0.0, 75.0), init_heading_sigma_deg=1.0,
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
