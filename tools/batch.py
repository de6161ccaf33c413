"""``fieldlog batch 'drives/*.mcap' --methods kf,dkf [--outages 30,60] [--scheduler tcp://HOST:PORT] --out DIR``.

Reprocesses a fleet's drives on Dask distributed, one task per drive (``drive_rows``): ``tools.info`` (duration,
time-sync quality, time-stamp error against ``/truth/imu`` when present), ``tools.fuse`` per method and the
error maths of ``tools.evaluation.evaluate`` (reference: ``/truth`` when the drive has it, else the GPS fixes).

Per drive and method:

- the whole drive fused without forced outages into ``DIR/fused/<drive>_<method>.mcap``; RMS errors over every
  solution row (``outage_s`` null);
- per outage length L of ``--outages``: windows placed as in ``fieldlog evaluate`` (``place_outages``), fused into
  ``DIR/fused/<drive>_<method>_<L>s.mcap``; RMS errors over the rows inside the windows (``outage_s`` = L).

Everything lands in one polars table, ``DIR/results.parquet``, one row per (drive, method, outage_s); a drive
that fails (unreadable, truncated, no IMU, ...) gives one row with ``status = "failed"`` and its ``error``,
and never stops the others. Columns (``RESULT_SCHEMA``): drive info first, then ``rms_<quantity>`` in
``tools.evaluation.evaluate.QUANTITIES`` order (m, m/s, deg; attitude null against GPS), ``pos_2d_m`` (horizontal,
hypot of the east and north RMS) and ``vel_3d_mps`` (norm of the three velocity RMS).

The cluster is a ``LocalCluster`` on 127.0.0.1 (processes, one thread each, no dashboard) unless a scheduler
address is given; then the workers must see the drive paths and ``DIR`` (shared file system).
"""

from __future__ import annotations

import math
import time
import traceback
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

import numpy as np
import polars as pl

from fieldlog.drive import outputs
from fieldlog.fusion.config import FusionConfig
from fieldlog.drive.reader import IN_TOPICS
from fieldlog.tools.evaluation.evaluate import (QUANTITIES, check_drive_names, check_methods, fix_quality,
                                                outage_error_series, place_outages, rms_columns)
from fieldlog.drive.drive import Drive
from fieldlog.tools.fuse import fuse
from fieldlog.tools.fuse_settings import drive_config
from fieldlog.tools.info import drive_info

RESULT_SCHEMA: dict[str, pl.DataType] = {
    "drive": pl.Utf8,
    "path": pl.Utf8,
    "status": pl.Utf8,  # "ok" or "failed"
    "error": pl.Utf8,
    "duration_s": pl.Float64,
    "sync_locked": pl.Float64,  # fraction of /time/sync records LOCKED
    "rate_ppm": pl.Float64,  # median DAQ clock rate error while locked
    "residual_us": pl.Float64,  # median PPS fit residual while locked
    "timing_rms_us": pl.Float64,  # IMU stamp error vs /truth/imu after first lock (simulated drives)
    "reference": pl.Utf8,  # "truth" or "gps"
    "method": pl.Utf8,
    "outage_s": pl.Float64,  # null: whole drive, no forced outage
    "windows": pl.Int64,  # outage windows placed (0 for the whole-drive rows)
    "solutions": pl.Int64,  # fused rows written
    "error_rows": pl.Int64,  # rows the RMS is taken over
    **{f"rms_{q}": pl.Float64 for q, _ in QUANTITIES},
    "pos_2d_m": pl.Float64,
    "vel_3d_mps": pl.Float64,
}


def _metrics(err: np.ndarray) -> dict[str, float | int | None]:
    """RMS columns from an (n, 9) error array (``tools.evaluation.evaluate`` quantity order)."""
    rms = rms_columns(err) if len(err) else np.full(len(QUANTITIES), np.nan)

    def f(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    out: dict[str, float | int | None] = {f"rms_{q}": f(rms[i]) for i, (q, _) in enumerate(QUANTITIES)}
    out["pos_2d_m"] = f(math.hypot(rms[0], rms[1]))
    out["vel_3d_mps"] = f(float(np.linalg.norm(rms[3:6])))
    out["error_rows"] = int(len(err))
    return out


def drive_rows(drive: str | Path, methods: Sequence[str], lengths: Sequence[float], out: str | Path,
               config: FusionConfig | None = None, force: bool = False) -> list[dict]:
    """All result rows of one drive (raises on a bad drive; ``safe_drive_rows`` turns that into a row).
    ``config`` None: the drive's own settings (``tools.fuse_settings.drive_config``). ``force``: replace fused files."""
    path, out = Path(drive), Path(out)
    drive = Drive.open(path)  # its files opened once and checked as one drive
    cfg = config or drive_config(drive)
    outputs.out_dir(out, "fused")
    info = drive_info(drive)
    span = [t for t in info.topics if t.topic in IN_TOPICS and t.count]
    if not any(t.topic == "/imu" for t in span):
        raise ValueError(f"{drive}: no /imu messages")
    names = {t.topic for t in info.topics if t.count}
    base = dict(drive=path.stem, path=str(path), status="ok", error=None, duration_s=info.duration_s,
                sync_locked=info.sync_states.get("locked", 0.0) if info.sync_states else None,
                rate_ppm=info.rate_ppm if math.isfinite(info.rate_ppm) else None,
                residual_us=info.residual_us if math.isfinite(info.residual_us) else None,
                timing_rms_us=info.timing.rms_us if info.timing else None,
                reference="truth" if "/truth/fix" in names else "gps")
    whole = [(min(t.first_ns for t in span), max(t.last_ns for t in span) + 1)]
    rows = []
    for m in methods:
        res = fuse(drive, m, fused_path(out, path, m), cfg, force=force, keep=True)
        _, err = outage_error_series(drive, res.solution, m, whole)
        rows.append({**base, "method": m, "outage_s": None, "windows": 0, "solutions": res.rows, **_metrics(err)})
    if lengths:
        t_fix, good, t0 = fix_quality(drive, cfg.gps.max_fix_sigma_m)
        for L in lengths:
            win = place_outages(t_fix, good, L)
            win_ns = [(t0 + int(round(s * 1e9)), t0 + int(round((s + n) * 1e9))) for s, n in win]
            for m in methods:
                row = {**base, "method": m, "outage_s": float(L), "windows": len(win)}
                if not win:  # no room for an outage of this length in good GPS
                    rows.append({**row, "solutions": 0, **_metrics(np.zeros((0, len(QUANTITIES))))})
                    continue
                res = fuse(drive, m, fused_path(out, path, m, L), cfg.replace(outages=tuple(win)), force=force,
                           keep=True)
                _, err = outage_error_series(drive, res.solution, m, win_ns)
                rows.append({**row, "solutions": res.rows, **_metrics(err)})
    return rows


def fused_path(out: Path, drive: Path, method: str, outage_s: float | None = None) -> Path:
    """Where a drive's run by ``method`` (over the whole drive, or with outages of ``outage_s``) is written."""
    return out / "fused" / (f"{drive.stem}_{method}.mcap" if outage_s is None else
                            f"{drive.stem}_{method}_{outage_s:g}s.mcap")


def failed_row(drive: str | Path, error: str) -> dict:
    return {"drive": Path(drive).stem, "path": str(drive), "status": "failed", "error": error}


def safe_drive_rows(drive: str, methods: Sequence[str], lengths: Sequence[float], out: str,
                    config: FusionConfig | None = None, force: bool = False) -> list[dict]:
    """``drive_rows``, or one failed row naming the exception (the task a worker runs)."""
    try:
        return drive_rows(drive, methods, lengths, out, config, force)
    except Exception as e:  # any bad drive: report it, keep the batch going
        last = traceback.extract_tb(e.__traceback__)[-1]
        return [failed_row(drive, f"{type(e).__name__}: {e} ({Path(last.filename).name}:{last.lineno})")]


def results_table(rows: list[dict]) -> pl.DataFrame:
    """Rows -> the results table (``RESULT_SCHEMA``), sorted by drive, method, outage length (whole drive first)."""
    table = pl.DataFrame([{k: r.get(k) for k in RESULT_SCHEMA} for r in rows], schema=RESULT_SCHEMA)
    return table.sort(["drive", "method", "outage_s"], nulls_last=False)


@contextmanager
def client_for(scheduler: str | None, workers: int) -> Iterator["object"]:
    """A Dask client: to ``scheduler``, or to a LocalCluster of ``workers`` single-threaded processes bound to
    127.0.0.1 without dashboard."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    # Dask's default MALLOC_TRIM_THRESHOLD_=65536 makes glibc hand every freed block array back to the kernel:
    # the fusion then spends about as long in page faults as in computing
    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    # dashboard off; the scheduler's bare HTTP server (health, metrics) on a free loopback port, not 8787
    no_dashboard = {"dashboard": False, "dashboard_address": "127.0.0.1:0"}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}), \
            LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                         dashboard_address=None, scheduler_kwargs=no_dashboard, silence_logs=40) as cluster, \
            Client(cluster) as client:
        yield client


@dataclass
class BatchResult:
    table: pl.DataFrame
    parquet: Path
    wall_s: float
    failed: list[str]  # drive paths


def _line(rows: list[dict]) -> str:
    if rows[0]["status"] != "ok":
        return f"FAILED  {rows[0]['error']}"
    parts = []
    for r in rows:
        tag = r["method"] + (f"@{r['outage_s']:g}s" if r["outage_s"] is not None else "")
        pos = "–" if r["pos_2d_m"] is None else f"{r['pos_2d_m']:.2f} m"
        parts.append(f"{tag} {pos}")
    return ", ".join(parts)


def run_batch(drives: Sequence[str | Path], methods: Sequence[str], lengths: Sequence[float], out: str | Path,
              scheduler: str | None = None, workers: int = 2, config: FusionConfig | None = None,
              say: Callable[[str], None] = print, progress: Callable[[float], None] | None = None,
              force: bool = False) -> BatchResult:
    """Process ``drives`` on Dask (one task per drive); writes ``out/results.parquet`` and ``out/fused/`` (new
    files unless ``force``: ``drive.outputs``). A line per drive goes to ``say`` as the drives complete, and the
    fraction done to ``progress``."""
    check_methods(list(methods))
    if not drives:
        raise ValueError("no drive to process")
    check_drive_names(drives)
    out = outputs.out_dir(Path(out).absolute())
    outputs.check_new(out / "results.parquet", force)
    for d in drives:  # every fused file too, before the first drive is read
        for m in methods:
            for L in (None, *lengths):
                outputs.check_new(fused_path(out, Path(d), m, L), force)
    paths = [str(Path(d).resolve()) for d in drives]
    t0 = time.monotonic()
    rows: list[dict] = []
    with client_for(scheduler, workers) as client:
        from distributed import as_completed

        where = scheduler or f"local cluster, {workers} workers"
        say(f"batch: {len(paths)} drives x {len(methods)} methods on {where}")
        futures = {client.submit(safe_drive_rows, p, list(methods), list(lengths), str(out), config, force,
                                 pure=False): p
                   for p in paths}
        for i, fut in enumerate(as_completed(futures), 1):
            p = futures[fut]
            try:
                got = fut.result()
            except Exception as e:  # the task itself was lost (worker died, ...)
                got = [failed_row(p, f"{type(e).__name__}: {e}")]
            rows += got
            say(f"[{i}/{len(paths)}] {time.monotonic() - t0:6.1f} s  {Path(p).name}: {_line(got)}")
            if progress:
                progress(i / len(paths))
    table = results_table(rows)
    parquet = out / "results.parquet"
    with outputs.create(parquet, force, root=out) as f:
        table.write_parquet(f)
    failed = table.filter(pl.col("status") == "failed")["path"].to_list()
    return BatchResult(table, parquet, time.monotonic() - t0, failed)


def summary(table: pl.DataFrame) -> str:
    """Mean (and worst) horizontal position and 3D velocity RMS per method and outage length over the drives."""
    ok = table.filter(pl.col("status") == "ok")
    lines = [f"{'method':<10} {'outage':>8} {'drives':>6} {'pos 2D m (mean / max)':>24} {'vel 3D m/s (mean)':>18}"]
    if len(ok):
        agg = (ok.group_by(["method", "outage_s"], maintain_order=True)
               .agg(pl.len().alias("n"), pl.col("pos_2d_m").mean().alias("p"), pl.col("pos_2d_m").max().alias("pm"),
                    pl.col("vel_3d_mps").mean().alias("v"))
               .sort(["outage_s", "method"], nulls_last=False))
        for m, L, n, p, pm, v in agg.iter_rows():
            fmt = (lambda x, d: "–" if x is None else f"{x:.{d}f}")
            lines.append(f"{m:<10} {'whole' if L is None else f'{L:g} s':>8} {n:>6} "
                         f"{fmt(p, 2) + ' / ' + fmt(pm, 2):>24} {fmt(v, 3):>18}")
    bad = table.filter(pl.col("status") == "failed")
    for path, err in bad.select("path", "error").iter_rows():
        lines.append(f"failed: {path}: {err}")
    return "\n".join(lines)
