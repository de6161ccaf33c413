"""The wheel-speed odometer's measurement model and scale-factor fit (fusion/odometer.py)."""
from __future__ import annotations

import numpy as np

from fieldlog.fusion import earth
from fieldlog.fusion.errmodel import ATT, BG, N_STATES, VEL
from fieldlog.fusion.ins import NavState
from fieldlog.fusion.odometer import ScaleEstimator, odometer_measurement


def _nav(v_n, heading, pitch=0.02, roll=-0.01):
    C_bn = earth.euler_to_dcm(heading, pitch, roll)
    return NavState(0.0, 0.8, 0.2, 100.0, np.asarray(v_n, float), earth.dcm_to_quat(C_bn))


def test_the_jacobian_matches_the_model_by_finite_differences():
    rng = np.random.default_rng(2)
    C_bn = earth.euler_to_dcm(0.7, 0.02, -0.01)
    v_b_true = np.array([0.0, 12.0, 0.0])
    r_b = np.array([0.1, -1.3, -0.3])
    omega = np.array([0.01, -0.02, 0.15])
    v_n = C_bn @ (v_b_true - np.cross(omega, r_b))      # the rear axle's centre moves straight ahead
    true = NavState(0.0, 0.8, 0.2, 100.0, v_n, earth.dcm_to_quat(C_bn))
    z0, H, R = odometer_measurement(true, omega, r_b, 12.0 * 1.003, 1e-6, 1.003, 0.0, 0.05)
    np.testing.assert_allclose(z0, 0.0, atol=1e-9)                  # the truth fits exactly
    dx = np.zeros(N_STATES)
    dx[VEL] = rng.normal(0, 0.05, 3)
    dx[ATT] = rng.normal(0, 1e-3, 3)
    dx[BG] = rng.normal(0, 1e-3, 3)
    phi = dx[ATT]
    C_c = (np.eye(3) - earth.skew(phi)) @ C_bn                     # errors: computed - true (bias: true - est.)
    comp = NavState(0.0, 0.8, 0.2, 100.0, v_n + dx[VEL], earth.dcm_to_quat(C_c))
    z1 = odometer_measurement(comp, omega + dx[BG], r_b, 12.0 * 1.003, 1e-6, 1.003, 0.0, 0.05)[0]
    np.testing.assert_allclose(z1 - z0, H @ dx, rtol=0.02, atol=2e-6)
    assert R[1, 1] < R[0, 0] == R[2, 2]


def test_a_stopped_wheel_is_a_zero_velocity_update():
    nav = _nav([0.2, -0.1, 0.05], 1.0)
    z, H, R = odometer_measurement(nav, np.zeros(3), np.zeros(3), 0.0, 1e-6, 1.004, 0.002, 0.05)
    np.testing.assert_allclose(z, nav.C_bn.T @ nav.v_n)           # the whole INS body velocity is the error
    np.testing.assert_allclose(np.linalg.norm(z), np.linalg.norm(nav.v_n))
    assert R[1, 1] == 1e-6 / 1.004 ** 2                            # no scale term at zero speed


def test_scale_fit_finds_the_tyre_error_within_its_sigma():
    rng = np.random.default_rng(5)
    est = ScaleEstimator()
    assert est.scale == 1.0 and est.sigma == est.prior_sigma       # nothing fitted yet
    s_true = 1.0042
    t = np.arange(0, 600, 0.02)
    v = 12 + 6 * np.sin(t / 30)
    sigma_ins = 0.03
    ins_err = np.repeat(rng.normal(0, sigma_ins, len(t) // 50 + 1), 50)[:len(t)]   # correlated over a second
    for ti, vi, ei in zip(t, v, ins_err):
        wheel = round(s_true * vi / 0.0028) * 0.0028                # a 0.01 km/h signal
        est.add(float(ti), wheel, float(vi + ei), sigma_ins ** 2)
    assert est.ready
    assert abs(est.scale - s_true) < 3 * est.sigma, (est.scale, est.sigma)
    assert est.sigma < 3e-4
    # slow samples do not count
    slow = ScaleEstimator()
    for ti in range(1000):
        slow.add(ti * 0.02, 1.0, 1.0, 1e-4)
    assert not slow.ready
