import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fieldlog.fusion import earth

RNG = np.random.default_rng(42)


def test_lla_ecef_round_trip():
    n = 2000
    lat = RNG.uniform(-np.pi / 2, np.pi / 2, n)
    lon = RNG.uniform(-np.pi, np.pi, n)
    h = RNG.uniform(-500.0, 40000.0, n)
    r_e = earth.lla_to_ecef(lat, lon, h)
    lat2, lon2, h2 = earth.ecef_to_lla(r_e)
    assert np.max(np.abs(lat2 - lat)) * earth.A < 1e-6
    assert np.max(np.abs((lon2 - lon) * np.cos(lat))) * earth.A < 1e-6
    assert np.max(np.abs(h2 - h)) < 1e-6
    assert np.max(np.linalg.norm(earth.lla_to_ecef(lat2, lon2, h2) - r_e, axis=-1)) < 1e-6


def test_ecef_known_points():
    np.testing.assert_allclose(earth.lla_to_ecef(0.0, 0.0, 0.0), [earth.A, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(earth.lla_to_ecef(np.pi / 2, 0.3, 100.0), [0.0, 0.0, earth.B + 100.0], atol=1e-6)
    lat, lon, h = earth.ecef_to_lla([0.0, earth.A + 10.0, 0.0])
    assert abs(lat) < 1e-15 and abs(lon - np.pi / 2) < 1e-15 and abs(h - 10.0) < 1e-9


def test_gravity_known_values():
    assert earth.gravity(0.0, 0.0) == pytest.approx(9.7803253359, abs=1e-10)
    assert earth.gravity(np.pi / 2, 0.0) == pytest.approx(9.8321849378, abs=1e-9)
    # 45 deg: 9.806199 from the GRS80 series formula, which differs from WGS-84 closed form by ~1.4e-6
    assert earth.gravity(np.radians(45.0), 0.0) == pytest.approx(9.806199, abs=3e-6)
    # free-air gradient about -3.086e-6 s^-2
    grad = (earth.gravity(np.radians(45.0), 1000.0) - earth.gravity(np.radians(45.0), 0.0)) / 1000.0
    assert grad == pytest.approx(-3.086e-6, rel=2e-3)
    g_n = earth.gravity_n(np.array([0.1, 0.2]), np.array([0.0, 50.0]))
    assert g_n.shape == (2, 3)
    np.testing.assert_array_equal(g_n[:, :2], 0.0)
    np.testing.assert_allclose(g_n[:, 2], -earth.gravity(np.array([0.1, 0.2]), np.array([0.0, 50.0])))


def test_principal_radii():
    rm, rn = earth.principal_radii(0.0, 0.0)
    assert rm == pytest.approx(earth.A * (1 - earth.E2)) and rn == pytest.approx(earth.A)
    rm, rn = earth.principal_radii(np.pi / 2, 10.0)
    assert rm == pytest.approx(earth.A**2 / earth.B + 10.0) and rn == pytest.approx(earth.A**2 / earth.B + 10.0)


def test_C_en_axes():
    lat, lon, h = 0.6, -1.2, 300.0
    C = earth.C_en(lat, lon)
    np.testing.assert_allclose(C @ C.T, np.eye(3), atol=1e-15)
    d = 1e-7
    east = (earth.lla_to_ecef(lat, lon + d, h) - earth.lla_to_ecef(lat, lon - d, h)) / (2 * d)
    north = (earth.lla_to_ecef(lat + d, lon, h) - earth.lla_to_ecef(lat - d, lon, h)) / (2 * d)
    up = earth.lla_to_ecef(lat, lon, h + 1.0) - earth.lla_to_ecef(lat, lon, h)
    np.testing.assert_allclose(C @ (east / np.linalg.norm(east)), [1, 0, 0], atol=1e-8)
    np.testing.assert_allclose(C @ (north / np.linalg.norm(north)), [0, 1, 0], atol=1e-8)
    np.testing.assert_allclose(C @ up, [0, 0, 1], atol=1e-8)
    np.testing.assert_allclose(earth.omega_ie_n(lat), C @ [0, 0, earth.OMEGA_IE], atol=1e-20)


def test_omega_en_is_rate_of_C_en():
    """d/dt C_en = -[omega_en_n x] C_en for a vehicle moving at v_n."""
    lat, lon, h = 0.7, 0.2, 50.0
    v_n = np.array([12.0, -7.0, 0.5])
    rm, rn = earth.principal_radii(lat, h)
    rate = np.array([v_n[1] / rm, v_n[0] / (rn * np.cos(lat))])  # dlat/dt, dlon/dt
    dt = 1e-3
    dC = (earth.C_en(lat + rate[0] * dt, lon + rate[1] * dt) - earth.C_en(lat - rate[0] * dt, lon - rate[1] * dt))
    dC /= 2 * dt
    w = earth.omega_en_n(lat, h, v_n)
    np.testing.assert_allclose(dC, -earth.skew(w) @ earth.C_en(lat, lon), atol=1e-12)
    np.testing.assert_allclose(earth.omega_en_n(0.0, 0.0, [0.0, 10.0, 0.0]),
                               [-10.0 / (earth.A * (1 - earth.E2)), 0.0, 0.0], rtol=1e-12)


def test_euler_conventions():
    fwd, right = np.array([0.0, 1.0, 0.0]), np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(earth.euler_to_dcm(np.pi / 2, 0, 0) @ fwd, [1, 0, 0], atol=1e-15)  # east
    assert (earth.euler_to_dcm(0, 0.1, 0) @ fwd)[2] > 0  # nose up
    assert (earth.euler_to_dcm(0, 0, 0.1) @ right)[2] < 0  # right side down
    h, p, r = RNG.uniform(0, 2 * np.pi, 500), RNG.uniform(-1.5, 1.5, 500), RNG.uniform(-3.1, 3.1, 500)
    C = earth.euler_to_dcm(h, p, r)
    np.testing.assert_allclose(C @ np.swapaxes(C, -1, -2), np.broadcast_to(np.eye(3), C.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(C), 1.0, atol=1e-14)
    h2, p2, r2 = earth.dcm_to_euler(C)
    np.testing.assert_allclose(np.stack([h2, p2, r2]), np.stack([h, p, r]), atol=1e-12)


def test_quaternion_dcm_rotvec_consistency():
    C = earth.euler_to_dcm(RNG.uniform(0, 6.28, 400), RNG.uniform(-1.5, 1.5, 400), RNG.uniform(-3.1, 3.1, 400))
    q = earth.dcm_to_quat(C)
    assert np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), C, atol=1e-14)  # scipy is [x, y, z, w]
    np.testing.assert_allclose(earth.quat_to_dcm(q), C, atol=1e-14)
    np.testing.assert_allclose(earth.quat_to_dcm(earth.quat_multiply(q[:200], q[200:])), C[:200] @ C[200:],
                               atol=1e-14)
    rv = earth.dcm_to_rotvec(C)
    np.testing.assert_allclose(rv, Rotation.from_matrix(C).as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(earth.rotvec_to_dcm(rv), C, atol=1e-14)
    small = np.array([[1e-9, -2e-9, 3e-10], [0.0, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-9]])
    np.testing.assert_allclose(earth.quat_to_rotvec(earth.rotvec_to_quat(small)), small, atol=1e-15, rtol=1e-12)
    np.testing.assert_allclose(earth.rotvec_to_dcm(small[0]), np.eye(3) + earth.skew(small[0]), atol=1e-17)


def test_one_quaternion_and_cross_products_give_numpys_numbers():
    """The float paths (one quaternion's DCM, ``cross``) equal numpy's stacked arithmetic to the bit."""
    rng = np.random.default_rng(5)
    q = rng.normal(size=(2000, 4)) * rng.choice([1e-3, 1.0, 1e3], size=(2000, 1))
    stacked = earth.quat_to_dcm(q)
    one = np.array([earth.quat_to_dcm(x) for x in q])
    assert np.array_equal(one.view(np.int64), stacked.view(np.int64))
    with np.errstate(invalid="ignore"):
        assert np.isnan(earth.quat_to_dcm(np.zeros(4))).all()  # numpy's 0/0, not an exception
    a, b = rng.normal(size=(2000, 3)), rng.normal(size=(2000, 3))
    assert np.array_equal(earth.cross(a, b).view(np.int64), np.cross(a, b).view(np.int64))
    assert np.array_equal(earth.cross(a[0], b).view(np.int64), np.cross(a[0], b).view(np.int64))


def test_fixed_axis_rpy_is_scipys_xyz_and_round_trips():
    """REP-103 roll, pitch, yaw (a calibration's imu_rpy_deg, a /tf_static rotation) as scipy's extrinsic xyz."""
    rng = np.random.default_rng(7)
    rpy = rng.uniform(-1.0, 1.0, (500, 3)) * [np.pi, 0.49 * np.pi, np.pi]
    C = Rotation.from_euler("xyz", rpy).as_matrix()
    np.testing.assert_allclose(earth.rpy_to_dcm(rpy), C, atol=1e-14)
    np.testing.assert_allclose(earth.dcm_to_rpy(C), rpy, atol=1e-12)
    assert np.array_equal(earth.rpy_to_dcm(np.zeros(3)), np.eye(3))
