import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from fieldlog.acquire.calib import G0, LSB_V, apply, default_calibration
from fieldlog.tools import allan
from fieldlog.tools.sim.sensors import ImuErrorConfig, apply_errors, draw_errors, flicker_noise, imu_counts

FS = 500.0
_QUIET = dict(
    gyro_noise_density_dps_rthz=0.0,
    gyro_bias_instability_dps=0.0,
    gyro_turn_on_bias_dps=0.0,
    gyro_scale_factor_ppm=0.0,
    gyro_misalignment_mrad=0.0,
    accel_noise_density_ug_rthz=0.0,
    accel_bias_instability_ug=0.0,
    accel_turn_on_bias_ug=0.0,
    accel_scale_factor_ppm=0.0,
    accel_misalignment_mrad=0.0,
)


def _static(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t_s = 1000.0 + np.arange(n) / FS * (1.0 + 40e-6)  # DAQ clock 40 ppm fast
    omega_ib_b = np.tile([0.0, 7.29e-5 * 0.77, 7.29e-5 * 0.64], (n, 1))  # Earth rate at ~50 deg N
    f_b = np.tile([0.0, 0.0, G0], (n, 1))
    return t_s, omega_ib_b, f_b


# --- allan_deviation / noise_parameters --------------------------------------------------------


def _adev_brute_force(x: np.ndarray, m: int, fs: float) -> float:
    ybar = np.array([x[k : k + m].mean() for k in range(x.size - m + 1)])
    return math.sqrt(np.mean((ybar[m:] - ybar[:-m]) ** 2) / 2.0)


def test_allan_deviation_matches_definition():
    rng = np.random.default_rng(0)
    x = np.cumsum(rng.standard_normal((400, 3)), axis=0) * 0.01 + rng.standard_normal((400, 3))
    taus, adev = allan.allan_deviation(x, 50.0, taus=np.array([0.02, 0.1, 0.5, 1.0, 3.98, 100.0]))
    assert np.allclose(taus, [0.02, 0.1, 0.5, 1.0, 3.98])  # 100 s is beyond half the record: dropped
    assert adev.shape == (5, 3)
    for i, tau in enumerate(taus):
        for j in range(3):
            assert adev[i, j] == pytest.approx(_adev_brute_force(x[:, j], round(tau * 50.0), 50.0), rel=1e-9)
    taus1, adev1 = allan.allan_deviation(x[:, 1], 50.0, taus)
    assert adev1.shape == (5,) and np.allclose(adev1, adev[:, 1], rtol=1e-12)


def test_allan_deviation_default_taus_white_noise():
    rng = np.random.default_rng(1)
    sigma = 0.3
    taus, adev = allan.allan_deviation(rng.normal(5.0, sigma, 200_000), FS)
    assert taus[0] == pytest.approx(1.0 / FS) and taus[-1] <= 100_000 / FS
    assert np.all(np.diff(taus) > 0) and taus.size > 40
    good = taus < 0.5  # >= 800 clusters: a 5 % check holds
    assert np.allclose(adev[good], sigma / np.sqrt(taus[good] * FS), rtol=0.05)


def test_noise_parameters_on_an_exact_curve_and_unit_names():
    N = math.radians(0.01)  # rad/s/sqrt(Hz)
    B = math.radians(0.02)  # rad/s
    K = 5e-5  # rad/s/sqrt(s): crosses the flicker floor at ~70 s
    taus = np.logspace(-2.7, 3.5, 60)
    adev = np.sqrt(N**2 / taus + (allan.FLICKER_ADEV_FACTOR * B) ** 2 + K**2 * taus / 3.0)
    p = allan.noise_parameters(taus, adev, "gyro")
    assert p["white_density"] == pytest.approx(N, rel=1e-6)
    assert p["bias_instability"] == pytest.approx(B, rel=1e-6)
    assert p["rate_random_walk"] == pytest.approx(K, rel=1e-6)
    assert p["quantization"] == pytest.approx(0.0, abs=1e-12)
    assert p["arw_dps_rthz"] == pytest.approx(0.01, rel=1e-6)
    assert p["arw_deg_rthr"] == pytest.approx(0.6, rel=1e-6)
    assert p["bias_instability_dps"] == pytest.approx(0.02, rel=1e-6)
    assert p["bias_instability_deg_hr"] == pytest.approx(72.0, rel=1e-6)
    assert p["rrw_deg_hr_rthr"] == pytest.approx(math.degrees(K) * 3600 * 60, rel=1e-6)

    Na, Ba = 5e-6 * G0, 20e-6 * G0
    adev_a = np.sqrt(Na**2 / taus + (allan.FLICKER_ADEV_FACTOR * Ba) ** 2)[:, None] * [1.0, 2.0]
    pa = allan.noise_parameters(taus, adev_a, "accel")
    assert pa["vrw_ug_rthz"] == pytest.approx([5.0, 10.0], rel=1e-6)
    assert pa["vrw_mps_rthr"] == pytest.approx([60 * Na, 120 * Na], rel=1e-6)
    assert pa["bias_instability_ug"] == pytest.approx([20.0, 40.0], rel=1e-6)
    assert np.all(np.isnan(pa["rrw_ug_rthr"]))  # no rate random walk in this curve: not visible
    with pytest.raises(ValueError, match="sensor"):
        allan.noise_parameters(taus, adev, "magnetometer")


# --- sensor model ------------------------------------------------------------------------------


def test_config_from_dict_checks_keys():
    cfg = ImuErrorConfig.from_dict({"rate_hz": 200, "gyro_noise_density_dps_rthz": 0.005})
    assert cfg.rate_hz == 200.0 and cfg.gyro_noise_density_dps_rthz == 0.005
    assert cfg.accel_noise_density_ug_rthz == 5.0 and cfg.gyro_bias_instability_dps == 0.02  # Table 2
    with pytest.raises(ValueError, match="gyro_noise_density"):
        ImuErrorConfig.from_dict({"gyro_noise_dps": 0.01})
    with pytest.raises(ValueError, match="accel_turn_on_bias_ug"):
        ImuErrorConfig.from_dict({"accel_turn_on_bias_ug": -1.0})
    with pytest.raises(ValueError, match="gyro_scale_factor_ppm"):
        ImuErrorConfig.from_dict({"gyro_scale_factor_ppm": "1000"})
    with pytest.raises(ValueError, match="bias_corr_time"):
        ImuErrorConfig.from_dict({"bias_corr_time_min_s": 100.0, "bias_corr_time_max_s": 10.0})


def test_same_seed_same_counts():
    t_s, omega_ib_b, f_b = _static(5000)
    cfg, cal = ImuErrorConfig(), default_calibration()
    a, ra = imu_counts(t_s, omega_ib_b, f_b, cfg, cal, np.random.default_rng(42))
    b, rb = imu_counts(t_s, omega_ib_b, f_b, cfg, cal, np.random.default_rng(42))
    c, _ = imu_counts(t_s, omega_ib_b, f_b, cfg, cal, np.random.default_rng(43))
    assert a.dtype == np.int32 and a.shape == (5000, 6)
    assert np.array_equal(a, b) and np.array_equal(ra["gyro_bias"], rb["gyro_bias"])
    assert not np.array_equal(a, c)



def test_errors_drawn_apart_from_the_signal_give_the_same_counts():
    """``draw_errors`` (here on another thread, as ``sim`` draws them beside the truth) then ``apply_errors``:
    the counts and realised errors of ``imu_counts`` with the same seed, for any true signal, coloured noise
    included."""
    t_s, omega_ib_b, f_b = _static(3000)
    cfg, cal = ImuErrorConfig(gyro_gm_sigma_dps=0.01, accel_gm_sigma_ug=30.0, gm_tau_s=2.0), default_calibration()
    with ThreadPoolExecutor(1) as pool:
        draws = pool.submit(draw_errors, t_s, cfg, np.random.default_rng(11)).result()
    for w, f in ((omega_ib_b, f_b), (omega_ib_b + 0.2, f_b * 1.5)):
        want, want_r = imu_counts(t_s, w, f, cfg, cal, np.random.default_rng(11))
        got, got_r = apply_errors(draws, w, f, cfg, cal)
        assert np.array_equal(got, want) and list(got_r) == list(want_r)
        assert all(np.array_equal(got_r[k], want_r[k]) for k in want_r)


def test_deterministic_errors_are_applied_as_modelled():
    cfg = ImuErrorConfig(
        **{
            **_QUIET,
            "gyro_turn_on_bias_dps": 0.05,
            "gyro_scale_factor_ppm": 5000.0,
            "gyro_misalignment_mrad": 5.0,
            "accel_turn_on_bias_ug": 1000.0,
            "accel_scale_factor_ppm": 5000.0,
            "accel_misalignment_mrad": 5.0,
            "accel_zero_bias_V": 0.2,
        }
    )
    cal = default_calibration()
    rng = np.random.default_rng(5)
    n = 2000
    t_s = np.arange(n) / FS
    omega_ib_b = rng.uniform(-0.3, 0.3, (n, 3))
    f_b = rng.uniform(-15.0, 15.0, (n, 3))
    counts, real = imu_counts(t_s, omega_ib_b, f_b, cfg, cal, rng)
    omega_m, f_m = apply(cal, counts)
    for name, x_true, x_meas, sens in (
        ("gyro", omega_ib_b, omega_m, cal.gyro.sensitivity),
        ("accel", f_b, f_m, cal.accel.sensitivity),
    ):
        gain = (np.eye(3) + np.diag(real[f"{name}_scale_factor"])) @ (np.eye(3) + real[f"{name}_misalignment"])
        expected = x_true @ gain.T + real[f"{name}_bias"]
        assert np.max(np.abs(x_meas - expected) * sens) <= 0.5 * LSB_V * (1 + 1e-6)  # quantisation only
        assert np.all(np.abs(real[f"{name}_scale_factor"]) > 0) and real[f"{name}_misalignment"][0, 1] != 0
    # The 0.2 V electrical zero-g spread shows up as a large accel bias (0.1 g per 0.2 V).
    accel_offset = real["accel_zero_bias_V"] / cal.accel.sensitivity
    assert np.allclose(real["accel_bias"][0], real["accel_turn_on_bias"] + accel_offset)
    assert np.all(np.abs(accel_offset) > 0.01)
    assert real["saturated"].tolist() == [0] * 6


def test_white_noise_follows_the_actual_sample_interval_and_saturation_is_counted():
    cfg = ImuErrorConfig(**{**_QUIET, "gyro_noise_density_dps_rthz": 0.01, "accel_noise_density_ug_rthz": 5.0})
    n = 200_000
    dt = np.where(np.arange(n) % 2 == 0, 0.001, 0.003)  # alternating 1 ms / 3 ms intervals
    t_s = np.cumsum(dt)
    omega_ib_b = np.zeros((n, 3))
    omega_ib_b[:100, 0] = math.radians(25.0)  # beyond the +-20 deg/s range
    f_b = np.tile([0.0, 0.0, G0], (n, 1))
    counts, real = imu_counts(t_s, omega_ib_b, f_b, cfg, default_calibration(), np.random.default_rng(9))
    assert real["saturated"].tolist() == [100, 0, 0, 0, 0, 0]
    omega_m, f_m = apply(default_calibration(), counts)
    short, long_ = slice(102, None, 2), slice(101, None, 2)  # t_s[k] - t_s[k-1] = dt[k]: 1 ms for even k
    for x, density in ((omega_m[:, 1], math.radians(0.01)), (f_m[:, 0], 5e-6 * G0)):
        assert np.std(x[short]) == pytest.approx(density / math.sqrt(0.001), rel=0.02)
        assert np.std(x[long_]) == pytest.approx(density / math.sqrt(0.003), rel=0.02)


def test_flicker_noise_allan_floor():
    rng = np.random.default_rng(11)
    t = np.arange(100_000) / FS
    x = flicker_noise(t, 16, 0.002, 1e4, rng)
    taus, adev = allan.allan_deviation(x, FS, taus=np.array([0.2, 0.5, 1.0, 2.0, 5.0]))
    assert np.mean(adev) == pytest.approx(allan.FLICKER_ADEV_FACTOR, rel=0.05)  # B = 1


# --- acceptance: 2 h static drive -> configured ARW / VRW and bias instability within 15 % -----


def test_two_hour_static_allan_recovers_configured_noise():
    n = int(2 * 3600 * FS)  # 3.6 M samples
    t_s, omega_ib_b, f_b = _static(n)
    cfg, cal = ImuErrorConfig(), default_calibration()
    counts, _ = imu_counts(t_s, omega_ib_b, f_b, cfg, cal, np.random.default_rng(2024))
    omega_m, f_m = apply(cal, counts)
    taus = allan.default_taus(n, FS, per_decade=5)
    taus, adev_g = allan.allan_deviation(omega_m, FS, taus)
    _, adev_a = allan.allan_deviation(f_m, FS, taus)
    g = allan.noise_parameters(taus, adev_g, "gyro")
    a = allan.noise_parameters(taus, adev_a, "accel")
    assert g["arw_dps_rthz"] == pytest.approx([cfg.gyro_noise_density_dps_rthz] * 3, rel=0.15)
    assert g["arw_deg_rthr"] == pytest.approx([60 * cfg.gyro_noise_density_dps_rthz] * 3, rel=0.15)
    assert g["bias_instability_dps"] == pytest.approx([cfg.gyro_bias_instability_dps] * 3, rel=0.15)
    assert a["vrw_ug_rthz"] == pytest.approx([cfg.accel_noise_density_ug_rthz] * 3, rel=0.15)
    assert a["bias_instability_ug"] == pytest.approx([cfg.accel_bias_instability_ug] * 3, rel=0.15)
    assert np.all(np.isnan(g["rate_random_walk"])) and np.all(np.isnan(a["rate_random_walk"]))  # none simulated
    text = allan.report(omega_m[: 60 * 500], f_m[: 60 * 500], FS)
    assert len(text.splitlines()) == 9 and "ARW deg/sqrt(h)" in text and "BI ug" in text


def test_drive_report_reads_the_imu_topic(tmp_path):
    from fieldlog.drive import messages
    from fieldlog.drive.recorder import Recorder

    n = 60 * 500
    t_s, omega_ib_b, f_b = _static(n)
    cal = default_calibration()
    counts, _ = imu_counts(t_s, omega_ib_b, f_b, ImuErrorConfig(), cal, np.random.default_rng(8))
    omega_m, f_m = apply(cal, counts)
    stamp_ns = 1_700_000_000 * 10**9 + np.round((t_s - t_s[0]) * 1e9).astype(np.int64)
    path = tmp_path / "static.mcap"
    with Recorder(path, flush_interval_s=None) as rec:
        rec.write_batch("/imu", stamp_ns, messages.encode_imu(stamp_ns, omega_m, f_m))
    text = allan.drive_report(str(path))
    assert text == allan.report(omega_m, f_m, (n - 1) / ((stamp_ns[-1] - stamp_ns[0]) * 1e-9))
    arw_x = float(text.splitlines()[2].split()[1])  # deg/sqrt(h), gyro x
    assert arw_x == pytest.approx(0.6, rel=0.1)


def test_compiled_first_order_filter_equals_scipy_lfilter_to_the_bit():
    """The flicker noise's Gauss-Markov levels are filtered by a compiled recursion instead of scipy's lfilter
    (scipy.signal is slow to import); the numbers must be lfilter's own."""
    from scipy.signal import lfilter

    from fieldlog.tools.sim.sensors import _ar1

    rng = np.random.default_rng(5)
    for phi in (0.0, 0.3, 0.999, 0.9999999):
        z = rng.standard_normal((2001, 6)) * rng.choice([1e-3, 1.0, 1e3])
        y_prev = rng.standard_normal(6)
        b0 = math.sqrt(1.0 - phi * phi)
        want, _ = lfilter([b0], [1.0, -phi], z, axis=0, zi=phi * y_prev[None, :])
        np.testing.assert_array_equal(_ar1(b0, phi, z, y_prev), want)
