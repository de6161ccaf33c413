"""``drive.drive.Drive``: a drive's files opened once and checked as one drive before the long work, on files
third-party writers made (mcap_ros2's ``Writer``, python-can's ``Logger``): two files that disagree on the IMU's
``/tf_static`` frame, a boot-relative candump log imported without a time base, or placed years from the drive,
each end in one line naming the files and exit code 2."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import can as pycan
import pytest
from mcap_ros2.writer import Writer

from fieldlog.drive import reader
from fieldlog.drive.drive import Drive, DriveError
from foreign_drives import TF_DEF, TF_QUAT, Foreign, write_foreign

ROOT = Path(__file__).resolve().parents[1]


def _cli(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fieldlog", *map(str, args)], cwd=cwd, capture_output=True,
                          text=True, timeout=600)


def _one_line(r: subprocess.CompletedProcess, *names: str) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert all(n in lines[0] for n in names), (names, lines[0])
    return lines[0]


def _tf_only(path: Path, frame: str, t_ns: int) -> Path:
    """A file holding only a /tf_static that puts ``imu`` in base_link with the axes ``frame``, at ``t_ns``."""
    x, y, z, w = TF_QUAT[frame]
    with open(path, "wb") as fh:
        wr = Writer(fh)
        s = wr.register_msgdef("tf2_msgs/msg/TFMessage", TF_DEF)
        msg = {"transforms": [{"header": {"stamp": {"sec": t_ns // 10**9, "nanosec": t_ns % 10**9},
                                          "frame_id": "base_link"}, "child_frame_id": "imu",
                               "transform": {"translation": {"x": 0.0, "y": 0.0, "z": 0.0},
                                             "rotation": {"x": x, "y": y, "z": z, "w": w}}}]}
        wr.write_message("/tf_static", s, msg, log_time=t_ns, publish_time=t_ns)
        wr.finish()
    return path


@pytest.fixture(scope="module")
def frd_drive(figure8_150s_seed3, tmp_path_factory) -> Path:
    """Another logger's 60 s drive, IMU ``imu`` in FRD as its own /tf_static says."""
    out = tmp_path_factory.mktemp("frd") / "drive.mcap"
    return write_foreign(figure8_150s_seed3, out, Foreign(frame="frd", tf_static=True, imu_frame_id="imu",
                                                          max_s=60.0))


def test_files_that_disagree_on_the_imu_frame_are_refused(frd_drive, tmp_path):
    t0 = int(reader.read_topic(frd_drive, "/sensors/imu")["log_time_ns"][0])
    other = _tf_only(tmp_path / "can.mcap", "rfu", t0)
    line = _one_line(_cli("fuse", frd_drive, other, "--imu-topic", "/sensors/imu", "--fix-topic",
                          "/sensors/gnss/fix", "--out", tmp_path / "fused.mcap", cwd=tmp_path),
                     str(frd_drive), str(other), "'imu'", "--tf-from")
    assert "fused.mcap" not in line and not (tmp_path / "fused.mcap").exists()
    # the same transform twice is no conflict; --tf-from says which file's wins
    assert Drive.open([frd_drive, _tf_only(tmp_path / "same.mcap", "frd", t0)]).tf_static()["imu"][0] == "base_link"
    d = Drive.open([frd_drive, other], tf_from=frd_drive)
    assert d.tf_static()["imu"][2].tolist() == d.transforms[frd_drive]["imu"][2].tolist()
    assert Drive.open([frd_drive, other], imu_axes_given=True)
    with pytest.raises(DriveError, match="not one of the drive's files"):
        Drive.open([frd_drive, other], tf_from=tmp_path / "elsewhere.mcap")
    r = _cli("fuse", "-q", frd_drive, other, "--imu-topic", "/sensors/imu", "--fix-topic", "/sensors/gnss/fix",
             "--tf-from", frd_drive, "--out", tmp_path / "fused.mcap", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "frd" in reader.read_metadata(tmp_path / "fused.mcap")["fusion"]["inputs"]


@pytest.mark.parametrize("command", ["replay", "view"])
def test_replay_and_view_open_the_drive_as_fuse_does(frd_drive, tmp_path, command):
    t0 = int(reader.read_topic(frd_drive, "/sensors/imu")["log_time_ns"][0])
    other = _tf_only(tmp_path / "can.mcap", "rfu", t0)
    rrd = tmp_path / "out.rrd"
    _one_line(_cli(command, frd_drive, other, "--imu-topic", "/sensors/imu", "--fix-topic", "/sensors/gnss/fix",
                   "--rrd", rrd, cwd=tmp_path), str(frd_drive), str(other), "'imu'", "--tf-from")
    assert not rrd.exists()


def _boot_log(path: Path, n: int = 250, t0_s: float = 12.5) -> Path:
    """A candump log as python-can writes it, stamped from the logger's boot (t0_s s on), 50 Hz."""
    with pycan.Logger(str(path)) as log:
        for i in range(n):
            log(pycan.Message(timestamp=t0_s + 0.02 * i, arbitration_id=0x123, is_extended_id=False,
                              data=bytes([i % 256, 1, 2, 3])))
    return path


def test_a_boot_relative_can_log_needs_a_time_base(frd_drive, tmp_path):
    log = _boot_log(tmp_path / "boot.log")
    os.utime(log, (4_000_000_000, 4_000_000_000))  # a modification time far from the drive: never a time base
    _one_line(_cli("import", "--can", log, "--out", tmp_path / "can.mcap", cwd=tmp_path), str(log),
              "--start", "--align-to")
    assert not (tmp_path / "can.mcap").exists()
    # aligned to the drive: its first frame at the drive's first log time, and the two make one drive
    r = _cli("import", "-q", "--can", log, "--align-to", frd_drive, "--out", tmp_path / "can.mcap", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    can_t = reader.read_topic(tmp_path / "can.mcap", "/raw/can")["log_time_ns"]
    drive = Drive.open([frd_drive, tmp_path / "can.mcap"])  # the import has no IMU: it claims no transform
    assert int(can_t[0]) == drive.sources[0].start_ns
    assert drive.sources[1].start_ns <= drive.sources[0].end_ns
    assert drive.transforms[tmp_path / "can.mcap"] == {}
    assert "/tf_static" not in {t.topic for t in reader.topics(tmp_path / "can.mcap")}
    # so the drive's own /tf_static places the IMU: read in FRD, with no option
    r = _cli("fuse", "-q", frd_drive, tmp_path / "can.mcap", "--imu-topic", "/sensors/imu", "--fix-topic",
             "/sensors/gnss/fix", "--out", tmp_path / "fused.mcap", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "frd" in reader.read_metadata(tmp_path / "fused.mcap")["fusion"]["inputs"]
    (tmp_path / "fused.mcap").unlink()
    # placed years before the drive: fuse refuses the pair before reading a block
    r = _cli("import", "-q", "--can", log, "--start", "2018-03-01T08:00:00Z", "--out", tmp_path / "old.mcap",
             cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert int(reader.read_topic(tmp_path / "old.mcap", "/raw/can")["log_time_ns"][0]) == 1_519_891_200 * 10**9
    _one_line(_cli("fuse", frd_drive, tmp_path / "old.mcap", "--imu-topic", "/sensors/imu", "--fix-topic",
                   "/sensors/gnss/fix", "--out", tmp_path / "fused.mcap", cwd=tmp_path),
              str(frd_drive), "old.mcap", "do not overlap")
    assert not (tmp_path / "fused.mcap").exists()


AUDIT = """
import os, sys
target, log = os.path.realpath(sys.argv[1]), sys.argv[2]
def hook(event, args):
    if event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
        if os.path.realpath(os.fsdecode(args[0])) == target:
            fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
            os.write(fd, b"open\\n")
            os.close(fd)
sys.addaudithook(hook)
from fieldlog.tools.cli import main
sys.exit(main(sys.argv[3:]))
"""


def test_fuse_of_a_one_file_drive_opens_it_once(figure8_150s_seed3, tmp_path):
    """Every open of the drive file, in the command's process and in the workers it forks (Python's audit
    events): the file is mapped and its summary read once, however many parts of fuse read the drive."""
    opens = tmp_path / "opens.txt"
    r = subprocess.run([sys.executable, "-c", AUDIT, str(figure8_150s_seed3), str(opens), "fuse", "-q",
                        str(figure8_150s_seed3), "--method", "dkf-rbfn", "--out", str(tmp_path / "f.mcap")],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert reader.topics(tmp_path / "f.mcap")  # it fused
    assert opens.read_text().splitlines() == ["open"]
