"""``fieldlog acquire ... --view-rrd`` (a child ``fieldlog view --live BUS --rrd``) against ``sim --serve`` ptys: the
live recording verifies with the rerun command line and holds what the daemon recorded."""
from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from test_daemon import start_daemon
from test_serve import start_serve, wait_served
from test_view_export import _rerun, _rows

from fieldlog.drive import reader
from fieldlog.replay import view as rview
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.fuse import fuse

os.environ["CI"] = "1"  # rerun analytics off
DURATION_S, SPEED = 120.0, 10.0
LOCK_WITHIN_S = 15.0  # the time sync locks within this much of the drive start


def _connections(bus: Path) -> int:
    """Unix sockets bound to ``bus`` (/proc/net/unix): the listener plus one per accepted client."""
    lines = Path("/proc/net/unix").read_text().splitlines()[1:]
    return sum(1 for line in lines if line.split()[-1] == str(bus))


def test_acquire_view_live_to_rrd(tmp_path: Path) -> None:
    bus, rrd, out = tmp_path / "bus.sock", tmp_path / "live.rrd", tmp_path / "drives"
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(f'[rotation]\nmax_duration_s = 0\n[daemon]\nbus = "{bus}"\n')
    serve, paths = start_serve("--scenario", "figure8", "--duration", f"{DURATION_S:g}", "--seed", "4", "--speed",
                               f"{SPEED:g}", "--hold")
    d, _ = start_daemon(out, paths, "--config", str(cfg), "--time-scale", f"{SPEED:g}", "--view-rrd", str(rrd))
    try:
        end = time.monotonic() + 60
        while _connections(bus) < 2:  # the child viewer is on the bus before any data flows
            assert time.monotonic() < end and d.poll() is None, "the live view did not connect"
            time.sleep(0.1)
        serve.send_signal(signal.SIGUSR1)
        wait_served(serve, d, 60)
        d.send_signal(signal.SIGTERM)
        assert d.wait(60) == 0, d.stderr.read()          # the daemon waits for its view to finish
    finally:
        for p in (serve, d):
            if p.poll() is None:
                p.kill()
                p.wait()
    printed = d.stdout.read()
    assert "viewed" in printed and str(rrd) in printed, printed + d.stderr.read()

    assert "1 file verified without error" in _rerun("verify", str(rrd))
    rows = _rows(_rerun("print", str(rrd)))
    (drive,) = sorted(out.glob("*/*.mcap"))
    n_imu = int(reader.read_topic(drive, "/imu")["valid"].sum())
    assert n_imu == DURATION_S * 500
    # the view fuses the bus's provisional /imu (stamped at once by the causal fit), which starts at the
    # first PPS lock (a few s in): every sample from there on, decimated
    gyro = rows["/imu/gyro", "Scalars:scalars"]
    assert gyro == rows["/imu/accel", "Scalars:scalars"]
    assert (n_imu - LOCK_WITHIN_S * 500) // rview.IMU_DECIMATION <= gyro < n_imu // rview.IMU_DECIMATION
    gps, epochs, _ = rview.gps_track(reader.read_topic(drive, "/gps/fix"))
    assert rows["/map/gps", "GeoPoints:positions"] == rows["/enu/gps", "LineStrips3D:strips"] == len(gps.t_ns) >= 110
    assert rows["/status/no_fix", "Scalars:scalars"] == len(epochs)
    offline = fuse(drive, "kf", tmp_path / "kf.mcap")     # the same engine over the recorded file
    live_kf = rows["/map/fusion/kf", "GeoPoints:positions"]
    print(f"IMU rows {gyro} of {n_imu // rview.IMU_DECIMATION}; kf live {live_kf}, offline {offline.rows}")
    assert rows["/enu/fusion/kf", "LineStrips3D:strips"] == live_kf
    assert abs(live_kf - offline.rows) <= 0.05 * offline.rows and live_kf > 0.5 * DURATION_S * 10
    sol_t = reader.read_topic(tmp_path / "kf.mcap", "/fusion/kf/fix")["log_time_ns"]
    scored = int(((gps.t_ns >= sol_t[0]) & (gps.t_ns <= sol_t[-1])).sum())  # no truth: errors at the GPS epochs
    assert scored - 2 <= rows["/errors/pos/east/kf", "Scalars:scalars"] <= scored
    assert any(e == "/time_panel" for e, _ in rows)      # the live blueprint follows the newest data


def test_view_live_argument_errors(tmp_path: Path, capsys) -> None:
    assert cli_main(["view", "--live", str(tmp_path / "bus.sock"), str(tmp_path / "drive.mcap")]) == 2
    assert "--live takes no drive files" in capsys.readouterr().err
    assert cli_main(["view"]) == 2
    assert cli_main(["view", "--live", "--config", str(tmp_path / "none.toml")]) == 2  # no such config
