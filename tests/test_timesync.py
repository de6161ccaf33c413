"""TimeSync against the simulator's DAQ clock: accuracy, holdover, rejection rules, chunking invariance,
a stalling host.

Run with -s to see the RMS figures.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from fieldlog.acquire.timesync import PpsEdge, SyncState, SyncStatus, TimeSync, TimeSyncConfig, theil_sen
from fieldlog.tools.sim.clock import ClockConfig, PpsTruth, pps_frames, sample_times

FRAME_S = 38 * 10 / 460800          # a 38-byte frame at 460800 baud
HOST_BOOT_S, HOST_PPM, WALL_OFFSET_S = 1234.5, 12.0, 0.37


@dataclass
class Drive:
    t_s: np.ndarray                  # true sample times
    pps: np.ndarray
    latch: np.ndarray
    latch_valid: np.ndarray
    truth: PpsTruth
    events: list                     # ('fix', utc_s, mono, wall) | ('read', k0, k1, mono, wall), in mono order
    start_utc_ns: int
    dropped_fix_utc: np.ndarray

    def truth_ns(self, k: np.ndarray) -> np.ndarray:
        return self.start_utc_ns + np.round(self.t_s[k] * 1e9).astype(np.int64)


def host(t: np.ndarray, start_utc_ns: int) -> tuple[np.ndarray, np.ndarray]:
    mono = np.round((HOST_BOOT_S + t * (1 + HOST_PPM * 1e-6)) * 1e9).astype(np.int64)
    wall = start_utc_ns + np.round((t + WALL_OFFSET_S) * 1e9).astype(np.int64)
    return mono, wall


def stalled(t: np.ndarray, starts: np.ndarray, stall_s: float, rng: np.random.Generator) -> np.ndarray:
    """Read times ``t`` (s) of a host that stalls for ``stall_s`` from each of ``starts``: a read due within a stall
    returns 0-3 ms after its end, with what was buffered."""
    i = np.searchsorted(starts, t, "right") - 1
    inside = (i >= 0) & (t < starts[np.maximum(i, 0)] + stall_s)
    out = t.copy()
    out[inside] = starts[i[inside]] + stall_s + rng.uniform(0.0, 0.003, int(inside.sum()))
    return np.maximum.accumulate(out)


def make_drive(duration_s: float, ccfg: ClockConfig, seed: int, dropped_fixes: int = 5,
               fixes_from_s: float = 0.0, stall_s: float = 0.0, stall_every_s: float = 1.0) -> Drive:
    """Sample clock + PPS from tools.sim.clock; DAQ reads every 5-25 ms; NMEA epochs 50-500 ms late. With
    ``stall_s``: the host stalls that long every ``stall_every_s`` (both ports read late, after the stall)."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * ccfg.fs_hz)
    t = sample_times(n, ccfg, rng)
    pps, latch, latch_valid, truth = pps_frames(t, ccfg, rng)
    done = t + FRAME_S
    read_t = ccfg.first_second() / 3 + np.cumsum(rng.uniform(0.005, 0.025, int(duration_s / 0.005) + 10))
    read_t = read_t[: np.searchsorted(read_t, done[-1]) + 1]
    cut = np.searchsorted(done, read_t, "right")
    sec_t = ccfg.first_second() + np.arange(len(truth.utc_s))
    latency = np.clip(rng.uniform(0.05, 0.4) + 0.03 * rng.standard_normal(len(sec_t)), 0.05, 0.5)
    keep = (sec_t >= fixes_from_s)
    dropped = rng.choice(np.flatnonzero(keep), dropped_fixes, replace=False)
    keep[dropped] = False
    fix_t = sec_t[keep] + latency[keep]
    if stall_s:
        starts = rng.uniform(0, stall_every_s) + np.arange(0, duration_s, stall_every_s)
        read_t, fix_t = stalled(read_t, starts, stall_s, rng), stalled(fix_t, starts, stall_s, rng)
        cut = np.searchsorted(done, read_t, "right")
    events: list = []
    rm, rw = host(read_t, ccfg.start_utc_ns)
    prev = 0
    for c, m, w in zip(cut.tolist(), rm.tolist(), rw.tolist()):
        if c > prev:
            events.append((m, "read", prev, c, w))
            prev = c
    fm, fw = host(fix_t, ccfg.start_utc_ns)
    for u, m, w in zip(truth.utc_s[keep].tolist(), fm.tolist(), fw.tolist()):
        events.append((m, "fix", u, w))
    events.sort(key=lambda e: e[0])
    return Drive(t, pps, latch, latch_valid, truth, events, ccfg.start_utc_ns, truth.utc_s[dropped])


@dataclass
class Run:
    k: np.ndarray
    ns: np.ndarray
    state: np.ndarray
    edges: list
    status: list
    ts: TimeSync


def run(drive: Drive, cfg: TimeSyncConfig, split_seed: int | None = None, poll_every: int = 1) -> Run:
    """Feed a drive in mono order, stamping samples as they become final.

    ``split_seed``: cut every read into random pieces (same mono/wall); ``poll_every``: poll outputs every N calls.
    """
    ts = TimeSync(cfg)
    rng = np.random.default_rng(split_seed)
    ks, nss, states, edges, status = [], [], [], [], []
    got = 0
    k_all = np.arange(len(drive.t_s), dtype=np.int64)

    def poll() -> None:
        nonlocal got
        fu = ts.final_until()
        if fu > got:
            k = np.arange(got, fu, dtype=np.int64)
            ns, st = ts.stamp(k)
            ks.append(k), nss.append(ns), states.append(st)
            got = fu
        eb, sb = ts.pop_edges(), ts.pop_status()
        edges.extend(PpsEdge(*row) for row in zip(eb.k_edge.tolist(), eb.mono_ns.tolist(), eb.label_s.tolist(),
                                                  eb.accepted.tolist(), eb.reason.tolist()))
        status.extend(SyncStatus(*row) for row in zip(sb.utc_ns.tolist(), sb.state.tolist(), sb.rate_ppm.tolist(),
                                                      sb.residual_us.tolist(), sb.edges_used.tolist(),
                                                      sb.edges_rejected.tolist()))

    for i, ev in enumerate(drive.events):
        if ev[1] == "fix":
            ts.add_fix(ev[2], ev[0], ev[3])
            continue
        a, b = ev[2], ev[3]
        cuts = [a, b]
        if split_seed is not None and b - a > 1:
            cuts = [a, *sorted(rng.choice(np.arange(a + 1, b), rng.integers(0, min(3, b - a - 1) + 1),
                                          replace=False).tolist()), b]
        for c0, c1 in zip(cuts[:-1], cuts[1:]):
            ts.add_frames(k_all[c0:c1], drive.pps[c0:c1], drive.latch[c0:c1], drive.latch_valid[c0:c1], ev[0], ev[4])
        if i % poll_every == 0:
            poll()
    ts.finish()
    poll()
    return Run(np.concatenate(ks), np.concatenate(nss), np.concatenate(states), edges, status, ts)


def locked_rms_us(drive: Drive, r: Run) -> float:
    first = min(e.k_edge for e in r.edges if e.accepted)
    m = (r.state == SyncState.LOCKED) & (r.k >= first)
    err = (r.ns[m] - drive.truth_ns(r.k[m])).astype(np.float64)
    return float(np.sqrt(np.mean(err**2)) / 1e3)


def check_common(drive: Drive, r: Run) -> None:
    assert np.array_equal(r.k, np.arange(len(drive.t_s)))             # every sample stamped exactly once
    assert np.all(np.diff(r.ns) > 0)                                  # strictly monotonic
    acc = [e for e in r.edges if e.accepted]
    # every accepted edge carries the right GPS second and lies within a sample of a true edge
    live = drive.truth.k >= 0
    for e in acc:
        j = np.searchsorted(drive.truth.utc_s, e.label)
        assert live[j] and abs(e.k_edge - (drive.truth.k[j] - 0.5)) <= 0.5 + 1e-9
    for k in drive.truth.glitch_k.tolist():
        (g,) = [e for e in r.edges if k - 1 <= e.k_edge <= k]
        assert not g.accepted and g.reason in ("disagree", "duplicate", "outlier", "stale_fix")
    secs = [s.utc_ns for s in r.status]
    assert secs == sorted(set(secs)) and all(s % 1_000_000_000 == 0 for s in secs)


@pytest.fixture(scope="module")
def flag_run():
    drive = make_drive(600, ClockConfig(pps_mode="flag", glitch_pps=3), seed=1)
    return drive, run(drive, TimeSyncConfig(pps_mode="flag"))


def test_flag_accuracy(flag_run):
    drive, r = flag_run
    check_common(drive, r)
    rms = locked_rms_us(drive, r)
    print(f"\nflag PPS, 600 s, 40 ppm + 0.5 ppm wander, 3 dropped edges, 5 dropped fixes: RMS {rms:.1f} us")
    assert rms <= 100.0
    locked = [s for s in r.status if s.state == SyncState.LOCKED]
    assert len(locked) > 500
    assert all(abs(s.rate_ppm - 40.0) < 5.0 for s in locked)    # 1.5 ppm 1-sigma over 120 s, + wander
    assert max(s.residual_us for s in locked) < 700.0


def test_latch_accuracy():
    drive = make_drive(600, ClockConfig(pps_mode="latch", glitch_pps=2), seed=2)
    r = run(drive, TimeSyncConfig(pps_mode="latch"))
    check_common(drive, r)
    rms = locked_rms_us(drive, r)
    print(f"\nlatched PPS, 600 s, same clock: RMS {rms:.3f} us")
    assert rms <= 5.0


def test_stale_and_missing_fix_rejects_edges(flag_run):
    drive, r = flag_run
    by_label = {e.label: e for e in r.edges if e.label >= 0}
    stale = [e for e in r.edges if e.reason == "stale_fix"]
    # the edge after a dropped epoch S is labelled from epoch S-1, more than 1.1 s old
    assert len(stale) >= len(drive.dropped_fix_utc) - 1
    for s in drive.dropped_fix_utc.tolist():
        assert s + 1 not in by_label or not by_label[s + 1].accepted
    assert sum(e.accepted for e in r.edges) >= len(drive.truth.utc_s) - 3 - 2 * 5 - 2


@pytest.mark.parametrize("seed", [11, 12, 13])
def test_a_stalling_host_loses_no_edge(seed: int) -> None:
    """The host stalls 0.7 s (beyond ``max_disagree_s``) every 2.3 s: the reads after a stall bring what the ports
    buffered, the fixes and the edges in either order. Each edge is placed at its frame's host time, not its read's,
    so a stall costs no edge but the one a late fix leaves without its label: each accepted edge has its own second,
    and the stamps are as good."""
    ccfg = ClockConfig(pps_mode="flag", glitch_pps=2)
    calm = make_drive(300, ccfg, seed=seed)
    drive = make_drive(300, ccfg, seed=seed, stall_s=0.7, stall_every_s=2.3)
    assert np.array_equal(drive.pps, calm.pps) and np.array_equal(drive.truth.utc_s, calm.truth.utc_s)
    a, b = run(calm, TimeSyncConfig(pps_mode="flag")), run(drive, TimeSyncConfig(pps_mode="flag"))
    check_common(drive, b)
    n_calm, n_stalled = sum(e.accepted for e in a.edges), sum(e.accepted for e in b.edges)
    # a fix of second S read after a stall that ended past the edge of S + 1 leaves that edge no label
    fixes = [(e[2], e[0]) for e in drive.events if e[1] == "fix"]
    edge_mono = dict(zip(drive.truth.utc_s.tolist(), host(drive.truth.t_s, drive.start_utc_ns)[0].tolist()))
    late = sum(m > edge_mono.get(u + 1, np.inf) for u, m in fixes)
    print(f"\nseed {seed}: edges accepted {n_calm} calm, {n_stalled} with stalls ({late} fixes read after the next "
          f"edge); RMS {locked_rms_us(calm, a):.1f} / {locked_rms_us(drive, b):.1f} us")
    assert n_calm - late - 2 <= n_stalled <= n_calm
    assert locked_rms_us(drive, b) <= 100.0


def test_pps_gap_holdover_then_free():
    ccfg = ClockConfig(pps_mode="latch", dropped_pps=0, glitch_pps=0, pps_gaps=[[100.0, 20.0], [200.0, 45.0]])
    drive = make_drive(320, ccfg, seed=3)
    r = run(drive, TimeSyncConfig(pps_mode="latch"))
    check_common(drive, r)
    t = drive.t_s[r.k]

    def states(a: float, b: float) -> set:
        return set(r.state[(t > a) & (t < b)].tolist())

    assert states(50, 99) == {SyncState.LOCKED}
    assert states(103.5, 119.5) == {SyncState.HOLDOVER}             # 20 s gap: holdover throughout
    assert states(121.5, 199) == {SyncState.LOCKED}
    assert states(203.5, 229.0) == {SyncState.HOLDOVER}
    assert states(231.0, 244.5) == {SyncState.FREE}                 # 45 s gap: free after 30 s
    assert states(246.5, 300) == {SyncState.LOCKED}
    err = np.abs(r.ns - drive.truth_ns(r.k)) / 1e3
    gap1 = (t > 100) & (t < 120)
    print(f"\nlatched PPS, 20 s gap (bridged): max error {err[gap1].max():.2f} us; "
          f"45 s gap (holdover fit): max error {err[(t > 200) & (t < 245)].max():.1f} us")
    assert err[gap1].max() < 5.0
    assert err[(t > 200) & (t < 245)].max() < 100.0


def test_chunking_and_polling_invariance():
    drive = make_drive(200, ClockConfig(pps_mode="flag", glitch_pps=2), seed=4)
    cfg = TimeSyncConfig(pps_mode="flag")
    a = run(drive, cfg)
    b = run(drive, cfg, split_seed=7, poll_every=997)
    assert np.array_equal(a.ns, b.ns) and np.array_equal(a.state, b.state)
    # an edge is at its read's host time less the samples after it in its call: a piece of a read ends no later
    # than the read, so the pieces' edges are no earlier, and nothing else changes while the gates pass them
    assert [(e.k_edge, e.label, e.accepted, e.reason) for e in a.edges] == \
        [(e.k_edge, e.label, e.accepted, e.reason) for e in b.edges]
    da = np.array([e.mono_ns for e in b.edges]) - np.array([e.mono_ns for e in a.edges])
    assert (da >= 0).all() and da.any()
    assert [repr(s) for s in a.status] == [repr(s) for s in b.status]


def test_before_first_lock_host_clock_then_first_fit():
    drive = make_drive(300, ClockConfig(pps_mode="flag", dropped_pps=0, glitch_pps=0), seed=5, dropped_fixes=0,
                       fixes_from_s=150.0)
    r = run(drive, TimeSyncConfig(pps_mode="flag"))
    check_common(drive, r)
    first = min(e.k_edge for e in r.edges if e.accepted) / 500.0    # ~151 s: first labelled edge
    t = drive.t_s[r.k]
    err = (r.ns - drive.truth_ns(r.k)) / 1e9
    pre = t < first - 60.0 - 0.01
    back = (t > first - 60.0 + 0.5) & (t < first)                   # after the 0.37 s forward clamp
    assert set(r.state[pre].tolist()) == {SyncState.FREE}
    assert np.all(np.abs(err[pre] - WALL_OFFSET_S) < 0.03)         # host wall clock, 0.37 s off
    assert np.all(np.abs(err[back]) < 2e-3)                          # samples just before the lock: first fit
    assert SyncState.FREE not in set(r.state[t > first].tolist())
    # mono_to_utc: locked, the host read time maps to UTC within a read period
    mono, _ = host(np.array([299.0]), drive.start_utc_ns)
    utc = r.ts.mono_to_utc(mono)
    assert abs(int(utc[0]) - (drive.start_utc_ns + 299 * 10**9)) < 30e6


def test_config_errors():
    with pytest.raises(ValueError, match="windw_s"):
        TimeSyncConfig.from_dict({"windw_s": 100})
    with pytest.raises(ValueError, match="window_s"):
        TimeSyncConfig.from_dict({"pps_mode": "flag", "window_s": 60})
    with pytest.raises(ValueError, match="pps_mode"):
        TimeSyncConfig.from_dict({"pps_mode": "edge"})
    assert TimeSyncConfig.from_dict({"pps_mode": "latch"}).window_s == 30.0
    with pytest.raises(ValueError, match="wander"):
        ClockConfig.from_dict({"wander": 1})


def test_theil_sen_gives_scipys_floats():
    """theil_sen is scipy.stats.theilslopes without the confidence interval: the same slope and intercept, bit
    for bit, on edge-like inputs (integer labels with gaps and repeats, outliers, ties in y)."""
    from scipy.stats import theilslopes
    rng = np.random.default_rng(3)
    for n in (2, 3, 10, 31, 80):
        for rep in range(30):
            x = np.sort(rng.choice(np.arange(-60, 60), n, replace=rep % 2 == 0)).astype(np.float64)
            if np.ptp(x) == 0:
                continue
            y = 0.37 * x + rng.normal(size=n) * 10.0 ** rng.uniform(-4, 1)
            y[rng.random(n) < 0.1] += 50.0
            if rep % 3 == 0:
                y = np.round(y, 1)
            ref = theilslopes(y, x)
            assert theil_sen(x, y) == (ref.slope, ref.intercept)


def test_robust_fit_gives_the_floats_of_numpys_means():
    """robust_fit's least squares (means as sums over the count) gives the floats of the same fit written with
    np.mean, on edge-like inputs: labels with gaps, outliers, windows of a few to a few hundred edges."""
    from fieldlog.acquire.timesync import robust_fit, theil_sen
    rng = np.random.default_rng(6)
    fs, tol, fitted = 500.0, 0.5, 0
    for n in (5, 17, 121, 300):
        for rep in range(20):
            label = np.sort(rng.choice(np.arange(10_000, 10_000 + 2 * n), n, replace=False))
            k_edge = 3e6 + (label - label[0]) * (fs + rng.normal(0, 0.05)) + rng.normal(0, 0.2, n)
            k_edge[rng.random(n) < 0.05] += 40.0
            lr, kr = int(label[-1]), int(np.floor(k_edge[-1]))
            x = (label - lr).astype(np.float64)
            y = k_edge - kr - fs * x
            slope, intercept = theil_sen(x, y)
            inl = np.abs(y - intercept - slope * x) <= tol
            got = robust_fit(label, k_edge, lr, kr, fs, tol, 3)
            if got is None:
                assert inl.sum() < 3
                continue
            fit, got_inl = got
            fitted += 1
            xi, yi = x[inl], y[inl]
            xm, ym = xi.mean(), yi.mean()
            e = float(((xi - xm) * (yi - ym)).sum() / float(((xi - xm) ** 2).sum()))
            c = float(ym - e * xm)
            assert (got_inl == inl).all()
            assert (fit.c, fit.e, fit.n, fit.x_mean, fit.sxx) == (c, e, int(inl.sum()), float(xm),
                                                                   float(((xi - xm) ** 2).sum()))
            assert fit.rms == float(np.sqrt(np.mean((yi - c - e * xi) ** 2)))
    assert fitted > 60
