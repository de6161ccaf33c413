"""The compiled filter cycles (fusion/_cycles.c) against their numpy reference (fusion/errmodel.py, the loops of
fusion/kf.py and fusion/consider.py): the same numbers to the bit where numpy's BLAS sums a matrix product as
sequential fused multiply-adds (OpenBLAS on x86-64 with FMA; the probe below checks the sizes taken); within
rounding elsewhere. The compiled updates (Joseph form, the consider update) and the distributed filter's fusion
against the numpy formulas they replace, to the rounding their conditioning allows."""
import ctypes
import functools
from fractions import Fraction

import numpy as np
import pytest

from fieldlog.fusion import consider, earth, engine, errmodel, ins, kernels, kf, still
from fieldlog.fusion.dkf import DistributedKF


def _fma_chain(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a @ b, each element the exact fused multiply-add chain over the inner index from +0 (in rationals)."""
    out = np.empty((a.shape[0], b.shape[1]))
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            acc = 0.0
            for k in range(a.shape[1]):
                acc = float(Fraction(a[i, k]) * Fraction(b[k, j]) + Fraction(acc))  # one rounding: an FMA
            out[i, j] = acc
    return out


@functools.lru_cache(maxsize=1)
def _blas_is_sequential_fma() -> bool:
    """Whether numpy's products of the sizes the kernel takes (15 x 15 by 15 x 15 and 3 x 3) are, element by
    element, the exact fused multiply-add chain over the inner index from +0."""
    rng = np.random.default_rng(0)
    pairs = [(rng.normal(size=(n, n)), rng.normal(size=(n, n))) for n in (15, 3)]
    return all(np.array_equal(a @ b, _fma_chain(a, b)) for a, b in pairs)


def _same(a: np.ndarray, b: np.ndarray) -> None:
    if _blas_is_sequential_fma():
        assert a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))  # signs of zero too
    else:
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-300)


def _cycles(rng: np.random.Generator, m: int):
    lat = rng.uniform(-1.4, 1.4, m)
    lat[0] = -0.0  # a signed zero through tan and the transport rate
    h = rng.uniform(-100.0, 3000.0, m)
    v = rng.normal(0.0, 15.0, (m, 3))
    v[-1] = 0.0  # standing still: zero rows in the products
    C = earth.quat_to_dcm(rng.normal(size=(m, 4)))
    f_n = rng.normal(0.0, 2.0, (m, 3)) + [0.0, 0.0, 9.8]
    dt = rng.uniform(0.002, 0.5, m)
    return lat, h, v, C, f_n, dt


@pytest.mark.parametrize("m", [1, 7, 40])
def test_compiled_cycle_matrices_equal_numpy(m):
    rng = np.random.default_rng(m)
    lat, h, v, C, f_n, dt = _cycles(rng, m)
    q = np.diag(rng.uniform(1e-9, 1e-4, 12))
    q[0, 5] = q[5, 0] = 1e-7  # a full PSD is taken as given, not as its diagonal
    Phi, Q = errmodel.discrete_cycles(lat, h, v, C, f_n, q, dt)
    want = errmodel.discretise(*errmodel.system_matrices(lat, h, v, C, f_n), q, dt)
    _same(Phi, want[0])
    _same(Q, want[1])


@pytest.mark.parametrize("sym, q_scale, n", [(True, 1.0, 15), (True, 2.5, 15), (False, 1.0, 15), (True, 1.0, 18)])
def test_compiled_covariance_cycles_equal_numpy(sym, q_scale, n):
    """n = 18: a filter with states beyond the 15 (the GPS error's, fusion.gpserror), which takes numpy's loop."""
    rng = np.random.default_rng(7)
    Phi, Q = errmodel.discrete_cycles(*_cycles(rng, 12)[:5], np.eye(12) * 1e-6, np.full(12, 0.1))
    if n > 15:
        Phi = np.stack([np.block([[F, np.zeros((15, n - 15))], [np.zeros((n - 15, 15)), 0.99 * np.eye(n - 15)]])
                        for F in Phi])
        Q = np.stack([np.block([[q, np.zeros((15, n - 15))], [np.zeros((n - 15, 15)), np.eye(n - 15)]]) for q in Q])
    A = rng.normal(size=(n, n))
    P0 = A @ A.T if sym else A  # P12 of the distributed filter is not symmetric
    P0[3] = 0.0
    P0[:, 3] = -0.0
    hist = errmodel.propagate_covariance(Phi, Q, P0, q_scale, sym)
    P = P0
    for i in range(len(Phi)):
        P = Phi[i] @ P @ Phi[i].T + q_scale * Q[i]
        P = 0.5 * (P + P.T) if sym else P
        _same(hist[i], P)
    assert np.array_equal(P0[3], np.zeros(n)), "the caller's P is left alone"


def test_the_kernels_refuse_shapes_they_do_not_take():
    rng = np.random.default_rng(2)
    lat, h, v, C, f_n, dt = _cycles(rng, 4)
    with pytest.raises(ValueError):
        errmodel.discrete_cycles(lat, h, v[:3], C, f_n, np.eye(12), dt)
    Phi, Q = errmodel.discrete_cycles(lat, h, v, C, f_n, np.eye(12), dt)
    with pytest.raises(ValueError):
        consider.GyroConsider(1e-3, 1e-3).propagate(Phi, C, np.zeros((4, 2)), dt)


def test_the_filter_cycles_keep_a_zero_state_zero_and_move_a_nonzero_one():
    rng = np.random.default_rng(3)
    Phi, Q = errmodel.discrete_cycles(*_cycles(rng, 5)[:5], np.eye(12) * 1e-6, np.full(5, 0.1))
    f = kf.KalmanFilter(np.eye(15), np.eye(12))
    f.x = -np.zeros(15)
    f.propagate(Phi, Q)
    assert np.array_equal(f.x, np.zeros(15)) and not np.signbit(f.x).any()  # numpy's Phi @ -0 is +0
    x0 = rng.normal(size=15)
    f.x = x0
    f.propagate(Phi, Q)
    want, blas = x0, x0
    for P in Phi:
        want, blas = _fma_chain(P, want[:, None])[:, 0], P @ blas
    assert np.array_equal(f.x, want)  # the fused multiply-add chain in k order, on any machine
    np.testing.assert_allclose(f.x, blas, rtol=0, atol=1e-14 * np.abs(blas).max())  # BLAS sums in another order
    assert not np.array_equal(f.x, x0)


def test_compiled_consider_cycles_equal_numpy():
    rng = np.random.default_rng(11)
    lat, h, v, C, f_n, dt = _cycles(rng, 9)
    Phi, _ = errmodel.discrete_cycles(lat, h, v, C, f_n, np.eye(12) * 1e-6, dt)
    w = rng.normal(0.0, 0.3, (9, 3))
    # B dt in numpy: column p of the attitude rows is -C_bn[:, i] times rate j, c = [s_x s_y s_z m_xy m_xz ... m_zy]
    axis, rate = [0, 1, 2, 0, 0, 1, 1, 2, 2], [0, 1, 2, 1, 2, 0, 2, 0, 1]
    Bdt = np.zeros((9, 15, 9))
    Bdt[:, 6:9] = -C[:, :, axis] * w[:, None, rate]
    Bdt = Bdt * dt[:, None, None]
    c = consider.GyroConsider(1e-3, 1e-3)
    c.S = rng.normal(size=(15, 9))
    S = c.S.copy()
    out = c.propagate(Phi, C, w, dt)
    for i in range(len(Phi)):
        S = Phi[i] @ S + 0.5 * (Bdt[i] + Phi[i] @ Bdt[i])
        _same(out[i], S)
    _same(c.S, S)


@pytest.mark.parametrize("n", [0, 1, 2, 7, 500, 12_000])
def test_compiled_interval_sums_equal_numpy(n):
    """The still detector's interval sums (``still.ImuSums.add``) are numpy's sums over the rows and
    einsum("ij,ij->j"), added to what the interval held, to the bit."""
    rng = np.random.default_rng(n)
    w, f = rng.normal(0.0, 0.5, (n + 3, 3)) * [1e-3, 1.0, 1e3], rng.normal(9.8, 0.3, (n + 3, 3))
    sums, want = still.ImuSums(), np.zeros((4, 3))
    for i0, i1 in ((-1, 2), (2, n + 2)):
        sums.add(w, f, i0, i1)
        ws, fs = w[i0 + 1:i1 + 1], f[i0 + 1:i1 + 1]
        want += [ws.sum(axis=0), fs.sum(axis=0), np.einsum("ij,ij->j", ws, ws), np.einsum("ij,ij->j", fs, fs)]
    _same(np.array([sums.sum_w, sums.sum_f, sums.sum_ww, sums.sum_ff]), want)
    assert sums.n == n + 3


def _spd(rng: np.random.Generator, n: int, cond: float) -> np.ndarray:
    """A random symmetric positive definite (n, n) matrix with eigenvalues spread over ``cond``, as a filter's."""
    U = np.linalg.qr(rng.normal(size=(n, n)))[0]
    return (U * np.geomspace(1.0, 1.0 / cond, n)) @ U.T


def _close(a: np.ndarray, b: np.ndarray, cond: float) -> None:
    """Equal to the rounding a well-posed problem of that condition number allows (the update and fusion kernels
    sum in their own order, not LAPACK's)."""
    assert a.shape == b.shape
    np.testing.assert_allclose(a, b, rtol=0, atol=64 * cond * np.finfo(float).eps * float(np.abs(b).max()))


@pytest.mark.parametrize("m, seed", [(1, 0), (3, 1), (6, 2), (9, 3), (32, 4)])
def test_compiled_update_equals_numpy_joseph_form(m, seed):
    rng = np.random.default_rng(seed)
    P, R = _spd(rng, 15, 1e6), _spd(rng, m, 1e2)
    H, z, x, P12 = rng.normal(size=(m, 15)), rng.normal(size=m), rng.normal(size=15), rng.normal(size=(15, 15))
    K = np.linalg.solve(H @ P @ H.T + R, H @ P).T
    A = np.eye(15) - K @ H
    want = A @ P @ A.T + K @ R @ K.T
    for side, P12_want in ((0, A @ P12), (1, P12 @ A.T)):
        x1, P1, K1, dx, P12_1 = kf.joseph_update(x, P, z, H, R, P12, side)
        _close(K1, K, 1e6)
        _close(dx, K @ (z - H @ x), 1e6)
        _close(x1, x + K @ (z - H @ x), 1e6)
        _close(P1, 0.5 * (want + want.T), 1e6)
        assert np.array_equal(P1, P1.T)
        _close(P12_1, P12_want, 1e6)
        c = consider.GyroConsider(1e-3, 1e-3)
        c.S = rng.normal(size=(15, 9))
        S0 = c.S.copy()
        c.update(P, H, R)
        _close(c.S, S0 - K @ (H @ S0), 1e6)
    f = kf.KalmanFilter(P, np.eye(12))
    f.x = x.copy()
    dx = f.update(z, H, R)
    assert np.array_equal(f.x, x1) and np.array_equal(f.P, P1) and np.array_equal(f.gain, K1)
    assert np.array_equal(dx, kf.joseph_update(x, P, z, H, R)[3])


def test_the_compiled_update_refuses_what_numpy_would():
    rng = np.random.default_rng(5)
    P, x = _spd(rng, 15, 10.0), np.zeros(15)
    H = np.zeros((2, 15))
    H[0, 0] = H[1, 0] = 1.0
    with pytest.raises(np.linalg.LinAlgError):  # S = [[p, p], [p, p]]: singular
        kf.joseph_update(x, np.diag(np.diag(P)), np.zeros(2), H, np.zeros((2, 2)))
    x0, P0 = rng.normal(size=15), P + 1e-9 * rng.normal(size=(15, 15))  # no rows (a fix without finite ones)
    x1, P1, K, dx, _ = kf.joseph_update(x0, P0, np.zeros(0), np.zeros((0, 15)), np.zeros((0, 0)))
    assert np.array_equal(x1, x0) and np.array_equal(P1, 0.5 * (P0 + P0.T)) and K.shape == (15, 0) and not dx.any()
    with pytest.raises(ValueError):
        kf.joseph_update(x, P, np.zeros(33), np.zeros((33, 15)), np.eye(33))
    with pytest.raises(ValueError):
        kf.joseph_update(x, P, np.zeros(2), np.zeros((2, 14)), np.eye(2))


@pytest.mark.parametrize("rows", [1, 3, 6, 40])
def test_compiled_nis_equals_numpy(rows):
    """The status book's NIS, y^T (H P H^T + R)^-1 y / k: compiled (up to 32 rows, 15 states) equal to numpy's
    formula to rounding, numpy's beyond; inf for a singular innovation covariance."""
    rng = np.random.default_rng(20 + rows)
    for n in (15, 17):
        for _ in range(20):
            P, x = _spd(rng, n, 1e6), rng.normal(size=n) * rng.integers(0, 2)
            z, H, R = rng.normal(size=rows), rng.normal(size=(rows, n)), np.diag(rng.uniform(0.01, 5.0, rows))
            y = z - H @ x
            want = float(y @ np.linalg.solve(H @ P @ H.T + R, y)) / rows
            assert kf.nis(x, P, (z, H, R)) == pytest.approx(want, rel=1e-10)
    H = np.zeros((2, 15))
    H[:, 0] = 1.0
    assert kf.nis(np.zeros(15), np.diag(np.diag(P[:15, :15])), (np.ones(2), H, np.zeros((2, 2)))) == np.inf


@pytest.mark.parametrize("cross", [True, False])
def test_compiled_fusion_equals_numpy(cross):
    """The distributed filter's eqs. 3-4 and the error covariance with the cross-covariance, per cycle."""
    from fieldlog.fusion import dkf

    rng = np.random.default_rng(9)
    m, cond = 4, 1e6
    P1 = np.stack([_spd(rng, 15, cond) for _ in range(m)])
    P2 = np.stack([_spd(rng, 15, cond) for _ in range(m)])
    P12 = 0.1 * rng.normal(size=(m, 15, 15)) if cross else None
    x1, x2 = rng.normal(size=(m, 15)), rng.normal(size=(m, 15))
    x, P, Pe = dkf.fuse(P1, P2, P12, x1, x2)
    for k in range(m):
        I1, I2 = np.linalg.inv(P1[k]), np.linalg.inv(P2[k])
        Pw = np.linalg.inv(I1 + I2)
        _close(P[k], Pw, cond ** 2)
        _close(x[k], Pw @ (I1 @ x1[k] + I2 @ x2[k]), cond ** 2)
        assert np.array_equal(P[k], P[k].T)
        if cross:
            W1, W2 = Pw @ I1, Pw @ I2
            C = W1 @ P12[k] @ W2.T
            _close(Pe[k], W1 @ P1[k] @ W1.T + W2 @ P2[k] @ W2.T + C + C.T, cond ** 2)
        else:
            assert Pe is None
    P1[1, 3, 3] = -1.0
    with pytest.raises(np.linalg.LinAlgError):
        dkf.fuse(P1, P2, P12, x1, x2)


@pytest.mark.parametrize("m, seed", [(0, 0), (1, 1), (7, 2)])
def test_distributed_propagation_in_one_call_equals_its_parts(m, seed):
    """DistributedKF.propagate (paper fusion, one compiled call) gives, to the bit, the local states and
    covariances of kf.propagate_state and errmodel.propagate_covariance, and per cycle the variances and, after
    the last, the estimate and covariances of dkf.fuse; ``predicted`` is fuse's covariance after each cycle."""
    from fieldlog.fusion import dkf

    rng = np.random.default_rng(30 + seed)
    f = DistributedKF(_spd(rng, 15, 1e6), np.eye(12))
    f.kf_vel.x, f.kf_pos.x = rng.normal(size=15), np.zeros(15)  # a zero state stays zero without a product
    f.kf_vel.P, f.kf_pos.P = _spd(rng, 15, 1e6), _spd(rng, 15, 1e6)
    f.P12 = 0.01 * rng.normal(size=(15, 15))
    f._fuse()
    Phi = np.eye(15) + 0.01 * rng.normal(size=(m, 15, 15))
    Q = np.array([_spd(rng, 15, 1e3) * 1e-4 for _ in range(m)]).reshape(m, 15, 15)
    before = f.state.copy(), f.covariance.copy()
    x1, x2 = kf.propagate_state(Phi, f.kf_vel.x), kf.propagate_state(Phi, f.kf_pos.x)
    P1, P2 = (errmodel.propagate_covariance(Phi, Q, g.P) for g in f.locals)
    P12 = errmodel.propagate_covariance(Phi, Q, f.P12, sym=False)
    x, P4, Pe = dkf.fuse(P1, P2, P12, x1, x2)
    d = f.propagate(Phi, Q)
    same = lambda a, b: a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))  # noqa: E731
    assert same(d, np.diagonal(Pe, axis1=1, axis2=2)) and same(f.predicted, Pe)
    assert same(f.local_states, np.stack([x1, x2], axis=1))
    assert same(f.local_diag, np.stack([np.diagonal(P1, axis1=1, axis2=2), np.diagonal(P2, axis1=1, axis2=2)], 1))
    if m:
        assert same(f.state, x[-1]) and same(f.fused_covariance, P4[-1]) and same(f.covariance, Pe[-1])
        assert same(f.P12, P12[-1]) and same(f.kf_pos.x, np.zeros(15)) and same(f.kf_vel.P, P1[-1])
    else:
        assert same(f.state, before[0]) and same(f.covariance, before[1])
    f.kf_vel.P = -f.kf_vel.P
    with pytest.raises(np.linalg.LinAlgError):
        f.propagate(np.eye(15)[None], np.zeros((1, 15, 15)))


def _numpy_rts(log) -> tuple[np.ndarray, np.ndarray]:
    """The RTS backward pass as numpy writes it (fusion/smoother.py's module docstring): y and diag(Ps), (N, 15)."""
    from fieldlog.fusion.smoother import _filtered_means

    r = log.read(0, len(log))
    n = len(r)
    y, d = np.zeros((n, 15)), np.zeros((n, 15))
    m_pred, m_upd = _filtered_means(log) if log.bridged else (None, None)
    Ps, Ss = r["pp"][-1], r["sp"][-1]
    y[-1] = 0.0 if m_upd is None else m_upd[-1]
    for k in range(n - 1, -1, -1):
        if k < n - 1:
            rn = r[k + 1]
            C = np.linalg.solve(rn["pm"], rn["phi"] @ r["pp"][k]).T
            v = y[k + 1] + rn["dx"] - (0.0 if m_pred is None else m_pred[k + 1])
            y[k] = C @ v + (0.0 if m_upd is None else m_upd[k])
            P = r["pp"][k] + C @ (Ps - rn["pm"]) @ C.T
            Ps, Ss = 0.5 * (P + P.T), r["sp"][k] + C @ (Ss - rn["sm"])
        d[k] = np.diag(Ps)
        if log.var_c is not None:
            d[k, 12:] += ((Ss * Ss) @ log.var_c)[12:]
    return y, d


@pytest.mark.parametrize("bridged, consider_c", [(False, False), (True, False), (False, True)])
def test_compiled_smoother_equals_numpy(bridged, consider_c):
    """fieldlog_rts_chunk over records spilled to the log's file and kept in memory, chunks carried across, a
    bridged run's forward means and the consider variances: numpy's backward pass to rounding."""
    from fieldlog.fusion.smoother import SmootherLog, rts

    rng = np.random.default_rng(11 + bridged + 2 * consider_c)
    log = SmootherLog(chunk=7)
    sd = np.repeat([1.0, 0.1, 1e-3, 1e-5, 1e-3], 3)  # the filter's scales: m, m/s, rad, rad/s, m/s^2
    A = rng.normal(size=(15, 15)) + 4.0 * np.eye(15)
    P = sd[:, None] * (A @ A.T) * sd
    log.start(0, P)
    log.sensitivity(rng.normal(size=(1, 15, 9)) * 1e-3)
    H = np.hstack([np.eye(6), np.zeros((6, 9))])
    for k in range(1, 60):
        Phi = np.eye(15) + 0.01 * sd[:, None] * rng.normal(size=(15, 15)) / sd
        Pm = Phi @ P @ Phi.T + np.diag((sd * rng.uniform(0.01, 0.1, 15)) ** 2)
        Pm = 0.5 * (Pm + Pm.T)
        log.cycles(np.array([k * 100_000_000]), Phi[None], Pm[None])
        S = rng.normal(size=(1, 15, 9)) * 1e-3
        log.sensitivity(S)
        P = Pm
        if k % 3 == 0:  # a GPS update: information form, and the correction fed back
            P = np.linalg.inv(np.linalg.inv(Pm) + H.T @ H / 4.0)
            P = 0.5 * (P + P.T)
            log.update(rng.normal(size=15) * 0.1, P)
            log.sensitivity_update(S[0] * 0.9)
        elif bridged and k % 5 == 1:
            log.bridge(rng.normal(size=15) * 0.05)
    if consider_c:
        log.var_c = rng.uniform(1e-8, 1e-4, 9)
    assert log.bridged == bridged and len(log._spill) > 0
    sm = rts(log)
    y, d = _numpy_rts(log)
    got_y, got_d, _ = sm.arrays()
    sm.close()
    for got, want in ((got_y, y), (got_d, d)):
        scale = np.abs(want).max(axis=0)
        assert np.all(np.abs(got - want) <= 1e-9 * scale + 1e-300), np.abs(got - want).max(axis=0) / scale
    log.close()


def test_compiled_rls_equals_numpy():
    """predictors.Rls over rows at once (a refresh) and one by one (the epochs): numpy's step to rounding, and
    a wrong shape refused."""
    from fieldlog.fusion.predictors import Rls

    rng = np.random.default_rng(5)
    n, forget = 9, 0.995
    A = np.exp(-rng.uniform(0.0, 3.0, (200, n)) ** 2)  # overlapping Gaussian units: correlated features
    y = A @ rng.normal(size=n) + rng.normal(0.0, 0.01, 200)
    w, P = np.zeros(n), np.eye(n) / 1e-3
    for phi, t in zip(A, y):
        Pphi = P @ phi
        k = Pphi / (forget + phi @ Pphi)
        w = w + k * (t - phi @ w)
        P = (P - np.outer(k, Pphi)) / forget
        P = 0.5 * (P + P.T)
    batch, single = Rls(n, forget, 1e-3), Rls(n, forget, 1e-3)
    batch.update(A, y)
    for phi, t in zip(A, y):
        single.update(phi, t)
    for r in (batch, single):
        assert r.updates == 200
        np.testing.assert_allclose(r.w, w, rtol=0, atol=1e-9 * np.abs(w).max())
        np.testing.assert_allclose(r.P, P, rtol=0, atol=1e-9 * np.abs(P).max())
    with pytest.raises(ValueError, match="needs"):
        batch.update(A[:, :-1], y)


@pytest.mark.parametrize("make", [kf.KalmanFilter, DistributedKF], ids=["kf", "dkf-paper"])
def test_predicted_covariances_of_one_call_equal_one_call_per_cycle(make):
    """A filter that ``keeps_predicted`` gives, in one ``propagate`` over m cycles, the covariances a call per
    cycle gives (what a smoother records), to the bit."""
    rng = np.random.default_rng(11)
    Phi, Q = errmodel.discrete_cycles(*_cycles(rng, 9)[:5], np.diag(rng.uniform(1e-9, 1e-4, 12)),
                                      rng.uniform(0.002, 0.5, 9))
    A = rng.normal(size=(15, 15))
    P0 = A @ A.T + np.eye(15)
    one, each = make(P0, 0.0), make(P0, 0.0)
    assert one.keeps_predicted
    diag = one.propagate(Phi, Q)
    covs = []
    for i in range(len(Phi)):
        each.propagate(Phi[i:i + 1], Q[i:i + 1])
        covs.append(each.covariance.copy())
    assert np.array_equal(one.predicted, np.stack(covs))
    assert np.array_equal(diag, np.diagonal(np.stack(covs), axis1=1, axis2=2))


@pytest.mark.parametrize("m", [1, 4, 25])
def test_segment_cycles_equal_their_numpy_formulas(m):
    """``errmodel.segment_cycles`` (one compiled call) gives the cycles that numpy's running sums, earth.quat_to_dcm,
    np.einsum and ``discrete_cycles`` give over the same INS segment."""
    rng = np.random.default_rng(40 + m)
    n = 20 * m + 1
    t = np.cumsum(rng.uniform(0.0015, 0.0025, n))
    w, f = rng.normal(0.0, 0.2, (n, 3)), rng.normal(0.0, 2.0, (n, 3)) + [0.0, 0.0, 9.8]
    start = ins.NavState(float(t[0]), 0.7, -1.2, 250.0, np.array([12.0, -3.0, 0.4]),
                         earth.rotvec_to_quat([0.1, -0.2, 2.0]))
    sol = ins.integrate(start, t, w, f)
    ends = np.sort(rng.choice(np.arange(1, n), m, replace=False))
    q = np.diag(rng.uniform(1e-9, 1e-4, 12))
    c = errmodel.segment_cycles(sol, ends, w, f, q)
    starts = np.concatenate([[0], ends[:-1]])
    mid = (starts + ends) // 2
    sums = [np.cumsum(np.vstack([np.zeros(3), x[1:]]), axis=0) for x in (w, f)]
    w_mean, f_mean = ((s[ends] - s[starts]) / (ends - starts)[:, None] for s in sums)
    C = earth.quat_to_dcm(sol.q[mid])
    Phi, Q = errmodel.discrete_cycles(sol.lat[mid], sol.h[mid], sol.v_n[mid], C, np.einsum("kij,kj->ki", C, f_mean), q,
                                      sol.t[ends] - sol.t[starts])
    for got, want in ((c.w_mean, w_mean), (c.f_mean, f_mean), (c.C_bn, C), (c.dt, sol.t[ends] - sol.t[starts]),
                      (c.Phi, Phi), (c.Q, Q)):
        _same(got, want)
    assert np.array_equal(c.starts, starts) and np.array_equal(c.mid, mid)
    with pytest.raises(ValueError, match="strictly increasing"):
        errmodel.segment_cycles(sol, ends[::-1] if m > 1 else np.array([n]), w, f, q)


@pytest.mark.parametrize("anchor", [None, 0.0, 0.05, -0.3])
def test_compiled_slot_starts_equal_numpy(anchor):
    """The engine's covariance-cycle slots (compiled) start where numpy's floor((t - anchor) / step) steps, samples
    on a slot's edge (t = anchor + k step in floating point) included."""
    rng = np.random.default_rng(7)
    step = 0.1
    t = np.sort(np.concatenate([np.cumsum(rng.uniform(0.0015, 0.0025, 3000)), np.arange(1, 60) * step]))
    t = t[np.concatenate([[True], np.diff(t) > 0])]
    a = t[0] if anchor is None else anchor
    want = np.flatnonzero(np.diff(np.floor((t - a) / step).astype(np.int64)) != 0) + 1
    assert np.array_equal(engine._slot_starts(t, anchor, step), want) and len(want) > 50
    assert len(engine._slot_starts(t[:1], anchor, step)) == 0


def test_kernel_address_is_the_data_of_a_writable_array_and_numpys_otherwise():
    """``kernels.address`` of a contiguous writable array is a view of its buffer at its data; a read-only or a
    strided array gives its data address as numpy does."""
    a = np.arange(15.0).reshape(5, 3)
    view = kernels.address(a)
    assert ctypes.addressof(view) == a.ctypes.data
    frozen = np.frombuffer(bytes(24))
    assert kernels.address(frozen) == frozen.ctypes.data
    assert kernels.address(a[:, 1]) == a[:, 1].ctypes.data
