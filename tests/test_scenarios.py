"""The papers' flight scenarios (aircraft: hybrid KF-UKF paper; flight600: SSR-SCKF paper) through the real
acquisition path at their own rates, coloured (Gauss-Markov) noise, the GPS noise schedule, and the [fusion]
table a scenario hands to `fieldlog fuse`."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire.config import ConfigError
from fieldlog.fusion import earth, ins
from fieldlog.drive import reader
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.evaluation.evaluate import outage_error_series
from fieldlog.tools.fuse_settings import drive_config, fusion_config
from fieldlog.tools.info import drive_info, format_info
from fieldlog.drive.reader import read_metadata
from fieldlog.tools.sim import trajectory as tj
from fieldlog.tools.sim.emit import GpsConfig, gps_solution
from fieldlog.tools.sim.sensors import ImuErrorConfig, gauss_markov, imu_counts
from fieldlog.tools.sim.simulate import simulate

NS = 1_000_000_000
AIRCRAFT_S = 120.0
FLIGHT_S = 120.0


@pytest.fixture(scope="module")
def aircraft(tmp_path_factory) -> Path:
    """The first 120 s of the aircraft: static, acceleration to 100 m/s, pitch up, 30-deg climb, pitch down."""
    path = tmp_path_factory.mktemp("aircraft") / "aircraft.mcap"
    assert fieldlog(["sim", "--scenario", "aircraft", "--duration", f"{AIRCRAFT_S:g}", "--seed", "3",
                     "--out", str(path)]) == 0
    return path


def _enu_error(fix: dict, truth: dict) -> np.ndarray:
    """GPS fix minus truth (interpolated to the fix times), ENU m."""
    t, tr = fix["stamp_ns"], truth["stamp_ns"]
    lat, lon, h = (np.interp(t, tr, truth[k]) for k in ("lat_deg", "lon_deg", "alt_m"))
    rm, rn = earth.principal_radii(np.radians(lat), h)
    return np.stack([np.radians(fix["lon_deg"] - lon) * rn * np.cos(np.radians(lat)),
                     np.radians(fix["lat_deg"] - lat) * rm, fix["alt_m"] - h], axis=1)


def test_aircraft_through_the_pipeline(aircraft, capsys):
    imu = reader.read_topic(aircraft, "/imu")
    fix = reader.read_topic(aircraft, "/gps/fix")
    truth = reader.read_topic(aircraft, "/truth/imu")
    # 200 Hz DAQ frames; 10 Hz epochs from the first whole UTC second (0.1-0.9 s after the start) to the end
    assert abs(len(imu["stamp_ns"]) - 200 * AIRCRAFT_S) <= 2
    assert 10 * (AIRCRAFT_S - 1) <= len(fix["stamp_ns"]) <= 10 * AIRCRAFT_S + 1
    # fractional-second NMEA epochs assemble into fixes stamped on the 100 ms grid of UTC, none lost
    assert np.all(fix["stamp_ns"] % (NS // 10) == 0) and np.all(np.diff(fix["stamp_ns"]) == NS // 10)
    assert np.all(fix["status"] >= 0)
    info = drive_info(aircraft)
    assert info.sync_states.get("locked", 0.0) > 0.99
    assert info.timing.rms_us <= 5.0, info.timing           # the foundation's bound with a PPS latch
    meta = read_metadata(aircraft)
    assert float(meta["drive"]["imu_rate_hz"]) == 200.0 and float(meta["drive"]["gps_rate_hz"]) == 10.0
    assert float(meta["timesync"]["fs_hz"]) == 200.0
    assert fieldlog(["info", str(aircraft)]) == 0
    assert "gps_rate_hz=10.0" in capsys.readouterr().out
    # Table 1 comes through NMEA at 2.4 km and 100 m/s: position noise 5 m horizontal, 10 m vertical
    err = _enu_error(fix, reader.read_topic(aircraft, "/truth/fix"))
    np.testing.assert_allclose(err.std(axis=0), [5.0, 5.0, 10.0], rtol=0.12)
    vel = reader.read_topic(aircraft, "/gps/vel")
    tv = reader.read_topic(aircraft, "/truth/vel")
    dv = vel["v_n"][:, :2] - np.stack([np.interp(vel["stamp_ns"], tv["stamp_ns"], tv["v_n"][:, i]) for i in (0, 1)], 1)
    assert 0.08 < dv.std() < 0.12                            # 0.1 m/s, plus the course's 0.01 deg rounding
    # Table 1 IMU white noise: 35 deg/h/sqrt(Hz) and 0.3 mg/sqrt(Hz) at 200 Hz, per sample
    d_w = np.diff(imu["omega_ib_b"] - truth["omega_ib_b"], axis=0).std(axis=0) / math.sqrt(2)
    d_f = np.diff(imu["f_b"] - truth["f_b"], axis=0).std(axis=0) / math.sqrt(2)
    np.testing.assert_allclose(d_w, np.radians(35 / 3600) * math.sqrt(200), rtol=0.05)
    np.testing.assert_allclose(d_f, 0.3e-3 * 9.80665 * math.sqrt(200), rtol=0.05)


def test_aircraft_fuse_kf(aircraft, tmp_path):
    """`fieldlog fuse --method kf` with the drive's own [fusion] figures. The 10 Hz GPS has 5 / 5 / 10 m white
    errors, 12 m 3D RMS; a filter whose INS holds to centimetres over 0.1 s averages them over its time
    constant (tens of epochs), so the fused 3D RMS must be well below it: < 2.5 m (after 45 s,
    through the acceleration, the pitch-up and the climb; GPS-only, as the paper's filters)."""
    out = tmp_path / "kf.mcap"
    assert fieldlog(["fuse", str(aircraft), "--method", "kf", "--out", str(out)]) == 0
    meta = read_metadata(out)["fusion"]
    assert "'gyro_noise_dps_rthz': 0.009722" in meta["config"]     # the drive's [fusion] table was used
    t0 = min(t.first_ns for t in reader.topics(aircraft) if t.topic == "/imu")
    t, err = outage_error_series(aircraft, out, "kf", [(t0 + 45 * NS, t0 + int(AIRCRAFT_S * NS))])
    assert len(t) > 600
    rms3d = math.sqrt(np.mean(np.sum(err[:, 0:3] ** 2, axis=1)))
    gps = np.sqrt(np.mean(np.sum(_enu_error(reader.read_topic(aircraft, "/gps/fix"),
                                            reader.read_topic(aircraft, "/truth/fix")) ** 2, axis=1)))
    assert rms3d < 2.5 and rms3d < 0.25 * gps, (rms3d, gps)
    # velocity: horizontal well below the GPS's own 0.1 m/s; vertical is seen only through the 10 m heights
    # (NMEA has no vertical velocity), through a 30-degree climb: a looser bound
    vel_rms = np.sqrt(np.mean(err[:, 3:6] ** 2, axis=0))
    assert vel_rms[:2].max() < 0.06 and vel_rms[2] < 0.4, vel_rms
    assert np.abs(err[:, 6:8]).max() < 0.5                       # roll, pitch within 0.5 deg through the manoeuvres


def test_explicit_config_wins_and_bad_keys_are_named(aircraft, tmp_path, capsys):
    good = tmp_path / "good.toml"
    good.write_text("[fusion]\ngyro_noise_dps_rthz = 0.05\nlever_arm_b = [0.0, 1.0, 0.5]\n"
                    "[fusion.predictor]\ncentres = 12\n")
    out = tmp_path / "ins.mcap"
    assert fieldlog(["fuse", str(aircraft), "--method", "ins", "--config", str(good), "--out", str(out)]) == 0
    cfg = read_metadata(out)["fusion"]["config"]
    assert "'gyro_noise_dps_rthz': 0.05" in cfg and "'lever_arm_b': (0.0, 1.0, 0.5)" in cfg and "'centres': 12" in cfg
    assert drive_config(aircraft).sensor.gyro_noise_dps_rthz == 0.009722
    capsys.readouterr()
    bad = tmp_path / "bad.toml"
    for text, named in (("[fusion]\ngyro_nosie_dps_rthz = 0.05\n", "[fusion] gyro_nosie_dps_rthz: unknown key"),
                        ("[fusion]\ncov_step_s = 'fast'\n", "[fusion] cov_step_s: expected a finite number"),
                        ("[fusion]\nlever_arm_b = [1.0, 2.0]\n", "[fusion] lever_arm_b: expected an array of 3"),
                        ("[fusion.predictor]\ncenters = 3\n", "[fusion.predictor] centers: unknown key")):
        bad.write_text(text)
        for cmd in (["fuse", str(aircraft), "--out", str(tmp_path / "x.mcap")],
                    ["evaluate", str(aircraft), "--report", str(tmp_path / "rep")]):
            assert fieldlog(cmd + ["--config", str(bad)]) == 2
            assert named in capsys.readouterr().err
    with pytest.raises(ConfigError, match=r"\[fusion\] outages\[0\]"):
        fusion_config({"outages": [[10.0, -1.0]]})
    with pytest.raises(ConfigError, match=r"\[fusion\] odometer_track_m: must be > 0"):
        fusion_config({"odometer_track_m": -1.6})  # a negative track would swap the left and right wheels
    with pytest.raises(ConfigError, match=r"\[fusion\] installation_span_s: must be >= 0"):
        fusion_config({"installation_span_s": -60.0})


def test_bad_fusion_key_in_a_scenario_fails_the_sim(tmp_path):
    sc = tmp_path / "typo.toml"
    sc.write_text('extends = "aircraft"\n[fusion]\naccel_noise_ug = 300.0\n')
    with pytest.raises(ConfigError, match=r"\[fusion\] accel_noise_ug: unknown key"):
        simulate(str(sc), 5.0, 1, tmp_path / "x.mcap")


def test_flight600_through_the_pipeline(tmp_path):
    path = tmp_path / "flight600.mcap"
    res = simulate("flight600", FLIGHT_S, 2, path)
    imu = reader.read_topic(path, "/imu")
    fix = reader.read_topic(path, "/gps/fix")
    assert abs(len(imu["stamp_ns"]) - 100 * FLIGHT_S) <= 2 and res.imu_samples == len(imu["stamp_ns"])
    assert FLIGHT_S - 1 <= len(fix["stamp_ns"]) <= FLIGHT_S + 1
    assert np.all(np.diff(fix["stamp_ns"]) == NS)
    info = drive_info(path)
    assert info.timing.rms_us <= 5.0, info.timing
    meta = read_metadata(path)
    assert float(meta["drive"]["imu_rate_hz"]) == 100.0 and float(meta["drive"]["gps_rate_hz"]) == 1.0
    cfg = drive_config(path)   # the paper's initial errors, as the filter's initial sigmas
    assert (cfg.init.init_vel_sigma_mps, cfg.init.init_level_sigma_deg, cfg.init.init_heading_sigma_deg) == (0.5, 2.0, 3.0)
    # 150 m/s at 120 s: the speed survives RMC/VTG formatting
    vel = reader.read_topic(path, "/gps/vel")
    assert np.hypot(vel["v_n"][-1, 0], vel["v_n"][-1, 1]) == pytest.approx(150.0, abs=0.5)


def test_flight600_locks_with_a_sampled_pps_flag(tmp_path):
    """At 100 Hz a flag-only PPS still locks, but its stamps carry the quantisation sawtooth of up to half a
    sample: 40 ppm moves the edge by 0.004 samples per second, too slowly for the 120 s fit window to see (the
    fitted rate error comes out near 0 ppm). Hence the scenarios' latch."""
    path = tmp_path / "flag.mcap"
    simulate("flight600", 150.0, 4, path, pps_mode="flag")
    info = drive_info(path)
    assert info.sync_states.get("locked", 0.0) > 0.9
    assert info.timing.rms_us < 5000.0 and info.timing.max_abs_us < 10000.0, info.timing
    assert "timestamp error vs truth" in format_info(info)


def _perfect_ins(name: str, rate_hz: float) -> tuple[tuple[float, float, float, float], float]:
    truth = tj.generate(tj.load_scenario(name))
    t = np.arange(0.0, truth.scenario.duration_s, 1.0 / rate_hz)
    s = truth.evaluate(t)
    sol = ins.integrate(ins.NavState(t[0], s.lat[0], s.lon[0], s.h[0], s.v_n[0], s.q[0]), t, s.omega_ib_b, s.f_b)
    rm, rn = earth.principal_radii(s.lat, s.h)
    d_hor = np.hypot((sol.lat - s.lat) * rm, (sol.lon - s.lon) * rn * np.cos(s.lat)).max()
    dq = earth.quat_multiply(sol.q, s.q * np.array([-1.0, -1.0, -1.0, 1.0]))
    d_att = np.linalg.norm(earth.quat_to_rotvec(dq), axis=1).max()
    turning = np.abs(s.roll) > np.radians(5.0)
    return (d_hor, np.abs(sol.h - s.h).max(), np.abs(sol.v_n - s.v_n).max(), d_att), np.abs(s.f_b[turning, 0]).max()


def test_perfect_ins_aircraft():
    """Error-free 200 Hz IMU output of the aircraft truth reproduces the flight (as figure8's perfect INS);
    its turns are coordinated (no sideways specific force in a bank)."""
    (d_hor, d_ver, d_vel, d_att), f_side = _perfect_ins("aircraft", 200.0)
    assert d_hor < 0.05 and d_ver < 0.01 and d_vel < 1e-3 and d_att < 3e-6
    assert f_side < 0.05                 # m/s^2 at 17 deg of bank (Earth rate and transport rate terms)
    truth = tj.generate(tj.load_scenario("aircraft"))
    s = truth.evaluate(np.array([29.0, 60.0, 85.0, 130.0, 165.0, 299.0]))
    np.testing.assert_allclose(np.linalg.norm(s.v_n, axis=1), [0, 100, 100, 100, 100, 100], atol=1e-9)
    np.testing.assert_allclose(np.degrees(s.pitch)[[2]], 30.0, atol=0.1)
    assert np.degrees(s.heading[4]) == pytest.approx(40.0, abs=0.1) and 2300 < s.h[3] < 2500


def test_perfect_ins_flight600():
    (d_hor, d_ver, d_vel, d_att), f_side = _perfect_ins("flight600", 100.0)
    # 100 Hz at up to 250 m/s and 2 g pull-ups over 600 s: bounds far below the paper's 10 m GPS noise
    assert d_hor < 0.5 and d_ver < 0.1 and d_vel < 3e-3 and d_att < 5e-6
    assert f_side < 0.1


def _acf(x: np.ndarray, lag: int) -> float:
    x = x - x.mean(axis=0)
    return float(np.sum(x[:-lag] * x[lag:]) / np.sum(x * x) * len(x) / (len(x) - lag))


def test_gauss_markov_std_and_correlation_time():
    """Unit std and E[x(t) x(t + tau)] = e^-1, on uneven sample times (exact discretisation per interval).
    200 000 samples x 4 channels at tau = 50 samples: about 8000 independent tau-blocks, so the std is good to
    ~1 % and the lag-tau autocorrelation to ~0.02 (1 sigma)."""
    rng = np.random.default_rng(11)
    dt = 0.01 * (1.0 + 0.3 * rng.uniform(-1, 1, 200_000))
    t = np.cumsum(dt)
    tau = 0.5
    x = gauss_markov(t, tau, rng.standard_normal((t.size, 4)))
    assert x.std(axis=0) == pytest.approx(np.ones(4), rel=0.04)
    # autocorrelation at lag tau, on a uniform resampling of the path (linear interpolation halves nothing at
    # this spacing: tau is 50 samples)
    tu = np.arange(t[0], t[-1], 0.01)
    xu = np.stack([np.interp(tu, t, x[:, i]) for i in range(4)], axis=1)
    assert _acf(xu, 50) == pytest.approx(math.exp(-1.0), abs=0.05)
    assert _acf(xu, 150) == pytest.approx(math.exp(-3.0), abs=0.05)
    np.testing.assert_array_equal(gauss_markov(t, 0.0, x), x)     # tau unset: white, untouched


def test_coloured_gps_and_imu_noise():
    """[gps] noise_tau_s and [imu] gm_tau_s / *_gm_sigma_*: configured std, autocorrelation e^-1 at lag tau."""
    sc = tj.load_scenario("coloured")
    assert sc.duration_s == 500.0 and sc.motion == tj.load_scenario("figure8").motion   # extends figure8
    truth = tj.generate(sc, 3000.0)
    cfg = GpsConfig.from_dict({**sc.gps, "white_h_m": 3.0, "white_v_m": 4.0, "gm_h_m": 0.0, "gm_v_m": 0.0,
                               "noise_tau_s": 10.0, "vel_noise_mps": 0.2})
    sol = gps_solution(truth, np.arange(0.0, 3000.0), cfg, np.random.default_rng(5))
    err, dv = sol["err_enu"], sol["v_n"] - truth.evaluate(np.arange(0.0, 3000.0)).v_n
    np.testing.assert_allclose(err.std(axis=0), [3.0, 3.0, 4.0], rtol=0.1)
    assert dv.std() == pytest.approx(0.2, rel=0.1)
    assert _acf(err / err.std(axis=0), 10) == pytest.approx(math.exp(-1.0), abs=0.08)
    assert _acf(dv, 10) == pytest.approx(math.exp(-1.0), abs=0.08)
    assert _acf(err, 1) > 0.85                                   # white would give 0
    icfg = ImuErrorConfig.from_dict({"gm_tau_s": 0.2, "gyro_gm_sigma_dps": 0.02, "accel_gm_sigma_ug": 500.0})
    t = np.arange(120_000) / 500.0
    zero = np.zeros((t.size, 3))
    from fieldlog.acquire.calib import load_calibration

    _, realised = imu_counts(t, zero, zero, icfg, load_calibration(None), np.random.default_rng(6))
    g, a = realised["gyro_coloured"], realised["accel_coloured"]
    np.testing.assert_allclose(g.std(axis=0), np.radians(0.02), rtol=0.06)
    np.testing.assert_allclose(a.std(axis=0), 500e-6 * 9.80665, rtol=0.06)
    assert _acf(g, 100) == pytest.approx(math.exp(-1.0), abs=0.05)


def test_noise_schedule_scales_the_gps_error():
    """flight600-noisy: GPS error std x3 in 200-400 s, x2 in 400-600 s; the receiver's sigma does not change."""
    sc = tj.load_scenario("flight600-noisy")
    base = tj.load_scenario("flight600")
    assert sc.motion == base.motion and sc.imu == base.imu and sc.fusion == base.fusion
    cfg = GpsConfig.from_dict(dict(sc.gps))
    truth = tj.generate(sc)
    t = np.arange(0.0, 600.0)
    sols = [gps_solution(truth, t, cfg, np.random.default_rng(seed)) for seed in range(4)]
    err = np.concatenate([s["err_enu"][:, None] for s in sols], axis=1)       # (600, 4 runs, 3)
    dv = np.concatenate([(s["v_n"] - truth.evaluate(t).v_n)[:, None] for s in sols], axis=1)
    for e, sigma in ((err, 10.0), (dv, 0.1)):
        s0, s1, s2 = (e[(t >= a) & (t < a + 200)].std() for a in (0, 200, 400))
        assert s0 == pytest.approx(sigma, rel=0.06)             # 2400 values per window: ~1.5 % (1 sigma)
        assert s1 / s0 == pytest.approx(3.0, rel=0.08) and s2 / s0 == pytest.approx(2.0, rel=0.08)
    assert np.all(sols[0]["sigma_h"] == 10.0)
    with pytest.raises(ValueError, match="noise_schedule"):
        GpsConfig.from_dict({"noise_schedule": [{"start_s": 5.0, "end_s": 1.0, "scale": 2.0}]})


def test_segment_vocabulary_is_checked(tmp_path):
    p = tmp_path / "bad.toml"
    for seg, msg in (("duration_s = 10.0\npitch_deg = 10.0\ngrade_pct = 2.0", "grade_pct or pitch_deg"),
                     ("duration_s = 10.0\npitch_deg = 10.0\nramp_s = 12.0", "shorter than its grade ramp"),
                     ("duration_s = 10.0\nspeed_mps = 50.0\nramp_s = 12.0", "shorter than its speed change"),
                     ("duration_s = 10.0\nspeed_mps = 50.0\nramp_s = 5.0\naccel_mps2 = 2.0", "replaces accel_mps2")):
        p.write_text(f'extends = "aircraft"\n[motion]\n[[motion.segments]]\n{seg}\n')
        with pytest.raises(ValueError, match=msg):
            tj.load_scenario(p)
    p.write_text('extends = "aircraft"\n[clock]\nfs_hz = 500.0\n')
    with pytest.raises(ValueError, match=r"\[clock\] fs_hz = 500 differs from \[imu\] rate_hz = 200"):
        simulate(str(p), 5.0, 1, tmp_path / "x.mcap")


OTHER_METHODS = ("kf-ukf", "sckf", "ssr-sckf", "hinf")


@pytest.mark.parametrize("scenario", sorted(p.stem for p in Path("tools/sim/scenarios").glob("*.toml")))
def test_other_papers_methods_fuse_and_evaluate_on_every_scenario(scenario, tmp_path, capsys):
    """kf-ukf, sckf, ssr-sckf and hinf through `fieldlog evaluate` (which fuses) on 140 s of each scenario, one
    10 s outage at 120 s: every method scores its window, and none is far off the plain kf. The static drive
    never moves, so no filter aligns: each run is reported as not scored, and nothing crashes."""
    drive = tmp_path / f"{scenario}.mcap"
    assert fieldlog(["sim", "--scenario", scenario, "--duration", "140", "--seed", "2", "--out", str(drive)]) == 0
    rep = tmp_path / "rep"
    assert fieldlog(["evaluate", str(drive), "--outages", "10", "--methods", ",".join(("kf",) + OTHER_METHODS),
                     "--report", str(rep)]) == 0
    import polars as pl

    t = pl.read_csv(rep / "table.csv")
    if scenario == "static":
        assert t.height == 0 and capsys.readouterr().out.count("not scored, no solution: the filter never aligned") == 5
        return
    wheels = {"figure8-real", "figure8-varied-real"}  # CAN wheel speeds: evaluate adds the -no-odometer columns
    assert set(t["method"]) == {f"{m}{tail}" for m in ("kf", *OTHER_METHODS)
                                for tail in ("", "-no-odometer")[:1 + (scenario in wheels)]}
    assert (t["windows"] == 1).all()
    pos = {r["method"]: r["mean"] for r in t.filter(pl.col("quantity") == "latitude").iter_rows(named=True)}
    for m in OTHER_METHODS:
        assert math.isfinite(pos[m]) and pos[m] < 2.0 * pos["kf"] + 1.0, (scenario, pos)


def test_laps_that_vary_differ_lap_to_lap_and_stay_on_the_track():
    """figure8-varied: the same seed gives the same drive, another seed another; its laps' periods differ (a
    predictor learning the lap in time cannot replay it), its track stays where figure8's is, and its perfect
    INS reproduces it as figure8's does."""
    sc = tj.load_scenario("figure8-varied")
    t = np.arange(0.0, 600.0, 0.5)
    a, a2, b = (tj.generate(sc, 600.0, seed).evaluate(t) for seed in (1, 1, 2))
    assert np.array_equal(a.lat, a2.lat) and np.abs(a.lat - b.lat).max() > 1e-6
    fixed = tj.generate(tj.load_scenario("figure8"), 600.0).evaluate(t)

    def lap_starts(s):  # the car crosses the track centre heading north-east once per lap
        h = np.degrees(s.heading) % 360.0
        near = np.abs(((h - 45.0) + 180.0) % 360.0 - 180.0) < 10.0
        return t[1:][near[1:] & ~near[:-1]]

    period_fixed = np.diff(lap_starts(fixed))
    period_varied = np.diff(lap_starts(a))
    assert np.ptp(period_fixed) <= 0.5 + 1e-9 and np.ptp(period_varied) > 3.0  # 0.5 s: the time grid
    speed = np.linalg.norm(a.v_n, axis=1)
    assert 7.0 < speed[t > 120].min() and speed.max() < 13.0  # 10 m/s, 1 sigma 10 %, clipped at 30 %
    truth = tj.generate(sc, 600.0, 1)
    p, p0 = truth.local_position(t), tj.generate(tj.load_scenario("figure8"), 600.0).local_position(t)
    assert np.abs(p).max() < 1.3 * np.abs(p0).max()
