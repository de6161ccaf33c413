"""A peer for the bench: KF-GINS, a loosely coupled GNSS/INS extended Kalman filter in C++ (i2Nav-WHU/KF-GINS on
GitHub, GPL-3; not part of fieldlog: the user builds it from its own repository, tools/dev/README.md).

A KF-GINS data set is a folder with a ``kf-gins.yaml`` (KF-GINS's configuration: ``imupath``, ``gnsspath``,
``imudatarate``, the initial state, ``imunoise``, ``antlever``), an IMU text file (GNSS seconds of week, then the
angle and velocity increments of the sample, rad and m/s, axes front-right-down) and a GNSS text file (seconds of
week, latitude and longitude deg, ellipsoidal height m, position 1-sigma north, east, down m). Here:

* :func:`dataset_from_drive` writes such a set from a simulated drive (its /imu and /gps/fix; the initial state
  from its truth), so the peer bench runs without KF-GINS's own IMU file (kept out of some copies of its
  repository by its size);
* :func:`drive_from_dataset` converts a set to a fieldlog drive (/imu in body RFU, /gps/fix), and
  :func:`fusion_toml` gives ``fieldlog fuse`` the set's IMU figures with the vehicle aids off (KF-GINS has none).
"""

from __future__ import annotations

import math
import shutil
import subprocess
from pathlib import Path

import numpy as np

G0 = 9.80665  # m/s^2 per g
SOW0 = 100_000.0  # the second of the week a set made from a drive starts at (its first IMU sample)
WEEK_START_NS = 1_767_225_600_000_000_000  # the drive's clock at second 0 of the data set's GNSS week (UTC ns)
FRD_RFU = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # front-right-down <-> right-front-up,
# and north-east-down <-> east-north-up: the same swap, its own inverse


def kfgins_binary(path: Path) -> Path:
    """The KF-GINS executable of ``path``: the executable itself, or a checkout of its repository (built there
    with its own CMake into ``build/`` and ``bin/`` when ``bin/KF-GINS`` is not there yet)."""
    path = Path(path)
    if path.is_file():
        return path
    exe = path / "bin" / "KF-GINS"
    if not exe.exists():
        if not (path / "CMakeLists.txt").exists():
            raise SystemExit(f"{path}: not a KF-GINS checkout nor its executable (tools/dev/README.md says how to "
                             "get it)")
        (path / "build").mkdir(exist_ok=True)
        subprocess.run(["cmake", "..", "-DCMAKE_BUILD_TYPE=Release"], cwd=path / "build", check=True)
        subprocess.run(["make", "-j2"], cwd=path / "build", check=True)
    return exe


def dataset_from_drive(drive: Path, folder: Path) -> Path:
    """Write a KF-GINS data set (module docstring) of the simulated ``drive`` into ``folder``: its IMU and fixes
    as they are, the initial state (at the first fix) and the lever arm from the drive's truth and calibration,
    the IMU figures those fieldlog's configuration gives the drive. Returns the set's ``kf-gins.yaml``."""
    import yaml

    from fieldlog.drive import reader
    from fieldlog.fusion import earth
    from fieldlog.tools.fuse import drive_config

    folder.mkdir(parents=True, exist_ok=True)
    imu, fix = reader.read_topic(drive, "/imu"), reader.read_topic(drive, "/gps/fix")
    cov = fix["position_covariance"]
    t0 = int(imu["stamp_ns"][0])
    sow = lambda t_ns: (np.asarray(t_ns, np.int64) - t0) * 1e-9 + SOW0  # noqa: E731 - one expression
    t = sow(imu["stamp_ns"])
    dt = np.diff(t, prepend=t[0] - float(np.median(np.diff(t))))[:, None]
    np.savetxt(folder / "imu.txt", np.column_stack([t, imu["omega_ib_b"] @ FRD_RFU * dt, imu["f_b"] @ FRD_RFU * dt]),
               fmt="%.6f " + " ".join(["%.12e"] * 6))
    ok = (np.isfinite(np.column_stack([fix["lat_deg"], fix["lon_deg"], fix["alt_m"], cov[:, [0, 4, 8]]])).all(axis=1)
          & (fix["stamp_ns"] > t0))  # KF-GINS takes a fix whole: a fix without height is left out
    np.savetxt(folder / "gnss.txt", np.column_stack([sow(fix["stamp_ns"]), fix["lat_deg"], fix["lon_deg"],
                                                     fix["alt_m"], *np.sqrt(cov[:, [4, 0, 8]]).T])[ok],
               fmt="%.6f %.10f %.10f %.4f %.4f %.4f %.4f")
    start = int(fix["stamp_ns"][ok][0])
    pos, vel, att = (reader.read_topic(drive, f"/truth/{x}") for x in ("fix", "vel", "attitude"))
    at = lambda d, k: np.array([np.interp(start, d["stamp_ns"], c) for c in np.atleast_2d(d[k].T)])  # noqa: E731
    C = FRD_RFU @ earth.quat_to_dcm(at(att, "q_xyzw").ravel()) @ FRD_RFU  # body FRD -> NED
    rpy = np.degrees([math.atan2(C[2, 1], C[2, 2]), -math.asin(C[2, 0]), math.atan2(C[1, 0], C[0, 0]) % (2 * math.pi)])
    cfg = drive_config(drive)
    s, lever = cfg.sensor, cfg.gps.lever_rfu()
    tau_h = 1.0  # KF-GINS's biases are first-order Gauss-Markov: fieldlog's random walk over an hour
    config = {
        "imupath": str(folder / "imu.txt"), "gnsspath": str(folder / "gnss.txt"), "outputpath": str(folder),
        "imudatalen": 7, "imudatarate": round(1.0 / float(np.median(np.diff(t)))),
        "starttime": float(sow(start)), "endtime": -1,
        "initpos": [float(at(pos, "lat_deg")[0]), float(at(pos, "lon_deg")[0]), float(at(pos, "alt_m")[0])],
        "initvel": (FRD_RFU @ at(vel, "v_n").ravel()).tolist(), "initatt": rpy.tolist(),
        "initgyrbias": [0.0] * 3, "initaccbias": [0.0] * 3, "initgyrscale": [0.0] * 3, "initaccscale": [0.0] * 3,
        "initposstd": [1.0, 1.0, 2.0], "initvelstd": [0.1, 0.1, 0.1], "initattstd": [0.5, 0.5, 2.0],
        "imunoise": {
            "arw": [s.gyro_noise_dps_rthz * 60.0] * 3,
            "vrw": [s.accel_noise_ug_rthz * 1e-6 * G0 * 60.0] * 3,
            "gbstd": [s.gyro_bias_rw_dps_rts * math.sqrt(tau_h * 3600.0 / 2.0) * 3600.0] * 3,
            "abstd": [s.accel_bias_rw_ug_rts * math.sqrt(tau_h * 3600.0 / 2.0) * G0 * 1e-6 / 1e-5] * 3,
            "gsstd": [s.gyro_scale_factor_ppm] * 3, "asstd": [s.accel_scale_factor_ppm] * 3, "corrtime": tau_h},
        "antlever": (FRD_RFU @ lever).tolist(),
    }
    (folder / "kf-gins.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return folder / "kf-gins.yaml"


def horizontal_rms(sim: Path, nav_file: Path, fused: Path, topic: str = "/fusion/kf/fix") -> tuple[float, float]:
    """Horizontal RMS (m) against the simulated drive's truth of KF-GINS's navigation result ``nav_file`` and of
    fieldlog's solution ``topic`` in ``fused``, both of a set made by :func:`dataset_from_drive` from ``sim``."""
    from fieldlog.drive import reader
    from fieldlog.fusion import earth

    truth = reader.read_topic(sim, "/truth/fix")
    t_truth = (truth["stamp_ns"] - int(reader.read_topic(sim, "/imu")["stamp_ns"][0])) * 1e-9 + SOW0
    nav, ours = np.loadtxt(nav_file, ndmin=2), reader.read_topic(fused, topic)
    out = []
    for sow, lat, lon in ((nav[:, 1], nav[:, 2], nav[:, 3]),
                          ((ours["stamp_ns"] - WEEK_START_NS) * 1e-9, ours["lat_deg"], ours["lon_deg"])):
        lat_t, lon_t = (np.interp(sow, t_truth, truth[k]) for k in ("lat_deg", "lon_deg"))
        rm, rn = earth.principal_radii(np.radians(lat_t), 0.0)
        d2 = (np.radians(lat - lat_t) * rm) ** 2 + (np.radians(lon - lon_t) * rn * np.cos(np.radians(lat_t))) ** 2
        out.append(float(np.sqrt(np.mean(d2))))
    return out[0], out[1]


def _config(yaml_path: Path) -> tuple[dict, Path, Path]:
    """A set's configuration and its IMU and GNSS files (relative paths are KF-GINS's: from where it runs, taken
    here from the set's folder's parent, as its own example's "./dataset/...")."""
    import yaml

    cfg = yaml.safe_load(Path(yaml_path).read_text())
    where = lambda p: Path(p) if Path(p).is_absolute() else Path(yaml_path).resolve().parent.parent / p  # noqa: E731
    return cfg, where(cfg["imupath"]), where(cfg["gnsspath"])


def drive_from_dataset(yaml_path: Path, out: Path) -> Path:
    """Convert the KF-GINS data set of ``yaml_path`` into a fieldlog drive at ``out``: /imu (the increments over
    each sample's interval as rate and specific force, body RFU) and /gps/fix (ENU covariance from the 1-sigmas),
    from the set's start time on, stamped from ``WEEK_START_NS``."""
    from fieldlog.drive import messages, recorder

    cfg, imu_path, gnss_path = _config(yaml_path)
    imu = np.loadtxt(imu_path, usecols=range(7), ndmin=2)
    gnss = np.loadtxt(gnss_path, usecols=range(7), ndmin=2)
    imu = imu[imu[:, 0] >= float(cfg.get("starttime", 0.0))]
    dt = np.diff(imu[:, 0], prepend=imu[0, 0] - 1.0 / float(cfg.get("imudatarate", 200)))[:, None]
    stamp = lambda sow: WEEK_START_NS + np.round(sow * 1e9).astype(np.int64)  # noqa: E731 - one expression
    t_imu, t_fix = stamp(imu[:, 0]), stamp(gnss[:, 0])
    cov = np.zeros((len(gnss), 9))
    cov[:, [0, 4, 8]] = gnss[:, [5, 4, 6]] ** 2  # north, east, down 1-sigmas -> ENU variances
    with recorder.Recorder(out, force=True) as rec:
        for s in range(0, len(t_imu), 2000):
            sl = slice(s, s + 2000)
            rec.write_batch("/imu", t_imu[sl], messages.encode_imu(
                t_imu[sl], imu[sl, 1:4] @ FRD_RFU / dt[sl], imu[sl, 4:7] @ FRD_RFU / dt[sl]))
        rec.write_batch("/gps/fix", t_fix, messages.encode_navsatfix(t_fix, gnss[:, 1], gnss[:, 2], gnss[:, 3], cov))
    return out


def fusion_toml(yaml_path: Path) -> str:
    """``fieldlog fuse --config`` text for a set: its IMU figures (``imunoise``; the Gauss-Markov biases as the
    random walk of the same short-term spread) and lever arm, the vehicle aids off."""
    cfg = _config(yaml_path)[0]
    n, tau_s = cfg["imunoise"], float(cfg["imunoise"]["corrtime"]) * 3600.0
    mean = lambda k: float(np.mean(n[k]))  # noqa: E731 - one expression
    lever = FRD_RFU @ np.asarray(cfg.get("antlever", [0.0, 0.0, 0.0]), float)
    return "\n".join([
        "[fusion]", "nhc = false", "zupt = false", "odometer = false",
        f"gyro_noise_dps_rthz = {mean('arw') / 60.0!r}",
        f"accel_noise_ug_rthz = {mean('vrw') / 60.0 / G0 * 1e6!r}",
        f"gyro_bias_rw_dps_rts = {mean('gbstd') / 3600.0 / math.sqrt(tau_s / 2.0)!r}",
        f"accel_bias_rw_ug_rts = {mean('abstd') * 1e-5 / G0 * 1e6 / math.sqrt(tau_s / 2.0)!r}",
        f"gyro_scale_factor_ppm = {mean('gsstd')!r}", f"accel_scale_factor_ppm = {mean('asstd')!r}",
        f"lever_arm_b = [{', '.join(repr(float(x)) for x in lever)}]", ""])


def copy_dataset(checkout: Path, folder: Path) -> Path | None:
    """KF-GINS's own example set (dataset/ of a full checkout) copied into ``folder``/dataset, with its output
    there; None when the checkout lacks its IMU file."""
    src = Path(checkout) / "dataset"
    if not Path(checkout).is_dir() or not (src / "kf-gins.yaml").exists():
        return None
    cfg, imu, gnss = _config(src / "kf-gins.yaml")
    if not (imu.exists() and gnss.exists()):
        return None
    shutil.copytree(src, folder / "dataset", dirs_exist_ok=True)
    return folder / "dataset" / "kf-gins.yaml"
