"""Leave-one-camera-out validation: the accuracy figure a user can have without ground truth.

For every camera c (a *fold*), every method is run on the session with camera c's observations removed
(the rig stays whole), and its 3D estimate is projected into camera c (raw, distorted pixels) and compared
with camera c's own observations; the table of these errors is batgraph.validation_table's. Fixed across
folds: the full session's pixel noise (``summary["pixel_sigma_px"]``) and every option; chosen again by
each fold: whatever a method estimates (the smoother's noise levels, its outliers). Folds run in worker
processes (one per core, "spawn", one BLAS and one kernel thread each), or serially inside a daemonic
process, when they are quick (:func:`n_workers`), or when the workers cannot start (a ``__main__`` read
from stdin). A fold that raises is reported as failed for its camera; the others go on.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pandas as pd
from threadpoolctl import threadpool_limits
from tqdm.auto import tqdm

from . import forked
from .evaluate import status_of
from .result import Options
from .runner import run_methods
from .session import Session
from .solver import threads as kernels
from .validation_table import Validation, empty_points, mark_subsets, summarise


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
    return max(1, min(forked.usable_cores(), n_folds))


def _expected_s(summary: dict | None, methods: list[str], n_folds: int) -> float | None:
    """The folds' expected serial time [s]: the full run's estimation time per method x folds, or None."""
    times = [((summary or {}).get("methods") or {}).get(m, {}).get("runtime_s") for m in methods]
    if not times or any(not isinstance(t, int | float) for t in times):
        return None
    return float(sum(times)) * n_folds


def _init_worker() -> None:
    # One BLAS thread, one kernel thread and no forked children (batgraph.forked) per process: the folds
    # already use every core.
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
    points = mark_subsets(pd.concat(parts, ignore_index=True) if parts else empty_points(methods), methods)
    table = summarise(points, methods, cameras)
    return Validation(table, points, methods, cameras, failed, time.perf_counter() - t0, n,
                      sigma if not isinstance(sigma, np.floating) else float(sigma))
