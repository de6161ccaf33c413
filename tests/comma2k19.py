"""The comma2k19 example segment (tests/data/comma2k19: a phone IMU, u-blox fixes, a Toyota's CAN wheel speeds
and comma's reference pose) written out as other loggers would write it, by third-party writers:

- ``write_candump``: the wheel-speed and speed frames as a candump log (python-can's ``CanutilsLogWriter``);
- ``write_drive``: an MCAP drive (mcap_ros2's ``Writer``) with ``sensor_msgs/Imu`` in the phone's FRD frame and a
  ``/tf_static`` saying so, ``sensor_msgs/NavSatFix``, the receiver's speed and bearing as an ENU
  ``TwistWithCovarianceStamped`` and the rear wheels' mean speed as ``TwistStamped``;
- ``reference``: the reference pose (ECEF positions and velocities, camera orientation) as geodetic tracks;
- ``mounting_deg``: the device's mounting against the car from the reference pose; ``attitude_error_deg``: a fused
  attitude against the reference's.

Clocks. The segment stamps everything on the phone's boot clock (s). ``global_pose/frame_gps_times`` gives
(GPS week, time of week) for each reference frame's boot time: their difference is one constant over the segment
(its spread is printed by ``boot_to_gps_s``), so boot time t maps to GPS time t + that offset, and to UTC by the
GPS-UTC leap seconds of the drive's date (18 s in 2018). A NavSatFix is stamped with the receiver's own
``utc_timestamp`` and logged at its boot arrival time mapped to UTC; the IMU and the CAN frames are stamped and
logged at their boot times mapped to UTC.

Run as a script (``python tests/comma2k19.py OUTDIR [--score]``) it writes ``drive.mcap``, ``wheels.log`` and the
DBC there, and with ``--score`` prints the figures of docs/results.md, "Real drives".
"""
from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path

import numpy as np

from fieldlog.fusion import earth

DATA = Path(__file__).resolve().parent / "data" / "comma2k19"
DBC = DATA / "_toyota_2017.dbc"
WHEEL_SIGNALS = {"wheel_fl": "WHEEL_SPEEDS.WHEEL_SPEED_FL", "wheel_fr": "WHEEL_SPEEDS.WHEEL_SPEED_FR",
                 "wheel_rl": "WHEEL_SPEEDS.WHEEL_SPEED_RL", "wheel_rr": "WHEEL_SPEEDS.WHEEL_SPEED_RR"}
DBC_RESOLUTION_MPS = 0.01 / 3.6  # WHEEL_SPEEDS: 0.01 km/h per bit
GPS_EPOCH_UNIX_S = 315964800  # 1980-01-06 in Unix time
LEAP_S = 18  # GPS - UTC in 2018
IMU_TOPIC, FIX_TOPIC, VEL_TOPIC, ODOM_TOPIC = "/phone/imu", "/ublox/fix", "/ublox/vel", "/car/wheel_twist"
FIX_SIGMA_M = (2.0, 2.0, 4.0)  # east, north, up 1-sigma given to the fixes (the segment carries no accuracy)
VEL_SIGMA_MPS = (0.2, 0.2, 1.0)  # east, north, up 1-sigma of the velocity from speed and bearing (no climb given)


def load() -> dict[str, np.ndarray]:
    """The excerpt's arrays (tests/data/comma2k19/README.md)."""
    with np.load(DATA / "segment.npz") as z:
        return {k: z[k] for k in z.files}


def boot_to_gps_s(seg: dict[str, np.ndarray]) -> tuple[float, float]:
    """GPS seconds since the GPS epoch minus boot seconds, and its spread over the segment (s)."""
    gps = seg["pose_gps_times"][:, 0] * 604800.0 + seg["pose_gps_times"][:, 1]
    off = gps - seg["pose_times"]
    return float(np.median(off)), float(np.ptp(off))


def boot_to_utc_ns(seg: dict[str, np.ndarray], t_boot: np.ndarray) -> np.ndarray:
    """Boot seconds to UTC ns (module docstring)."""
    off, _ = boot_to_gps_s(seg)
    return np.round((np.asarray(t_boot) + off + GPS_EPOCH_UNIX_S - LEAP_S) * 1e9).astype(np.int64)


def reference(seg: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The reference pose: UTC ns, lat/lon (deg), ellipsoidal height (m), ENU velocity (m/s) and C_ne of each
    frame, and the camera's FRD axes in ENU, C_fn (3, 3) per frame (columns: forward, right, down)."""
    lat, lon, h = earth.ecef_to_lla(seg["pose_positions"])
    C_en = earth.C_en(lat, lon)                       # ECEF -> ENU
    v_n = np.einsum("kij,kj->ki", C_en, seg["pose_velocities"])
    w, x, y, z = seg["pose_orientations"].T           # Hamilton [w, x, y, z]: camera FRD -> ECEF
    C_fe = earth.quat_to_dcm(np.stack([x, y, z, w], axis=1))
    C_fn = np.einsum("kij,kjl->kil", C_en, C_fe)
    return {"t_ns": boot_to_utc_ns(seg, seg["pose_times"]), "lat_deg": np.degrees(lat),
            "lon_deg": np.degrees(lon), "h_m": h, "v_n": v_n, "C_fn": C_fn}


def mounting_deg(seg: dict[str, np.ndarray], min_speed_mps: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """The device's mounting against the car (roll, pitch, yaw in degrees, FRD convention: pitch up positive, yaw
    right positive) and each angle's standard deviation over the frames: the camera's forward axis against the
    reference velocity's direction (the car moves along its forward axis) for pitch and yaw, and the camera's roll
    about that axis against the local level for roll (the road's bank is in it), over frames faster than
    ``min_speed_mps``."""
    ref = reference(seg)
    v = ref["v_n"]
    fast = np.linalg.norm(v[:, :2], axis=1) > min_speed_mps
    C = ref["C_fn"][fast]
    fwd, right = C[:, :, 0], C[:, :, 1]
    u = v[fast] / np.linalg.norm(v[fast], axis=1, keepdims=True)
    pitch = np.arcsin(fwd[:, 2]) - np.arcsin(u[:, 2])
    yaw = -(np.arctan2(fwd[:, 1], fwd[:, 0]) - np.arctan2(u[:, 1], u[:, 0]))   # ENU angles are counter-clockwise
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    roll = np.arcsin(-right[:, 2] / np.cos(np.arcsin(fwd[:, 2])))            # right axis down: roll right
    rpy = np.degrees(np.stack([roll, pitch, yaw], axis=1))
    return rpy.mean(axis=0), rpy.std(axis=0)


def attitude_error_deg(ref: dict[str, np.ndarray], t_ns: np.ndarray, q_xyzw: np.ndarray) -> np.ndarray:
    """The error angles (deg, about east, north, up; small-angle) of a fused attitude (quaternions body RFU -> ENU,
    x, y, z, w, at t_ns) against the reference camera's, the phone's FRD axes taken as its body's, at the nearest
    reference frame."""
    from foreign_drives import TO_FRAME

    i = np.clip(np.searchsorted(ref["t_ns"], t_ns), 0, len(ref["t_ns"]) - 1)
    C_ref = ref["C_fn"][i] @ TO_FRAME["frd"]                   # body RFU -> ENU
    E = np.einsum("kij,klj->kil", earth.quat_to_dcm(q_xyzw), C_ref)
    return np.degrees(np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], 1) / 2)


def write_candump(seg: dict[str, np.ndarray], out: Path) -> Path:
    """The excerpt's CAN frames as a candump log with UTC stamps (python-can's writer)."""
    import can as pycan

    t_ns = boot_to_utc_ns(seg, seg["can_t"])
    with pycan.CanutilsLogWriter(str(out), channel="can0") as log:
        for t, addr, data in zip(t_ns, seg["can_address"], seg["can_data"]):
            log.on_message_received(pycan.Message(timestamp=int(t) * 1e-9, arbitration_id=int(addr),
                                                  is_extended_id=False, data=bytes(data).ljust(8, b"\0")))
    return out


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def write_drive(seg: dict[str, np.ndarray], out: Path, odometer: bool = True) -> Path:
    """The excerpt as an MCAP drive (module docstring); ``odometer``: with the rear wheels' mean speed."""
    from foreign_drives import FIX_DEF, HEADER, IMU_DEF, ODOM_DEFS, TF_DEF, TF_QUAT, TIME, TWIST, VECTOR3, _msgdef
    from mcap_ros2.writer import Writer

    vel_def = _msgdef("std_msgs/Header header\ngeometry_msgs/TwistWithCovariance twist\n",
                      ("std_msgs/Header", HEADER), ("builtin_interfaces/Time", TIME),
                      ("geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist twist\nfloat64[36] covariance\n"),
                      ("geometry_msgs/Twist", TWIST), ("geometry_msgs/Vector3", VECTOR3))

    t_imu = boot_to_utc_ns(seg, seg["imu_t"])
    t_fix_log = boot_to_utc_ns(seg, seg["gnss_t"])
    fix = seg["gnss_value"]   # lat, lon, speed, utc_timestamp (ms), altitude, bearing
    t_odo = boot_to_utc_ns(seg, seg["wheel_speed_t"])
    v_rear = seg["wheel_speed"][:, 2:].mean(axis=1)
    cov = [FIX_SIGMA_M[0] ** 2, 0.0, 0.0, 0.0, FIX_SIGMA_M[1] ** 2, 0.0, 0.0, 0.0, FIX_SIGMA_M[2] ** 2]
    events = [(int(t), 0, i) for i, t in enumerate(t_imu)] + [(int(t), 1, i) for i, t in enumerate(t_fix_log)]
    if odometer:
        events += [(int(t), 2, i) for i, t in enumerate(t_odo)]
    events.sort()
    with open(out, "wb") as fh:
        wr = Writer(fh)
        s_imu = wr.register_msgdef("sensor_msgs/msg/Imu", IMU_DEF)
        s_fix = wr.register_msgdef("sensor_msgs/msg/NavSatFix", FIX_DEF)
        s_tf = wr.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF)
        s_vel = wr.register_msgdef("geometry_msgs/msg/TwistWithCovarianceStamped", vel_def)
        vel_cov = [0.0] * 36
        for k in range(3):
            vel_cov[7 * k] = VEL_SIGMA_MPS[k] ** 2
        s_odom = wr.register_msgdef("geometry_msgs/msg/TwistStamped", ODOM_DEFS["geometry_msgs/msg/TwistStamped"])
        t0 = events[0][0]
        x, y, z, w = TF_QUAT["frd"]
        wr.write_message("/tf_static", s_tf, {"transforms": [{
            "header": {"stamp": _stamp(t0), "frame_id": "base_link"}, "child_frame_id": "phone_imu",
            "transform": {"translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                          "rotation": {"x": x, "y": y, "z": z, "w": w}}}]}, log_time=t0, publish_time=t0)
        for log_t, kind, i in events:
            if kind == 0:
                msg = {"header": {"stamp": _stamp(log_t), "frame_id": "phone_imu"},
                       "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                       "orientation_covariance": [-1.0] + [0.0] * 8,
                       "angular_velocity": dict(zip("xyz", map(float, seg["imu_gyro"][i]))),
                       "angular_velocity_covariance": [0.0] * 9,
                       "linear_acceleration": dict(zip("xyz", map(float, seg["imu_accel"][i]))),
                       "linear_acceleration_covariance": [0.0] * 9}
                wr.write_message(IMU_TOPIC, s_imu, msg, log_time=log_t, publish_time=log_t)
            elif kind == 1:
                stamp = int(round(fix[i, 3] * 1e6))
                msg = {"header": {"stamp": _stamp(stamp), "frame_id": "gnss"},
                       "status": {"status": 0, "service": 1},
                       "latitude": float(fix[i, 0]), "longitude": float(fix[i, 1]), "altitude": float(fix[i, 4]),
                       "position_covariance": cov, "position_covariance_type": 2}
                wr.write_message(FIX_TOPIC, s_fix, msg, log_time=log_t, publish_time=log_t)
                bearing = np.radians(fix[i, 5])      # degrees clockwise from north
                vel = {"header": {"stamp": _stamp(stamp), "frame_id": "gnss"},
                       "twist": {"twist": {"linear": {"x": float(fix[i, 2] * np.sin(bearing)),
                                                      "y": float(fix[i, 2] * np.cos(bearing)), "z": 0.0},
                                           "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}, "covariance": vel_cov}}
                wr.write_message(VEL_TOPIC, s_vel, vel, log_time=log_t, publish_time=log_t)
            else:
                msg = {"header": {"stamp": _stamp(log_t), "frame_id": "base_link"},
                       "twist": {"linear": {"x": float(v_rear[i]), "y": 0.0, "z": 0.0},
                                 "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}}
                wr.write_message(ODOM_TOPIC, s_odom, msg, log_time=log_t, publish_time=log_t)
        wr.finish()
    return out


def horizontal_error_en(ref: dict[str, np.ndarray], t_ns: np.ndarray, lat_deg: np.ndarray,
                        lon_deg: np.ndarray) -> np.ndarray:
    """East and north error (m, (n, 2)) of a track against the reference interpolated at its times (NaN outside
    the reference)."""
    inside = (t_ns >= ref["t_ns"][0]) & (t_ns <= ref["t_ns"][-1])
    lat = np.interp(t_ns, ref["t_ns"], ref["lat_deg"])
    lon = np.interp(t_ns, ref["t_ns"], ref["lon_deg"])
    de = np.radians(lon_deg - lon) * earth.A * np.cos(np.radians(lat))
    dn = np.radians(lat_deg - lat) * earth.A
    return np.where(inside[:, None], np.stack([de, dn], axis=1), np.nan)


def horizontal_error_m(ref: dict[str, np.ndarray], t_ns: np.ndarray, lat_deg: np.ndarray,
                       lon_deg: np.ndarray) -> np.ndarray:
    """2-D distance (m) of a track from the reference interpolated at its times (NaN outside the reference)."""
    return np.hypot(*horizontal_error_en(ref, t_ns, lat_deg, lon_deg).T)


def growth_m(e_en: np.ndarray, window: np.ndarray) -> float:
    """The largest 2-D distance (m) of the error in a window from its value at the window's first row: the drift
    the outage adds, without the offset the aided solution already had against the reference (the fixes lie a
    median 2.2 m from it)."""
    i = np.flatnonzero(window)
    return float(np.nanmax(np.hypot(*(e_en[i] - e_en[i[0]]).T)))


OUTAGES = ((20.0, 15.0), (40.0, 12.0))  # s from the first IMU sample: GNSS withheld (the car moves throughout)
SWITCHES = {"defaults": "", "nhc = false": "nhc = false\n", "odometer = false": "odometer = false\n",
            "aids off": "nhc = false\nodometer = false\n"}


def virtual_odometer_held_out(seg: dict[str, np.ndarray]) -> dict:
    """The virtual odometer (``fusion.pseudo``) on the segment, scored held out against the CAN wheel speeds.

    Trained at each u-blox fix on the receiver's speed (the car drives forward) from the phone's IMU (FRD taken to
    RFU) and the reference's attitude (the INS's pitch input), as the engine trains it while GNSS is good; copies
    frozen every ``pseudo.SNAPSHOT_S`` predict each later fix ``pseudo.HORIZON_S`` (30-60 s) after their freeze,
    before any training on it, against the rear wheels' mean speed (m/s). Zero-skill baselines on the same pairs:
    the receiver's speed at the freeze, held; the mean trained speed. ``pseudo.HeldOut`` scores the same copies
    against the receiver's speed, as the engine does, and says whether the engine would use the prediction.

    Returns
    -------
    dict
        ``rms``: RMS error (m/s) against the CAN speed of the candidate in use at each fix (``model``), of each
        candidate (``line``, ``network``) and of the baselines (``hold``, ``mean``); ``pairs`` scored; ``on``, ``skill``,
        ``sigma_mps``, ``candidate``: the engine's switch, its held-out skill and sigma and the candidate it uses.
    """
    from fieldlog.fusion import pseudo
    from fieldlog.fusion.ins import NavState
    from fieldlog.fusion.predictors import PredictorConfig

    C = earth.C_rfu_from("frd")
    w_b, f_b = seg["imu_gyro"] @ C.T, seg["imu_accel"] @ C.T
    t_imu, t_fix, v_fix = seg["imu_t"], seg["gnss_t"], seg["gnss_value"][:, 2]
    dt = float(np.median(np.diff(t_imu)))
    ref = reference(seg)
    v_can = np.interp(t_fix, seg["wheel_speed_t"], seg["wheel_speed"][:, 2:].mean(axis=1))
    cfg = PredictorConfig()
    model, window, held = pseudo.new_network(cfg), pseudo.ImuWindow(), pseudo.HeldOut(cfg.window)
    copies: list[tuple[float, object, float, float]] = []  # (freeze time s, copy, speed then, mean trained speed)
    e: dict[str, list[float]] = {"model": [], "line": [], "network": [], "hold": [], "mean": []}
    trained: list[float] = []
    i_prev = int(np.searchsorted(t_imu, t_fix[0], side="right")) - 1
    for t, v, v_true in zip(t_fix[1:], v_fix[1:], v_can[1:]):
        i = int(np.searchsorted(t_imu, t, side="right")) - 1
        if i <= i_prev:
            continue
        window.add(w_b, f_b, i_prev, i, dt)
        k = min(int(np.searchsorted(seg["pose_times"], t)), len(seg["pose_times"]) - 1)
        nav = NavState(float(t), 0.0, 0.0, 0.0, ref["v_n"][k], earth.dcm_to_quat(ref["C_fn"][k] @ C.T))
        x = window.features(nav, dt)
        if x is not None:
            held.score(float(t), x, float(v), w_b[i_prev + 1:i + 1].mean(axis=0), f_b[i_prev + 1:i + 1].mean(axis=0),
                       (i - i_prev) * dt)
            for t0, copy, v0, m0 in copies:
                if pseudo.HORIZON_S[0] <= t - t0 <= pseudo.HORIZON_S[1]:
                    line, net = copy.predict_each(x)
                    for name, p in (("model", (line, net)[held.best]), ("line", line), ("network", net), ("hold", v0),
                                    ("mean", m0)):
                        e[name].append(v_true - p)
            model.train(x, float(v))
            trained.append(float(v))
            held.freeze(float(t), model, nav, float(v), np.zeros(3), np.zeros(3))
            if model.ready and (not copies or t - copies[-1][0] >= pseudo.SNAPSHOT_S):
                copies.append((float(t), model.frozen(), float(v), float(np.mean(trained))))
        i_prev = i
    rms = {k: float(np.sqrt(np.nanmean(np.square(v)))) for k, v in e.items()}
    on = held.scored >= pseudo.MIN_SCORED and held.skill > 0.0
    return dict(rms=rms, pairs=len(e["model"]), on=on, skill=held.skill, sigma_mps=math.sqrt(held.R),
                candidate=pseudo.SpeedModel.CANDIDATES[held.best])


def score(seg: dict[str, np.ndarray], drive: Path) -> None:
    """Print docs/results.md's "Real drives" table: kf with each aid switch and free INS, GNSS withheld in
    ``OUTAGES``: the median error with GNSS and each window's maximum error against the reference (m), in brackets
    its growth in the window (:func:`growth_m`); then the virtual odometer's held-out errors
    (:func:`virtual_odometer_held_out`)."""
    import contextlib
    import io
    import json

    from fieldlog.drive import reader
    from fieldlog.tools.cli import main as fieldlog

    ref = reference(seg)
    t0 = int(boot_to_utc_ns(seg, seg["imu_t"][:1])[0])
    runs = [(name, "kf", table) for name, table in SWITCHES.items()] + [("ins", "ins", "")]
    for name, method, table in runs:
        cfg = drive.with_name(f"{method}-{len(table)}.toml")
        cfg.write_text("[fusion]\n" + table)
        out = drive.with_name(f"{method}-{len(table)}.mcap")
        args = ["fuse", str(drive), "--method", method, "--out", str(out), "--imu-topic", IMU_TOPIC, "--fix-topic",
                FIX_TOPIC, "--vel-topic", VEL_TOPIC, "--odom-topic", ODOM_TOPIC, "--config", str(cfg), "--force",
                "--json"] + [x for a, n in OUTAGES for x in ("--outage", f"{a:g}:{n:g}")]
        with contextlib.redirect_stdout(io.StringIO()) as summary:
            fieldlog(args)
        js = json.loads(summary.getvalue())
        f = reader.read_topic(out, f"/fusion/{method}/fix")
        t = f["log_time_ns"]
        e_en = horizontal_error_en(ref, t, f["lat_deg"], f["lon_deg"])
        e = np.hypot(*e_en.T)
        windows = [(t >= t0 + a * 1e9) & (t < t0 + (a + n) * 1e9) for a, n in OUTAGES]
        aided = ~np.any(windows, axis=0) & (t > t0 + 5e9)
        print(f"| {method} {name} | {np.nanmedian(e[aided]):.2f} | "
              + " | ".join(f"{np.nanmax(e[w]):.2f} ({growth_m(e_en, w):.2f})" for w in windows)
              + f" | scale {js['odometer_scale']} +- {js['odometer_scale_sigma']}, slip {js['odometer_slip_skipped']}")
    fix = seg["gnss_value"]
    e_fix = horizontal_error_m(ref, (fix[:, 3] * 1e6).astype(np.int64), fix[:, 0], fix[:, 1])
    print(f"fixes: median {np.nanmedian(e_fix):.2f} m")
    vo = virtual_odometer_held_out(seg)
    print("virtual odometer, held out 30-60 s against the CAN rear wheels, RMS m/s: "
          + ", ".join(f"{k} {v:.2f}" for k, v in vo["rms"].items())
          + f"; {vo['pairs']} pairs, uses the {vo['candidate']}, sigma {vo['sigma_mps']:.2f} m/s, "
          f"skill against the IMU {vo['skill']:.2f}, {'on' if vo['on'] else 'off'}")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    dest = Path(sys.argv[1])
    dest.mkdir(parents=True, exist_ok=True)
    segment = load()
    write_drive(segment, dest / "drive.mcap")
    write_candump(segment, dest / "wheels.log")
    shutil.copy(DBC, dest / DBC.name)
    print(f"wrote {dest}/drive.mcap, wheels.log, {DBC.name}; boot->GPS offset {boot_to_gps_s(segment)} s; "
          f"mounting roll, pitch, yaw {mounting_deg(segment)} deg")
    if "--score" in sys.argv[2:]:
        score(segment, dest / "drive.mcap")
