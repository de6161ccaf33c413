"""The wheels' scale factor estimated from a simulated drive (``sim --can``: each seed draws its own tyre-radius
scale error, tools/sim/vehicle.py) and reported by ``fieldlog fuse --json`` with its sigma."""
from __future__ import annotations

import json

import numpy as np
import pytest

from fieldlog.drive import messages
from fieldlog.drive import reader

pytest.importorskip("cantools", reason="needs cantools (the can extra)")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_scale_is_within_three_sigma_of_the_simulated_one(tmp_path, capsys, seed):
    """Over seeds: the fused scale lies within 3 sigma of the drive's true ratio of the reported forward speed to
    the true one (the tyre error the seed drew, with the slip the simulator adds), with a sigma tighter than the
    prior's (the fit, not the prior)."""
    from fieldlog.tools.cli import main as fieldlog
    from fieldlog.tools.sim.simulate import simulate

    drive = tmp_path / "figure8-can.mcap"
    simulate("figure8", 150.0, seed, drive, can=True)
    capsys.readouterr()
    assert fieldlog(["fuse", str(drive), "--method", "kf", "--out", str(tmp_path / "kf.mcap"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    scale, sigma = summary["odometer_scale"], summary["odometer_scale_sigma"]
    _, _, p = reader.read_payloads(drive, "/vehicle/twist")
    _, _, pt = reader.read_payloads(drive, "/truth/vehicle/twist")
    v, vt = messages.decode_twist(p)["v_n"][:, 0], messages.decode_twist(pt)["v_n"][:, 0]
    ratio = np.sum(v[vt > 3]) / np.sum(vt[vt > 3])
    assert abs(scale - ratio) < 3 * sigma, (seed, scale, ratio, sigma)
    assert sigma < 0.005, sigma   # Odometer's prior_sigma
