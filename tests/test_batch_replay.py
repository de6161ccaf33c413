"""`fieldlog batch` on a local Dask cluster against the same drives one by one in-process, and `fieldlog replay`
into an .rrd (checked with the rerun command line) and into a `rerun --serve-grpc` server on loopback."""

import os
import re
import signal
import socket
import subprocess
import time
from pathlib import Path

import polars as pl
import pytest
from test_view_export import RERUN, _rerun, _rows

from fieldlog.replay import view as rview
from fieldlog.drive.reader import read_topic
from fieldlog.tools.batch import RESULT_SCHEMA, drive_rows, results_table
from fieldlog.tools.cli import main as cli_main
from fieldlog.tools.dev.cluster import loopback_cluster
from fieldlog.tools.fuse import fuse
from fieldlog.tools.sim.simulate import simulate

os.environ["CI"] = "1"  # rerun analytics off
SEEDS = (1, 2, 3)
DURATION_S = 160.0  # room for one 30 s outage after the 120 s convergence time of the outage study


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    for s in SEEDS:
        simulate("figure8", DURATION_S, s, d / f"drive{s}.mcap")
    (d / "garbage.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(4000))
    whole = (d / "drive1.mcap").read_bytes()
    (d / "truncated.mcap").write_bytes(whole[: len(whole) // 2])  # cut short, as by a power loss
    return d


@pytest.mark.slow
def test_batch_on_two_workers_equals_one_by_one_and_skips_the_garbage(fleet, tmp_path, capsys):
    out = tmp_path / "batch"
    rc = cli_main(["batch", str(fleet / "*.mcap"), "--methods", "kf,dkf", "--outages", "30", "--workers", "2",
                   "--out", str(out)])
    printed = capsys.readouterr().out
    assert rc == 0
    assert "garbage.mcap: FAILED" in printed and "truncated.mcap: FAILED" in printed
    assert "batch wall time" in printed
    n = len(SEEDS) + 2
    assert len(re.findall(rf"^\[\d/{n}\]", printed, re.M)) == n  # a progress line per drive done

    table = pl.read_parquet(out / "results.parquet")
    assert table.schema == pl.Schema(RESULT_SCHEMA)
    failed = table.filter(pl.col("status") == "failed")
    assert failed["drive"].to_list() == ["garbage", "truncated"] and failed["error"].is_not_null().all()
    ok = table.filter(pl.col("status") == "ok")
    assert sorted(set(ok["drive"])) == [f"drive{s}" for s in SEEDS]
    assert len(ok) == len(SEEDS) * 2 * 2  # (whole drive, 30 s outages) x (kf, dkf)
    assert (ok["reference"] == "truth").all() and ok["timing_rms_us"].is_not_null().all()
    assert ok.filter(pl.col("outage_s") == 30.0)["windows"].min() >= 1
    for s in SEEDS:
        for m in ("kf", "dkf"):
            assert (out / "fused" / f"drive{s}_{m}.mcap").is_file()
            assert (out / "fused" / f"drive{s}_{m}_30s.mcap").is_file()
    # the outage rows score the outage windows, not the whole drive; with the vehicle aids (NHC) on by default a
    # 30 s outage costs little on figure8, so it is bounded rather than necessarily worse than the whole drive
    whole = ok.filter(pl.col("outage_s").is_null()).sort("drive", "method")["pos_2d_m"]
    gap = ok.filter(pl.col("outage_s") == 30.0).sort("drive", "method")["pos_2d_m"]
    assert (whole < 5.0).all() and (gap < 10.0).all() and (gap != whole).all()

    rows = []
    for s in SEEDS:
        rows += drive_rows(fleet / f"drive{s}.mcap", ["kf", "dkf"], [30.0], tmp_path / "one_by_one")
    ref = results_table(rows)
    assert ok.drop("path").equals(ref.drop("path"))


@pytest.mark.slow
def test_batch_on_a_scheduler_reuses_warm_workers(fleet, tmp_path, capsys):
    """`--scheduler` on a cluster started as machines start one (a `dask scheduler` and two `dask worker`
    processes on 127.0.0.1): the rows equal the in-process ones, and a worker that ran several drives is one
    process that holds the INS kernel loaded: imports and compiled kernels stay warm from drive to drive."""
    from distributed import Client

    def worker_state(dask_worker) -> tuple[int, int, int]:  # local, so it is sent by value to the workers
        """(drives run, INS kernels loaded (0 or 1: once per process), pid) of a Dask worker."""
        from fieldlog.fusion import kernels

        return dask_worker.state.executed_count, int("fieldlog.fusion._ins" in kernels._loaded), os.getpid()

    drives = [str(fleet / f"drive{s}.mcap") for s in SEEDS]
    with loopback_cluster(2, tmp_path / "cluster") as address:
        rc = cli_main(["batch", *drives, "--methods", "kf", "--scheduler", address, "--out", str(tmp_path / "b")])
        with Client(address) as client:
            workers = list(client.run(worker_state).values())
    assert rc == 0 and f"on {address}" in capsys.readouterr().out
    runs = [n for n, _, _ in workers]
    assert sum(runs) == len(SEEDS) and max(runs) >= 2 and len({pid for _, _, pid in workers}) == 2
    assert all(loads == (1 if n else 0) for n, loads, _ in workers), workers
    table = pl.read_parquet(tmp_path / "b" / "results.parquet")
    ref = results_table([r for d in drives for r in drive_rows(d, ["kf"], [], tmp_path / "one_by_one")])
    assert (table["status"] == "ok").all() and table.drop("path").equals(ref.drop("path"))


def _check_recording(rrd: Path, drive: Path, tmp_path: Path) -> None:
    """The recording verifies and holds the live entities with the rows of the same fusion run offline."""
    assert "1 file verified without error" in _rerun("verify", str(rrd))
    rows = _rows(_rerun("print", str(rrd)))
    fused = fuse(drive, "kf", tmp_path / "kf.mcap")
    assert rows["/map/fusion/kf", "GeoPoints:positions"] == fused.rows > 0
    assert rows["/enu/fusion/kf", "LineStrips3D:strips"] == fused.rows
    gps, _, _ = rview.gps_track(read_topic(drive, "/gps/fix"))
    assert rows["/map/gps", "GeoPoints:positions"] == len(gps.t_ns) > 0
    imu = read_topic(drive, "/imu")
    assert rows["/imu/gyro", "Scalars:scalars"] == int(imu["valid"].sum()) // rview.IMU_DECIMATION
    assert rows["/map/truth", "GeoPoints:positions"] == -(-len(read_topic(drive, "/truth/fix")["log_time_ns"])
                                                           // rview.TRUTH_DECIMATION)
    assert fused.rows * 0.9 < rows["/errors/pos/east/kf", "Scalars:scalars"] <= fused.rows
    for entity, comp in (("/enu/fusion/kf/base_link", "Transform3D:translation"),
                         ("/attitude/heading/kf", "Scalars:scalars")):  # the vehicle, every solution row
        assert rows[entity, comp] == fused.rows, entity
    assert rows["/enu/fusion/kf/base_link", "Boxes3D:half_sizes"] == 1
    # the live status: as fuse writes it, the rows before the alignment too
    assert rows["/solution_status/kf", "Scalars:scalars"] == len(read_topic(tmp_path / "kf.mcap",
                                                                            "/fusion/kf/status")["log_time_ns"])
    assert any(e == "/time_panel" for e, _ in rows)  # the blueprint's time panel follows the newest data


def test_replay_to_rrd(fleet, tmp_path, capsys):
    drive = fleet / "drive1.mcap"
    rrd = tmp_path / "replay.rrd"
    assert cli_main(["replay", str(drive), "--speed", "200", "--method", "kf", "--rrd", str(rrd)]) == 0
    assert "160.0 s of" in capsys.readouterr().out
    _check_recording(rrd, drive, tmp_path)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, deadline_s: float) -> bool:
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return True
        time.sleep(0.1)
    return False


def test_replay_live_to_a_rerun_server_on_loopback(fleet, tmp_path):
    """`rerun --serve-grpc` on 127.0.0.1 receives the stream; `rerun download` reads back what it buffered
    (the proxy stream never ends, so the download is stopped once the rows are in and the copy compacted)."""
    drive = fleet / "drive1.mcap"
    port = _free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    env = {**os.environ, "CI": "1"}
    # own process groups: .venv/bin/rerun is a Python launcher whose child is the real server
    server = subprocess.Popen([str(RERUN), "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, start_new_session=True)
    download = None
    try:
        assert _wait_port(port, 15.0), "rerun server did not listen"
        assert cli_main(["replay", str(drive), "--speed", "200", "--method", "kf", "--connect", url]) == 0
        dl = tmp_path / "dl"
        dl.mkdir()
        download = subprocess.Popen([str(RERUN), "download", url, "-o", str(dl)], stdout=subprocess.DEVNULL,
                                    stderr=subprocess.DEVNULL, env=env, start_new_session=True)
        received = dl / "output.rrd"
        expected = int(read_topic(drive, "/imu")["valid"].sum()) // rview.IMU_DECIMATION
        end = time.monotonic() + 30.0
        got = 0
        while time.monotonic() < end and got < expected:
            time.sleep(0.5)
            if received.is_file():
                res = subprocess.run([str(RERUN), "rrd", "print", str(received)], capture_output=True, text=True,
                                     timeout=60, env=env)
                got = _rows(res.stdout)["/imu/gyro", "Scalars:scalars"]
        assert got == expected
    finally:
        for proc in (download, server):
            if proc is not None:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=10)
    compact = tmp_path / "received.rrd"
    with open(compact, "wb") as f:
        res = subprocess.run([str(RERUN), "rrd", "optimize", str(received)], stdout=f, stderr=subprocess.PIPE,
                             text=True, timeout=60, env=env)
    assert res.returncode == 0, res.stderr
    _check_recording(compact, drive, tmp_path)
