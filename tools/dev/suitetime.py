"""Where the test suite's time goes: a pytest plugin that writes each test's wall and CPU time, and a summary.

    FIELDLOG_SUITETIME=times.jsonl python -m pytest -n 3 -p fieldlog.tools.dev.suitetime
    python -m fieldlog.tools.dev.suitetime times.jsonl

One JSON line per test: [worker, test id, start, end (s, host clock), CPU s of the worker and of the children it
waited for]. A test's wall time above its CPU time is time spent waiting (on the clock, on a child it did not
wait for yet, on the other workers' load); the summary gives each worker's busy and CPU time, the modules by
wall time and the tests that ended the run.
"""

from __future__ import annotations

import collections
import json
import os
import resource
import sys
import time

import pytest

ENV = "FIELDLOG_SUITETIME"


def _cpu_s() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    path = os.environ.get(ENV)
    t0, c0 = time.time(), _cpu_s()
    yield
    if path:
        with open(path, "a") as f:
            f.write(json.dumps([os.environ.get("PYTEST_XDIST_WORKER", "main"), item.nodeid, t0, time.time(),
                                _cpu_s() - c0]) + "\n")


def summary(path: str, top: int = 20) -> str:
    rows = [json.loads(line) for line in open(path)]
    t0, t1 = min(r[2] for r in rows), max(r[3] for r in rows)
    out = [f"{len(rows)} tests over {t1 - t0:.0f} s"]
    workers = collections.defaultdict(list)
    for w, _, a, b, c in rows:
        workers[w].append((b - a, c))
    for w, xs in sorted(workers.items()):
        out.append(f"{w}: {len(xs)} tests, busy {sum(x for x, _ in xs):.0f} s, CPU {sum(c for _, c in xs):.0f} s")
    modules = collections.defaultdict(lambda: [0.0, 0.0, 0])
    for _, test, a, b, c in rows:
        m = modules[test.split("::")[0]]
        m[0], m[1], m[2] = m[0] + b - a, m[1] + c, m[2] + 1
    out.append("wall s   CPU s  tests  module")
    for name, (wall, cpu, n) in sorted(modules.items(), key=lambda kv: -kv[1][0])[:top]:
        out.append(f"{wall:6.1f} {cpu:7.1f} {n:6d}  {name}")
    out.append("the last tests to end (worker, start, end s from the first start):")
    for w, test, a, b, _ in sorted(rows, key=lambda r: r[3])[-5:]:
        out.append(f"{w} {a - t0:5.0f} {b - t0:5.0f}  {test}")
    return "\n".join(out)


if __name__ == "__main__":
    print(summary(sys.argv[1]))
