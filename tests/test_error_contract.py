"""The error contract at its edges: times past 2038, hostile TOML and YAML, full disks, planted files.

Every case ends in exit 0, or exit 2 with one line naming the file; never an internal error (exit 1)."""
from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np
import pytest

from fieldlog.acquire import gnss, nmea, novatel
from fieldlog.drive import messages
from fieldlog.drive import reader
from fieldlog.tools.cli import main

NS = 1_000_000_000


def cli(capsys, *args: str) -> tuple[int, list[str]]:
    """``fieldlog ARGS`` in this process: the exit code and the lines on stderr."""
    code = main([*args, "-q"])
    return code, capsys.readouterr().err.strip().splitlines()


# ------------------------------------------------------------------------------------------- 64-bit times

def nmea_log(day: dt.date, zda_year: int | None = None, n: int = 20) -> bytes:
    """``n`` one-second epochs (RMC, GGA, ZDA) at noon of ``day``; the ZDA says ``zda_year`` if given."""
    out = b""
    for i in range(n):
        t = f"1200{i:02d}.00"
        out += nmea.sentence(f"GPRMC,{t},A,4807.038,N,01131.000,E,0.0,0.0,{day:%d%m%y},,,A")
        out += nmea.sentence(f"GPGGA,{t},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
        out += nmea.sentence(f"GPZDA,{t},{day:%d},{day:%m},{zda_year or day.year},00,00")
    return out


def novatel_log(week: int, n: int = 20) -> bytes:
    return b"".join(novatel.format_timea(week, 100.0 + i, 18, (2040, 1, 1, 0, 0, 0))
                    + novatel.format_bestposa(week, 100.0 + i, 48.1, 11.5, 500.0, 47.0, (1.0, 1.0, 2.0), 10)
                    + novatel.format_bestvela(week, 100.0 + i, (0.0, 0.0, 0.0)) for i in range(n))


def test_header_stamps_carry_every_time_to_2106_and_lay_out_earlier_ones_as_int32() -> None:
    t = np.array([0, 1_700_000_000 * NS + 5, (2**31 - 1) * NS, 2**31 * NS + 7, messages.STAMP_END_NS - 1])
    sec, nsec = messages.split_stamp(t)
    assert np.array_equal(messages.join_stamp(sec, nsec), t)
    assert sec.dtype == np.int32 and np.array_equal(sec[:3], t[:3] // NS)       # int32 as before 2038
    for stamp in t.tolist():
        raw = messages.encode_raw(stamp, 42, "gps", b"$x")
        assert messages.decode_raw(raw)[:2] == (stamp, 42)
        batch = reader.decode_raw_batch(messages.Packed.from_list([raw]))
        assert batch["stamp_ns"][0] == stamp and batch["valid"][0]
        s = messages.encode_sentence(stamp, "$GPGGA")
        assert s[4:12] == raw[4:12]                                              # the same header layout
    assert (messages.STAMP_END_NS - 1) // NS // 86400 // 365 + 1970 >= gnss.YEAR_MAX


@pytest.mark.parametrize("case", ["nmea-2040", "zda-2200", "novatel-3100", "novatel-4000", "novatel-9999"])
def test_gps_times_past_2038_import_or_are_refused_in_one_line(tmp_path: Path, capsys, case: str) -> None:
    """A receiver in 2040 (past int32 seconds) records its true times; a year or week no header can carry (2200,
    week 9999) is counted in bad_fields and refused, the rest of the log kept."""
    kind, value = case.split("-")
    year = int(value)
    log = tmp_path / "gps.log"
    if kind == "novatel":
        log.write_bytes(novatel_log(year))
        utc0 = novatel.utc_ns_of(year, 100_000, 18)
    else:
        day = dt.date(2040, 1, 1)
        log.write_bytes(nmea_log(day, zda_year=year if kind == "zda" else None))
        utc0 = gnss.utc_ns(day, 12 * 3600.0)
    out = tmp_path / "d.mcap"
    code, err = cli(capsys, "import", "--gps", str(log), "--out", str(out))
    if year > gnss.WEEK_MAX and kind == "novatel":
        assert code == 2 and len(err) == 1 and str(log) in err[0], err
        assert not out.exists()
        return
    assert code == 0, err
    assert utc0 > 2**31 * NS
    fix = reader.read_topic(out, "/gps/fix")
    assert len(fix["stamp_ns"]) == 20 and fix["stamp_ns"][0] == utc0
    assert np.array_equal(fix["stamp_ns"], fix["log_time_ns"])
    raw = reader.read_raw(out, "/raw/gps")
    assert np.array_equal(raw["stamp_ns"], raw["log_time_ns"]) and raw["stamp_ns"][0] >= utc0
    counters = reader.read_metadata(out)["acquire.counters"]
    assert int(counters["nmea.bad_fields"]) == (20 if kind == "zda" else 0)
    rebuilt = tmp_path / "r.mcap"
    assert cli(capsys, "rebuild", str(out), "--out", str(rebuilt))[0] == 0
    assert np.array_equal(reader.read_topic(rebuilt, "/gps/fix")["stamp_ns"], fix["stamp_ns"])


# ------------------------------------------------------------------------------------------- TOML and YAML

DEEP = 5000
BAGS = {"integer paths": "rosbag2_bagfile_information:\n  storage_identifier: mcap\n  relative_file_paths: [1, 2]\n",
        "list paths": "rosbag2_bagfile_information:\n  relative_file_paths: [[a.mcap, b.mcap]]\n",
        "files not mappings": "rosbag2_bagfile_information:\n  files: [3]\n",
        "deep": "rosbag2_bagfile_information: " + "[" * DEEP + "]" * DEEP + "\n",
        "deep mapping": "".join(f"{' ' * i}k{i}:\n" for i in range(200)) + " " * 200 + "x: 1\n",
        "alias bomb": "".join(f"{c}: &{c} [{', '.join([f'*{p}' if p else 'x'] * 9)}]\n"
                              for p, c in zip(" abcdefg", "abcdefgh")) + "rosbag2_bagfile_information: [*h]\n",
        "no yaml": "\x00\x01 not: yaml: [ at all\n\t- x\n",
        "not a mapping": "just text\n",
        "outside": "rosbag2_bagfile_information:\n  relative_file_paths: [../drive.mcap]\n",
        "absolute": "rosbag2_bagfile_information:\n  relative_file_paths: [ABS]\n"}


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    from fieldlog.tools.sim import simulate

    path = tmp_path_factory.mktemp("drive") / "drive.mcap"
    simulate.simulate("figure8", 10.0, 1, path)
    return path


@pytest.mark.parametrize("case", sorted(BAGS))
def test_a_hostile_metadata_yaml_is_one_line_and_exit_2(drive: Path, tmp_path: Path, capsys, case: str) -> None:
    bag = tmp_path / "bag"
    bag.mkdir()
    (tmp_path / "drive.mcap").symlink_to(drive)            # what "outside" and "absolute" name: never opened
    (bag / "metadata.yaml").write_text(BAGS[case].replace("ABS", str(drive)))
    for command in (["info", str(bag)], ["filter", str(bag), "--out", str(tmp_path / "f.mcap")]):
        code, err = cli(capsys, *command)
        assert code == 2 and len(err) == 1 and str(bag / "metadata.yaml") in err[0], err
    assert not (tmp_path / "f.mcap").exists()


@pytest.mark.parametrize("form", ["array", "inline table", "table header"])
def test_a_toml_nested_5000_deep_is_one_line_and_exit_2(tmp_path: Path, capsys, form: str) -> None:
    value = {"array": "[" * DEEP + "]" * DEEP, "inline table": "{b = " * DEEP + "1" + "}" * DEEP}.get(form)
    text = f"a = {value}\n" if value else "[" + ".".join(["a"] * DEEP) + "]\nx = 1\n"
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    cal = tmp_path / "cal.toml"
    cal.write_text(text.replace("a =", "[gyro]\nsensitivity ="))
    scenario = tmp_path / "s.toml"
    scenario.write_text(text.replace("a =", "[trajectory]\na ="))
    for command, f in ((["acquire", "--config", str(cfg), "--daq", "a", "--gps", "b", "--out", str(tmp_path)], cfg),
                       (["import", "--gps", "x", "--can", "y", "--config", str(cfg), "--out", "o.mcap"], cfg),
                       (["sim", "--scenario", str(scenario), "--duration", "2", "--out", str(tmp_path / "s")],
                        scenario)):
        code, err = cli(capsys, *command)
        assert code == 2 and len(err) == 1 and str(f) in err[0], (command, err)
    from fieldlog.acquire import calib

    with pytest.raises(ValueError, match=str(cal)):
        calib.load_calibration(cal)


@pytest.mark.parametrize("text, key", [("[daemon]\nbus = 5\n", "[daemon] bus"), ("daemon = [1, 2]\n", "[daemon]"),
                                       ("[recorder]\nchunk_size = 'x'\n", "[recorder] chunk_size")])
def test_a_config_of_the_wrong_types_names_the_file_and_the_key(tmp_path: Path, capsys, text: str, key: str) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    code, err = cli(capsys, "acquire", "--config", str(cfg), "--daq", "a", "--gps", "b", "--out", str(tmp_path))
    assert code == 2 and len(err) == 1 and str(cfg) in err[0] and key in err[0], err


# ------------------------------------------------------------------------------------------- failures leave nothing

@pytest.mark.parametrize("topic", ["/tf_static", "/imu"])
def test_a_damaged_transform_or_first_imu_message_is_one_line(drive: Path, tmp_path: Path, capsys, topic) -> None:
    """The drive copied by mcap's own writer with the first message of ``topic`` cut to 18 bytes: /tf_static's
    transforms and the IMU's frame are read field by field (``drive.messages.decode_tf``, ``header_frame_id``),
    and a message cut short is one line naming the file."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    bad = tmp_path / "bad.mcap"
    with open(drive, "rb") as src, open(bad, "wb") as out:
        r, w = make_reader(src), Writer(out)
        w.start(profile="ros2")
        summary, schemas, channels, cut = r.get_summary(), {}, {}, False
        for sid, sc in summary.schemas.items():
            schemas[sid] = w.register_schema(sc.name, sc.encoding, sc.data)
        for cid, ch in summary.channels.items():
            channels[cid] = w.register_channel(ch.topic, ch.message_encoding, schemas[ch.schema_id])
        for _, ch, m in r.iter_messages(log_time_order=False):
            data = m.data
            if ch.topic == topic and not cut:
                data, cut = data[:18], True  # cut inside its first header
            w.add_message(channels[ch.id], m.log_time, data, m.publish_time)
        w.finish()
    code, err = cli(capsys, "fuse", str(bad), "--out", str(tmp_path / "kf.mcap"))
    assert code == 2 and len(err) == 1 and str(bad) in err[0] and "does not decode" in err[0], err
    assert not (tmp_path / "kf.mcap").exists()
    # view: /tf_static is read as the drive is opened; without the IMU's frame it shows the drive as it is
    code, err = cli(capsys, "view", str(bad), "--rrd", str(tmp_path / "v.rrd"))
    if topic == "/tf_static":
        assert code == 2 and len(err) == 1 and str(bad) in err[0] and "does not decode" in err[0], err
    else:
        assert code == 0 and (tmp_path / "v.rrd").stat().st_size > 0


@pytest.fixture
def small_disk(tmp_path: Path):
    """A 256 kB tmpfs (root only; skipped in one line where mounting is not permitted)."""
    import os
    import subprocess

    d = tmp_path / "small"
    d.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(d)], capture_output=True, text=True) \
        if os.geteuid() == 0 else None
    if r is None or r.returncode != 0:
        pytest.skip("a small tmpfs cannot be mounted here (needs root and mount permission)")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


@pytest.fixture(scope="module")
def captures(drive: Path) -> tuple[Path, Path]:
    """The drive's DAQ and GPS bytes as capture files, for ``import``."""
    out = []
    for port in ("daq", "gps"):
        f = drive.parent / f"{port}.bin"
        f.write_bytes(reader.read_raw(drive, f"/raw/{port}")["data"].buf.tobytes())
        out.append(f)
    return out[0], out[1]


FULL = {"sim": lambda d, o, c: ["sim", "--scenario", "figure8", "--duration", "20", "--out", f"{o}/x.mcap"],
        "rebuild": lambda d, o, c: ["rebuild", str(d), "--out", f"{o}/x.mcap"],
        "import": lambda d, o, c: ["import", "--daq", str(c[0]), "--gps", str(c[1]), "--out", f"{o}/x.mcap"],
        "filter": lambda d, o, c: ["filter", str(d), "--out", f"{o}/x.mcap"],
        "filter --bag": lambda d, o, c: ["filter", str(d), "--bag", "--out", f"{o}/x"],
        "export": lambda d, o, c: ["export", str(d), "--out", f"{o}/tables", "--format", "csv"]}


@pytest.mark.parametrize("command", sorted(FULL))
def test_a_full_disk_is_one_line_naming_the_file_and_leaves_no_file(drive, captures, small_disk, capsys,
                                                                       command: str) -> None:
    code, err = cli(capsys, *FULL[command](drive, small_disk, captures))
    assert code == 2 and len(err) == 1 and "No space left on device" in err[0], err
    assert str(small_disk) in err[0] and "Traceback" not in err[0]                       # names the file
    assert [p for p in small_disk.rglob("*") if not p.is_dir()] == []                    # nothing half-written


@pytest.mark.slow
def test_acquire_on_a_full_disk_exits_2_naming_the_file_and_keeps_it(small_disk: Path) -> None:
    import signal

    from fieldlog.acquire.recovery import has_footer
    from test_daemon import start_daemon
    from test_serve import start_serve

    serve, paths = start_serve("--scenario", "figure8", "--duration", "120", "--speed", "20", "--hold")
    try:
        d, _ = start_daemon(small_disk, paths)
        serve.send_signal(signal.SIGUSR1)
        code, log = d.wait(300), d.stderr.read()
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(60)
    (f,) = sorted(small_disk.glob("*/*.mcap"))
    errors = [line for line in log.splitlines() if "ERROR" in line or "error:" in line]
    assert code == 2 and len(errors) == 1 and str(f) in errors[0] and "disk full" in errors[0], log
    assert "Traceback" not in log and not has_footer(f) and f.stat().st_size > 0        # kept for recover


@pytest.mark.parametrize("planted", ["link", "stale"])
def test_recover_of_a_session_with_a_planted_recovered_file_says_what_to_do(drive, tmp_path: Path, capsys,
                                                                            planted: str) -> None:
    from fieldlog.drive.files import drive_files

    session = tmp_path / "session"
    session.mkdir()
    cut = session / "s_0001.mcap"
    data = drive.read_bytes()
    cut.write_bytes(data[:len(data) * 2 // 3])
    victim = tmp_path / "victim.mcap"
    victim.write_bytes(b"precious")
    dst = session / "s_0001.recovered.mcap"
    if planted == "link":
        dst.symlink_to(victim)
    else:
        dst.write_bytes(data[:1000])                           # a recovery cut short, older than the file
        import os
        os.utime(dst, ns=(cut.stat().st_mtime_ns - NS,) * 2)
    assert drive_files(session) == [cut]                      # readers never take it in the cut file's place
    code, err = cli(capsys, "recover", str(session))
    assert code == 2 and len(err) == 1 and str(dst) in err[0] and str(cut) in err[0], err
    assert ("symbolic link" if planted == "link" else "--force") in err[0]
    assert victim.read_bytes() == b"precious" and cut.read_bytes() == data[:len(data) * 2 // 3]
    if planted == "link":
        dst.unlink()
    code, err = cli(capsys, "recover", str(session), *(["--force"] if planted == "stale" else []))
    assert code == 0, err
    assert drive_files(session) == [dst] and not dst.is_symlink()
    assert reader.read_metadata(dst)["recover"]
    code, err = cli(capsys, "recover", str(session))            # once is enough
    assert code == 0 and drive_files(session) == [dst]


def test_filter_bag_refuses_a_symbolic_link_for_its_folder_as_export_does(drive, tmp_path: Path, capsys) -> None:
    target = tmp_path / "elsewhere"
    target.mkdir()
    link = tmp_path / "bag"
    link.symlink_to(target)
    for command in (["filter", str(drive), "--bag", "--out", str(link)], ["export", str(drive), "--out", str(link)]):
        code, err = cli(capsys, *command)
        assert code == 2 and len(err) == 1 and "symbolic link" in err[0] and str(link) in err[0], err
    assert list(target.iterdir()) == []


def test_garbage_on_the_live_bus_is_counted_and_logged_and_the_client_still_served(tmp_path: Path, caplog) -> None:
    import socket

    from fieldlog.acquire.daemon import BusServer
    from fieldlog.replay import live

    bus = BusServer(str(tmp_path / "bus"))
    try:
        c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        c.connect(str(tmp_path / "bus"))
        garbage = np.random.default_rng(1).bytes(200_000)
        sent = 0
        c.setblocking(False)
        while sent < len(garbage):
            try:
                sent += c.send(garbage[sent:sent + 65536])
            except BlockingIOError:
                pass
            bus.pump()
        for _ in range(100):
            bus.pump()
        assert bus.ignored_bytes == len(garbage) and len(bus.clients) == 1
        assert len([r for r in caplog.records if "bus.ignored_bytes" in r.getMessage()]) == 1
        t = np.array([NS], np.int64)
        bus.publish("/gps/nmea", t, messages.Packed.from_list([messages.encode_sentence(NS, "$GPGGA")]))
        c.setblocking(True)
        c.settimeout(10)
        n = int.from_bytes(live._read_exact(c, 4), "little")
        assert live.parse_frame(live._read_exact(c, n)).topic == "/gps/nmea"           # still served
        c.close()
    finally:
        bus.close()


def test_foxglove_sdk_warnings_go_through_fieldlogs_log(capsys) -> None:
    import socket
    import time

    pytest.importorskip("foxglove", reason="foxglove-sdk (the [foxglove] extra) is not installed")
    from fieldlog.tools.cli import setup_logging
    from fieldlog.tools.foxglove_live import _Server

    setup_logging("replay", 0)
    with _Server("127.0.0.1:0", "kf", []) as s:
        port = int(s.address.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as c:
            c.sendall(b"GARBAGE\r\n\r\n" * 100)
            time.sleep(0.5)
        end = time.monotonic() + 20
        err = ""
        while "Dropping client" not in err and time.monotonic() < end:
            time.sleep(0.1)
            err += capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and all(line.startswith("fieldlog replay: ") for line in lines), lines


def test_the_daemons_start_says_what_to_do_with_a_planted_recovered_file(drive, tmp_path: Path) -> None:
    import os

    from fieldlog.acquire.daemon import recover_unfinished

    session = tmp_path / "out" / "session"
    session.mkdir(parents=True)
    cut = session / "s_0001.mcap"
    data = drive.read_bytes()
    cut.write_bytes(data[:len(data) // 2])
    dst = session / "s_0001.recovered.mcap"
    dst.write_bytes(data[:1000])
    os.utime(dst, ns=(cut.stat().st_mtime_ns - NS,) * 2)
    said: list[str] = []
    assert recover_unfinished(tmp_path / "out", said.append) == []
    assert len(said) == 1 and str(dst) in said[0] and "fieldlog recover" in said[0]
    assert dst.read_bytes() == data[:1000]
    dst.unlink()
    assert recover_unfinished(tmp_path / "out", said.append) == [(cut, dst)]
    assert recover_unfinished(tmp_path / "out", said.append) == []                 # once
