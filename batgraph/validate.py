"""Leave-one-camera-out validation: the accuracy figure a user can have without ground truth.

For every camera c (a *fold*), every method is run on the session with camera c's observations removed
(the rig stays whole), and its 3D estimate is projected into camera c (raw, distorted pixels) and compared
with camera c's own observations. A method that predicts an unseen camera well has found the points where
they are; the figures are in pixels of the held-out camera.

Definitions (also in the README):

* status of a held-out observation: the status of its (frame, marker) *in the fold*, i.e. the number of
  views without camera c: ``observed`` (>= 2), ``single_view`` (1), ``unobserved`` (0).
* subset ``common``: observations every method estimates (so that methods are compared on the same points;
  with triangulation among the methods, these are observed points only).
* subset ``smoother_only``: observations the smoother estimates and triangulation cannot (fewer than two
  other views, or triangulation failed there); every method other than triangulation that estimates all of
  them is reported on them too. Absent without the smoother.
* held_out ``all``: every camera's held-out observations pooled.

What is fixed across folds: the pixel noise (the full session's, from ``summary["pixel_sigma_px"]``: the
folds do not re-estimate it) and every option. What each fold chooses again from its own data: anything a
method estimates (e.g. the smoother's per-marker q, its outlier set). Folds run in parallel worker
processes (one per core, "spawn" start method, one BLAS and one kernel thread each), or serially, inside a
daemonic process (a Dask worker) or when they are quick (:func:`n_workers`); progress bars are off inside
folds. When the worker processes cannot run
(they re-import ``__main__``, which fails for a program read from stdin), the folds run serially here. A
fold that raises (e.g. an InputError from a self-check) is reported as failed for that camera; the others
go on.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from .evaluate import STATUSES, status_of
from .forked import usable_cores
from .result import Options
from .session import Session

SUBSETS = ("common", "smoother_only")
COLUMNS = ["held_out", "method", "status", "subset", "n", "median_px", "p90_px"]
POOLED = "all"  # held_out value of the rows that pool every camera
CSV_NAME = "validation.csv"


@dataclass
class Validation:
    """The outcome of :func:`validate_session`.

    table: tidy, COLUMNS; one row per (held_out, method, status, subset) with n > 0, n = held-out
        observations, median_px / p90_px = median and 90th percentile of |projection - observation| [px]
        in the held-out camera. Cameras in rig order, then ``all``.
    points: one row per held-out observation: held_out, frame, marker, status (in the fold), u, v [px], and
        per method ``err_px_<method>`` (NaN where the method gives no estimate); plus bool ``common`` and
        ``smoother_only``.
    failed: camera -> one-line message, for folds that raised.
    pixel_sigma_px: the pixel noise every fold used (float or {camera: sigma}).
    """

    table: pd.DataFrame
    points: pd.DataFrame
    methods: list[str]
    cameras: list[str]
    failed: dict[str, str] = field(default_factory=dict)
    runtime_s: float = 0.0
    workers: int = 1
    pixel_sigma_px: object = None

    def verdict(self) -> str:
        """One line: smoother vs triangulation (or the methods' medians) on common observed points, pooled,
        the smoother's figure where triangulation cannot estimate, and the camera with the largest error."""
        return verdict(self.table, self.methods, self.failed)

    def to_summary(self) -> dict:
        """summary.json's ``validation`` section (strict JSON: no NaN)."""
        return {
            "methods": list(self.methods), "cameras": list(self.cameras),
            "verdict": self.verdict(), "failed": dict(self.failed), "runtime_s": round(self.runtime_s, 3),
            "workers": self.workers, "pixel_sigma_px": self.pixel_sigma_px,
            "table": table_records(self.table),
        }


# ----------------------------------------------------------------------------------------------
# one fold
# ----------------------------------------------------------------------------------------------
def held_out_session(session: Session, camera: str, pixel_sigma_px=None) -> Session:
    """The session without ``camera``'s observations; the rig and everything else unchanged.

    pixel_sigma_px: the noise to use (float, or {camera: sigma}); None keeps the session's. Truth, reference
    and planted mislabels are dropped (a fold needs none of them, and their statistics cost time).
    """
    obs = session.observations
    return dataclasses.replace(
        session, observations=obs[obs["camera"] != camera].reset_index(drop=True),
        truth=None, reference=None, mislabels=None,
        pixel_sigma_px=session.pixel_sigma_px if pixel_sigma_px is None else pixel_sigma_px,
        warnings=[])


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


def run_fold(session: Session, camera: str, methods: list[str], options: Options,
             pixel_sigma_px=None) -> tuple[str, pd.DataFrame | None, str | None]:
    """Fold ``camera``: (camera, per-observation errors or None, failure message or None); never raises.

    The per-observation table has held_out, frame, marker, status, u, v, and err_px_<method> for each
    method. Module-level so that worker processes import it by name.
    """
    from .pipeline import run_methods

    obs_c = session.observations[session.observations["camera"] == camera]
    fold = held_out_session(session, camera, pixel_sigma_px)
    if len(obs_c) == 0:
        return camera, None, "no observations in this camera"
    if len(fold.observations) == 0:
        return camera, None, "no observations in the other cameras"
    try:
        result = run_methods(fold, list(methods), dataclasses.replace(options, progress=False))
    except Exception as e:  # noqa: BLE001 - a failing fold is reported for its camera, never stops the others
        return camera, None, _one_line(e)
    d = result.dense
    F, M = len(d.frames), len(d.markers)
    frame = obs_c["frame"].to_numpy()
    fi = np.minimum(np.searchsorted(d.frames, frame), F - 1)  # the fold's (compacted) frame axis; F > 0 here
    mi = obs_c["marker"].map({m: j for j, m in enumerate(d.markers)}).to_numpy(float)
    ok = (d.frames[fi] == frame) & np.isfinite(mi)  # a frame or marker only this camera saw is not in the fold
    fi, mi = np.where(ok, fi, 0).astype(int), np.where(ok, mi, 0).astype(int)
    n_views = np.where(ok, d.n_views[fi, mi] if F and M else 0, 0)
    uv = obs_c[["u", "v"]].to_numpy(float)
    cam = session.rig[camera]
    out = pd.DataFrame({"held_out": camera, "frame": obs_c["frame"].to_numpy(), "marker": obs_c["marker"].to_numpy(),
                        "status": status_of(n_views), "u": uv[:, 0], "v": uv[:, 1]})
    for name in methods:
        xyz = np.where(ok[:, None], result.estimates[name].xyz_m[fi, mi], np.nan)
        out[f"err_px_{name}"] = np.linalg.norm(cam.project(xyz) - uv, axis=-1)
    return camera, out, None


# ----------------------------------------------------------------------------------------------
# all folds
# ----------------------------------------------------------------------------------------------
SERIAL_BELOW_S = 5.0
"""Automatic worker count: folds expected to take less than this in all [s] run serially, because starting
worker processes (a fresh interpreter importing numpy, pandas, GTSAM: ~1-2 s each) would cost more."""


def n_workers(n_folds: int, workers: int | None = None, expected_s: float | None = None) -> int:
    """Processes for ``n_folds`` folds: ``workers`` if given, else one per core; 1 inside a daemonic process
    (a Dask or multiprocessing worker may not start children) or when the folds are expected to take less
    than SERIAL_BELOW_S in all (expected_s: that expectation, e.g. the full run's time x folds)."""
    if workers is not None:
        return max(1, min(int(workers), n_folds))
    if multiprocessing.current_process().daemon:
        return 1
    if expected_s is not None and expected_s < SERIAL_BELOW_S:
        return 1
    return max(1, min(usable_cores(), n_folds))


def _expected_s(summary: dict | None, methods: list[str], n_folds: int) -> float | None:
    """The folds' expected serial time [s]: the full run's estimation time per method x folds, or None."""
    times = [((summary or {}).get("methods") or {}).get(m, {}).get("runtime_s") for m in methods]
    if not times or any(not isinstance(t, int | float) for t in times):
        return None
    return float(sum(times)) * n_folds


def _init_worker() -> None:
    # One BLAS thread, one kernel thread and no forked children (batgraph.forked) per process: the folds
    # already use every core.
    from threadpoolctl import threadpool_limits

    from . import forked
    from .solver import threads as kernels

    threadpool_limits(1)
    kernels.set_threads(1)
    os.environ[forked.ENV] = "0"


def fold_pixel_sigma(session: Session, summary: dict | None):
    """The pixel noise the folds use: the full run's (``summary["pixel_sigma_px"]``: {camera: sigma} or a
    number) when present, else the session's own."""
    used = (summary or {}).get("pixel_sigma_px")
    if isinstance(used, dict):
        return dict(used)
    if isinstance(used, int | float) and not isinstance(used, bool) and math.isfinite(used):
        return float(used)
    return session.pixel_sigma_px


def validate_session(session: Session, methods: list[str], options: Options | None = None, *,
                     summary: dict | None = None, workers: int | None = None,
                     progress: bool | None = None) -> Validation:
    """Leave-one-camera-out validation of ``methods`` on a loaded session (see the module docstring).

    summary: the full session's run_methods summary; its ``pixel_sigma_px`` is reused by every fold. Without
        it, and when the session's pixel_sigma_px is None (estimate it), the full session is first run with
        triangulation only, to estimate the noise once.
    workers: processes (None: one per core, or serial on one core or when the full run in ``summary`` says
        the folds are quick, see :func:`n_workers`; 1: serial, in this process).
    progress: a bar over folds (default: options.progress).
    """
    from .pipeline import run_methods

    options = options or Options()
    progress = options.progress if progress is None else progress
    methods = list(dict.fromkeys(methods))
    t0 = time.perf_counter()
    if summary is None and session.pixel_sigma_px is None:
        summary = run_methods(session, ["triangulate"], dataclasses.replace(options, progress=False)).summary
    sigma = fold_pixel_sigma(session, summary)
    cameras = session.rig.names
    n = n_workers(len(cameras), workers, _expected_s(summary, methods, len(cameras)))
    fold_opts = dataclasses.replace(options, progress=False)
    results: dict[str, tuple[pd.DataFrame | None, str | None]] = {}
    bar = tqdm(total=len(cameras), desc=f"{session.name}: validation folds", disable=not progress, leave=False)
    if n == 1:
        for cam in cameras:
            _, pts, err = run_fold(session, cam, methods, fold_opts, sigma)
            results[cam] = (pts, err)
            bar.update()
    else:
        ctx = multiprocessing.get_context("spawn")  # no fork of a process that may hold threads (BLAS, tqdm)
        broken = []
        with ProcessPoolExecutor(n, mp_context=ctx, initializer=_init_worker) as pool:
            futures = {pool.submit(run_fold, session, cam, methods, fold_opts, sigma): cam for cam in cameras}
            for fut in as_completed(futures):
                cam = futures[fut]
                try:
                    _, pts, err = fut.result()
                except BrokenProcessPool:  # workers could not start (e.g. a __main__ they cannot re-import) or died
                    broken.append(cam)
                    continue
                except Exception as e:  # noqa: BLE001 - e.g. a fold result that cannot be unpickled
                    pts, err = None, _one_line(e)
                results[cam] = (pts, err)
                bar.update()
        for cam in cameras:  # in rig order: those folds run here instead
            if cam in broken:
                _, pts, err = run_fold(session, cam, methods, fold_opts, sigma)
                results[cam] = (pts, err)
                bar.update()
        if broken and len(broken) == len(cameras):
            n = 1
    bar.close()
    failed = {c: results[c][1] for c in cameras if results[c][1] is not None}
    parts = [results[c][0] for c in cameras if results[c][0] is not None]
    points = mark_subsets(pd.concat(parts, ignore_index=True) if parts else _empty_points(methods), methods)
    table = summarise(points, methods, cameras)
    return Validation(table, points, methods, cameras, failed, time.perf_counter() - t0, n,
                      sigma if not isinstance(sigma, np.floating) else float(sigma))


def leave_one_camera_out(session: Session, methods: list[str], options: Options | None = None,
                         **kwargs) -> pd.DataFrame:
    """The tidy table of :func:`validate_session` (COLUMNS); ``table.attrs["failed"]``: camera -> message."""
    v = validate_session(session, methods, options, **kwargs)
    v.table.attrs["failed"] = dict(v.failed)
    return v.table


# ----------------------------------------------------------------------------------------------
# statistics
# ----------------------------------------------------------------------------------------------
def _empty_points(methods: list[str]) -> pd.DataFrame:
    cols = ["held_out", "frame", "marker", "status", "u", "v"] + [f"err_px_{m}" for m in methods]
    return pd.DataFrame({c: pd.Series(dtype=float if c.startswith(("err", "u", "v")) else object) for c in cols})


def mark_subsets(points: pd.DataFrame, methods: list[str]) -> pd.DataFrame:
    """Add bool columns ``common`` (every method has an error) and ``smoother_only`` (the smoother has one,
    triangulation has none: by its own result when it ran, else where the fold has < 2 views)."""
    err = {m: np.isfinite(points[f"err_px_{m}"].to_numpy(float)) for m in methods}
    points["common"] = np.logical_and.reduce(list(err.values())) if err else np.zeros(len(points), bool)
    if "smoother" in methods:
        tri = err["triangulate"] if "triangulate" in methods else (points["status"] == "observed").to_numpy()
        points["smoother_only"] = err["smoother"] & ~tri
    else:
        points["smoother_only"] = np.zeros(len(points), bool)
    return points


def _stats(e: np.ndarray) -> tuple[int, float, float]:
    return len(e), float(np.median(e)), float(np.percentile(e, 90))


def summarise(points: pd.DataFrame, methods: list[str], cameras: list[str]) -> pd.DataFrame:
    """The tidy table (COLUMNS) from the per-observation errors (see :class:`Validation`)."""
    rows = []
    others = [m for m in methods if m != "triangulate"]
    for held_out in [*cameras, POOLED]:
        p = points if held_out == POOLED else points[points["held_out"] == held_out]
        for status in STATUSES:
            ps = p[p["status"] == status]
            for subset in SUBSETS:
                if subset == "common":
                    sel, ms = ps[ps["common"]], methods
                elif "smoother" in methods:
                    sel = ps[ps["smoother_only"]]
                    sel = sel[np.logical_and.reduce([np.isfinite(sel[f"err_px_{m}"]) for m in others])]
                    ms = others
                else:
                    continue
                if not len(sel):
                    continue
                for m in ms:
                    n, med, p90 = _stats(sel[f"err_px_{m}"].to_numpy(float))
                    rows.append([held_out, m, status, subset, n, med, p90])
    return pd.DataFrame(rows, columns=COLUMNS).astype({"n": int})


def table_records(table: pd.DataFrame) -> list[dict]:
    """The table as JSON records (NaN -> None)."""
    recs = table.to_dict(orient="records")
    return [{k: (None if isinstance(v, float) and not math.isfinite(v) else
                 int(v) if isinstance(v, np.integer) else v) for k, v in r.items()} for r in recs]


def _row(table: pd.DataFrame, held_out: str, method: str, status: str, subset: str) -> dict | None:
    t = table[(table["held_out"] == held_out) & (table["method"] == method) & (table["status"] == status)
              & (table["subset"] == subset)]
    return None if t.empty else t.iloc[0].to_dict()


def verdict(table: pd.DataFrame, methods: list[str], failed: dict[str, str] | None = None) -> str:
    """The one-line verdict of a validation table (see :meth:`Validation.verdict`)."""
    parts = []
    if "smoother" in methods and "triangulate" in methods:
        s, t = (_row(table, POOLED, m, "observed", "common") for m in ("smoother", "triangulate"))
        if s and t:
            parts.append(f"smoother vs triangulate on common observed points (n={s['n']}, cameras pooled): "
                         f"median {s['median_px']:.2f} px vs {t['median_px']:.2f} px, "
                         f"p90 {s['p90_px']:.2f} px vs {t['p90_px']:.2f} px")
    elif methods:
        got = [(m, _row(table, POOLED, m, "observed", "common")) for m in methods]
        got = [(m, r) for m, r in got if r]
        if got:
            parts.append(f"median on common observed points (n={got[0][1]['n']}, cameras pooled): "
                         + ", ".join(f"{m} {r['median_px']:.2f} px" for m, r in got))
    if "smoother" in methods:
        so = table[(table["held_out"] == POOLED) & (table["method"] == "smoother")
                   & (table["subset"] == "smoother_only")]
        if len(so):
            n = int(so["n"].sum())
            parts.append(f"where triangulation cannot estimate (n={n}): smoother median "
                         + ", ".join(f"{r.median_px:.2f} px ({r.status.replace('_', ' ')})" for r in so.itertuples()))
    ref = "smoother" if "smoother" in methods else (methods[0] if methods else None)
    per_cam = table[(table["held_out"] != POOLED) & (table["method"] == ref) & (table["status"] == "observed")
                    & (table["subset"] == "common")].sort_values("median_px", ascending=False)
    if len(per_cam) >= 2:
        a, b = per_cam.iloc[0], per_cam.iloc[1]
        parts.append(f"largest held-out error: {a['held_out']} ({ref} median {a['median_px']:.2f} px; "
                     f"next {b['held_out']} {b['median_px']:.2f} px)")
    if failed:
        parts.append("failed folds: " + ", ".join(f"{c} ({m})" for c, m in failed.items()))
    return "; ".join(parts) if parts else "no held-out observation could be predicted"


# ----------------------------------------------------------------------------------------------
# presentation
# ----------------------------------------------------------------------------------------------
def _groups(table: pd.DataFrame) -> list[tuple[str, str]]:
    present = set(zip(table["status"], table["subset"], strict=True))
    return [(st, sub) for sub in SUBSETS for st in STATUSES if (st, sub) in present]


def group_label(status: str, subset: str) -> str:
    """Short column-group title, e.g. 'observed, common' / '1-view, no triangulation'."""
    st = {"observed": "observed", "single_view": "1-view", "unobserved": "0-view"}[status]
    return f"{st}, {'common' if subset == 'common' else 'no triangulation'}"


def format_table(table: pd.DataFrame) -> list[str]:
    """Terminal lines: one row per (held-out camera, method); per (status, subset) group n, median, p90 [px]."""
    if table.empty:
        return ["validation: no held-out observation could be predicted"]
    groups = _groups(table)
    cams = list(dict.fromkeys(table["held_out"]))
    wc = max(len("held out"), *(len(str(c)) for c in cams))
    wm = max(len("method"), *(len(str(m)) for m in table["method"]))
    head1 = f"{'':<{wc}}  {'':<{wm}}" + "".join(f"{group_label(*g):>27}" for g in groups)
    head2 = f"{'held out':<{wc}}  {'method':<{wm}}" + "".join(f"{'n':>11}{'med px':>8}{'p90 px':>8}" for _ in groups)
    lines = [head1, head2]
    idx = table.set_index(["held_out", "method", "status", "subset"])
    for cam in cams:
        for m in dict.fromkeys(table.loc[table["held_out"] == cam, "method"]):
            line = f"{str(cam):<{wc}}  {m:<{wm}}"
            for st, sub in groups:
                if (cam, m, st, sub) in idx.index:
                    r = idx.loc[(cam, m, st, sub)]
                    line += f"{int(r['n']):>11}{r['median_px']:>8.2f}{r['p90_px']:>8.2f}"
                else:
                    line += f"{'-':>11}{'-':>8}{'-':>8}"
            lines.append(line)
    return lines


def write_csv(table: pd.DataFrame, path) -> None:
    """validation.csv (COLUMNS), atomically."""
    from .formats import csv_text

    csv_text.write_csv(path, table[COLUMNS], "%.4f")
