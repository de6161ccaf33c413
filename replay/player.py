"""``fieldlog replay DRIVE --speed X [--method M] [--rrd OUT.rrd | --connect URL]``: live fusion into rerun.

The drive is read in ``PLAY_BLOCK_S`` blocks as ``fuse`` reads it (``replay.inputs.InputStream``: header
stamps, late-logged messages re-sequenced), each block goes through the incremental ``fusion.engine.Engine``
in the loop of every front end (``replay.loop.run``) and what it holds and produced is logged at once on the
``gps_time`` timeline by the ``Player`` sink, paced so that data time runs X times faster than the wall clock.
``play`` takes any source of ``replay.inputs.InputBlock`` with their data: ``live_view`` (``fieldlog view
--live``, ``fieldlog acquire --view``) feeds it the daemon's live bus (``replay.loop.live_inputs``), unpaced.

The entities and colours are those of ``replay.view`` (its module docstring), with the blueprint of
``replay.view.blueprint`` plus a time panel that follows the newest data. Logged live: ``map/gps``,
``enu/gps``, ``map/truth`` and ``enu/truth`` (every ``TRUTH_DECIMATION``-th row), ``map/fusion/<method>``,
``enu/fusion/<method>`` (one row per solution row; ENU origin: the first GPS fix, else the first truth
point), ``errors/{pos,vel}/<axis>/<method>`` (against the truth when the drive has it, else the GPS),
``status/no_fix``, ``status/outage``, ``solution_status/<method>``, ``imu/gyro``, ``imu/accel`` (decimated by ``IMU_DECIMATION`` block means),
``enu/fusion/<method>/base_link`` and ``attitude/<angle>/<method>`` with its sigma (the vehicle; base_link
through the drive's ``/tf_static``, live from the bus the default mounting).
The whole-track GeoLineStrings of ``fieldlog view`` are not logged: the track grows in the 3D view up to the
cursor.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, fields
from typing import Callable, Iterable

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from fieldlog.drive import outputs
from fieldlog.fusion.config import FusionConfig
from fieldlog.fusion.engine import Engine
from fieldlog.fusion.types import Outage, Solution
from fieldlog.drive import reader
from fieldlog.replay import inputs
from fieldlog.drive.files import DriveSpec
from fieldlog.drive.reader import IN_TOPICS
from fieldlog.replay import view as rv
from fieldlog.replay.inputs import InputBlock
from fieldlog.replay.loop import Pace, live_inputs, run

PLAY_BLOCK_S = 1.0  # data seconds per logged block
TOPICS = (*IN_TOPICS, "/truth/fix", "/truth/vel")


@dataclass
class ReplayResult:
    sink: str
    blocks: int = 0
    solutions: int = 0
    updates: int = 0  # GPS updates the filter made
    gps_fixes: int = 0
    imu_rows: int = 0
    outages: int = 0
    data_s: float = 0.0  # drive time played, s
    wall_s: float = 0.0


def live_blueprint(method: str) -> rrb.Blueprint:
    """``replay.view.blueprint`` (its time panel follows the newest data on ``gps_time``), the close-up view
    on ``method``'s vehicle."""
    return rv.blueprint(follow=f"fusion/{method}")


class _Source:
    """One positioned source on the map and in 3D, logged block by block (segments continue across blocks)."""

    def __init__(self, rec: rr.RecordingStream, src: str, color, radius: float) -> None:
        self.rec, self.src, self.color, self.radius = rec, src, color, radius
        self.last: np.ndarray | None = None  # last ENU point, m

    def log(self, trk: rv.Track, origin: tuple[float, float, float]) -> None:
        if len(trk.t_ns) == 0:
            return
        times = rv._times(trk.t_ns)
        rr.send_columns(f"map/{self.src}", indexes=times,
                        columns=rr.GeoPoints.columns(positions=np.stack([trk.lat_deg, trk.lon_deg], axis=1)),
                        recording=self.rec)
        p = rv.to_enu(trk.lat_deg, trk.lon_deg, trk.alt_m, origin)
        seg = rv._step_segments(p)
        if self.last is not None:
            seg[0, 0] = self.last
        else:
            self.rec.log(f"map/{self.src}", rr.GeoPoints.from_fields(radii=rr.Radius.ui_points(self.radius),
                                                                     colors=[self.color]), static=True)
            self.rec.log(f"enu/{self.src}", rr.LineStrips3D.from_fields(colors=[self.color],
                                                                        radii=rr.Radius.ui_points(1.5)), static=True)
        self.last = p[-1]
        rr.send_columns(f"enu/{self.src}", indexes=times, columns=rr.LineStrips3D.columns(strips=seg),
                        recording=self.rec)


def _columns(t: rv.Track) -> list[np.ndarray | None]:
    return [getattr(t, f.name) for f in fields(rv.Track)]


def _cat(a: rv.Track | None, b: rv.Track) -> rv.Track:
    """``a`` then ``b`` (``b``'s optional fields decide; a missing one in ``a`` is NaN)."""
    if a is None or len(a.t_ns) == 0:
        return b

    def join(x: np.ndarray | None, y: np.ndarray | None) -> np.ndarray | None:
        if y is None:
            return None
        return np.concatenate([x if x is not None else np.full((len(a.t_ns), *y.shape[1:]), np.nan), y])

    return rv.Track(*(join(x, y) for x, y in zip(_columns(a), _columns(b))))


def _fused_track(s: Solution) -> rv.Track:
    return rv.Track(s.t_ns, np.degrees(s.lat), np.degrees(s.lon), s.h, v_n=s.v_n, sigma_pos=s.sigma[:, 0:3],
                    sigma_vel=s.sigma[:, 3:6])


class Player:
    """The loop's rerun sink (``replay.loop.Sink``): logs blocks and their fusion output into ``rec``, flushed
    after each block; state carried between blocks."""

    def __init__(self, rec: rr.RecordingStream, method: str,
                 mount: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.rec, self.method = rec, method
        self.mount = mount if mount is not None else rv.mounting(None)  # base_link -> imu (view.mounting)
        self.origin: tuple[float, float, float] | None = None
        self.gps = _Source(rec, "gps", rv.GPS_COLOR, 3.0)
        self.truth = _Source(rec, "truth", rv.TRUTH_COLOR, 2.0)
        self.fused = _Source(rec, f"fusion/{method}", rv.method_color(method, 0), 2.5)
        self.truth_row = 0  # rows of /truth/fix seen, for the decimation phase
        self.gps_pending: rv.Track | None = None  # GPS epochs not yet reached by the solutions
        self.last_sol: rv.Track | None = None  # the newest solution row, to interpolate across blocks
        self.imu_carry = (np.zeros(0, np.int64), np.zeros((0, 6)))
        self.res = ReplayResult("")
        self._styled: set[str] = set()

    def _style(self, path: str, archetype) -> None:
        if path not in self._styled:
            self.rec.log(path, archetype, static=True)
            self._styled.add(path)

    def _imu(self, imu: dict) -> None:
        if not len(imu.get("log_time_ns", ())):
            return
        ok = imu["valid"]
        t = np.concatenate([self.imu_carry[0], imu["log_time_ns"][ok]])
        x = np.concatenate([self.imu_carry[1], np.hstack([imu["omega_ib_b"][ok], imu["f_b"][ok]])])
        tm, xm = rv.decimate_means(t, x, rv.IMU_DECIMATION)
        self.imu_carry = (t[len(tm) * rv.IMU_DECIMATION:], x[len(tm) * rv.IMU_DECIMATION:])
        if not len(tm):
            return
        xyz = [(220, 50, 50), (40, 160, 40), (40, 90, 230)]
        for path, cols, names in (("imu/gyro", slice(0, 3), ["gyro x (rad/s)", "gyro y", "gyro z"]),
                                  ("imu/accel", slice(3, 6), ["accel x (m/s²)", "accel y", "accel z"])):
            rr.send_columns(path, indexes=rv._times(tm), columns=rr.Scalars.columns(scalars=xm[:, cols]),
                            recording=self.rec)
            self._style(path, rr.SeriesLines(names=names, colors=xyz))
        self.res.imu_rows += len(tm)

    def _outages(self, done: list[Outage]) -> None:
        if not done:
            return
        t = np.array([x for o in done for x in (o.start_ns, o.end_ns)], np.int64)
        level = np.tile([1.0, 0.0], len(done))
        order = np.argsort(t, kind="stable")
        rr.send_columns("status/outage", indexes=rv._times(t[order]), columns=rr.Scalars.columns(
            scalars=level[order]), recording=self.rec)
        self._style("status/outage", rr.SeriesLines(names=["outage"], colors=[rv.OUTAGE_COLOR[:3]],
                                                    interpolation_mode=rr.components.InterpolationMode.StepAfter))
        self.res.outages += len(done)

    def _status(self, sol: Solution) -> None:
        st = sol.status
        if st is None or not len(st.t_ns):
            return
        path = f"solution_status/{self.method}"
        rr.send_columns(path, indexes=rv._times(st.t_ns), columns=rr.Scalars.columns(
            scalars=st.code.astype(float)), recording=self.rec)
        self._style(path, rr.SeriesLines(names=[f"{self.method} status"], colors=[self.fused.color],
                                         interpolation_mode=rr.components.InterpolationMode.StepAfter))

    def block(self, b: InputBlock, sol: Solution, done: list[Outage]) -> None:
        """Log one block (its data: ``InputBlock.data``) and its fusion output.

        Parameters
        ----------
        b : InputBlock
            The block, with its rows per topic.
        sol : Solution
            The engine's rows for it (UTC ns, WGS-84 rad and m, ENU m/s).
        done : list of Outage
            The outage windows it closed (UTC ns).
        """
        d = b.data or {}
        imu = d.get("/imu", {})
        self._imu(imu)
        self._status(sol)
        ref, ref_is_truth = None, False
        fix = d.get("/gps/fix")
        if fix is not None and len(fix["log_time_ns"]):
            gps, epochs_t, no_fix = rv.gps_track(fix)
            vel = d.get("/gps/vel")
            if vel is not None and len(vel["log_time_ns"]):
                gps.v_n = rv._interp(gps.t_ns, vel["log_time_ns"][vel["valid"]], vel["v_n"][vel["valid"]])
            if self.origin is None and len(gps.t_ns):
                self.origin = (float(gps.lat_deg[0]), float(gps.lon_deg[0]), float(gps.alt_m[0]))
            if self.origin is not None:
                self.gps.log(gps, self.origin)
            if len(epochs_t):
                rr.send_columns("status/no_fix", indexes=rv._times(epochs_t),
                                columns=rr.Scalars.columns(scalars=no_fix.astype(float)), recording=self.rec)
                self._style("status/no_fix", rr.SeriesLines(
                    names=["GPS no fix"], colors=[rv.NO_FIX_COLOR],
                    interpolation_mode=rr.components.InterpolationMode.StepAfter))
            self.res.gps_fixes += len(gps.t_ns)
            ref, ref_is_truth = gps, False
        tf = d.get("/truth/fix")
        if tf is not None and len(tf["log_time_ns"]):
            truth = rv.truth_track(tf, d.get("/truth/vel"))
            ref, ref_is_truth = truth, True
            if self.origin is None:  # no GPS fix yet: the truth's first point
                self.origin = (float(truth.lat_deg[0]), float(truth.lon_deg[0]), float(truth.alt_m[0]))
            if self.origin is not None:
                sl = slice((-self.truth_row) % rv.TRUTH_DECIMATION, None, rv.TRUTH_DECIMATION)
                self.truth.log(rv.Track(truth.t_ns[sl], truth.lat_deg[sl], truth.lon_deg[sl], truth.alt_m[sl]),
                               self.origin)
            self.truth_row += len(tf["log_time_ns"])
        if ref is not None and not ref_is_truth:
            ref = self.gps_pending = _cat(self.gps_pending, ref)
        self._solution(sol, ref, ref_is_truth)
        self._outages(done)
        self.rec.flush()

    def _solution(self, sol: Solution, ref: rv.Track | None, ref_is_truth: bool) -> None:
        """Log fused rows, and their errors against ``ref`` (truth, or the GPS epochs not yet scored)."""
        if len(sol.t_ns) and self.origin is not None:
            trk = _fused_track(sol)
            self.fused.log(trk, self.origin)
            pose = rv.base_pose(trk, sol.q, self.mount, self.origin)
            color, first = rv.method_color(self.method, 0), self.res.solutions == 0
            rv._log_pose(self.rec, f"fusion/{self.method}", pose, color, style=first)
            sigma = rv.attitude_sigma_deg(sol.sigma[:, 6:9], pose.euler_deg()[:, 2])
            rv._log_attitude(self.rec, self.method, pose, sigma, color, style=first)
            if ref is not None and not ref_is_truth:
                # GPS epochs are scored once solutions reach them (the engine may lag a block), across blocks
                trk_e = _cat(self.last_sol, trk)
                self.gps_pending = ref.take(ref.t_ns > trk.t_ns[-1])
                self.last_sol = trk.take(slice(-1, None))
                trk = trk_e
            if ref is not None and len(ref.t_ns):
                rv._log_errors(self.rec, self.method, rv.errors(trk, ref, ref_is_truth, self.origin),
                               rv.method_color(self.method, 0))
        self.res.solutions += len(sol.t_ns)

    def finish(self, sol: Solution, done: list[Outage]) -> None:
        """Log the engine's last rows (scored against the GPS epochs still pending) and outage windows.

        Parameters
        ----------
        sol : Solution
            The rows of ``Engine.finish``.
        done : list of Outage
            Its outage windows.
        """
        self._solution(sol, self.gps_pending, False)
        self._outages(done)


def play(rec: rr.RecordingStream, blocks: Iterable[InputBlock], method: str, pace: Pace,
         config: FusionConfig | None = None, mount: tuple[np.ndarray, np.ndarray] | None = None) -> ReplayResult:
    """Fuse and log ``blocks`` (with their data) into ``rec`` through ``replay.loop.run``.

    Parameters
    ----------
    rec : rerun.RecordingStream
        The recording, its sink set.
    blocks : iterable of InputBlock
        The source, each block with its rows per topic (``InputBlock.data``).
    method : str
        The fusion method.
    pace : Pace
        Speed against the wall clock and progress.
    config : FusionConfig, optional
        The fusion settings (None: the defaults).
    mount : tuple of ndarray, optional
        The drive's base_link -> imu (``view.mounting``; None: the default mounting).

    Returns
    -------
    ReplayResult
        What was logged, log time played and wall time (s).
    """
    player = Player(rec, method, mount)
    engine = Engine(method, config)
    ran = run(blocks, engine, [player], pace)
    res = player.res
    res.blocks, res.updates, res.data_s, res.wall_s = ran.blocks, engine.updates, ran.data_s, ran.wall_s
    return res


def _check_sink(rrd: str | os.PathLike[str] | None, connect: str | None) -> None:
    if connect is None and rrd is None and not rv.has_display():
        raise ValueError("no display to open the viewer on: pass --rrd OUT.rrd or --connect URL")


def _open(rrd: str | os.PathLike[str] | None, connect: str | None, method: str) -> tuple[rr.RecordingStream, str]:
    """A recording with the live blueprint, sent to ``connect`` (a gRPC URL, e.g.
    ``rerun+http://127.0.0.1:9876/proxy``), else streamed into the ``rrd`` file, else to a spawned viewer."""
    rec = rr.RecordingStream("fieldlog")
    bp = live_blueprint(method)
    if connect is not None:
        rec.connect_grpc(connect, default_blueprint=bp)
        return rec, connect
    if rrd is not None:
        rec.save(rrd, default_blueprint=bp)
        return rec, str(rrd)
    rec.spawn(default_blueprint=bp)
    return rec, "viewer"


def _play_into(rrd: str | os.PathLike[str] | None, connect: str | None, blocks: Iterable[InputBlock],
               method: str, pace: Pace, config: FusionConfig | None, force: bool = False,
               mount: tuple[np.ndarray, np.ndarray] | None = None) -> ReplayResult:
    """``play`` into the sink of ``_open``; an ``rrd`` file is a new name unless ``force`` (``outputs.staged``)."""
    to_file = rrd is not None and connect is None
    with outputs.staged(rrd, force) if to_file else contextlib.nullcontext() as work:
        rec, sink = _open(work, connect, method)
        try:
            res = play(rec, blocks, method, pace, config, mount)
        finally:
            rec.flush()
            rec.disconnect()
    res.sink = str(rrd) if to_file else sink
    return res


def replay(drive: DriveSpec, method: str, speed: float, rrd: str | os.PathLike[str] | None = None,
           connect: str | None = None, config: FusionConfig | None = None,
           progress: Callable[[float], None] | None = None, imap: inputs.InputMap | None = None,
           force: bool = False) -> ReplayResult:
    """Play ``drive`` into a rerun viewer: ``connect`` (a gRPC URL, e.g. ``rerun+http://127.0.0.1:9876/proxy``),
    else the ``rrd`` file, else a spawned viewer. ``imap``: the topics and IMU frame of another logger's drive
    (``replay.inputs.resolve``; None: resolved from the drive). The drive is read as ``fuse`` reads it
    (``replay.inputs.InputStream``: on the header stamps, late-logged messages re-sequenced, wheel speeds when
    mapped), so the solution is ``fuse``'s."""
    imap = imap or inputs.resolve(drive)
    tops = [t for t in reader.topics(drive) if t.topic in imap.topics and t.count]
    blocks = inputs.InputStream(drive, imap, PLAY_BLOCK_S, TOPICS[len(IN_TOPICS):]).inputs(keep_data=True)
    _check_sink(rrd, connect)
    pace = Pace(speed, (min(t.first_ns for t in tops), max(t.last_ns for t in tops)), progress)
    return _play_into(rrd, connect, blocks, method, pace, config, force, rv.mounting(drive))


def live_view(address: str, method: str, rrd: str | os.PathLike[str] | None = None, connect: str | None = None,
              config: FusionConfig | None = None, wait_s: float = 30.0, force: bool = False) -> ReplayResult:
    """``fieldlog view --live``: the daemon's live bus at ``address`` (its Unix socket, ``[daemon] bus``) through
    the same incremental fusion and logging as ``replay`` (``play``, unpaced: data comes at the car's pace).
    Waits up to ``wait_s`` for the daemon to open the bus; ends when the daemon closes it, on Ctrl-C or SIGTERM."""
    from fieldlog.replay import live

    _check_sink(rrd, connect)
    blocks = live_inputs(live.batch_blocks(live.follow(address, wait_s), IN_TOPICS, PLAY_BLOCK_S))
    return _play_into(rrd, connect, blocks, method, Pace(), config, force=force)
