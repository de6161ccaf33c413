from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from fieldlog.fusion import earth, ins
from fieldlog.tools.sim import trajectory as tj


@pytest.fixture(scope="module")
def figure8():
    return tj.generate(tj.load_scenario("figure8"))


def _daq_times(duration_s: float, rate_hz: float = 500.0, ppm: float = 40.0) -> np.ndarray:
    """Sample instants of a DAQ clock running ppm fast, with a slow wander of +-0.2 ms."""
    k = np.arange(int(duration_s * rate_hz * (1 + ppm * 1e-6)))
    t = k / (rate_hz * (1 + ppm * 1e-6)) + 2e-4 * np.sin(2 * np.pi * k / rate_hz / 97.0)
    return t[t <= duration_s]


def _errors(truth: tj.TruthSample, sol: ins.NavSolution):
    rm, rn = earth.principal_radii(truth.lat, truth.h)
    d_hor = np.hypot((sol.lat - truth.lat) * rm, (sol.lon - truth.lon) * rn * np.cos(truth.lat))
    d_ver = np.abs(sol.h - truth.h)
    d_vel = np.abs(sol.v_n - truth.v_n).max(axis=1)
    dq = earth.quat_multiply(sol.q, truth.q * np.array([-1.0, -1.0, -1.0, 1.0]))
    d_att = np.linalg.norm(earth.quat_to_rotvec(dq), axis=1)
    return d_hor.max(), d_ver.max(), d_vel.max(), d_att.max()


def _run_perfect_ins(truth: tj.Truth, duration_s: float):
    t = _daq_times(duration_s)
    s = truth.evaluate(t)
    state = ins.NavState(t[0], s.lat[0], s.lon[0], s.h[0], s.v_n[0], s.q[0])
    return s, ins.integrate(state, t, s.omega_ib_b, s.f_b)


def test_scenarios_load():
    for name, dur in [("figure8", 600.0), ("urban", 900.0), ("static", 7200.0)]:
        sc = tj.load_scenario(name)
        assert sc.name == name and sc.duration_s == dur and sc.description
        assert sc.imu["rate_hz"] == 500 and sc.gps["rate_hz"] == 1
        assert isinstance(sc.clock, dict)
    urban = tj.load_scenario("urban")
    lengths = [length for _, length in urban.gps["outages"]]
    assert len(lengths) >= 3 and min(lengths) >= 20 and max(lengths) <= 90
    assert all(5 <= factor <= 10 for _, _, factor in urban.gps["degraded"])


def test_loader_rejects_typos(tmp_path):
    text = (tj.SCENARIO_DIR / "figure8.toml").read_text().replace("distance_m = 80.0", "distanse_m = 80.0")
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ValueError, match="unknown keys"):
        tj.load_scenario(p)


def test_figure8_shape(figure8):
    sc = figure8.scenario
    t = np.arange(0.0, 600.0, 0.05)
    s = figure8.evaluate(t)
    speed = np.linalg.norm(s.v_n, axis=1)
    assert np.all(speed[t < sc.motion.static_s] < 1e-9)
    assert 9.9 < speed[t > 60].min() and speed.max() < 10.0 + 1e-9
    p = figure8.local_position(t)
    size = p.max(axis=0) - p.min(axis=0)
    assert 100 < size[0] < 400 and 100 < size[1] < 400 and size[2] < 1e-6
    # the track is a figure eight: the heading turns both ways by a full loop
    dpsi = np.unwrap(s.heading)
    assert dpsi.max() - dpsi.min() > 1.4 * np.pi
    assert np.degrees(np.abs(s.roll)).max() < 2.0


def test_truth_is_self_consistent(figure8):
    """Finite differences of the truth obey the INS equations (independent of fusion.ins)."""
    t = np.sort(np.random.default_rng(1).uniform(40.0, 590.0, 400))
    d = 1e-3
    s, sp, sm = figure8.evaluate(t), figure8.evaluate(t + d), figure8.evaluate(t - d)
    # position rate
    v_e = (sp.r_e - sm.r_e) / (2 * d)
    v_n = np.einsum("nij,nj->ni", earth.C_en(s.lat, s.lon), v_e)
    np.testing.assert_allclose(v_n, s.v_n, atol=1e-5)
    # velocity rate: dv_n/dt = C_bn f_b - (2 w_ie + w_en) x v_n + g_n
    w_ie, w_en = earth.omega_ie_n(s.lat), earth.omega_en_n(s.lat, s.h, s.v_n)
    dv = np.einsum("nij,nj->ni", s.C_bn, s.f_b) - np.cross(2 * w_ie + w_en, s.v_n) + earth.gravity_n(s.lat, s.h)
    np.testing.assert_allclose((sp.v_n - sm.v_n) / (2 * d), dv, atol=1e-5)
    # attitude rate: C_bn^T dC_bn/dt = [omega_nb_b x], omega_nb_b = omega_ib_b - C_bn^T omega_in_n
    S = np.einsum("nji,njk->nik", s.C_bn, (sp.C_bn - sm.C_bn) / (2 * d))
    w_nb = np.stack([S[:, 2, 1], S[:, 0, 2], S[:, 1, 0]], axis=1)
    expect = s.omega_ib_b - np.einsum("nji,nj->ni", s.C_bn, w_ie + w_en)
    np.testing.assert_allclose(w_nb, expect, atol=1e-7)
    np.testing.assert_allclose(earth.quat_to_dcm(s.q), s.C_bn, atol=1e-14)


def test_imu_output_is_smooth(figure8):
    """Angular acceleration and jerk are finite: no steps between consecutive 500 Hz samples."""
    s = figure8.evaluate(np.arange(0.0, 600.0, 0.002))
    assert np.abs(np.diff(s.omega_ib_b, axis=0)).max() < 0.002 * 1.0  # < 1 rad/s^2
    assert np.abs(np.diff(s.f_b, axis=0)).max() < 0.002 * 5.0  # < 5 m/s^3


def test_perfect_ins_figure8(figure8):
    s, sol = _run_perfect_ins(figure8, 600.0)
    d_hor, d_ver, d_vel, d_att = _errors(s, sol)
    # tighter than the target of 0.5 m, 0.01 m/s (docs/results.md)
    assert d_hor < 0.1 and d_ver < 0.01 and d_vel < 1e-3 and d_att < 1e-6


def test_perfect_ins_urban():
    truth = tj.generate(tj.load_scenario("urban"), 300.0)
    s, sol = _run_perfect_ins(truth, 300.0)
    d_hor, d_ver, d_vel, d_att = _errors(s, sol)
    assert d_hor < 0.05 and d_ver < 0.01 and d_vel < 1e-3 and d_att < 1e-6


def test_static_imu_and_ins():
    sc = tj.load_scenario("static")
    truth = tj.generate(sc, 600.0)
    t = _daq_times(600.0)
    s = truth.evaluate(t)
    g = earth.gravity(s.lat, s.h)
    np.testing.assert_allclose(s.f_b, np.stack([0 * g, 0 * g, g], axis=1), atol=1e-12)
    w_b = np.einsum("nji,nj->ni", s.C_bn, earth.omega_ie_n(s.lat))
    np.testing.assert_allclose(s.omega_ib_b, w_b, atol=1e-18)
    lat0 = np.radians(sc.origin.lat_deg)
    psi = np.radians(sc.motion.initial_heading_deg)
    expect = earth.OMEGA_IE * np.array([-np.cos(lat0) * np.sin(psi), np.cos(lat0) * np.cos(psi), np.sin(lat0)])
    np.testing.assert_allclose(s.omega_ib_b[0], expect, atol=1e-15)
    np.testing.assert_allclose(s.heading, psi, atol=1e-12)
    state = ins.NavState(t[0], s.lat[0], s.lon[0], s.h[0], s.v_n[0], s.q[0])
    d_hor, d_ver, d_vel, d_att = _errors(s, ins.integrate(state, t, s.omega_ib_b, s.f_b))
    assert d_hor < 1e-6 and d_ver < 1e-6 and d_vel < 1e-8 and d_att < 1e-10


def test_step_and_blocks_match_integrate(figure8):
    t = _daq_times(60.0)
    t = t[t > 40.0]
    s = figure8.evaluate(t)
    state = ins.NavState(t[0], s.lat[0], s.lon[0], s.h[0], s.v_n[0], s.q[0])
    whole = ins.integrate(state, t, s.omega_ib_b, s.f_b)
    m = 3000
    first = ins.integrate(state, t[:m], s.omega_ib_b[:m], s.f_b[:m])
    second = ins.integrate(first.state(-1), t[m - 1:], s.omega_ib_b[m - 1:], s.f_b[m - 1:])
    np.testing.assert_array_equal(second.lat, whole.lat[m - 1:])
    np.testing.assert_array_equal(second.q, whole.q[m - 1:])
    st = state
    for k in range(1, 50):
        st = ins.step(st, t[k], s.omega_ib_b[k - 1], s.f_b[k - 1], s.omega_ib_b[k], s.f_b[k])
    assert st.t == t[49] and st.lat == whole.lat[49] and st.h == whole.h[49]
    np.testing.assert_array_equal(st.v_n, whole.v_n[49])
    with pytest.raises(ValueError):
        ins.integrate(state, t[::-1], s.omega_ib_b, s.f_b)
    for bad in (t[5], np.nan):  # a repeated stamp, a NaN: refused, starting at the state's time
        tb = t.copy()
        tb[6] = bad
        with pytest.raises(ValueError, match="strictly increasing"):
            ins.integrate(state, tb, s.omega_ib_b, s.f_b)


@pytest.mark.parametrize("name", ["figure8", "figure8-real", "urban"])
def test_evaluate_in_blocks_keeps_every_bit(name):
    """``Truth.evaluate`` of more than ``EVAL_BLOCK`` times, in blocks, equals its evaluation of each time on its
    own footing: the same bits as evaluating any slice of them (a standing car's bumps and idle included)."""
    truth = tj.generate(tj.load_scenario(name), 120.0, seed=4)
    rng = np.random.default_rng(9)
    t = np.sort(rng.uniform(truth.t_min, truth.t_max, 2 * tj.EVAL_BLOCK + 77))
    whole = truth.evaluate(t)
    cuts = [0, 5, tj.EVAL_BLOCK - 3, tj.EVAL_BLOCK + 40, len(t)]
    pieces = [truth.evaluate(t[a:b]) for a, b in zip(cuts, cuts[1:])]
    for name_ in ("t", "lat", "lon", "h", "v_n", "r_e", "C_bn", "f_b", "omega_ib_b"):
        got = getattr(whole, name_)
        want = np.concatenate([getattr(p, name_) for p in pieces])
        assert got.shape == want.shape and np.array_equal(got.view(np.uint64), want.view(np.uint64)), name_
    for n in (tj.EVAL_BLOCK + 1, 2 * tj.EVAL_BLOCK + 1):     # a last block of one time is not left alone
        blocked, at_once = truth.evaluate(t[:n]), truth._evaluate(t[:n])
        for name_ in ("lat", "lon", "h", "v_n", "r_e", "C_bn", "f_b", "omega_ib_b"):
            assert np.array_equal(getattr(blocked, name_).view(np.uint64), getattr(at_once, name_).view(np.uint64))
    with ThreadPoolExecutor(1) as beside:                  # blocks shared with a thread beside: the same bits
        shared = truth.evaluate(t, beside)
    for name_ in ("t", "lat", "lon", "h", "v_n", "r_e", "C_bn", "f_b", "omega_ib_b"):
        assert np.array_equal(getattr(shared, name_).view(np.uint64), getattr(whole, name_).view(np.uint64))
