"""Square-root cubature filters (``fusion.sckf``): the cubature rules' degree, the square-root time update and
both measurement updates against the KF on a linear model, the nonlinear time update against the KF for small
errors, the moving-window R (tracking a tripled GPS noise, its floor) and `fieldlog fuse` with sckf and ssr-sckf."""

import math
from itertools import combinations_with_replacement

import numpy as np
import pytest
from test_fusion import _errors

from fieldlog.fusion import earth, errmodel, ins, kf, measurements, sckf, ukf
from fieldlog.fusion.config import FusionConfig
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.fuse import fuse

N = 15
RULES = {"spherical-radial": sckf.spherical_radial_rule(N), "simplex-radial": sckf.simplex_radial_rule(N)}


@pytest.fixture(scope="module")
def drive(figure8_150s_seed3):
    """figure8, 150 s, seed 3 (conftest; read-only)."""
    return figure8_150s_seed3


def _gauss_moment(powers: np.ndarray) -> float:
    """E[prod x_i^p_i] for x ~ N(0, I): prod (p_i - 1)!! over even p_i, 0 if any p_i is odd."""
    if (powers % 2).any():
        return 0.0
    return float(np.prod([math.prod(range(p - 1, 0, -2)) for p in powers]))


def _rule_errors(rule: sckf.Rule, degree: int) -> np.ndarray:
    """|rule - Gaussian expectation| of every monomial of exactly this degree in N variables."""
    xi, w = rule
    errs = []
    for idx in combinations_with_replacement(range(N), degree):
        powers = np.bincount(np.array(idx, dtype=int), minlength=N)
        errs.append(abs(w @ np.prod(xi[:, list(idx)], axis=1) - _gauss_moment(powers)))
    return np.array(errs)


def _system(rng):
    """A 15-state model: P0 (SPD, correlated), Phi and Q of 10 cycles of 0.1 s, a nav state for the GPS rows."""
    A = rng.standard_normal((N, N))
    P0 = np.diag(np.r_[np.full(3, 9.0), np.full(3, 0.04), np.full(3, 1e-4), np.full(3, 1e-7), np.full(3, 1e-4)])
    P0 = P0 + 1e-3 * np.sqrt(np.outer(np.diag(P0), np.diag(P0))) * np.tanh(A @ A.T / N)
    C = earth.euler_to_dcm(0.4, 0.02, -0.01)
    F, G = errmodel.system_matrices(0.5, 50.0, np.array([5.0, 5.0, 0.0]), C, C @ np.array([0.3, -0.2, 9.8]))
    q = errmodel.noise_psd(1e-3, 1e-2, 1e-5, 1e-4)
    Phi, Q = errmodel.discretise(np.repeat(F[None], 10, 0), np.repeat(G[None], 10, 0), q, 0.1)
    nav = ins.NavState(0.0, 0.5, 2.0, 50.0, C @ np.array([0.0, 7.0, 0.0]), earth.dcm_to_quat(C))
    return P0, q, Phi, Q, nav


def _gps(nav, rng, pos_sd=1.5, vel_sd=0.1):
    """Real GPS rows (lever arm 1 m: H has attitude and gyro-bias columns) with random z."""
    lever = np.array([0.3, 1.0, 1.2])
    pos = measurements.position_measurement(nav, 0.0, nav.lat, nav.lon, nav.h, pos_sd ** 2 * np.eye(3), lever)
    vel = measurements.velocity_measurement(nav, nav.v_n, vel_sd ** 2 * np.eye(3), np.array([0.0, 0.0, 0.2]), lever, 100.0)
    pos = (rng.standard_normal(3) * pos_sd, pos[1], pos[2])
    vel = (rng.standard_normal(3) * vel_sd, vel[1], vel[2])
    return vel, pos


def _linear_predict(f: sckf.CubatureKF, Phi: np.ndarray, Q: np.ndarray) -> None:
    """The filter's cubature time update with the linear model Phi instead of the nonlinear one."""
    xi, w = f.rule
    for i in range(len(Phi)):
        X = (f.x + xi @ f.S.T) @ Phi[i].T
        f.x, f.S = sckf.time_update(X, w, sckf.psd_sqrt(Q[i]))


def _rel(A: np.ndarray, P: np.ndarray) -> float:
    """max |A - P|_ij / sqrt(P_ii P_jj): covariance difference in correlation units."""
    s = np.sqrt(np.diag(P))
    return float(np.abs((A - P) / np.outer(s, s)).max())


# -- cubature rules ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", RULES)
def test_rules_are_exact_to_degree_3_and_not_4(name):
    _, w = RULES[name]
    assert len(w) == {"spherical-radial": 2 * N, "simplex-radial": 2 * (N + 1)}[name]  # 30, 32: Table 1
    assert (w > 0).all() and abs(w.sum() - 1.0) < 1e-14
    for degree in (1, 2, 3):  # all 816 monomials of degree <= 3 in 15 variables (with the constant)
        assert _rule_errors(RULES[name], degree).max() < 1e-12, degree
    assert _rule_errors(RULES[name], 4).max() > 1.0  # e.g. E[x_1^4] = 3


def test_simplex_vertices_of_eq_14():
    a = sckf.simplex_vertices(N)
    assert a.shape == (N + 1, N)
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-15)
    assert np.abs(a.sum(axis=0)).max() < 1e-14
    assert np.allclose(a.T @ a, (N + 1) / N * np.eye(N), atol=1e-14)
    # the n + 1 vertices alone (one-sided, 16 points) are only a degree-2 rule: the +-pairs are needed for 3
    half = (math.sqrt(N) * a, np.full(N + 1, 1.0 / (N + 1)))
    assert _rule_errors(half, 2).max() < 1e-12 and _rule_errors(half, 3).max() > 0.1


# -- square-root form and the updates against the KF on a linear model -------------------------------


@pytest.mark.parametrize("name", RULES)
def test_square_root_time_update_equals_the_full_covariance_form(name):
    rng = np.random.default_rng(1)
    P0, q, Phi, Q, _ = _system(rng)
    k = kf.KalmanFilter(P0, q)
    k.x = rng.standard_normal(N) * np.sqrt(np.diag(P0))
    c = sckf.CubatureKF(P0, q, RULES[name], svd=True, adaptive=None)
    c.x = k.x.copy()
    for _ in range(3):
        k.propagate(Phi, Q)
        _linear_predict(c, Phi, Q)
        assert _rel(c.covariance, k.covariance) < 1e-9
        assert np.allclose(c.state, k.state, rtol=0, atol=1e-9 * np.sqrt(np.diag(k.covariance)).max())
    assert np.allclose(np.triu(c.S, 1), 0.0)  # a triangular factor (QR), not a full P


@pytest.mark.parametrize("name,svd", [("spherical-radial", False), ("simplex-radial", True),
                                      ("simplex-radial", False), ("spherical-radial", True)])
def test_cubature_and_svd_updates_equal_the_kf_update(name, svd):
    rng = np.random.default_rng(2)
    P0, q, Phi, Q, nav = _system(rng)
    k = kf.KalmanFilter(P0, q)
    c = sckf.CubatureKF(P0, q, RULES[name], svd=svd, adaptive=None)
    for epoch in range(5):
        k.propagate(Phi, Q)
        _linear_predict(c, Phi, Q)
        vel, pos = _gps(nav, rng)
        if epoch == 3:
            vel = None  # position alone
        k.update_gps(vel, pos)
        c.update_gps(vel, pos)
        assert np.abs(k.state).max() > 0
        assert np.allclose(c.state, k.state, rtol=0, atol=1e-9 * np.abs(k.state).max())
        assert _rel(c.covariance, k.covariance) < 1e-9
        assert np.allclose(c.R, pos[2] if vel is None else np.diag(np.r_[np.full(3, 0.01), np.full(3, 2.25)]))
        k.reset()
        c.reset()
        assert not c.state.any()


def test_svd_update_survives_a_singular_innovation_covariance():
    """P_zz singular (R = 0 on a state with zero variance): the pseudo-inverse of eq. 19 leaves it unchanged."""
    P = np.diag(np.r_[np.zeros(1), np.ones(N - 1)])
    S = np.sqrt(P)
    H = np.zeros((2, N))
    H[0, 0], H[1, 1] = 1.0, 1.0
    x, S2 = sckf.svd_update(np.zeros(N), S, np.array([5.0, 1.0]), H, np.diag([0.0, 1.0]))
    assert x[0] == 0.0 and x[1] == pytest.approx(0.5)  # the unobservable-and-noiseless row is ignored
    assert np.isfinite(S2).all() and (S2 @ S2.T)[1, 1] == pytest.approx(0.5)


# -- the nonlinear time update ---------------------------------------------------------------------


def _straight_nav():
    C = earth.euler_to_dcm(0.3, 0.0, 0.0)
    return ins.NavState(0.0, 0.5, 1.8, 400.0, C @ np.array([0.0, 10.0, 0.0]), earth.dcm_to_quat(C))


def test_nonlinear_time_update_is_the_kf_prediction_for_small_errors():
    """10 s with small errors, the nav state held (``predict``): the cubature points through the nonlinear model
    give the KF's Phi P Phi^T + Q; the hybrid filter's points (ukf.propagate_points) agree."""
    nav, f_b = _straight_nav(), np.array([0.0, 0.0, 9.79])
    sd = np.r_[np.full(3, 0.1), np.full(3, 0.01), np.full(3, 1e-4), np.full(3, 1e-6), np.full(3, 1e-4)]
    P0 = np.diag(sd ** 2)
    q = errmodel.noise_psd(1e-3, 1e-3, 1e-6, 1e-5)
    filters = [kf.KalmanFilter(P0, q), sckf.sckf(P0, q), sckf.ssr_sckf(P0, q)]
    for _ in range(100):
        for f in filters:
            f.predict(0.1, nav, (np.zeros(3), f_b))
    k, sr, ssr = filters
    for c in (sr, ssr):
        assert _rel(c.covariance, k.covariance) < 2e-3
    assert k.covariance[0, 0] > 3 * P0[0, 0]  # it did grow
    # the KF keeps x = 0; the points carry the second-order mean shift, mostly dv_U = -g E[1 - cos(tilt)]
    # (the tilt sigma reaches 3 mrad), the same for both third-degree rules
    shift = sr.state / np.sqrt(np.diag(k.covariance))
    assert not k.state.any() and np.argmax(np.abs(shift[0:9])) == 5 and 0.01 < abs(shift[5]) < 0.1
    assert np.allclose(ssr.state, sr.state, rtol=0, atol=0.01 * np.abs(sr.state).max())


# -- adaptive R ------------------------------------------------------------------------------------


def test_adaptive_r_tracks_a_tripled_gps_noise():
    """Closed loop on the nonlinear error model (the truth error propagated like the filter's points, plus the
    process noise; 0.5 s cycles); GPS noise x3 from 60 s to 120 s. The window R follows it up within 30 s and
    back down."""
    rng = np.random.default_rng(5)
    nav, f_b = _straight_nav(), np.array([0.0, 0.0, 9.79])
    cyc = ukf.cycle_at(nav, f_b, 0.5)
    F, G = errmodel.system_matrices(nav.lat, nav.h, nav.v_n, nav.C_bn, nav.C_bn @ f_b)
    q = errmodel.noise_psd(math.radians(0.01), 3e-3, math.radians(1e-4), 1e-4)
    Phi, Q = errmodel.discretise(F[None], G[None], q, np.array([0.5]))
    SQ = sckf.psd_sqrt(Q[0])
    sd0 = np.r_[np.full(3, 2.0), np.full(3, 0.1), np.radians([0.5, 0.5, 2.0]), np.full(3, 1e-4), np.full(3, 0.01)]
    adaptive, plain = sckf.ssr_sckf(np.diag(sd0 ** 2), q), sckf.sckf(np.diag(sd0 ** 2), q)
    H = np.zeros((6, N))  # z = [dv; dp] as the engine stacks them
    H[0:3, 3:6], H[3:6, 0:3] = np.eye(3), np.eye(3)
    R_nom = np.diag(np.r_[np.full(3, 0.1 ** 2), np.full(3, 1.5 ** 2)])
    truth = {id(f): rng.standard_normal(N) * sd0 for f in (adaptive, plain)}
    ratio, err = [], {id(f): [] for f in (adaptive, plain)}
    for t in range(1, 181):
        factor = 3.0 if 60 < t <= 120 else 1.0
        v = rng.standard_normal(6) * np.sqrt(np.diag(R_nom)) * factor
        for f in (adaptive, plain):
            e = truth[id(f)]
            for _ in range(2):
                f.queue(cyc)
                f.propagate(Phi, Q)
                e = ukf.propagate_samples(e, cyc) + SQ @ rng.standard_normal(N)
            z = H @ e + v
            f.update_gps((z[0:3], H[0:3], R_nom[0:3, 0:3]), (z[3:6], H[3:6], R_nom[3:6, 3:6]))
            e = e - f.state  # the correction fed back into the INS
            f.reset()
            truth[id(f)] = e
            err[id(f)].append(e[0:3])
        ratio.append(np.sqrt(np.diag(adaptive.R) / np.diag(R_nom)))
        assert np.array_equal(plain.R, R_nom)
    ratio = np.array(ratio)  # (180, 6), row t - 1
    assert (ratio[:20] == 1.0).all()  # nominal until the window (20 epochs before this one) is full
    assert (ratio >= 1.0).all() and (ratio[20:60] > 1.0).any()  # the default floor: R is only inflated
    assert (ratio[40:60] < 1.6).all()
    up = ratio[60:90]  # the 30 s after the step
    assert (up >= 2.5).any(axis=0).all(), up.max(axis=0)  # every channel reaches 2.5 x nominal
    assert (ratio[100:120] > 2.0).all()
    assert (ratio[150:180] < 1.6).all() and (ratio[150:180] > 0.5).all()  # back within 30 s of the drop
    # the adaptive filter's position error in the noisy phase is no worse than the filter that keeps R
    noisy = slice(80, 120)
    rms = {k: float(np.sqrt(np.mean(np.square(np.array(v)[noisy])))) for k, v in err.items()}
    assert rms[id(adaptive)] < 1.05 * rms[id(plain)], rms
    # a non-GPS aid (here a zero-rate update of the gyro bias) goes through update(): its R as given, no window
    H_aid, R_aid = np.zeros((3, N)), 1e-8 * np.eye(3)
    H_aid[:, 9:12] = np.eye(3)
    adaptive.update(np.zeros(3), H_aid, R_aid)
    assert adaptive.adaptive.epochs == 180 and adaptive.R is R_aid


def test_window_r_floor_when_the_estimate_is_not_positive_definite():
    R_nom = np.diag([4.0, 1.0, 0.25])
    ch = np.array([0, 1, 5])
    w = sckf.MovingWindowR(window=4, floor=0.1)
    for _ in range(3):
        w.push(ch, np.zeros(3), 2.0 * R_nom, R_nom)  # y = 0, H P H^T > 0: R_y - H P H^T = -2 R_nom
    assert w.estimate(ch, R_nom) is R_nom  # window not yet full
    w.push(ch, np.zeros(3), 2.0 * R_nom, R_nom)
    assert np.allclose(w.estimate(ch, R_nom), 0.1 * R_nom) and w.floored == 1
    # indefinite: one direction large, the others negative -> kept where above the floor, floored elsewhere
    w = sckf.MovingWindowR(window=4, floor=0.1)
    for _ in range(4):
        w.push(ch, np.array([6.0, 0.0, 0.0]), 0.5 * R_nom, R_nom)  # D = diag(36 - 2, -0.5, -0.125)
    R = w.estimate(ch, R_nom)
    assert np.allclose(R, np.diag([34.0, 0.1, 0.025]))
    assert np.linalg.eigvalsh(R).min() > 0
    # fewer than half the window has the requested channels: nominal
    w.push(np.array([0, 1]), np.zeros(2), np.zeros((2, 2)), R_nom[:2, :2])
    w.push(np.array([0, 1]), np.zeros(2), np.zeros((2, 2)), R_nom[:2, :2])
    w.push(np.array([0, 1]), np.zeros(2), np.zeros((2, 2)), R_nom[:2, :2])
    assert w.estimate(ch, R_nom) is R_nom
    assert np.allclose(w.estimate(ch[:2], R_nom[:2, :2]), np.diag([8.5, 0.1]))  # 3 epochs of zeros, 1 of 34


# -- fieldlog fuse ---------------------------------------------------------------------------------


def test_fuse_sckf_and_ssr_sckf_position_close_to_kf(drive, tmp_path):
    ref = fuse(drive, "kf", tmp_path / "kf.mcap", FusionConfig()).path
    kf_pos = _errors(drive, ref, "kf")[0]
    for method in ("sckf", "ssr-sckf"):
        out = tmp_path / f"{method}.mcap"
        assert cli_main(["fuse", str(drive), "--method", method, "--out", str(out)]) == 0
        pos, vel, _, _ = _errors(drive, out, method)
        print(f"{method}: position RMS {pos:.2f} m (kf {kf_pos:.2f} m), velocity RMS {vel:.3f} m/s")
        assert pos < 1.5 * kf_pos + 0.5 and vel < 0.2
