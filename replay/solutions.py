"""A fused solution as topics, ``/fusion/<method>/*`` (docs/data-model.md): the one module that writes them and
names them.

``write_solution`` writes a method's solution rows (``fusion.types.Solution``): position, velocity, attitude, their
sigmas, the IMU bias estimate, the status (``write_status``: ``fusion.output.StatusBook``, also before the alignment)
and, for the distributed methods, the local solutions; ``Odometry`` the same rows as
REP-105 frames (``odom``, ``datum``, ``/tf``, ``/tf_static``). Both write into a ``Recorder`` (``fieldlog fuse``) or
anything with its ``write`` and ``write_batch`` (the Foxglove sink of ``fieldlog replay --foxglove``). ``topics``
lists every topic they write for a method (a live server advertises them before the first row), ``topic`` names
one for the readers (``replay.view``, ``tools.evaluation.evaluate``), and ``read`` reads one back as arrays, from
a fused file or from the rows in memory.
"""

from __future__ import annotations

import numpy as np

from fieldlog.acquire import calib, frames
from fieldlog.drive import messages, reader
from fieldlog.drive.files import DriveSpec
from fieldlog.drive.recorder import Recorder
from fieldlog.fusion import earth, output
from fieldlog.fusion.types import Solution, Status

PREFIX = "/fusion/"
OUTAGE = "/fusion/outage"  # outage windows (injected and detected), shared by every method of a file
SOLUTION = ("fix", "vel", "attitude", "std", "attitude_std", "imu_bias")  # write_solution, every method
STATUS = "status"  # write_status, every method: /fusion/<method>/status (fieldlog_msgs/SolutionStatus)
ODOMETRY = ("datum", "odom")  # Odometry, per method
LOCALS = ("kf1/fix", "kf1/vel", "kf2/fix", "kf2/vel")  # write_solution, the methods with local filters
TF, TF_STATIC = "/tf", "/tf_static"  # Odometry's frames, shared by every method


def topic(method: str, name: str) -> str:
    """``/fusion/<method>/<name>``, e.g. ``topic("kf", "fix")``."""
    return f"{PREFIX}{method}/{name}"


def topics(method: str, has_locals: bool) -> list[str]:
    """Every topic ``write_solution`` and ``Odometry`` write for ``method``; ``has_locals``: the method's filter
    has local solutions (``fusion.methods.Method.local_filters``)."""
    names = [*SOLUTION, STATUS, *ODOMETRY, *(LOCALS if has_locals else ())]
    return [topic(method, n) for n in names] + [TF, TF_STATIC]


def method_of(name: str) -> str | None:
    """The method whose solution topic ``name`` is (``/fusion/<method>/fix``); None for any other topic."""
    parts = name.split("/")
    return parts[2] if len(parts) == 4 and parts[1] == "fusion" and parts[3] == "fix" else None


def has(fused: DriveSpec | Solution, method: str, name: str) -> bool:
    """Whether ``fused`` (a fused file, or the solution rows in memory) holds messages of
    ``/fusion/<method>/<name>``."""
    if isinstance(fused, Solution):
        if name == STATUS:
            return fused.status is not None and len(fused.status.t_ns) > 0
        return len(fused.t_ns) > 0 and (name in SOLUTION or (name in LOCALS and fused.local is not None))
    return any(t.topic == topic(method, name) and t.count for t in reader.topic_counts(fused))


def read(fused: DriveSpec | Solution, method: str, name: str) -> dict[str, object]:
    """The ``/fusion/<method>/<name>`` messages of ``fused`` as arrays (``drive.reader.read_topic``): a fused
    file, or the solution rows in memory (``tools.fuse.fuse(..., keep=True)``; ``name`` of ``SOLUTION``,
    ``LOCALS`` or ``STATUS``), whose messages are those ``write_solution`` writes, decoded as the file's are, so
    both give the same arrays to the bit."""
    if isinstance(fused, Solution) and name == STATUS:
        return reader.decode(messages.SOLUTION_STATUS, fused.status.t_ns, _status_payloads(fused.status))
    if isinstance(fused, Solution):
        return reader.decode(messages.topic_type(topic(method, name)), fused.t_ns, _payloads(fused, name))
    return reader.read_topic(fused, topic(method, name))


class Diverged(ValueError):
    """The solution became NaN or inf: nothing from that row on is written."""


def write_solution(rec: Recorder, method: str, s: Solution) -> None:
    """The ``/fusion/<method>/*`` rows of ``s`` into ``rec`` (a Recorder, or anything with its ``write_batch``);
    its status rows (``write_status``) up to the first row that is not finite, which raises ``Diverged``."""
    bad = ~output.finite(s)
    if bad.any():
        write_status(rec, method, s, until_ns=int(s.t_ns[np.argmax(bad)]))
        raise Diverged(f"the {method} solution diverged (NaN or inf) at UTC {int(s.t_ns[np.argmax(bad)]) * 1e-9:.3f} s; "
                       "nothing from there on was written: check the IMU frame (--imu-frame) and units")
    if len(s.t_ns):
        for name in (*SOLUTION, *(LOCALS if s.local is not None else ())):
            rec.write_batch(topic(method, name), s.t_ns, _payloads(s, name))
    write_status(rec, method, s)


def write_status(rec: Recorder, method: str, s: Solution, until_ns: int | None = None) -> None:
    """The ``/fusion/<method>/status`` rows of ``s`` (none when it has no status), those up to until_ns UTC
    if given."""
    st = s.status
    if st is None or len(st.t_ns) == 0:
        return
    if until_ns is not None:
        st = st.take(st.t_ns <= until_ns)
    rec.write_batch(topic(method, STATUS), st.t_ns, _status_payloads(st))


def _status_payloads(st: Status) -> messages.Packed:
    """The ``/fusion/<method>/status`` messages of the status rows st (frame imu: the solution's point)."""
    return messages.encode_solution_status(st.t_ns, st.code, st.since_update_s, st.sigma_h_m, st.nis,
                                           frame_id=frames.IMU)


def _payloads(s: Solution, name: str) -> messages.Packed:
    """The messages of ``/fusion/<method>/<name>`` (a name of ``SOLUTION``, or of ``LOCALS`` when ``s`` has local
    solutions) for the rows of ``s``: positions are the IMU's (frame imu); ENU vectors and the attitude body -> ENU
    are in map's axes."""
    t = s.t_ns
    var = s.sigma ** 2
    if name in LOCALS:
        loc = s.local[:, LOCALS.index(name) // 2]
        if name.endswith("/fix"):
            pos_cov = np.zeros((len(t), 9))
            pos_cov[:, [0, 4, 8]] = loc[:, 6:9] ** 2
            return messages.encode_navsatfix(t, np.degrees(loc[:, 0]), np.degrees(loc[:, 1]), loc[:, 2], pos_cov,
                                             covariance_type=2, frame_id=frames.IMU)
        vel_cov = np.zeros((len(t), 36))
        vel_cov[:, [0, 7, 14]] = loc[:, 9:12] ** 2
        vel_cov[:, [21, 28, 35]] = messages.UNKNOWN_VARIANCE
        return messages.encode_twist(t, loc[:, 3:6], covariance=vel_cov, frame_id=frames.MAP)
    if name == "fix":
        pos_cov = np.zeros((len(t), 9))
        pos_cov[:, [0, 4, 8]] = var[:, 0:3]
        return messages.encode_navsatfix(t, np.degrees(s.lat), np.degrees(s.lon), s.h, pos_cov, covariance_type=2,
                                         frame_id=frames.IMU)
    if name == "vel":
        vel_cov = np.zeros((len(t), 36))
        vel_cov[:, [0, 7, 14]] = var[:, 3:6]
        vel_cov[:, [21, 28, 35]] = messages.UNKNOWN_VARIANCE  # angular part: not estimated
        return messages.encode_twist(t, s.v_n, covariance=vel_cov, frame_id=frames.MAP)
    if name == "attitude":
        return messages.encode_quaternion(t, s.q, frame_id=frames.MAP)
    if name == "std":
        return messages.encode_vector3(t, s.sigma[:, 0:3], frame_id=frames.MAP)
    if name == "attitude_std":
        return messages.encode_vector3(t, s.sigma[:, 6:9], frame_id=frames.MAP)
    if name == "imu_bias":
        bias_cov = np.zeros((len(t), 2, 9))
        bias_cov[:, :, [0, 4, 8]] = var[:, 9:15].reshape(-1, 2, 3)
        return messages.encode_imu(t, s.bias[:, 0:3], s.bias[:, 3:6], bias_cov[:, 0], bias_cov[:, 1],
                                   frame_id=frames.IMU)
    raise KeyError(f"not a topic of write_solution: {name!r}")


class Odometry:
    """The REP-105 frames of a fused solution: ``/tf_static``, ``/tf`` map -> odom -> base_link,
    ``/fusion/<method>/odom`` (nav_msgs/Odometry in odom / base_link) and ``/fusion/<method>/datum``.

    ``map`` is a local ENU frame whose origin is the first solution row (the alignment point, in geodetic
    coordinates of the IMU): ``/fusion/<method>/datum`` (NavSatFix, once, latched) and the ``fusion.map``
    metadata record give it, and ``/tf_static`` holds ``earth -> map`` (ECEF, REP-105) with the drive's
    ``base_link -> imu -> gps_antenna``. The filter's state is the IMU (RFU axes, ``C_bn``); base_link follows
    from the calibration's mounting (``acquire.frames``): C_base_n = C_bn C_imu_base^T, origin = IMU - C_base_n
    imu_position_m; the local ENU axes at the vehicle are taken as map's (they differ by the meridian
    convergence and the tilt of the vertical: about 0.16 mrad per km from the origin).

    ``odom`` is continuous as robot_localization's odom frame: base_link's odom position is the fused velocity
    integrated (trapezoid, row to row), so it never jumps when a GPS update or the end of an outage corrects the
    fused position; its orientation is the fused attitude (map and odom axes stay parallel), and
    ``map -> odom`` (a translation) absorbs the corrections: map -> odom -> base_link equals the fused pose at
    every row. Pose covariance: position ENU and attitude error (phi E, N, U) of the filter, diagonal. Twist in
    base_link: the IMU point's velocity rotated into base_link (with its covariance rotated too; the lever-arm
    term w x r is left out); the angular rate from the row's attitude and the one before it (0 at the first row),
    with the variance ``messages.UNKNOWN_VARIANCE`` because the filter does not estimate it.
    """

    def __init__(self, method: str, mounting: calib.Mounting) -> None:
        self.method = method
        self.topic = topic(method, "odom")
        self.mounting = mounting
        self.C_imu_base = frames.C_imu_base(mounting)
        self.imu_position_m = np.asarray(mounting.imu_position_m, float)
        self.origin: tuple[float, float, float] | None = None
        self._last: tuple | None = None   # the last row's t_ns, v_n, odom position and C_base_n

    def _start(self, rec: Recorder, s: Solution) -> None:
        """The origin of map from the first row: datum, /tf_static."""
        self.origin = (float(s.lat[0]), float(s.lon[0]), float(s.h[0]))
        lat0, lon0, h0 = self.origin
        t0 = s.t_ns[:1]
        rec.write_batch(topic(self.method, "datum"), t0, messages.encode_navsatfix(
            t0, [np.degrees(lat0)], [np.degrees(lon0)], [h0], np.zeros(9), covariance_type=2,
            frame_id=frames.MAP))   # (the origin is defined, not measured: zero covariance, known)
        earth_map = (frames.EARTH, frames.MAP, earth.lla_to_ecef(lat0, lon0, h0),
                     frames.quat_xyzw(earth.C_en(lat0, lon0).T))
        rec.write(TF_STATIC, int(t0[0]), messages.encode_tf(
            int(t0[0]), [*frames.static_transforms(self.mounting), earth_map]))

    def metadata(self) -> dict[str, str]:
        """The ``fusion.map`` record: map's geodetic origin (deg, deg, m above the WGS-84 ellipsoid)."""
        lat0, lon0, h0 = self.origin
        return {"frame": frames.MAP, "datum_topic": topic(self.method, "datum"), "lat_deg": repr(float(np.degrees(lat0))),
                "lon_deg": repr(float(np.degrees(lon0))), "h_m": repr(h0)}

    def write(self, rec: Recorder, s: Solution) -> None:
        n = len(s.t_ns)
        if n == 0:
            return
        if self.origin is None:
            self._start(rec, s)
        lat0, lon0, h0 = self.origin
        dr_e = earth.lla_to_ecef(s.lat, s.lon, s.h) - earth.lla_to_ecef(lat0, lon0, h0)
        p_imu = dr_e @ earth.C_en(lat0, lon0).T
        C_base_n = earth.quat_to_dcm(s.q) @ self.C_imu_base.T
        p_base = p_imu - C_base_n @ self.imu_position_m
        q_base = earth.dcm_to_quat(C_base_n)
        C_n_base = np.swapaxes(C_base_n, 1, 2)
        v_base = np.einsum("nij,nj->ni", C_n_base, s.v_n)
        t = s.t_ns
        # the row before each (the drive's first row: itself), carried over from the last block, so the rows do
        # not depend on where the blocks end
        t_prev, v_prev, p_prev, C_prev = self._last or (int(t[0]), s.v_n[0], p_base[0], C_base_n[0])
        dt_s = np.diff(np.concatenate(([t_prev], t))) / 1e9
        C_before = np.concatenate([C_prev[None], C_base_n[:-1]])
        omega = earth.dcm_to_rotvec(np.swapaxes(C_before, 1, 2) @ C_base_n) / np.where(dt_s > 0, dt_s, np.inf)[:, None]
        v_before = np.vstack([v_prev[None], s.v_n[:-1]])
        p_odom = np.cumsum(np.concatenate([p_prev[None], 0.5 * (v_before + s.v_n) * dt_s[:, None]]), axis=0)[1:]
        self._last = (int(t[-1]), s.v_n[-1].copy(), p_odom[-1].copy(), C_base_n[-1].copy())
        p_map_odom = p_base - p_odom
        var = s.sigma ** 2
        pose_cov = np.zeros((n, 6, 6))
        pose_cov[:, [0, 1, 2, 3, 4, 5], [0, 1, 2, 3, 4, 5]] = var[:, [0, 1, 2, 6, 7, 8]]
        twist_cov = np.zeros((n, 6, 6))
        twist_cov[:, :3, :3] = C_n_base @ (var[:, 3:6, None] * C_base_n)
        twist_cov[:, [3, 4, 5], [3, 4, 5]] = messages.UNKNOWN_VARIANCE
        rec.write_batch(self.topic, t, messages.encode_odometry(
            t, p_odom, q_base, pose_cov.reshape(n, 36), v_base, omega, twist_cov.reshape(n, 36),
            frame_id=frames.ODOM, child_frame_id=frames.BASE_LINK))
        identity = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (n, 4))
        rec.write_batch(TF, t, messages.encode_tf_rows(t, [(frames.MAP, frames.ODOM, p_map_odom, identity),
                                                           (frames.ODOM, frames.BASE_LINK, p_odom, q_base)]))
