"""The drive's coordinate frames at the ROS boundary (REP-103, REP-105), from the calibration's mounting.

Internally everything stays in the papers' frames: body right-forward-up (RFU, the IMU triad), navigation ENU.
ROS tools place the data through these frames, written as ``/tf_static`` (``tf2_msgs/msg/TFMessage``) in every
drive:

- ``base_link``: the vehicle, REP-103 forward-left-up (FLU);
- ``base_link -> imu``: the IMU's RFU triad (``/imu`` ``frame_id``), at ``[mounting] imu_position_m`` (FLU, m),
  rotated by -90 deg about up (RFU -> FLU) and by ``imu_rpy_deg`` (the triad vs the vehicle's RFU axes);
- ``imu -> gps_antenna``: the lever arm ``[mounting] antenna_m`` (IMU axes, m), no rotation.

``fieldlog fuse`` adds REP-105's world frames: ``earth -> map`` (``/tf_static``: ECEF to a local ENU frame at
the alignment point), ``map -> odom -> base_link`` (``/tf``; odom continuous, map -> odom absorbing the GPS
corrections) and ``/fusion/<method>/odom`` in odom (``replay.solutions.Odometry``).
"""
from __future__ import annotations

import math

import numpy as np

from fieldlog.acquire import calib
from fieldlog.drive import messages

BASE_LINK, IMU, GPS_ANTENNA, MAP, ODOM, EARTH = "base_link", "imu", "gps_antenna", "map", "odom", "earth"

# C_rfu_flu: a vector in RFU axes -> the same vector in FLU axes (forward = y_rfu, left = -x_rfu, up = z_rfu)
C_RFU_FLU = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def C_imu_base(mounting: calib.Mounting) -> np.ndarray:
    """DCM IMU axes -> base_link axes (v_base = C @ v_imu): RFU -> FLU after the triad's mounting rotation
    (fixed-axis roll, then pitch, then yaw, as REP-103 RPY)."""
    return C_RFU_FLU @ _rotation_xyz_deg(mounting.imu_rpy_deg)


def _rotation_xyz_deg(rpy_deg) -> np.ndarray:
    """The rotation matrix of fixed-axis roll, pitch, yaw (deg) by scipy's ``Rotation.from_euler("xyz", rpy_deg,
    degrees=True).as_matrix()`` operations, so the same floats (tests/test_frames.py) without importing
    scipy.spatial (slow): the elementary quaternions composed extrinsically, then the matrix of the quaternion."""
    q: list[float] = []
    for axis, deg in enumerate(rpy_deg):
        half = float(deg) * (math.pi / 180.0) / 2.0
        e = [0.0, 0.0, 0.0, math.cos(half)]
        e[axis] = math.sin(half)
        if not q:
            q = e
            continue
        c = (e[1] * q[2] - e[2] * q[1], e[2] * q[0] - e[0] * q[2], e[0] * q[1] - e[1] * q[0])  # e x q
        q = [e[3] * q[i] + q[3] * e[i] + c[i] for i in range(3)] + [e[3] * q[3] - e[0] * q[0] - e[1] * q[1]
                                                                   - e[2] * q[2]]
    x, y, z, w = q
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), -x2 + y2 - z2 + w2, 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), -x2 - y2 + z2 + w2]])


def quat_xyzw(C: np.ndarray) -> np.ndarray:
    """Unit quaternion x, y, z, w (w >= 0) of rotation matrices (..., 3, 3)."""
    C = np.asarray(C, dtype=float)
    flat = C.reshape(-1, 3, 3)
    if len(flat) <= 16 and all(_orthonormal(m) for m in flat):
        q = np.array([_quat_of_rotation(m) for m in flat]).reshape(C.shape[:-2] + (4,))
    else:
        from scipy.spatial.transform import Rotation  # only here: importing scipy.spatial is slow

        q = Rotation.from_matrix(flat).as_quat().reshape(C.shape[:-2] + (4,))
    return q * np.where(q[..., 3:4] < 0.0, -1.0, 1.0)


def _orthonormal(m: np.ndarray) -> bool:
    """A proper rotation to 1e-12, the tolerance under which scipy's ``Rotation.from_matrix`` takes the matrix as
    it is (no SVD)."""
    return bool(np.linalg.det(m) > 0.0) and float(np.max(np.abs(m @ m.T - np.eye(3)))) <= 1e-12


def _quat_of_rotation(m: np.ndarray) -> np.ndarray:
    """x, y, z, w of one rotation matrix, by the same operations as scipy's ``Rotation.from_matrix`` (Shepperd's
    choice of the largest of the diagonal and the trace), so the same floats."""
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    choice = int(np.argmax([m[0, 0], m[1, 1], m[2, 2], tr]))
    q = [0.0, 0.0, 0.0, 0.0]
    if choice == 3:
        q = [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 1 + tr]
    else:
        i = choice
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1 - tr + 2 * m[i, i]
        q[j] = m[j, i] + m[i, j]
        q[k] = m[k, i] + m[i, k]
        q[3] = m[k, j] - m[j, k]
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return np.array(q) / n


def static_transforms(mounting: calib.Mounting) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(parent, child, translation m in the parent's axes, rotation x, y, z, w child -> parent) of /tf_static."""
    return [(BASE_LINK, IMU, np.asarray(mounting.imu_position_m, float), quat_xyzw(C_imu_base(mounting))),
            (IMU, GPS_ANTENNA, np.asarray(mounting.antenna_m, float), np.array([0.0, 0.0, 0.0, 1.0]))]


def tf_static_message(mounting: calib.Mounting, stamp_ns: int) -> bytes:
    """The drive's ``/tf_static`` message, stamped ``stamp_ns`` (UTC ns)."""
    return messages.encode_tf(stamp_ns, static_transforms(mounting))
