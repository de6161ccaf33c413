"""A Dask cluster on 127.0.0.1 started as a cluster of machines starts one: a ``dask scheduler`` process and
``dask worker`` processes (one thread each, no nanny, no dashboard) that connect to it by address. ``fieldlog
batch --scheduler ADDRESS`` then runs on it as on a real cluster (the bench's fleet throughput, the batch test).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


def _wait(what: str, ready, procs: list[subprocess.Popen], timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while not ready():
        if any(p.poll() is not None for p in procs):
            dead = [p.args[2] for p in procs if p.poll() is not None]
            raise RuntimeError(f"{what}: a dask process exited ({', '.join(dead)})")
        if time.monotonic() > end:
            raise TimeoutError(f"{what}: not ready after {timeout_s:g} s")
        time.sleep(0.1)


@contextmanager
def loopback_cluster(workers: int, folder: Path, timeout_s: float = 60.0) -> Iterator[str]:
    """Yield the scheduler's address (``tcp://127.0.0.1:PORT``) once ``workers`` workers have joined; every
    process is stopped on exit. ``folder``: where the scheduler file and the processes' logs go."""
    from distributed import Client

    folder.mkdir(parents=True, exist_ok=True)
    sched_file = folder / "scheduler.json"
    sched_file.unlink(missing_ok=True)
    procs: list[subprocess.Popen] = []

    def start(args: list[str], log: str) -> None:
        with open(folder / log, "wb") as f:
            procs.append(subprocess.Popen(args, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL))

    try:
        start([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0",
               "--no-dashboard", "--no-show", "--scheduler-file", str(sched_file)], "scheduler.log")
        _wait("dask scheduler", sched_file.exists, procs, timeout_s)
        _wait("dask scheduler", lambda: "address" in sched_file.read_text(), procs, timeout_s)
        address = json.loads(sched_file.read_text())["address"]
        for i in range(workers):
            start([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nthreads", "1", "--no-nanny",
                   "--host", "127.0.0.1", "--no-dashboard", "--name", f"w{i}"], f"worker{i}.log")
        with Client(address, timeout=timeout_s) as client:
            client.wait_for_workers(workers, timeout=timeout_s)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
