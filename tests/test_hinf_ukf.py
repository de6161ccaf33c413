"""H-infinity filter (``fusion.hinf``) and hybrid KF/UKF (``fusion.ukf``): limits, existence bound, the
nonlinear error model against the linear one and the INS, the UT against Monte Carlo, and both through
`fieldlog fuse` on a short figure-eight."""

import math

import numpy as np
import pytest

from fieldlog.fusion import earth, errmodel, hinf, ins, kf, ukf
from fieldlog.fusion.config import FusionConfig
from fieldlog.drive.reader import read_topic
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.fuse import fuse
from fieldlog.drive.reader import read_metadata

DURATION = 150.0
OUTAGE = (95.0, 25.0)


@pytest.fixture(scope="module")
def drive(figure8_150s_seed3):
    """figure8, DURATION s, seed 3 (conftest; read-only)."""
    return figure8_150s_seed3


def _system(rng):
    """A real 15-state model: P0 (SPD), q, Phi and Q (10 cycles of 0.1 s), GPS H and R."""
    A = rng.standard_normal((15, 15))
    P0 = np.diag(np.r_[np.full(3, 9.0), np.full(3, 0.04), np.full(3, 1e-4), np.full(3, 1e-7), np.full(3, 1e-4)])
    P0 = P0 + 1e-3 * np.sqrt(np.outer(np.diag(P0), np.diag(P0))) * np.tanh(A @ A.T / 15)
    C = earth.euler_to_dcm(0.4, 0.02, -0.01)
    F, G = errmodel.system_matrices(0.5, 50.0, np.array([5.0, 5.0, 0.0]), C, C @ np.array([0.3, -0.2, 9.8]))
    q = errmodel.noise_psd(1e-3, 1e-2, 1e-5, 1e-4)
    Phi, Q = errmodel.discretise(np.repeat(F[None], 10, 0), np.repeat(G[None], 10, 0), q, 0.1)
    H = np.zeros((6, 15))
    H[:, 0:6] = np.eye(6)
    R = np.diag(np.r_[np.full(3, 4.0), np.full(3, 0.01)])
    return P0, q, Phi, Q, H, R


def _nav(heading=0.4):
    C = earth.euler_to_dcm(heading, 0.03, -0.02)
    return ins.NavState(0.0, 0.6, 2.0, 120.0, C @ np.array([0.0, 12.0, 0.0]), earth.dcm_to_quat(C))


# -- H-infinity ------------------------------------------------------------------------------------


def test_hinf_with_huge_gamma_equals_the_kf():
    rng = np.random.default_rng(1)
    P0, q, Phi, Q, H, R = _system(rng)
    k, h = kf.KalmanFilter(P0, q), hinf.HInfinityFilter(P0, q, gamma=1e12)
    imu = (np.array([0.0, 0.0, 0.1]), np.array([-1.2, 0.1, 9.8]))
    for _ in range(4):
        for f in (k, h):
            f.propagate(Phi, Q)
            f.predict(0.1, _nav(), imu)
        z = rng.standard_normal(6) * np.sqrt(np.diag(R))
        dk, dh = k.update(z, H, R), h.update(z, H, R)
        assert np.abs(dk).max() > 0
        assert np.allclose(dh, dk, rtol=1e-9, atol=1e-9 * np.abs(dk).max())
        assert np.allclose(h.state, k.state, rtol=1e-9, atol=1e-9 * np.abs(k.state).max())
        assert np.allclose(h.covariance, k.covariance, rtol=1e-9, atol=1e-12)
        k.reset()
        h.reset()


def test_hinf_finite_gamma_gives_a_larger_covariance_than_the_kf():
    rng = np.random.default_rng(2)
    P0, q, Phi, Q, H, R = _system(rng)
    gamma = 3.0 * hinf.existence_bound(P0, hinf.position_velocity_weights())
    k, h = kf.KalmanFilter(P0, q), hinf.HInfinityFilter(P0, q, gamma)
    for _ in range(3):
        for f in (k, h):
            f.propagate(Phi, Q)
            f.update(np.zeros(6), H, R)
            f.reset()
        diff = h.covariance - k.covariance
        assert np.linalg.eigvalsh(diff).min() > -1e-12 * np.abs(k.covariance).max()  # P_hinf >= P_kf
        assert np.trace(diff[0:6, 0:6]) > 1e-3 * np.trace(k.covariance[0:6, 0:6])
    # and the gap closes as gamma grows
    wide = hinf.HInfinityFilter(P0, q, 30.0 * gamma)
    kk = kf.KalmanFilter(P0, q)
    for f in (wide, kk):
        f.propagate(Phi, Q)
        f.update(np.zeros(6), H, R)
    assert 0 < np.trace(wide.covariance - kk.covariance) < np.trace(h.covariance - k.covariance) / 10


def test_hinf_gamma_below_the_existence_bound_raises():
    rng = np.random.default_rng(3)
    P0, q, _, _, H, R = _system(rng)
    L = hinf.position_velocity_weights()
    bound = hinf.existence_bound(P0, L)
    assert bound == pytest.approx(math.sqrt(np.linalg.eigvalsh(P0[0:6, 0:6])[-1]), rel=1e-9)  # L picks P's block
    with pytest.raises(hinf.GammaTooSmall, match="existence bound"):
        hinf.HInfinityFilter(P0, q, 0.95 * bound).update(np.zeros(6), H, R)
    ok = hinf.HInfinityFilter(P0, q, 1.05 * bound)
    ok.update(np.zeros(6), H, R)
    assert np.linalg.eigvalsh(ok.covariance).min() > 0
    with pytest.raises(ValueError):
        hinf.HInfinityFilter(P0, q, 0.0)


def test_hinf_relative_gamma_policy_keeps_a_margin_over_the_bound():
    rng = np.random.default_rng(4)
    P0, q, _, _, H, R = _system(rng)
    bound = hinf.existence_bound(P0, hinf.position_velocity_weights())
    auto = hinf.HInfinityFilter(P0, q, 0.5 * bound, min_ratio=1.5)
    fixed = hinf.HInfinityFilter(P0, q, 1.5 * bound)
    auto.update(np.zeros(6), H, R)
    fixed.update(np.zeros(6), H, R)
    assert auto.raised == 1 and np.allclose(auto.covariance, fixed.covariance, rtol=1e-12, atol=0)
    loose = hinf.HInfinityFilter(P0, q, 10.0 * bound, min_ratio=1.5)  # gamma already above: untouched
    loose.update(np.zeros(6), H, R)
    assert loose.raised == 0
    with pytest.raises(ValueError, match="min_ratio"):
        hinf.HInfinityFilter(P0, q, bound, min_ratio=0.9)


def test_hinf_small_gamma_rides_through_an_outage_with_the_relative_policy(drive, tmp_path):
    with pytest.raises(hinf.GammaTooSmall):
        fuse(drive, "hinf", tmp_path / "fixed.mcap", FusionConfig.from_flat(outages=(OUTAGE,), hinf_gamma=3.0,
                                                                   hinf_min_ratio=0.0))
    res = fuse(drive, "hinf", tmp_path / "auto.mcap", FusionConfig.from_flat(outages=(OUTAGE,), hinf_gamma=3.0))
    fix = read_topic(res.path, "/fusion/hinf/fix")
    assert np.isfinite(fix["lat_deg"]).all() and fix["log_time_ns"][-1] - fix["log_time_ns"][0] > 100e9
    # the record says which gamma ran: raised above 3 in the outage, so the run's largest gamma exceeds it
    meta = read_metadata(res.path)["fusion.hinf"]
    assert float(meta["gamma"]) == 3.0 and int(meta["raised"]) == res.gamma_raised > 0
    assert float(meta["gamma_run_max"]) > 3.0 and int(meta["paper_gamma_exists"]) < int(meta["epochs"])
    assert meta["equals_kf"] == "false" and float(meta["worst_inflation"]) >= hinf.KF_EQUAL_INFLATION


def test_hinf_defaults_say_which_gamma_ran_and_that_it_equals_kf(drive, tmp_path, capsys):
    """`fieldlog fuse --method hinf` on its defaults prints and records the gamma that ran; there it is the KF."""
    out = tmp_path / "hinf.mcap"
    assert cli_main(["fuse", str(drive), "--method", "hinf", "--out", str(out)]) == 0
    said = capsys.readouterr()
    line = next(x for x in (said.out + said.err).splitlines() if "hinf: gamma" in x)
    meta = read_metadata(out)["fusion.hinf"]
    g = FusionConfig().filter.hinf_gamma
    assert f"configured {g:g}" in line and "equal to kf here" in line and meta["note"] in line
    assert float(meta["gamma_run_min"]) >= g and meta["equals_kf"] == "true"
    assert 1.0 <= float(meta["worst_inflation"]) < hinf.KF_EQUAL_INFLATION
    assert cli_main(["fuse", str(drive), "--method", "kf", "--out", str(tmp_path / "kf.mcap")]) == 0  # same settings
    kf_fix = read_topic(tmp_path / "kf.mcap", "/fusion/kf/fix")
    hinf_fix = read_topic(out, "/fusion/hinf/fix")
    assert np.abs(hinf_fix["lat_deg"] - kf_fix["lat_deg"]).max() * 111e3 < 0.01  # m: "equal" means to the cm


def test_hinf_with_huge_gamma_equals_the_kf_end_to_end(drive, tmp_path):
    cfg = FusionConfig.from_flat(outages=(OUTAGE,), hinf_gamma=1e12)
    a = fuse(drive, "kf", tmp_path / "kf.mcap", cfg).path
    b = fuse(drive, "hinf", tmp_path / "hinf.mcap", cfg).path
    fa, fb = read_topic(a, "/fusion/kf/fix"), read_topic(b, "/fusion/hinf/fix")
    assert len(fa["lat_deg"]) > 1000 and np.array_equal(fa["log_time_ns"], fb["log_time_ns"])
    for k in ("lat_deg", "lon_deg"):
        assert np.abs(fb[k] - fa[k]).max() < 1e-9  # deg, 0.1 mm
    assert np.abs(fb["alt_m"] - fa["alt_m"]).max() < 1e-6
    assert np.allclose(fb["position_covariance"], fa["position_covariance"], rtol=1e-9, atol=1e-12)
    va, vb = read_topic(a, "/fusion/kf/vel"), read_topic(b, "/fusion/hinf/vel")
    assert np.abs(vb["v_n"] - va["v_n"]).max() < 1e-7


# -- nonlinear SINS error model and the UT ---------------------------------------------------------


def test_nonlinear_error_model_linearises_to_the_kf_model():
    lat, h, v = 0.6, 300.0, np.array([12.0, -7.0, 0.5])
    C = earth.euler_to_dcm(0.7, 0.05, -0.03)
    f_b = np.array([0.5, 1.2, 9.8])
    F, _ = errmodel.system_matrices(lat, h, v, C, C @ f_b)
    rm, rn = earth.principal_radii(lat, h)
    to_m = np.array([rn * math.cos(lat), rm, 1.0])

    def rates(x):
        y = x.copy()
        y[0:3] /= to_m
        d = ukf.error_rates(y, lat, h, v, C, f_b)
        d[0:3] *= to_m
        return d

    step = np.r_[np.full(6, 1e-3), np.full(9, 1e-6)]
    J = np.stack([(rates(e) - rates(-e)) / (2 * s) for e, s in zip(np.diag(step), step)], axis=1)
    # equal but for the ~1e-6 /s frame-rotation terms of the position rows (metres vs eq. 11's angles)
    assert np.allclose(J, F, rtol=1e-5, atol=2e-6)
    # velocity and attitude rows to 2e-8: the model's exact normal gravity (its latitude term and the exact
    # height gradient against F's 2 g / R) is all that differs
    assert np.allclose(J[3:9], F[3:9], rtol=1e-5, atol=2e-8)
    assert np.abs(J[3:6, 6:9]).max() > 9.0  # f x phi is there


def _turning_ins(seconds):
    """A car turning at 0.1 rad/s for `seconds`; the true INS run and the cycles (0.1 s) of its nodes."""
    dt, n = 0.01, round(seconds / 0.01)
    t = np.arange(n + 1) * dt
    w = np.tile([0.0, 0.0, 0.1], (n + 1, 1))
    f = np.tile([-1.0, 0.0, 9.80], (n + 1, 1))
    C0 = earth.euler_to_dcm(0.3, 0.0, 0.0)
    true = ins.NavState(0.0, 0.5, 1.8, 400.0, C0 @ np.array([0.0, 10.0, 0.0]), earth.dcm_to_quat(C0))
    sol = ins.integrate(true, t, w, f)
    ends = np.arange(10, n + 1, 10)
    starts = ends - 10
    cyc = ukf.cycles_from_ins(sol.lat, sol.h, sol.v_n, sol.q, starts, starts + 5, ends, np.tile(f[0], (len(ends), 1)),
                              t[ends] - t[starts])
    return true, sol, t, w, f, cyc


def test_nonlinear_model_follows_the_ins_error_where_the_linear_one_does_not():
    """A 15 deg heading error for 20 s: the INS itself (perturbed minus true) against eqs. 9-11 and Phi."""
    true, sol, t, w, f, cyc = _turning_ins(20.0)
    x0 = np.zeros(15)
    x0[6:9] = [0.01, -0.01, math.radians(15.0)]
    x0[12:15] = [2e-3, -1e-3, 0.0]
    Cp = ukf.euler_error_dcm(x0[6:9]) @ true.C_bn  # computed C_bn = C_n^n' C_bn true
    pert = ins.NavState(0.0, true.lat, true.lon, true.h, true.v_n, earth.dcm_to_quat(Cp))
    b = ins.integrate(pert, t, w, f + x0[12:15])
    rm, rn = earth.principal_radii(sol.lat[-1], sol.h[-1])
    err_r = np.array([(b.lon[-1] - sol.lon[-1]) * rn * math.cos(sol.lat[-1]), (b.lat[-1] - sol.lat[-1]) * rm])
    err_v = b.v_n[-1, :2] - sol.v_n[-1, :2]
    # the nodes are the computed (perturbed) INS, as in the filter
    cyc_c = ukf.cycles_from_ins(b.lat, b.h, b.v_n, b.q, np.arange(0, len(t) - 1, 10), np.arange(5, len(t), 10),
                                np.arange(10, len(t), 10), cyc.f_b + x0[12:15], cyc.dt)
    xn = ukf.propagate_samples(x0, cyc_c)
    C = earth.quat_to_dcm(b.q[5::10])
    F, G = errmodel.system_matrices(b.lat[5::10], b.h[5::10], b.v_n[5::10], C, C @ (f[0] + x0[12:15]))
    Phi, _ = errmodel.discretise(F, G, np.eye(12), 0.1)
    xl = x0.copy()
    for P in Phi:
        xl = P @ xl
    assert np.linalg.norm(err_v) > 1.0 and np.linalg.norm(err_r) > 10.0  # a large, nonlinear error
    assert np.linalg.norm(xn[3:5] - err_v) < 0.02 * np.linalg.norm(err_v)
    assert np.linalg.norm(xn[0:2] - err_r) < 0.02 * np.linalg.norm(err_r)
    assert np.linalg.norm(xl[3:5] - err_v) > 3 * np.linalg.norm(xn[3:5] - err_v)


def test_unscented_propagation_matches_monte_carlo_on_a_short_outage():
    """5 s of outage in a turn with a 12 deg heading uncertainty: the UT (31 points) against 8000 samples
    through the same nonlinear model with the same per-cycle noise Q."""
    rng = np.random.default_rng(4)
    *_, cyc = _turning_ins(5.0)
    sd = np.r_[np.full(3, 2.0), np.full(3, 0.1), math.radians(1.0), math.radians(1.0), math.radians(12.0),
               np.full(3, math.radians(0.05)), np.full(3, 5e-3)]
    P0 = np.diag(sd ** 2)
    q = errmodel.noise_psd(math.radians(0.05), 3e-3, math.radians(1e-3), 1e-4)
    C = cyc.C_bn[:, 1]
    F, G = errmodel.system_matrices(cyc.lat[:, 1], cyc.h[:, 1], cyc.v_n[:, 1], C, np.einsum("kij,kj->ki", C, cyc.f_b))
    Phi, Q = errmodel.discretise(F, G, q, cyc.dt)
    u = ukf.HybridKfUkf(P0, q)
    u.start_outage()
    u.queue(cyc)
    u.propagate(Phi, Q)

    X = rng.standard_normal((8000, 15)) * sd
    for i in range(len(cyc)):
        w, V = np.linalg.eigh(Q[i])
        noise = (rng.standard_normal((len(X), 15)) * np.sqrt(np.maximum(w, 0.0))) @ V.T
        X = ukf.propagate_samples(X, cyc[i:i + 1]) + noise
    P_mc = np.cov(X.T)
    m = slice(0, 9)  # position, velocity, attitude (the biases only take Q)
    rel = np.abs(np.diag(u.covariance)[m] / np.diag(P_mc)[m] - 1.0)
    assert rel.max() < 0.05, rel
    s = np.sqrt(np.diag(P_mc))
    assert np.abs((u.covariance - P_mc) / np.outer(s, s))[m, m].max() < 0.05  # correlations too
    # the nonlinear mean shift (the linear prediction keeps x = 0) is the Monte Carlo's
    mc_mean, se = X.mean(axis=0), X.std(axis=0) / np.sqrt(len(X))
    assert abs(mc_mean[3]) > 5 * se[3]
    assert abs(u.state[3] - mc_mean[3]) < 0.25 * abs(mc_mean[3])


def test_kf_ukf_through_fieldlog_fuse_with_an_outage(drive, tmp_path):
    out = tmp_path / "kf-ukf.mcap"
    spec = f"{OUTAGE[0]:g}:{OUTAGE[1]:g}"
    assert cli_main(["fuse", str(drive), "--method", "kf-ukf", "--outage", spec, "--out", str(out)]) == 0
    ref = tmp_path / "kf.mcap"  # the same command, the same installation pass
    assert cli_main(["fuse", str(drive), "--method", "kf", "--outage", spec, "--out", str(ref)]) == 0
    t0 = int(read_topic(drive, "/imu")["log_time_ns"][0])
    su, sk = read_topic(out, "/fusion/kf-ukf/std"), read_topic(ref, "/fusion/kf/std")
    assert np.array_equal(su["log_time_ns"], sk["log_time_ns"])
    t = su["log_time_ns"]
    inside = (t > t0 + int((OUTAGE[0] + 2) * 1e9)) & (t < t0 + int(sum(OUTAGE) * 1e9))
    assert not np.allclose(su["xyz"][inside], sk["xyz"][inside], rtol=1e-6)  # the UT ran in the outage ...
    before = t < t0 + int(OUTAGE[0] * 1e9)
    assert np.allclose(su["xyz"][before], sk["xyz"][before])  # the same linear KF before it
    # ... and its covariance grew through it as the KF's did (the printed sigma also carries the correlated GPS
    # term, the same for both: compare the growth of the variance)
    grow_u, grow_k = (float(s["xyz"][inside][-1, 0] ** 2 - s["xyz"][inside][0, 0] ** 2) for s in (su, sk))
    assert grow_k > 0.0 and 0.5 * grow_k < grow_u < 2.0 * grow_k, (grow_u, grow_k)
    tr = read_topic(drive, "/truth/fix")
    after = (t0 + int(sum(OUTAGE) * 1e9), t0 + int((sum(OUTAGE) + 20) * 1e9))
    errs = []
    for path, method in ((out, "kf-ukf"), (ref, "kf")):
        s = read_topic(path, f"/fusion/{method}/fix")
        m = (s["log_time_ns"] >= after[0]) & (s["log_time_ns"] < after[1])
        lat = np.radians(np.interp(s["log_time_ns"][m], tr["log_time_ns"], tr["lat_deg"]))
        lon = np.radians(np.interp(s["log_time_ns"][m], tr["log_time_ns"], tr["lon_deg"]))
        rm, rn = earth.principal_radii(lat, 0.0)
        de = (np.radians(s["lon_deg"][m]) - lon) * rn * np.cos(lat)
        dn = (np.radians(s["lat_deg"][m]) - lat) * rm
        errs.append(float(np.sqrt(np.mean(de ** 2 + dn ** 2))))
    assert errs[0] < 10.0 and errs[0] < 1.2 * errs[1] + 0.5, errs  # reconverges like the kf after the outage


def test_hinf_inflates_once_per_epoch_not_at_each_update():
    rng = np.random.default_rng(6)
    P0, q, Phi, Q, H, R = _system(rng)
    gamma = 2.0 * hinf.existence_bound(P0, hinf.position_velocity_weights())
    h = hinf.HInfinityFilter(P0, q, gamma)
    k = kf.KalmanFilter(h.inflated(), q)  # the epoch's Pbar, then plain KF updates
    z1, z2 = rng.standard_normal(6) * 0.1, rng.standard_normal(6) * 0.1
    for f in (h, k):
        f.update(z1[:3], H[3:], R[3:, 3:])  # e.g. a velocity aid, then the GPS, at one epoch
        f.update(z2, H, R)
    assert np.allclose(h.covariance, k.covariance, rtol=1e-10, atol=1e-14)
    h.propagate(Phi, Q)  # the next epoch inflates again
    plain = kf.KalmanFilter(h.covariance.copy(), q)
    inflated = kf.KalmanFilter(h.inflated(), q)
    for f in (h, plain, inflated):
        f.update(z1, H, R)
    assert np.allclose(h.covariance, inflated.covariance, rtol=1e-10, atol=1e-14)
    assert not np.allclose(h.covariance, plain.covariance, rtol=1e-6, atol=0)
