"""The command line as a script sees it: -q/-v on every command, fuse's short default output and its settings in
the fused file, --json that parses, the --out-dir names and their old aliases, one time origin, and progress on
a real terminal only."""
from __future__ import annotations

import ast
import gc
import json
import os
import pty
import select
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.reader import make_reader

from fieldlog.drive import reader
from fieldlog.tools.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent


def _subparsers():
    return next(a for a in build_parser()._actions if a.dest == "command").choices


def test_every_command_takes_quiet_and_verbose():
    commands = _subparsers()
    assert len(commands) >= 16
    for name, s in commands.items():
        flags = {o for a in s._actions for o in a.option_strings}
        assert {"-q", "--quiet", "-v", "--verbose"} <= flags, name


def _run(capsys, argv):
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 0, (argv, out, err)
    return out, err


def test_fuse_prints_a_short_summary_and_keeps_the_settings_in_the_file(figure8_150s_seed3, tmp_path, capsys):
    drive = figure8_150s_seed3
    fused = tmp_path / "kf.mcap"
    argv = ["fuse", str(drive), "--method", "kf", "--outage", "95:25", "--out", str(fused)]
    out, err = _run(capsys, argv)
    text = out + err
    assert len(text.splitlines()) <= 6 and len(text) <= 800, text
    line = out.splitlines()[0]
    assert str(drive.name) in line and str(fused) in line and " kf" in line and "95:25" in line, line
    assert "fusion settings" not in text
    n_fix = next(t.count for t in reader.topics(fused) if t.topic == "/fusion/kf/fix")
    assert f"{n_fix} solutions" in line
    # -v: the settings with their sources; they are the ones the fused file's metadata records
    verbose, _ = _run(capsys, ["fuse", "-v", *argv[1:], "--force"])
    assert "fusion settings (--outage): outages=((95, 25))" in verbose
    with open(fused, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["fusion"]
    config = ast.literal_eval(meta["config"])
    assert config["outages"] == ((95.0, 25.0),) and meta["method"] == "kf"
    for item in verbose.split("fusion settings (default): ", 1)[1].splitlines()[0].split(", ")[:6]:
        key, value = item.split("=", 1)
        assert key in config, key
    # -q: nothing at all on a clean run
    assert _run(capsys, ["fuse", "-q", *argv[1:], "--force"]) == ("", "")


def test_fuse_json_summary_parses_and_agrees_with_the_file(figure8_150s_seed3, tmp_path, capsys):
    fused = tmp_path / "dkf.mcap"
    out, err = _run(capsys, ["fuse", str(figure8_150s_seed3), "--method", "dkf", "--outage", "95:25", "--json",
                             "--out", str(fused)])
    s = json.loads(out)
    assert s["method"] == "dkf" and s["out"] == str(fused) and s["forced_outages"] == [[95.0, 25.0]]
    counts = {t.topic: t.count for t in reader.topics(fused)}
    assert s["solutions"] == counts["/fusion/dkf/fix"] and s["outages"] == counts["/fusion/outage"] >= 1
    assert s["imu_samples"] == next(t.count for t in reader.topics(figure8_150s_seed3) if t.topic == "/imu")
    assert 0 < s["gps_updates"] < counts["/fusion/dkf/fix"]


def test_evaluate_json_table_and_the_old_report_name(figure8_150s_seed3, tmp_path, capsys):
    argv = [str(figure8_150s_seed3), "--outages", "10", "--methods", "ins"]
    out, _ = _run(capsys, ["evaluate", *argv, "--json", "--out-dir", str(tmp_path / "new")])
    table = json.loads(out)
    rows = table["rows"]
    assert rows and {r["method"] for r in rows} == {"ins"} and all(r["outage_s"] == 10.0 for r in rows)
    csv = (tmp_path / "new" / "table.csv").read_text().splitlines()
    assert len(csv) == len(rows) + 1
    out, _ = _run(capsys, ["evaluate", "-q", *argv, "--report", str(tmp_path / "old")])  # the deprecated name
    assert (tmp_path / "old" / "table.md").read_text() in out                       # the product, even with -q
    assert (tmp_path / "old" / "table.csv").read_text() == (tmp_path / "new" / "table.csv").read_text()


def test_out_dir_names_and_their_aliases():
    p = build_parser()
    for argv, dest in ((["evaluate", "--report", "R"], "out_dir"), (["evaluate", "--out-dir", "R"], "out_dir"),
                       (["study", "cost", "--out", "R"], "out_dir"), (["study", "cost", "--out-dir", "R"], "out_dir"),
                       (["export", "d.mcap", "--out", "R"], "out_dir"), (["batch", "x", "--out-dir", "R"], "out_dir"),
                       (["acquire", "--out", "R"], "out_dir"), (["demo", "--out-dir", "R"], "out_dir")):
        assert getattr(p.parse_args(argv), dest) == "R", argv
    for name in ("evaluate", "study", "export", "batch", "acquire", "demo"):
        assert "--out-dir" in _subparsers()[name].format_help(), name
    for name in ("fuse", "filter", "rebuild", "import", "sim", "recover"):   # one file each
        assert "--out-dir" not in _subparsers()[name].format_help(), name


def test_export_out_dir_and_out_give_the_same_tables(figure8_150s_seed3, tmp_path, capsys):
    for opt in ("--out-dir", "--out"):
        _run(capsys, ["export", "-q", str(figure8_150s_seed3), "--topics", "/gps/fix", "--format", "csv", opt,
                      str(tmp_path / opt.strip("-"))])
    a, b = (sorted(p.name for p in (tmp_path / d).rglob("*.csv")) for d in ("out-dir", "out"))
    assert a == b and a
    verbose, _ = _run(capsys, ["export", "-v", str(figure8_150s_seed3), "--topics", "/gps/fix", "--out-dir",
                               str(tmp_path / "v")])
    assert "/gps/fix" in verbose and "wrote 1 tables" in verbose


def test_quiet_and_verbose_on_the_file_commands(figure8_150s_seed3, tmp_path, capsys):
    drive = str(figure8_150s_seed3)
    out, _ = _run(capsys, ["filter", drive, "--start", "30", "--end", "40", "--out", str(tmp_path / "s.mcap")])
    assert len(out.splitlines()) == 1 and "wrote" in out
    out, _ = _run(capsys, ["filter", "-v", drive, "--start", "30", "--end", "40", "--out", str(tmp_path / "s.mcap"),
                           "--force"])
    assert "/imu" in out and len(out.splitlines()) > 2
    assert _run(capsys, ["filter", "-q", drive, "--end", "40", "--out", str(tmp_path / "q.mcap")]) == ("", "")
    assert _run(capsys, ["rebuild", "-q", str(tmp_path / "q.mcap"), "--out", str(tmp_path / "r.mcap")]) == ("", "")
    out, _ = _run(capsys, ["info", "-q", drive])
    assert "/imu" in out  # info's table is its product: -q keeps it
    assert json.loads(_run(capsys, ["info", "-v", "--json", drive])[0])
    assert _run(capsys, ["recover", "-q", str(tmp_path / "q.mcap"), "--out", str(tmp_path / "rq.mcap")]) == ("", "")
    out, _ = _run(capsys, ["recover", "-v", str(tmp_path / "q.mcap"), "--out", str(tmp_path / "rv.mcap")])
    assert "wrote" in out and "/imu" in out
    assert _run(capsys, ["sim", "-q", "--duration", "10", "--out", str(tmp_path / "sim.mcap")]) == ("", "")


def test_times_count_from_the_first_imu_sample(figure8_150s_seed3, tmp_path, capsys):
    """filter --start and fuse --outage share one origin, and both say so in --help."""
    for name in ("filter", "fuse"):
        assert "first IMU sample" in " ".join(_subparsers()[name].format_help().split()), name
    drive = figure8_150s_seed3
    t_imu = int(reader.read_topic(drive, "/imu")["log_time_ns"][0])
    first = min(t.first_ns for t in reader.topics(drive) if t.count)
    assert first < t_imu
    _run(capsys, ["filter", "-q", str(drive), "--start", "95", "--end", "120", "--topics", "/imu",
                  "--out", str(tmp_path / "s.mcap")])
    imu = reader.read_topic(tmp_path / "s.mcap", "/imu")["log_time_ns"]
    period = (reader.read_topic(drive, "/imu")["log_time_ns"][1] - t_imu)
    assert t_imu + 95 * 10**9 <= imu[0] < t_imu + 95 * 10**9 + 2 * period
    fused = tmp_path / "kf.mcap"
    _run(capsys, ["fuse", "-q", str(drive), "--outage", "95:25", "--out", str(fused)])
    with open(fused, "rb") as f:
        outage = [m for _, _, m in make_reader(f).iter_messages(topics=["/fusion/outage"])]
    assert any(abs(m.log_time - (t_imu + 95 * 10**9)) < 10**7 for m in outage), [m.log_time for m in outage]


def _on_a_terminal(argv: list[str], timeout_s: float = 300.0) -> tuple[int, str]:
    """Run ``fieldlog argv`` with stderr on a real pseudo-terminal; (exit code, what the terminal showed)."""
    master, slave = pty.openpty()
    env = {**os.environ, "COLUMNS": "100"}
    p = subprocess.Popen([sys.executable, "-m", "fieldlog", *argv], stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=slave, cwd=ROOT, env=env)
    os.close(slave)
    shown = b""
    try:
        while True:
            ready, _, _ = select.select([master], [], [], timeout_s)
            if not ready:
                p.kill()
                break
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                break
            if not chunk:
                break
            shown += chunk
    finally:
        os.close(master)
    return p.wait(timeout=60), shown.decode(errors="replace")


@pytest.mark.slow
def test_progress_with_eta_on_a_terminal_only(tmp_path):
    rc, shown = _on_a_terminal(["sim", "--duration", "10", "--out", str(tmp_path / "t.mcap")])
    assert rc == 0, shown
    assert "sim figure8:" in shown and "%|" in shown and "<" in shown, shown   # a bar, elapsed<remaining
    assert shown.count("100%") <= 1, shown
    rc, shown = _on_a_terminal(["sim", "-q", "--duration", "10", "--out", str(tmp_path / "q.mcap")])
    assert rc == 0 and "%|" not in shown, shown
    r = subprocess.run([sys.executable, "-m", "fieldlog", "sim", "--duration", "10", "--out", str(tmp_path / "p.mcap")],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0 and r.stderr == "" and r.stdout.startswith("wrote"), r.stderr


@pytest.mark.parametrize("how", ["process substitution", "stdin"])
def test_fuse_config_through_a_pipe_takes_effect(figure8_150s_seed3, tmp_path, how):
    """``--config <(...)`` and ``--config /dev/stdin`` give their bytes once: the command reads them once, and the
    fused file's ``fusion`` record carries what they said (the drive's own record and the defaults have the NHC
    on, so a config read empty would show)."""
    exe = Path(sys.executable).parent / "fieldlog"
    fused = tmp_path / "kf.mcap"
    fuse = f"'{exe}' fuse -q '{figure8_150s_seed3}' --method kf --out '{fused}'"
    table = r"printf '[fusion]\nnhc = false\n'"
    script = {"process substitution": f"{fuse} --config <({table})",
              "stdin": f"{table} | {fuse} --config /dev/stdin"}[how]
    run = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    fused_config = ast.literal_eval(reader.read_metadata(fused)["fusion"]["config"])
    assert fused_config["nhc"] is False
    drive_record = reader.read_metadata(figure8_150s_seed3).get("fusion.config", {})
    assert ast.literal_eval(drive_record.get("nhc", "True")) is True


def test_the_program_exits_with_the_commands_code_and_main_keeps_the_collector(figure8_150s_seed3, tmp_path,
                                                                               capsys):
    """``run`` (the ``fieldlog`` program, ``python -m fieldlog``) freezes the heap before the interpreter's exit
    and exits with the command's code; ``main`` called in a process that goes on leaves the collector alone."""
    frozen = gc.get_freeze_count()
    assert main(["info", str(figure8_150s_seed3)]) == 0
    assert gc.get_freeze_count() == frozen
    capsys.readouterr()
    exe = Path(sys.executable).parent / "fieldlog"
    for argv, code in ((["info", str(tmp_path / "missing.mcap")], 2), (["info", str(figure8_150s_seed3)], 0)):
        for program in ([str(exe)], [sys.executable, "-m", "fieldlog"]):
            r = subprocess.run([*program, *argv], capture_output=True, text=True, cwd=ROOT, timeout=120)
            assert r.returncode == code, (program, r.stderr)
            assert (len(r.stderr.splitlines()), bool(r.stdout)) == ((1, False) if code else (0, True)), r.stderr


@pytest.mark.parametrize("command, threads", [("sim", None), ("fuse", "1")])
def test_the_entry_sets_numpy_and_openblas_before_numpy_loads(command, threads):
    """The entry's environment for numpy, set before it loads (``tools.cli``): no huge-page advice for its arrays,
    one OpenBLAS thread for the commands that write no drive; a setting in the environment wins."""
    probe = ("import sys, os; sys.argv = ['fieldlog', %r, '--help']; import fieldlog.tools.cli; import numpy; "
             "from numpy._core import multiarray; "
             "print(multiarray._get_madvise_hugepage(), os.environ.get('OPENBLAS_NUM_THREADS'))" % command)
    env = {k: v for k, v in os.environ.items() if k not in ("NUMPY_MADVISE_HUGEPAGE", "OPENBLAS_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", str(threads)]
    out = subprocess.run([sys.executable, "-c", probe], env={**env, "NUMPY_MADVISE_HUGEPAGE": "1"},
                         capture_output=True, text=True, check=True).stdout
    assert out.split()[0] == "True"
