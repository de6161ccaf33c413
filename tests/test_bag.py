"""Sessions and outputs as rosbag2 directories: the daemon's session (real subprocess on ``sim --serve`` ptys,
rotated), ``fuse --bag``, ``recover`` of a killed session; opened with rosbags' ``Reader`` (a third-party reader)
and counted against the MCAP files themselves."""
from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader

from fieldlog.drive import bagdir
from fieldlog.acquire.daemon import is_finished
from fieldlog.tools.sim.simulate import simulate
from test_daemon import run, start_daemon
from test_serve import start_serve, wait_served

rosbags = pytest.importorskip("rosbags.rosbag2")
from rosbags.typesys import Stores, get_typestore  # noqa: E402


@pytest.fixture(scope="module")
def figure8_short(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("drive") / "figure8.mcap"
    simulate("figure8", 120, 1, path)
    return path


def counts_in_files(files: list[Path]) -> dict[str, int]:
    """Messages per topic, counted by reading every message of the MCAP files."""
    out: dict[str, int] = {}
    for f in files:
        with open(f, "rb") as fh:
            for _s, ch, _m in make_reader(fh).iter_messages():
                out[ch.topic] = out.get(ch.topic, 0) + 1
    return out


def read_bag(d: Path) -> tuple[dict[str, int], dict[str, str], int]:
    """rosbags' Reader on a directory: messages per topic it yields, types per topic, its message total."""
    got: dict[str, int] = {}
    with rosbags.Reader(d) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        for conn, _t, _raw in r.messages():
            got[conn.topic] = got.get(conn.topic, 0) + 1
        total = r.message_count
    return got, types, total


def start_session(tmp_path: Path, out: Path, rotate_s: float, duration_s: float, seed: int):
    """``sim --serve`` at x10 and the daemon recording it into ``out``, rotating every ``rotate_s`` of host time;
    the drive started. Returns both processes."""
    cfg = tmp_path / "acquire.toml"
    cfg.write_text(f"[rotation]\nmax_duration_s = {rotate_s}\n[recorder]\nfsync = false\n")
    serve, paths = start_serve("--scenario", "figure8", "--duration", str(duration_s), "--seed", str(seed),
                               "--speed", "10", "--hold")
    try:
        d, _ = start_daemon(out, paths, "--config", str(cfg), "--time-scale", "10")
    except BaseException:
        serve.kill()
        raise
    serve.send_signal(signal.SIGUSR1)
    return serve, d


def wait_for(condition, daemon, timeout_s: float = 60) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline and daemon.poll() is None, "timed out (or the daemon exited)"
        time.sleep(0.2)


@pytest.mark.slow
def test_daemon_session_is_a_rosbag2_directory_rotation_by_rotation(tmp_path: Path) -> None:
    out = tmp_path / "drives"
    serve, d = start_session(tmp_path, out, rotate_s=6.0, duration_s=150, seed=2)
    try:
        # after the first rotation, before the session ends: the metadata lists the closed file(s) only
        wait_for(lambda: list(out.glob("*/metadata.yaml")), d)
        (session,) = [p.parent for p in out.glob("*/metadata.yaml")]
        listed = yaml.safe_load((session / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        closed = [session / n for n in listed["relative_file_paths"]]
        assert closed and all(is_finished(f) for f in closed)
        mid, _, mid_total = read_bag(session)
        assert mid == counts_in_files(closed) and mid_total == sum(mid.values())
        wait_served(serve, d, 60)
    finally:
        if serve.poll() is None:
            serve.kill()
    d.send_signal(signal.SIGTERM)
    assert d.wait(30) == 0, d.stderr.read()
    files = sorted(session.glob("*.mcap"))
    assert len(files) >= 3 and [f.name for f in files[:len(closed)]] == [f.name for f in closed]
    meta = yaml.safe_load((session / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == [f.name for f in files] == [x["path"] for x in meta["files"]]
    want = counts_in_files(files)
    got, types, total = read_bag(session)
    assert got == want and total == sum(want.values()) == meta["message_count"]
    assert got["/imu"] == 150 * 500 and types["/imu"] == "sensor_msgs/msg/Imu"
    per_file = [counts_in_files([f]) for f in files]
    assert [x["message_count"] for x in meta["files"]] == [sum(c.values()) for c in per_file]
    for x, f in zip(meta["files"], files):            # each file's start and duration from its own log times
        with open(f, "rb") as fh:
            t = [m.log_time for _s, _c, m in make_reader(fh).iter_messages(log_time_order=False)]
        assert x["starting_time"]["nanoseconds_since_epoch"] == min(t)
        assert x["duration"]["nanoseconds"] == max(t) - min(t)
    for tw in meta["topics_with_message_count"]:
        tm = tw["topic_metadata"]
        assert tm["serialization_format"] == "cdr" and tm["offered_qos_profiles"][0]["reliability"] == "reliable"
        assert tw["message_count"] == want[tm["name"]]
    # a Jazzy typestore decodes what the Reader yields
    store = get_typestore(Stores.ROS2_JAZZY)
    with rosbags.Reader(session) as r:
        conn = [c for c in r.connections if c.topic == "/imu"]
        _, _, raw = next(r.messages(connections=conn))
        assert store.deserialize_cdr(raw, "sensor_msgs/msg/Imu").header.frame_id == "imu"
    # every reader command takes the directory, several files and one file
    info_dir = json.loads(run("info", str(session), "--json").stdout)
    info_files = json.loads(run("info", *map(str, files), "--json").stdout)
    assert info_dir.pop("path") == str(session) and info_dir == {k: v for k, v in info_files.items() if k != "path"}
    # info gives what `ros2 bag info` gives, computed from the files here
    chunks = 0
    for f in files:
        with open(f, "rb") as fh:
            chunks += len(make_reader(fh).get_summary().chunk_indexes)
    assert info_files["size_bytes"] == sum(f.stat().st_size for f in files)
    assert info_files["message_total"] == meta["message_count"] and info_files["chunks"] == chunks > len(files)
    assert info_files["start_ns"] == meta["starting_time"]["nanoseconds_since_epoch"]
    assert info_files["end_ns"] - info_files["start_ns"] == meta["duration"]["nanoseconds"]
    assert info_files["compression"] == ["zstd"]
    text = run("info", str(session)).stdout
    assert f"{meta['message_count']} messages in {chunks} chunks, compression zstd" in text
    one = run("info", str(files[-1]))
    assert one.returncode == 0 and "/imu" in one.stdout


@pytest.mark.slow
def test_killed_session_recovered_into_its_metadata(tmp_path: Path) -> None:
    out = tmp_path / "drives"
    serve, d = start_session(tmp_path, out, rotate_s=2.0, duration_s=100, seed=3)
    try:
        wait_for(lambda: len(list(out.glob("*/*.mcap"))) >= 2, d)
        time.sleep(1.0)
        d.send_signal(signal.SIGKILL)
        d.wait(10)
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(10)
    (session,) = {f.parent for f in out.glob("*/*.mcap")}
    files = sorted(session.glob("*.mcap"))
    cut = files[-1]
    assert not is_finished(cut)
    before = yaml.safe_load((session / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert cut.name not in before["relative_file_paths"]
    r = run("recover", str(session))
    assert r.returncode == 0, r.stderr
    meta = yaml.safe_load((session / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    rec = cut.with_name(cut.stem + ".recovered.mcap")
    assert meta["relative_file_paths"] == [f.name for f in files[:-1]] + [rec.name]
    got, _, _ = read_bag(session)
    assert got == counts_in_files([*files[:-1], rec]) and got["/imu"] > 0


@pytest.mark.slow
def test_fused_file_as_a_bag_and_metadata_never_follows_a_symlink(tmp_path: Path, figure8_short: Path) -> None:
    out = tmp_path / "fused"
    r = run("fuse", str(figure8_short), "--method", "kf", "--out", str(out), "--bag")
    assert r.returncode == 0, r.stderr
    (mcap,) = out.glob("*.mcap")
    assert mcap.name == "fused.mcap" and (out / "metadata.yaml").is_file()
    got, types, total = read_bag(out)
    assert got == counts_in_files([mcap]) and total == sum(got.values())
    assert types["/fusion/kf/fix"] == "sensor_msgs/msg/NavSatFix"
    # a symlink planted at metadata.yaml is replaced, its target untouched
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (out / "metadata.yaml").unlink()
    os.symlink(victim, out / "metadata.yaml")
    bagdir.write_bag_metadata(mcap)
    assert victim.read_text() == "keep" and not (out / "metadata.yaml").is_symlink()
    assert read_bag(out)[0] == got
    # rebuild and filter write the same way
    for cmd in (["rebuild", str(figure8_short)], ["filter", str(figure8_short), "--topics", "/imu"]):
        dst = tmp_path / cmd[0]
        r = run(*cmd, "--out", str(dst), "--bag")
        assert r.returncode == 0, r.stderr
        assert read_bag(dst)[0] == counts_in_files(list(dst.glob("*.mcap")))
