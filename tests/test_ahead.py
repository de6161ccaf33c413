"""replay.ahead: a generator (Ahead) or an object (Remote) in a forked worker gives its caller the same items,
answers and exceptions as in place, and leaves no worker behind; and fuse with its workers writes the file it
writes in place. Each worker case runs in a fresh interpreter (one thread, as ``fieldlog`` runs): a pytest-xdist
worker has threads of its own, and there the work runs in place."""
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from fieldlog.replay.ahead import Ahead
from fieldlog.tools.cli import main

PRELUDE = """
import os, sys, threading
import numpy as np
from fieldlog.replay.ahead import Ahead, Remote

class Tally:
    def __init__(self, start):
        self.total, self.calls = start, []
    def add(self, x):
        self.total += x
        self.calls.append(x)
    def fail(self):
        raise KeyError("no such channel")
    def state(self):
        return self.total, len(self.calls), os.getpid()

class Unpicklable(Exception):
    def __init__(self, a, b):  # pickling re-creates it with one argument: it fails to load
        super().__init__(f"{a} and {b}")

def reaped(pid):
    try:
        os.waitpid(pid, os.WNOHANG)
        return "still a child"
    except ChildProcessError:
        return "reaped"

def numbers(n, fail=None):
    for i in range(n):
        yield i, os.getpid(), np.full(1000, float(i))
    if fail == "value":
        raise ValueError("bad byte at 12")
    if fail == "unpicklable":
        raise Unpicklable(1, 2)
    if fail == "die":
        os._exit(3)
    return {"count": n, "pid": os.getpid()}
"""


def run(body: str) -> str:
    r = subprocess.run([sys.executable, "-c", PRELUDE + textwrap.dedent(body)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_items_and_return_value_come_from_a_worker_in_order():
    out = run("""
        with Ahead(lambda: numbers(50)) as it:
            got = []
            def take():
                result = yield from it
                got.append(result)
            items = list(take())
        assert [i for i, _, _ in items] == list(range(50))
        assert all(np.array_equal(a, np.full(1000, float(i))) for i, _, a in items)
        pids = {p for _, p, _ in items}
        assert pids == {got[0]["pid"]} and os.getpid() not in pids and got[0]["count"] == 50
        print("ok")
    """)
    assert out == "ok"


@pytest.mark.parametrize("fail,raised", [("value", "ValueError: bad byte at 12"),
                                         ("unpicklable", "RuntimeError: Unpicklable: 1 and 2"),
                                         ("die", "RuntimeError: the drive's reading worker ended without a result")])
def test_a_failure_in_the_worker_is_raised_in_the_consumer_after_its_items(fail, raised):
    out = run(f"""
        seen = 0
        try:
            with Ahead(lambda: numbers(5, {fail!r})) as it:
                for _ in it:
                    seen += 1
        except Exception as e:
            print(seen, f"{{type(e).__name__}}: {{e}}")
    """)
    assert out == f"5 {raised}"


def test_stopping_early_ends_and_reaps_the_worker():
    out = run("""
        it = Ahead(lambda: numbers(10 ** 9))
        pid = it._pid
        for i, _, _ in it:
            if i == 3:
                break
        print(reaped(pid))
        with Ahead(lambda: numbers(10 ** 9)) as never:  # never iterated: leaving the block ends it
            pid = never._pid
        print(reaped(pid))
    """)
    assert out == "reaped\nreaped"


def test_with_other_threads_running_it_runs_in_place():
    out = run("""
        stop = threading.Event()
        t = threading.Thread(target=stop.wait)
        t.start()
        with Ahead(lambda: numbers(3)) as it:
            pids = {p for _, p, _ in it}
        stop.set()
        t.join()
        print(pids == {os.getpid()})
    """)
    assert out == "True"


def test_on_one_cpu_it_runs_in_place():
    """With one CPU to run on (``taskset -c 0``) a worker would only take turns with its caller: the generator and
    the remote object run in place, with the same items and answers."""
    out = run("""
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        with Ahead(lambda: numbers(3)) as it:
            items = [(i, p) for i, p, _ in it]
        with Remote(lambda: Tally(10)) as r:
            for x in range(5):
                r.send("add", x)
            state = r.ask("state")
        print(items == [(i, os.getpid()) for i in range(3)], state == (20, 5, os.getpid()))
    """)
    assert out == "True True"


def test_it_is_iterated_once():
    def gen():
        yield 1
        return 2

    with Ahead(gen) as it:
        assert list(it) == [1]
        with pytest.raises(RuntimeError):
            list(it)


def test_a_remote_object_answers_after_every_call_sent_before_and_passes_its_failure_back():
    out = run("""
        with Remote(lambda: Tally(10)) as r:
            for x in range(100):
                r.send("add", x)
            total, n, pid = r.ask("state")
            assert (total, n) == (10 + sum(range(100)), 100) and pid != os.getpid()
            r.send("fail")
            try:
                r.ask("state")
            except KeyError as e:
                print("KeyError", e)
        print(reaped(pid))
    """)
    assert out == "KeyError 'no such channel'\nreaped"


def test_fuse_with_its_workers_writes_the_file_it_writes_in_place(simulated, tmp_path: Path):
    """dkf-rbfn reads ahead and trains its predictor in workers; with a thread running here, or on one CPU
    (``taskset -c 0``), both run in place."""
    drive = simulated("figure8", 400.0, 1)
    args = ["fuse", str(drive), "--method", "dkf-rbfn", "--outage", "150:40", "--outage", "300:30", "-q", "--out"]
    r = subprocess.run([sys.executable, "-m", "fieldlog", *args, str(tmp_path / "workers.mcap")], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    stop = threading.Event()
    busy = threading.Thread(target=stop.wait)
    busy.start()
    try:
        assert main([*args, str(tmp_path / "here.mcap")]) == 0
    finally:
        stop.set()
        busy.join()
    assert (tmp_path / "workers.mcap").read_bytes() == (tmp_path / "here.mcap").read_bytes()
    one_cpu = [sys.executable, "-c", "import os, sys; from fieldlog.tools.cli import main; "
               "os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); sys.exit(main(sys.argv[1:]))"]
    r = subprocess.run([*one_cpu, *args, str(tmp_path / "one.mcap")], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "one.mcap").read_bytes() == (tmp_path / "here.mcap").read_bytes()


def test_view_reports_a_bad_input_option_its_worker_found_in_one_line(simulated, tmp_path: Path):
    """view resolves the drive's inputs in its worker, beside the rerun-sdk import: the error comes back."""
    drive = simulated("figure8", 400.0, 1)
    r = subprocess.run([sys.executable, "-m", "fieldlog", "view", str(drive), "--imu-topic", "/nope", "--rrd",
                        str(tmp_path / "x.rrd")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "no topic /nope (--imu-topic)" in r.stderr and not (tmp_path / "x.rrd").exists()


def test_a_stream_started_early_reads_the_same_blocks_and_its_close_ends_the_worker(simulated):
    """``InputStream.start`` forks the reading worker before the first iteration (the fuse command's modules
    load meanwhile): the same blocks as a stream started by its iteration; closing a started stream that was
    never iterated reaps the worker. The read-ahead pipe holds ``PIPE_BYTES`` (Linux)."""
    drive = simulated("figure8", 150.0, 1)
    out = run(f"""
        import fcntl
        from fieldlog.replay.ahead import PIPE_BYTES
        from fieldlog.replay.inputs import InputStream, resolve
        imap = resolve({str(drive)!r})
        early = InputStream({str(drive)!r}, imap, 30.0)
        early.start()
        pid, pipe = early._ahead._pid, early._ahead._pipe.fileno()
        print(pid != 0, fcntl.fcntl(pipe, fcntl.F_GETPIPE_SZ) >= PIPE_BYTES)
        a = list(early)
        b = list(InputStream({str(drive)!r}, imap, 30.0))
        same = len(a) == len(b) > 3 and all(
            np.array_equal(x.imu.t_ns, y.imu.t_ns) and np.array_equal(x.imu.f_b, y.imu.f_b)
            and np.array_equal(x.gps.t_ns, y.gps.t_ns) for x, y in zip(a, b))
        print(same, early.samples == sum(len(x.imu.t_ns) for x in a) > 0, reaped(pid))
        idle = InputStream({str(drive)!r}, imap, 30.0)
        idle.start()
        pid = idle._ahead._pid
        idle.close()
        print(reaped(pid))
    """)
    assert out == "True True\nTrue True reaped\nreaped"


def test_a_damaged_chunk_the_early_worker_reads_is_one_line_and_no_file(simulated, tmp_path: Path):
    """``fuse --method ins`` (one pass: its reading worker started before the fusion is set up) of a drive with an
    IMU chunk overwritten mid-body: the worker's error comes back as one line, exit 2, and no fused file."""
    from fieldlog.drive.files import open_drive

    drive = simulated("figure8", 150.0, 1)
    f = open_drive(drive)[0]
    imu = list(f.pieces.cids).index(next(c for c, ch in f.channels.items() if ch.topic == "/imu"))
    j = np.flatnonzero(f.pieces.has[:, imu])[1]
    data = bytearray(drive.read_bytes())
    at = int(f.pieces.body[j]) + int(f.pieces.body_len[j]) // 2
    data[at:at + 512] = b"\x55" * 512
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(data))
    out = tmp_path / "ins.mcap"
    r = subprocess.run([sys.executable, "-m", "fieldlog", "fuse", str(bad), "--method", "ins", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0, r.stderr
    assert "damaged chunk" in r.stderr and bad.name in r.stderr and not out.exists()
