"""Shared fixtures: the simulated drives several modules read, each built once per session (per worker under
pytest-xdist). The ``slow`` marker (pyproject.toml) marks the long tests: ``make test`` runs them all,
``make test-fast`` leaves them out.

A shared drive is read-only: tests write their outputs under their own ``tmp_path`` (or a directory of their
module's own), never beside the drive, and never change it."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import pytest


@pytest.fixture(scope="session")
def simulated(tmp_path_factory) -> Callable[[str, float, int], Path]:
    """``simulated(scenario, duration_s, seed)``: that drive (``fieldlog.tools.sim.simulate`` with its defaults
    otherwise), simulated on the first call and the same file on every later one."""
    from fieldlog.tools.sim.simulate import simulate

    built: dict[tuple[str, float, int], Path] = {}

    def get(scenario: str, duration_s: float, seed: int) -> Path:
        key = (scenario, float(duration_s), int(seed))
        if key not in built:
            path = tmp_path_factory.mktemp(f"{scenario}_{duration_s:g}s_seed{seed}") / f"{scenario}.mcap"
            simulate(scenario, duration_s, seed, path)
            built[key] = path
        return built[key]

    return get


@pytest.fixture(scope="session")
def figure8_600s_seed1(tmp_path_factory) -> Path:
    """The reference drive: figure8, 600 s, seed 1, PPS as a sampled flag (40 ppm, wander, 3 dropped edges,
    5 dropped sentences are the scenario defaults), written by the `fieldlog sim` command itself."""
    from fieldlog.tools.cli import main

    path = tmp_path_factory.mktemp("figure8_600s_seed1") / "X.mcap"
    assert main(["sim", "--scenario", "figure8", "--duration", "600", "--seed", "1", "--out", str(path)]) == 0
    return path


@pytest.fixture(scope="session")
def figure8_240s_seed3(simulated) -> Path:
    """figure8, 240 s, seed 3."""
    return simulated("figure8", 240.0, 3)


@pytest.fixture(scope="session")
def figure8_150s_seed3(simulated) -> Path:
    """figure8, 150 s, seed 3."""
    return simulated("figure8", 150.0, 3)
