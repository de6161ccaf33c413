"""RBFN and TDLN predictors (fusion.predictors) and the outage-bridging methods rbfn, tdln, dkf-rbfn."""

import numpy as np
import pytest

from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.predictors import (RBF, OutagePredictor, PredictorConfig, Rbfn, Tdln, delay_rows, kmeans_1d,
                                        kmeans_centres)
from fieldlog.drive.reader import read_topic
from fieldlog.tools.evaluation.evaluate import outage_errors
from fieldlog.tools.fuse import fuse
from fieldlog.tools.sim.simulate import simulate

DURATION = 300.0
OUTAGE = (190.0, 30.0)  # alignment at ~40 s: 150 s of training before it


def test_rbfn_fits_a_smooth_function_with_centres_in_the_data():
    x = np.linspace(-2.0, 4.0, 400)
    f = lambda t: np.sin(1.5 * t) + 0.2 * t  # noqa: E731
    net = Rbfn(centres=12).fit(x, f(x))
    assert len(net.centres) == 12
    assert np.all((net.centres > x.min()) & (net.centres < x.max()))
    assert np.all(np.diff(net.centres) > 0)
    inner = np.linspace(-1.7, 3.7, 500)  # away from the last centre at each end
    assert np.abs(net.predict(inner) - f(inner)).max() < 0.03
    # noisy targets: the fit averages the noise down instead of following it
    rng = np.random.default_rng(0)
    noisy = Rbfn(centres=12).fit(x, f(x) + 0.2 * rng.standard_normal(len(x)))
    assert np.sqrt(np.mean((noisy.predict(inner) - f(inner)) ** 2)) < 0.06
    # far outside the data the Gaussians vanish: no correction rather than an extrapolated one
    assert abs(net.predict(np.array([40.0]))[0]) < 1e-6


def test_kmeans_centres_are_distinct_and_few_for_few_values():
    x = np.repeat([1.0, 2.0, 5.0], 50)
    c = kmeans_centres(x, 10)
    assert np.allclose(c, [1.0, 2.0, 5.0])


def test_kmeans_1d_equals_scipys_kmeans2_to_the_bit():
    """Smooth, rounded (ties, emptied clusters), heavy-tailed and repeated samples, k from 1 to 11."""
    import warnings

    from scipy.cluster.vq import kmeans2

    for trial in range(400):
        rng = np.random.default_rng(trial)
        n = int(rng.integers(2, 300))
        x = (rng.normal(size=n), np.round(rng.normal(size=n), 1), rng.standard_cauchy(size=n),
             np.repeat(rng.normal(size=n // 7 + 1), 7)[:n])[trial % 4]
        k = min(int(rng.integers(1, 12)), len(np.unique(x)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # kmeans2 warns of an emptied cluster
            want, _ = kmeans2(x[:, None], k, minit="++", rng=np.random.default_rng(trial))
        assert np.array_equal(kmeans_1d(x, k, np.random.default_rng(trial)), want[:, 0]), trial


def test_tdln_recovers_a_known_fir():
    rng = np.random.default_rng(1)
    taps = 200
    h = rng.standard_normal(taps) * np.exp(-np.arange(taps) / 40.0)
    u = rng.standard_normal(1200) + 3.0
    y = np.convolve(u, h)[:len(u)] + 0.7
    y[:taps - 1] = np.nan  # the delay line is not full there
    net = Tdln(taps).fit(u[:1000], y[:1000])
    bias, fir = net.fir
    assert np.abs(fir - h).max() < 1e-6 and abs(bias - 0.7) < 1e-5
    assert np.abs(net.predict(u)[1000:] - y[1000:]).max() < 1e-5  # unseen samples
    assert np.array_equal(delay_rows(np.arange(4.0), 3), [[0, 0, 0], [1, 0, 0], [2, 1, 0], [3, 2, 1]])


@pytest.mark.parametrize("training", ["batch", "online"])
def test_outage_predictor_trains_after_settling_and_clips_to_the_trained_range(training):
    cfg = PredictorConfig(min_train=20, settle_s=10.0, centres=5, training=training)
    p = OutagePredictor(RBF, cfg)
    for t in range(60):  # target = 0.1 * input on channel 0, nothing observed on channel 5
        u = np.full(6, float(t))
        p.train(float(t), u, np.array([0.1 * t, 1.0, 1.0, 1.0, 1.0, np.nan]))
    y = p.predict(np.full(6, 30.0))
    assert abs(y[0] - 3.0) < 0.1 and np.isnan(y[5])
    fits = p.fits
    # batch: one fit at the outage; online: refreshed while training (the input kept leaving the centres' span)
    assert fits == 1 if training == "batch" else fits >= 2
    # far outside, the RBFN output vanishes; clipped to the trained targets, 1.0 .. 5.9 (t >= 10 s only)
    assert p.predict(np.full(6, 1e3))[0] == pytest.approx(1.0)
    p.predict(np.full(6, 31.0))
    assert p.fits == fits  # no refit inside an outage


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """figure8, a 30 s forced outage after 150 s of good GPS, every method; RMS errors inside the outage."""
    d = tmp_path_factory.mktemp("pred")
    drive = d / "figure8.mcap"
    simulate("figure8", DURATION, 3, drive)
    t0 = int(read_topic(drive, "/imu")["log_time_ns"][0])
    win = (t0 + int(OUTAGE[0] * 1e9), t0 + int(sum(OUTAGE) * 1e9))
    res, runs = {}, {}
    for m in ("dkf", "rbfn", "tdln", "dkf-rbfn"):
        runs[m] = fuse(drive, m, d / f"{m}.mcap", FusionConfig.from_flat(outages=(OUTAGE,)))
        e = outage_errors(drive, runs[m].path, m, [win])
        res[m] = np.sqrt(np.mean(e[:, :6] ** 2, axis=0))
    print("30 s outage, RMS inside (2D m, E N U m, vE vN vU m/s): " + "; ".join(
        f"{m} {np.hypot(r[0], r[1]):.2f} [{' '.join(f'{v:.2f}' for v in r)}]" for m, r in res.items()))
    return drive, win, res, runs


def test_every_withheld_epoch_is_bridged(study):
    drive, win, res, runs = study
    for m in ("rbfn", "tdln", "dkf-rbfn"):
        assert runs[m].predicted == 30  # one prediction per withheld epoch
    # the relations between the methods, over seeds: tests/test_dkf.py and `fieldlog evaluate --paper`


def test_predictor_methods_equal_dkf_while_gps_is_good(study):
    drive, win, res, runs = study
    a = read_topic(runs["dkf"].path, "/fusion/dkf/fix")
    b = read_topic(runs["dkf-rbfn"].path, "/fusion/dkf-rbfn/fix")
    assert np.array_equal(a["log_time_ns"], b["log_time_ns"])
    before = a["log_time_ns"] < win[0]
    assert before.sum() > 1000
    assert np.array_equal(a["lat_deg"][before], b["lat_deg"][before])
    assert not np.array_equal(a["lat_deg"][~before], b["lat_deg"][~before])
