"""The simulator as rough as a real car (``figure8-real``): the IMU's true mounting, delay and vibration and the
wheel speeds' scale are in the drive's truth (``sim.truth``) and recoverable from its topics; a scenario without
them is untouched."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fieldlog.drive import metavalue
from fieldlog.fusion import earth
from fieldlog.drive import reader
from fieldlog.tools.cli import main as fieldlog
from fieldlog.tools.sim import simulate, trajectory, vehicle, vibration

DURATION_S = 150.0
SEEDS = (1, 2, 3)
NS = 1_000_000_000


@pytest.fixture(scope="module", params=SEEDS)
def real(request, simulated):
    return simulated("figure8-real", DURATION_S, request.param)


def _at(stamp_ns: np.ndarray, x: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t_ns, stamp_ns, x[:, i]) for i in range(x.shape[1])], axis=1)


def _means(t_ns: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Means of x (n, m) over consecutive windows of window_s from t_ns[0]."""
    k = (t_ns - t_ns[0]) // int(window_s * NS)
    n = np.bincount(k)
    return np.stack([np.bincount(k, x[:, i]) / n for i in range(x.shape[1])], axis=1)


def _sensed(path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """/imu less the sensor errors (/truth/imu_bias): the IMU's stamps, rate and specific force; /truth/imu."""
    imu, bias = reader.read_topic(path, "/imu"), reader.read_topic(path, "/truth/imu_bias")
    t = imu["stamp_ns"]
    w = imu["omega_ib_b"] - _at(bias["stamp_ns"], bias["omega_ib_b"], t)
    f = imu["f_b"] - _at(bias["stamp_ns"], bias["f_b"], t)
    return t, w, f, reader.read_topic(path, "/truth/imu")


def _delay(path, lags_s: np.ndarray) -> float:
    """The lag (s) that best lines up the 1 s means of |rate| of /imu with those of /truth/imu."""
    t, w, _, tr = _sensed(path)
    measured = np.linalg.norm(_means(t, w, 1.0), axis=1)
    cost = [np.mean((measured - np.linalg.norm(_means(t, _at(tr["stamp_ns"], tr["omega_ib_b"], t - int(d * NS)),
                                                             1.0), axis=1)) ** 2) for d in lags_s]
    return float(lags_s[int(np.argmin(cost))])


def test_truth_record(real):
    meta = reader.read_metadata(real)["sim.truth"]
    assert metavalue.load(meta["imu_mounting_rpy_deg"]) == [2.0, -4.0, 5.0]
    assert metavalue.load(meta["imu_delay_s"]) == 0.1
    scale = np.array(metavalue.load(meta["wheel_speed_scale"]))
    assert np.all(np.abs(scale - 0.008) < 5 * vehicle.CanSimConfig().tyre_scale_wheel)


def test_mounting_recovered_from_imu_against_truth(real):
    """The rotation taking the truth's car-frame rate and force (at the true delay) onto the IMU's, fitted over
    1 s means (Kabsch), is the configured mounting."""
    t, w, f, tr = _sensed(real)
    d = int(0.1 * NS)
    A = np.concatenate([_means(t, f, 1.0), 10.0 * _means(t, w, 1.0)])
    B = np.concatenate([_means(t, _at(tr["stamp_ns"], tr["f_b"], t - d), 1.0),
                        10.0 * _means(t, _at(tr["stamp_ns"], tr["omega_ib_b"], t - d), 1.0)])
    U, _, Vt = np.linalg.svd(B.T @ A)
    C_bm = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    heading, pitch, roll = earth.dcm_to_euler(C_bm)
    got = np.degrees([roll, pitch, math.remainder(float(heading), 2 * math.pi)])
    assert np.all(np.abs(got - [2.0, -4.0, 5.0]) < 0.3), got


def test_delay_recovered_and_zero_without_it(real, simulated, tmp_path):
    lags = np.arange(-0.05, 0.2, 0.002)
    assert abs(_delay(real, lags) - 0.1) < 0.012
    seed = int(reader.read_metadata(real)["drive"]["seed"])
    prompt = tmp_path / "prompt.mcap"
    assert fieldlog(["sim", "--scenario", "figure8-real", "--duration", "90", "--seed", str(seed), "--imu-delay",
                     "0.01", "--mounting", "0,0,0", "--out", str(prompt)]) == 0
    meta = reader.read_metadata(prompt)["sim.truth"]
    assert metavalue.load(meta["imu_mounting_rpy_deg"]) == [0.0, 0.0, 0.0]
    assert abs(_delay(prompt, lags) - 0.01) < 0.012


def test_wheel_speeds_read_high_by_the_scale(real):
    meas, true = reader.read_topic(real, "/vehicle/twist"), reader.read_topic(real, "/truth/vehicle/twist")
    n = min(len(meas["v_n"]), len(true["v_n"]))
    v, v_true = meas["v_n"][:n, 0], true["v_n"][:n, 0]
    cruise = v_true > 5.0
    scale = np.array(metavalue.load(reader.read_metadata(real)["sim.truth"]["wheel_speed_scale"]))
    ratio = np.median(v[cruise] / v_true[cruise]) - 1.0
    assert abs(ratio - scale[2:].mean()) < 0.001, (ratio, scale)


def _window_std(t_ns: np.ndarray, x: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Root of the summed per-axis variances of x over each second of the selection."""
    k = (t_ns[sel] - t_ns[sel][0]) // NS
    return np.array([math.sqrt(float(np.sum(np.var(x[sel][k == j], axis=0)))) for j in np.unique(k)])


def test_idle_vibration_of_order_one_degree_per_second_and_it_carries_the_speed(real):
    imu = reader.read_topic(real, "/imu")
    t, w = imu["stamp_ns"], imu["omega_ib_b"]
    s = (t - t[0]) / NS
    idle = (s > 5.0) & (s < 55.0)
    sd = np.degrees(_window_std(t, w, idle))
    assert 0.3 < np.median(sd) < 3.0 and sd.max() < 3.0 * np.median(sd)
    nav = reader.read_topic(real, "/truth/vel")
    speed = np.interp(t, nav["stamp_ns"], np.linalg.norm(nav["v_n"], axis=1))
    rate_hz = float(reader.read_metadata(real)["drive"]["imu_rate_hz"])

    def peak(sel: np.ndarray) -> float:
        x = w[sel] - w[sel].mean(axis=0)
        power = np.sum(np.abs(np.fft.rfft(x, axis=0)) ** 2, axis=1)
        freq = np.fft.rfftfreq(len(x), 1.0 / rate_hz)
        power[freq < 10.0] = 0.0
        return float(freq[np.argmax(power)])

    cruise = (speed > 9.9) & (s > 100.0)
    cruise &= s < s[cruise][0] + 10.0
    for sel in (idle, cruise):     # the strongest line is one of the engine's at the engine speed the speed gives
        rot_hz = float(vehicle.engine_rpm(np.median(speed[sel]))) / 60.0
        assert min(abs(peak(sel) / (order * rot_hz) - 1.0) for order, _ in vibration.ENGINE_ORDERS) < 0.03, (
            peak(sel), rot_hz)


def test_vibration_figures_are_the_vector_rms():
    cfg = vibration.VibrationConfig()
    t = np.arange(200_000) / 500.0
    rng = np.random.default_rng(5)
    for v in (0.0, cfg.ref_speed_mps):
        w, f = vibration.vibration(t, np.full_like(t, v), cfg, rng)
        rel = v / cfg.ref_speed_mps
        want_w = math.hypot(cfg.engine_gyro_dps, rel * cfg.wheel_gyro_dps, rel * cfg.road_gyro_dps)
        want_f = math.hypot(cfg.engine_accel_mps2, rel * cfg.wheel_accel_mps2, rel * cfg.road_accel_mps2)
        got_w = math.degrees(math.sqrt(float(np.sum(np.var(w, axis=0)))))
        got_f = math.sqrt(float(np.sum(np.var(f, axis=0))))
        assert abs(got_w / want_w - 1.0) < 0.1 and abs(got_f / want_f - 1.0) < 0.1, (v, got_w, got_f)


def test_bad_mounting_option_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        fieldlog(["sim", "--scenario", "figure8-real", "--mounting", "2,-4", "--out", str(tmp_path / "x.mcap")])
    assert e.value.code == 2
    assert "ROLL,PITCH,YAW" in capsys.readouterr().err


def _same(a, b) -> bool:
    """Equal to the bit, through dicts, lists, tuples, arrays and dataclasses (a truth sample)."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if hasattr(a, "__dataclass_fields__") and not isinstance(a, simulate.RawRead):
        return all(_same(getattr(a, k), getattr(b, k)) for k in a.__dataclass_fields__ if k != "scenario")
    return a == b


def test_make_reads_beside_or_in_turn_alike(monkeypatch):
    """``make_reads`` runs what needs no IMU truth on threads when it may use two CPUs and in turn on one: the
    reads and every truth array are the same (the rough car, CAN and a NovAtel receiver included)."""
    sc = trajectory.load_scenario("figure8-real")
    beside = simulate.make_reads(sc, 20.0, 7, None, "novatel", can=True)
    monkeypatch.setattr(reader, "cpus", lambda: 1)
    in_turn = simulate.make_reads(sc, 20.0, 7, None, "novatel", can=True)
    assert isinstance(simulate._beside(), simulate._InTurn)
    assert beside[0] == in_turn[0] and len(beside[0]) > 1000
    assert _same(beside[1], in_turn[1])


def test_simulate_leaves_the_collector_as_it_found_it(tmp_path):
    """``simulate`` freezes the objects alive on entry and collects the youngest generation less often while it
    runs; afterwards the thresholds are the caller's and nothing is left frozen."""
    import gc

    thresholds, frozen = gc.get_threshold(), gc.get_freeze_count()
    simulate.simulate("figure8", 3.0, 1, tmp_path / "d.mcap")
    assert gc.get_threshold() == thresholds and gc.get_freeze_count() == frozen
