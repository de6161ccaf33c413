"""Outputs are created, never followed: a planted symbolic link (at a file name or as a folder inside --out) is
refused in one line and its target left alone; an existing file is replaced only with --force; the daemon skips
taken names and records on."""
from __future__ import annotations

import datetime as _dt
import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from fieldlog.drive import outputs
from fieldlog.acquire.config import NAME_FORMAT
from fieldlog.acquire.daemon import is_finished
from fieldlog.tools.sim import simulate
from test_daemon import raw_stream, start_daemon
from test_serve import expected_bytes, start_serve, wait_served

PRECIOUS = b"precious bytes, not an MCAP file\n"


@pytest.fixture(scope="module")
def drive(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("drive")
    path = d / "d.mcap"
    simulate.simulate("figure8", 20.0, 2, path)
    return path


def plant(link: Path, target: Path) -> None:
    target.write_bytes(PRECIOUS)
    link.symlink_to(target)


# ------------------------------------------------------------------------------------------- the helper

def test_create_refuses_links_and_existing_names_and_force_replaces_only_files(tmp_path: Path) -> None:
    target, link, dangling = tmp_path / "target", tmp_path / "link", tmp_path / "dangling"
    plant(link, target)
    dangling.symlink_to(tmp_path / "nowhere" / "x")
    for force in (False, True):
        for p in (link, dangling):
            with pytest.raises(outputs.Refused, match="symbolic link"):
                outputs.create(p, force)
    assert target.read_bytes() == PRECIOUS and not (tmp_path / "nowhere").exists()
    f = tmp_path / "file"
    with outputs.create(f) as out:
        out.write(b"one")
    with pytest.raises(outputs.Refused, match="--force"):
        outputs.create(f)
    assert f.read_bytes() == b"one"
    with outputs.create(f, force=True) as out:
        out.write(b"two")
    assert f.read_bytes() == b"two"
    with pytest.raises(IsADirectoryError):
        outputs.create(tmp_path, force=True)


def test_folders_inside_an_output_folder_are_never_links(tmp_path: Path) -> None:
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir()
    (out / "gps").symlink_to(elsewhere)
    with pytest.raises(outputs.Refused, match="'gps' inside the output folder"):
        outputs.create(out / "gps" / "fix.csv", root=out)
    with pytest.raises(outputs.Refused, match="'gps' inside the output folder"):
        outputs.out_dir(out, "gps")
    with outputs.create(out / "a" / "b" / "c.csv", root=out) as f:   # folders made as needed
        f.write(b"x")
    assert (out / "a" / "b" / "c.csv").read_bytes() == b"x" and list(elsewhere.iterdir()) == []
    (tmp_path / "linked").symlink_to(out)
    with pytest.raises(outputs.Refused, match="output folder"):
        outputs.out_dir(tmp_path / "linked")


def test_staged_files_appear_only_complete_and_never_over_a_link(tmp_path: Path) -> None:
    dst = tmp_path / "x.rrd"
    with outputs.staged(dst) as work:
        work.write_bytes(b"data")
        assert not dst.exists() and work.parent.parent == tmp_path and oct(work.parent.stat().st_mode)[-3:] == "700"
    assert dst.read_bytes() == b"data" and sorted(tmp_path.iterdir()) == [dst]
    with pytest.raises(RuntimeError), outputs.staged(tmp_path / "y.rrd") as work:
        work.write_bytes(b"half")
        raise RuntimeError
    assert sorted(tmp_path.iterdir()) == [dst]                  # an error leaves nothing behind
    target, link = tmp_path / "target", tmp_path / "z.rrd"
    with pytest.raises(outputs.Refused), outputs.staged(tmp_path / "z.rrd") as work:  # planted meanwhile
        work.write_bytes(b"data")
        plant(link, target)
    assert target.read_bytes() == PRECIOUS and link.is_symlink()


# ------------------------------------------------------------------------------------------- the commands

WRITERS = {"rebuild": lambda d, o: ["rebuild", d, "--out", o], "filter": lambda d, o: ["filter", d, "--out", o],
           "fuse": lambda d, o: ["fuse", d, "--out", o], "recover": lambda d, o: ["recover", d, "--out", o],
           "view": lambda d, o: ["view", d, "--rrd", o], "export": lambda d, o: ["export", d, "--out-dir", o],
           "sim": lambda d, o: ["sim", "--duration", "5", "--out", o],
           "import": lambda d, o: ["import", "--gps", d, "--out", o]}


@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("command", sorted(WRITERS))
def test_every_command_refuses_a_symlinked_output_in_one_line(drive, tmp_path, capsys, command, force) -> None:
    from fieldlog.tools.cli import main

    src = str(drive)
    if command == "import":
        src = str(tmp_path / "gps.nmea")
        Path(src).write_bytes(b"$GPGGA,120000.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*5C\r\n")
    target, link = tmp_path / "target", tmp_path / "out.link"
    plant(link, target)
    code = main(WRITERS[command](src, str(link)) + ["--force"] * force)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and str(link) in err[0] and "symbolic link" in err[0], err
    assert target.read_bytes() == PRECIOUS and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gps.nmea", "out.link", "target"][command != "import":]


def test_an_existing_output_is_kept_unless_force(drive, tmp_path, capsys) -> None:
    from fieldlog.tools.cli import main

    out = tmp_path / "f.mcap"
    out.write_bytes(PRECIOUS)
    assert main(["filter", str(drive), "--end", "5", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0] and out.read_bytes() == PRECIOUS
    assert main(["filter", str(drive), "--end", "5", "--out", str(out), "--force"]) == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"


@pytest.mark.parametrize("command, first_work", [("fuse", ("fieldlog.tools.fuse", "estimate_installation")),
                                                    ("view", ("fieldlog.replay.viewdata", "start")),
                                                    ("replay", ("fieldlog.replay.player", "replay"))])
def test_an_existing_output_is_refused_before_the_work(drive, tmp_path, capsys, monkeypatch, command,
                                                       first_work) -> None:
    """fuse's installation pass, view's and replay's read of the drive (seconds to minutes on a long drive) come
    after the refusal, not before it."""
    import importlib

    from fieldlog.tools.cli import main

    def not_before_the_check(*a, **k):
        raise AssertionError(f"{first_work[1]} ran before the output was checked")

    monkeypatch.setattr(importlib.import_module(first_work[0]), first_work[1], not_before_the_check)
    out = tmp_path / "out"
    out.write_bytes(PRECIOUS)
    args = ["replay", str(drive), "--rrd", str(out)] if command == "replay" else WRITERS[command](str(drive), str(out))
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists" in err[0] and "--force" in err[0] and out.read_bytes() == PRECIOUS


@pytest.mark.parametrize("existing", ["table.md", "fused/s_kf_5s.mcap"])
def test_evaluate_refuses_an_existing_output_before_its_first_run(tmp_path, capsys, existing) -> None:
    """evaluate fuses every drive with every method at every outage length (here ins, then kf) before it writes
    its tables: an existing table, or a later run's fused file, (without --force) is refused before the first
    run, and nothing is written."""
    from fieldlog.tools.cli import main

    drive = tmp_path / "s.mcap"
    simulate.simulate("figure8", 60.0, 2, drive)
    out = tmp_path / "study"
    (out / "fused").mkdir(parents=True)
    (out / existing).write_bytes(PRECIOUS)
    args = ["evaluate", str(drive), "--out-dir", str(out), "--methods", "ins,kf", "--outages", "5",
            "--first-outage", "20"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and existing.split("/")[-1] in err[0] and "--force" in err[0], err
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == sorted(["fused", existing])
    assert main([*args, "--force"]) == 0 and (out / existing).read_bytes() != PRECIOUS


def test_batch_refuses_an_existing_fused_file_before_its_cluster_starts(drive, tmp_path, capsys, monkeypatch) -> None:
    """A fused file batch would write exists (without --force): one line and exit 2 before the cluster starts,
    not a failed row per drive from its workers."""
    from fieldlog.tools import batch
    from fieldlog.tools.cli import main

    def not_before_the_check(*a, **k):
        raise AssertionError("the cluster started before the outputs were checked")

    monkeypatch.setattr(batch, "client_for", not_before_the_check)
    out = tmp_path / "fleet"
    (out / "fused").mkdir(parents=True)
    (out / "fused" / f"{drive.stem}_kf_30s.mcap").write_bytes(PRECIOUS)
    assert main(["batch", str(drive), "--methods", "kf", "--outages", "30", "--out-dir", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{drive.stem}_kf_30s.mcap" in err[0] and "--force" in err[0], err
    assert sorted(p.name for p in out.rglob("*")) == ["d_kf_30s.mcap", "fused"]


def test_export_refuses_an_existing_table_before_the_first_is_written(drive, tmp_path, capsys) -> None:
    """An existing table (without --force), the last of the drive's topics here, is refused before any table is
    read or written: one line, and nothing else in the folder."""
    from fieldlog.tools.cli import main

    first = tmp_path / "first"
    assert main(["export", str(drive), "--out-dir", str(first), "--format", "csv"]) == 0
    tables = sorted(first.rglob("*.csv"), key=lambda p: p.stat().st_mtime_ns)
    last = tables[-1].relative_to(first)
    out = tmp_path / "tables"
    (out / last).parent.mkdir(parents=True)
    (out / last).write_bytes(PRECIOUS)
    capsys.readouterr()
    assert main(["export", str(drive), "--out-dir", str(out), "--format", "csv"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(tables) > 3 and len(err) == 1 and str(last) in err[0] and "--force" in err[0], err
    assert sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file()) == [last]
    assert sorted(p.relative_to(out) for p in out.rglob("*") if p.is_dir()) == sorted(
        p.relative_to(out) for p in (out / last).parents if p != out and out in p.parents)


def test_export_refuses_a_link_planted_as_a_folder_inside_out(drive, tmp_path, capsys) -> None:
    from fieldlog.tools.cli import main

    out, elsewhere = tmp_path / "tables", tmp_path / "elsewhere"
    out.mkdir()
    elsewhere.mkdir()
    (out / "gps").symlink_to(elsewhere)                 # /gps/fix would go to tables/gps/fix.csv
    code = main(["export", str(drive), "--out-dir", str(out), "--format", "csv", "--topics", "/gps/fix"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "'gps'" in err[0] and str(out) in err[0], err
    assert list(elsewhere.iterdir()) == []
    (out / "gps").unlink()
    assert main(["export", str(drive), "--out-dir", str(out), "--format", "csv", "--topics", "/gps/fix"]) == 0
    assert (out / "gps" / "fix.csv").is_file()
    assert main(["export", str(drive), "--out-dir", str(out), "--format", "csv", "--topics", "/gps/fix"]) == 2
    assert main(["export", str(drive), "--out-dir", str(out), "--format", "csv", "--topics", "/gps/fix", "--force"]) == 0


# ------------------------------------------------------------------------------------------- the daemon

def test_a_live_daemon_skips_planted_links_under_its_next_names_and_loses_nothing(tmp_path: Path) -> None:
    """Links planted under the session directory names of the next minute (to a folder, and dangling), and,
    once the daemon has started, under its next 40 file names in the session (to files, dangling, and a few
    regular files); the daemon rotates every second (host), skips each taken name, logs each link it passes in one
    line, never touches a target, and records every byte the simulator sent."""
    out, targets = tmp_path / "drives", tmp_path / "targets"
    out.mkdir()
    targets.mkdir()
    cfg = tmp_path / "acquire.toml"
    cfg.write_text("[rotation]\nmax_duration_s = 0.3\n")
    elsewhere = targets / "folder"
    elsewhere.mkdir()
    now = int(time.time())
    for sec in range(now - 2, now + 60):                # the session directory: its name and the next taken
        stamp = _dt.datetime.fromtimestamp(sec, _dt.timezone.utc).strftime(NAME_FORMAT)
        (out / stamp).symlink_to(elsewhere)
        (out / f"{stamp}-2").symlink_to(targets / f"{stamp}-2")
    truth = tmp_path / "truth.mcap"
    serve, paths = start_serve("--scenario", "figure8", "--duration", "200", "--seed", "6", "--speed", "20",
                               "--hold", "--truth", str(truth))
    d, log = start_daemon(out, paths, "--config", str(cfg))
    first = Path(log.split(" to ")[-1].strip())
    session = first.parent
    assert session.name.endswith("-3") and not session.is_symlink() and (out / session.name[:-2]).is_symlink()
    planted: dict[Path, tuple[str, Path | None]] = {}   # name -> (kind, link target)
    stem = session.name[:-2]
    for i in range(3, 41):
        name, target = session / f"{stem}_{i:04d}.mcap", targets / f"file_{i}"
        if i % 3 == 1:                                  # free
            continue
        if i % 9 == 0:                                  # a regular file: taken, kept as it is
            name.write_bytes(PRECIOUS)
            planted[name] = ("file", None)
        elif i % 2:                                     # dangling: its target must not appear
            name.symlink_to(target)
            planted[name] = ("dangling", target)
        else:
            plant(name, target)
            planted[name] = ("link", target)
    made = sorted(os.listdir(targets))
    serve.send_signal(signal.SIGUSR1)
    wait_served(serve, d, 300)
    d.send_signal(signal.SIGTERM)
    assert d.wait(300) == 0
    log += d.stderr.read()
    assert "Traceback" not in log
    assert list(elsewhere.iterdir()) == [] and sorted(os.listdir(targets)) == made
    files = sorted(p for p in session.glob("*.mcap") if p not in planted)
    index = [int(f.stem.rsplit("_", 1)[1]) for f in files]
    assert len(files) >= 6 and all(i < 3 or i % 3 == 1 for i in index if i <= 40) and max(index) > 12
    assert all(is_finished(f) for f in files)
    for name, (kind, target) in planted.items():        # nothing written through a link or over a file
        assert name.read_bytes() == PRECIOUS if kind != "dangling" else not target.exists()
        assert (kind == "file") != name.is_symlink()
    assert all((targets / t).read_bytes() == PRECIOUS for t in made if t != "folder")
    passed = [n for n, (kind, _) in planted.items() if kind != "file" and int(n.stem.rsplit("_", 1)[1]) < max(index)]
    assert len(passed) >= 4 and all(log.count(str(n)) == 1 for n in passed), log
    assert f"{out / stem} is a symbolic link" in log and f"{out / stem}-2 is a symbolic link" in log
    want = expected_bytes(truth, "figure8", 200.0, 6)
    assert b"".join(raw_stream(f, "daq")[0] for f in files) == want["daq"]
    assert b"".join(raw_stream(f, "gps")[0] for f in files) == want["gps"]
    mono = np.concatenate([raw_stream(f, "daq")[1] for f in files])
    assert np.all(np.diff(mono) >= 0)


def test_the_bus_socket_is_never_bound_through_a_link(tmp_path: Path) -> None:
    from fieldlog.acquire.daemon import BusError, BusServer

    link, target = tmp_path / "bus.sock", tmp_path / "elsewhere" / "bus.sock"
    link.symlink_to(target)
    with pytest.raises(BusError, match="symbolic link"):
        BusServer(str(link))
    assert link.is_symlink() and not target.parent.exists()
