"""The virtual odometer (``[fusion] predictor_mode = "pseudo"``, ``fusion.pseudo``): its network, features,
held-out score and wiring, the report's verdict on it, and, over seeds of a rough car, its gain over dkf."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from fieldlog.fusion import pseudo
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.predictors import PredictorConfig, SpeedNetwork


def test_predictor_mode_is_validated_and_paper_is_the_default():
    assert FusionConfig().get("predictor_mode") == "paper"
    with pytest.raises(ValueError, match=r"\[fusion\] predictor_mode: 'neural'"):
        FusionConfig.from_flat(predictor_mode="neural").validate()


def test_pseudo_mode_replaces_the_bridge_by_a_measurement_and_paper_keeps_it():
    def learnt(e: Engine) -> list:
        return [m for m in e.measurements if m.__class__.__name__ == "VirtualOdometer"]

    paper = Engine("dkf-rbfn")
    assert paper.bridge is not None and not learnt(paper)
    pseudo_engine = Engine("dkf-rbfn", FusionConfig.from_flat(predictor_mode="pseudo"))
    assert pseudo_engine.bridge is None and len(learnt(pseudo_engine)) == 1
    assert not learnt(Engine("dkf", FusionConfig.from_flat(predictor_mode="pseudo")))


@pytest.mark.parametrize("seed", range(4))
def test_speed_network_learns_a_smooth_function_of_several_inputs_held_out(seed):
    """Trained online on 300 samples of y = 8 + 2 sin(x0) + x1 x2 + noise, it predicts 100 new ones with an RMS
    error well below the target's spread and near the noise."""
    rng = np.random.default_rng(seed)

    def target(x: np.ndarray) -> np.ndarray:
        return 8.0 + 2.0 * np.sin(x[:, 0]) + x[:, 1] * x[:, 2]

    net = SpeedNetwork(3, PredictorConfig())
    X = rng.uniform(-2.0, 2.0, (400, 3))
    y = target(X) + 0.05 * rng.standard_normal(400)
    for x, t in zip(X[:300], y[:300]):
        net.train(x, float(t))
    pred = np.array([net.predict(x) for x in X[300:]])
    err = float(np.sqrt(np.mean((pred - target(X[300:])) ** 2)))
    assert err < 0.35 * float(np.std(y)), (err, np.std(y))
    frozen = net.frozen()
    assert frozen.predict(X[0]) == net.predict(X[0])


@pytest.mark.parametrize("seed", range(4))
def test_peak_frequency_finds_a_line_between_the_bins(seed):
    """A 1-s window at 500 Hz has 1 Hz bins; a line anywhere in the band, in noise, is found within 0.15 Hz."""
    rng = np.random.default_rng(seed)
    dt = 0.002
    t = np.arange(500) * dt
    for f0 in rng.uniform(3.0, 12.0, 5):
        x = np.sin(2 * math.pi * f0 * t + rng.uniform(0, 6.3)) + 0.3 * rng.standard_normal(len(t))
        freq = np.fft.rfftfreq(len(t), dt)
        power = np.abs(np.fft.rfft((x - x.mean()) * np.hanning(len(t)))) ** 2
        assert abs(pseudo.peak_frequency(freq, power) - f0) < 0.15, f0


@pytest.mark.parametrize("seed", range(3))
def test_line_odometer_follows_the_wheel_line_beyond_the_trained_speeds(seed):
    """Trained at 8-10 m/s on features whose line is speed / (2 pi r) plus scatter (and a few wrong picks), it
    predicts 12-14 m/s from the line within a few tenths of a m/s, where a network clipped to its trained
    targets could not go above 10."""
    rng = np.random.default_rng(seed)
    r = 0.31

    def features(v: float) -> np.ndarray:
        x = rng.normal(0.0, 0.05, pseudo.N_FEATURES)
        x[-1] = v / (2 * math.pi * r) * (1 + 0.01 * rng.standard_normal())
        if rng.uniform() < 0.05:
            x[-1] *= 0.5
        return x

    model = pseudo.new_network(PredictorConfig())
    for v in rng.uniform(8.0, 10.0, 200):
        model.train(features(v), float(v))
    assert model.ready and model.k == pytest.approx(2 * math.pi * r, rel=0.01)
    frozen = model.frozen()
    err = [frozen.predict(features(v)) - v for v in np.linspace(12.0, 14.0, 20)]
    assert np.median(np.abs(err)) < 0.3, err


def test_reckoner_holds_the_speed_of_a_level_car_and_drifts_with_a_gyro_bias():
    """Standing level with the specific force of gravity, the dead reckoning holds its start speed; with an
    uncorrected pitch-rate bias eps it drifts as g eps t^2 / 2 (the INS's along-track error)."""
    from fieldlog.fusion import earth
    from fieldlog.fusion.ins import NavState

    lat = math.radians(30.0)
    nav = NavState(0.0, lat, 0.0, 0.0, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
    g = float(earth.gravity(lat, 0.0))
    w_ie_b = nav.C_bn.T @ earth.omega_ie_n(lat)
    for eps, want in ((0.0, 0.0), (1e-4, -0.5 * g * 1e-4 * 60.0 ** 2)):
        dr = pseudo.ForwardReckoner(nav, 10.0, np.zeros(3), np.zeros(3))
        for _ in range(60):
            dr.step(w_ie_b + np.array([eps, 0.0, 0.0]), np.array([0.0, 0.0, g]), 1.0)
        assert dr.v - 10.0 == pytest.approx(want, abs=0.02 + 0.05 * abs(want))


def test_verdict_names_drives_windows_and_the_drift_ratio_of_the_virtual_odometer():
    from fieldlog.tools.evaluation.evaluate import PSEUDO, verdict

    def runs(e: list[float]) -> list[np.ndarray]:
        return [np.r_[x, x, np.zeros(7)] for x in e]

    per = {(PSEUDO, 60.0): runs([2.0, 3.0, 2.5, 2.2]), ("dkf", 60.0): runs([6.0, 8.0, 7.0, 6.5])}
    drifts = {(PSEUDO, 60.0): [3.0, 4.0, 3.5, 3.1], ("dkf", 60.0): [9.0, 12.0, 10.0, 9.5]}
    lines = verdict(per, {(PSEUDO, 60.0): 8}, drifts)
    rms = next(x for x in lines if x.startswith("- 60 s") and "2D RMS" in x)
    assert rms.startswith("- 60 s (4 drives, 8 windows): dkf-rbfn (pseudo) 2D RMS")
    assert "better than dkf" in rms and "resolved: " in rms
    drift = next(x for x in lines if "drift" in x)
    assert f"{np.mean(drifts[(PSEUDO, 60.0)]) / np.mean(drifts[('dkf', 60.0)]):.2f}" in drift
    one = verdict({(PSEUDO, 60.0): runs([2.0]), ("dkf", 60.0): runs([6.0])}, {(PSEUDO, 60.0): 2})
    assert "not resolved against dkf" in one[2] and "%" not in one[2] and "(1 drive, 2 windows)" in one[2]


SEEDS = (1, 2, 3, 4)
DRIVE_S = 250.0  # 60 s parked, then laps; one 60 s outage after the network has trained and been scored
OUTAGE = (180.0, 60.0)


@pytest.mark.slow
@pytest.mark.parametrize("setup", ["gps-only", "car-aids"])
def test_virtual_odometer_beats_dkf_in_outages_over_seeds(simulated, tmp_path, capsys, setup):
    """figure8-varied-real (laps whose speed varies, a car whose vibration carries it), one 60 s outage per drive,
    the issue's targets as relations over seeds: with GPS only (the paper's set-up) the 2D RMS in the outage is
    below dkf's on every drive, the paired t test of the log ratios resolving it, and the mean at most 0.7 of
    dkf's; with the car's aids (NHC and ZUPT, no wheel odometer) the drift over the outage (the error less its
    value at the start) likewise, at most 0.8 of dkf's. The virtual odometer runs (positive held-out skill,
    reported by ``fuse --json``; the full study: docs/studies/pseudo)."""
    from fieldlog.tools.cli import main
    from fieldlog.tools.evaluation.evaluate import drift_2d, fix_quality, outage_error_series, paired
    from fieldlog.tools.fuse import fuse
    from fieldlog.tools.fuse_settings import drive_config

    aids = dict(nhc=False, zupt=False) if setup == "gps-only" else {}
    target = 0.7 if setup == "gps-only" else 0.8
    err = {"dkf": [], "pseudo": []}
    for seed in SEEDS:
        drive = simulated("figure8-varied-real", DRIVE_S, seed)
        cfg = drive_config(drive).replace(odometer=False, outages=(OUTAGE,), **aids)
        _, _, t0 = fix_quality(drive, cfg.gps.max_fix_sigma_m)
        win = [(t0 + int(OUTAGE[0] * 1e9), t0 + int(sum(OUTAGE) * 1e9))]
        for name, method, c in (("dkf", "dkf", cfg), ("pseudo", "dkf-rbfn", cfg.replace(predictor_mode="pseudo"))):
            res = fuse(drive, method, tmp_path / f"{seed}_{name}.mcap", c, keep=True)
            t, e = outage_error_series(drive, res.solution, method, win)
            err[name].append(float(np.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))) if setup == "gps-only"
                             else drift_2d(t, e, win))
        vo = res.virtual_odometer
        assert vo["ran"] and vo["held_out_skill"] > 0 and vo["epochs_used"] >= 50, vo
    dkf, ours = np.array(err["dkf"]), np.array(err["pseudo"])
    pt = paired(np.log(ours / dkf))  # dkf's error spreads over drives with its gyro biases: compare ratios
    assert (ours < dkf).all() and pt.resolved and pt.mean < 0, (err, pt)
    assert ours.mean() <= target * dkf.mean(), err
    # fuse --json reports the held-out skill and whether it ran
    cfg_file = tmp_path / "pseudo.toml"
    cfg_file.write_text('[fusion]\npredictor_mode = "pseudo"\nodometer = false\n'
                        + "".join(f"{k} = false\n" for k in aids))
    capsys.readouterr()
    assert main(["fuse", str(simulated("figure8-varied-real", DRIVE_S, SEEDS[0])), "--method", "dkf-rbfn",
                 "--config", str(cfg_file), "--outage", f"{OUTAGE[0]:g}:{OUTAGE[1]:g}", "--json",
                 "--out", str(tmp_path / "cli.mcap")]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["predictor_mode"] == "pseudo" and summary["virtual_odometer"]["ran"] is True
    assert summary["virtual_odometer"]["held_out_skill"] > 0 and summary["virtual_odometer"]["model"] == "wheel line"


def test_on_a_real_car_the_switch_agrees_with_the_can_wheel_speeds_held_out():
    """comma2k19's minute (a phone in a RAV4 on a highway, tests/data/comma2k19): trained on the receiver's speed
    and scored 30-60 s after each freeze against the CAN rear wheels' speed. A phone's vibration has no wheel line
    to follow: the held-out residuals choose the network over the line (which errs by tens of m/s), and the
    engine's switch (the held-out skill against the IMU's dead reckoning) is on exactly when the chosen model's
    RMS error against the CAN speed is below the zero-skill baseline's (the speed at the freeze, held)."""
    from comma2k19 import load, virtual_odometer_held_out

    res = virtual_odometer_held_out(load())
    rms = res["rms"]
    assert res["pairs"] >= 100 and res["candidate"] == "network" and rms["line"] > rms["network"], res
    assert res["on"] == (rms["model"] < rms["hold"]), res
