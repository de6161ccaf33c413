"""Shared fixtures: the simulated drives several modules read, each built once per run (the pytest-xdist workers
share them: one builds, the others wait for it). The ``slow`` marker (pyproject.toml) marks the long tests:
``make test`` runs them all, ``make test-fast`` leaves them out.

A shared drive is read-only: tests write their outputs under their own ``tmp_path`` (or a directory of their
module's own), never beside the drive, and never change it."""
from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import Callable

import pytest


def _shared(tmp_path_factory, name: str) -> Path:
    """A directory ``name`` that every pytest-xdist worker of this run sees (the run's base temporary directory;
    the session's own without xdist)."""
    base = tmp_path_factory.getbasetemp()
    if "PYTEST_XDIST_WORKER" in os.environ:
        base = base.parent
    d = base / "shared" / name
    d.mkdir(parents=True, exist_ok=True)
    return d


def _once(folder: Path, file_name: str, build: Callable[[Path], object]) -> Path:
    """``folder/file_name``, made by ``build(path)`` once per run: the first worker to ask builds it while the
    others wait on the folder's lock, then every worker reads the same file."""
    path = folder / file_name
    with open(folder / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = folder / f".{file_name}.done"  # per file: two builders may share a folder name
        if not done.exists():
            build(path)
            done.touch()
    return path


@pytest.fixture(scope="session")
def simulated(tmp_path_factory) -> Callable[..., Path]:
    """``simulated(scenario, duration_s, seed, **options)``: that drive (``fieldlog.tools.sim.simulate`` with
    those options, its defaults otherwise), simulated on the first call in the run and the same file on every
    later one, in every worker."""
    from fieldlog.tools.sim.simulate import simulate

    def get(scenario: str, duration_s: float, seed: int, **options: object) -> Path:
        extra = "".join(f"_{k}-{v}" for k, v in sorted(options.items()))
        folder = _shared(tmp_path_factory, f"{scenario}_{duration_s:g}s_seed{seed}{extra}")
        return _once(folder, f"{scenario}.mcap", lambda p: simulate(scenario, duration_s, seed, p, **options))

    return get


@pytest.fixture(scope="session")
def figure8_600s_seed1(tmp_path_factory) -> Path:
    """The reference drive: figure8, 600 s, seed 1, PPS as a sampled flag (40 ppm, wander, 3 dropped edges,
    5 dropped sentences are the scenario defaults), written by the `fieldlog sim` command itself."""
    from fieldlog.tools.cli import main

    def build(path: Path) -> None:
        assert main(["sim", "--scenario", "figure8", "--duration", "600", "--seed", "1", "--out", str(path)]) == 0

    return _once(_shared(tmp_path_factory, "figure8_600s_seed1"), "X.mcap", build)


@pytest.fixture(scope="session")
def figure8_240s_seed3(simulated) -> Path:
    """figure8, 240 s, seed 3."""
    return simulated("figure8", 240.0, 3)


@pytest.fixture(scope="session")
def figure8_150s_seed3(simulated) -> Path:
    """figure8, 150 s, seed 3."""
    return simulated("figure8", 150.0, 3)
