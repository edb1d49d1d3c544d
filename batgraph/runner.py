"""Run the chosen methods on a loaded session: self-checks, each method take by take, the tables and summary.

The functions that run each method are registered here (:data:`RUN`, :data:`RUN_GTSAM`), by name as in
batgraph.methods; ``reconstruct`` (batgraph.pipeline) and each fold of the leave-one-camera-out validation
(batgraph.validate) call :func:`run_methods`. Nothing is written here.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from . import checks, evaluate, forked
from . import summary as summary_mod
from .filters.ekf import run_ekf
from .filters.ukf import run_ukf
from .measurement import IdealObservations
from .methods import get as get_method
from .result import Estimate, Options
from .session import DenseObservations, Session, dense_observations, retime
from .solver.filter import run as run_filter
from .solver.schedule import run_smoother
from .timing import scan_lags, timing_check
from .triangulate import dlt_points
from .triangulate import run as run_triangulate

RunFunction = Callable[..., Estimate]
"""``run(session, dense, ideal, options) -> Estimate`` (the filters also take ``on_frame``, see run_by_take)."""


RUN: dict[str, RunFunction] = {"smoother": run_smoother, "filter": run_filter, "ekf": run_ekf, "ukf": run_ukf,
                               "triangulate": run_triangulate}
"""The run function of each method of batgraph.methods; the smoother and filter take Options.solver ("fast", or
"gtsam": GTSAM's Levenberg-Marquardt and iSAM2 on the same cost) themselves."""


def run_function(name: str, solver: str = "fast") -> RunFunction:
    """The run function of method ``name`` (InputError for an unknown name)."""
    get_method(name)
    return RUN[name]


@dataclass
class Run:
    """What running the methods on one session produced (nothing written).

    session: the session with every warning of the run; dense: its observations on the result's frame axis;
    trajectories, reprojection: the tables of every method stacked; summary: summary.json as a dict.
    """

    session: Session
    trajectories: pd.DataFrame
    reprojection: pd.DataFrame
    summary: dict
    estimates: dict[str, Estimate] = field(default_factory=dict)
    dense: DenseObservations | None = None


def run_methods(session: Session, methods: list[str], options: Options, live=None) -> Run:
    """Run ``methods`` on a loaded session; returns tables and summary (nothing written).

    live: an optional ``viewer.LiveViewer``; the filter streams each frame to it as it goes.
    The methods are independent: with the fast solver and no live viewer they run side by side in forked
    processes (batgraph.forked.map_jobs; the first method here or in a child, its estimate pickled back),
    the first listed (the costliest of the defaults, the smoother) showing its progress.
    """
    sync = options.estimates_sync(session)
    dense = dense_observations(session, timing=True if sync else None)  # the timing's estimate needs the rows
    pre = checks.preflight(session, dense)  # raises InputError when the geometry cannot be right
    if sync:  # the lag scan first: the smoother refines offsets within a frame or so
        session, dense, pre = with_scanned_offsets(session, dense, pre)
    session = dataclasses.replace(pre.session, warnings=list(session.warnings) + pre.warnings)
    ideal = pre.ideal

    def estimate(i: int, on_frame=None, progress: bool = False) -> Estimate:
        run = run_function(methods[i], options.solver)
        t0 = time.perf_counter()
        est = run_by_take(run, session, dense, ideal, dataclasses.replace(options, progress=progress), on_frame)
        est.runtime_s = est.runtime_s or time.perf_counter() - t0
        return est

    # GTSAM's own threads (TBB) are not known to survive a fork: its solvers run one after the other
    if live is None and options.solver == "fast" and len(methods) > 1:
        ests = forked.map_jobs(lambda i: estimate(i, progress=options.progress and i == 0), len(methods))
    else:
        ests = [estimate(i, live.update if (live is not None and name == "filter") else None, options.progress)
                for i, name in enumerate(tqdm(methods, desc=f"{session.name}: methods", disable=not options.progress,
                                              leave=False))]
    estimates = dict(zip(methods, ests, strict=True))
    traj_all = pd.concat([evaluate.trajectories_table(session, dense, est) for est in ests], ignore_index=True)
    reproj_all = evaluate.reprojection_tables(session, dense, ests)  # the observations' columns gathered once
    figures, warned = dict(pre.figures), take_warnings(session, dense)
    if not sync:
        figures["timing"], timing_warnings = timing_self_check(session, ideal, estimates)
        warned = warned + timing_warnings
    summary = summary_mod.summarize(
        session, traj_all, reproj_all, runtimes={m: e.runtime_s for m, e in estimates.items()},
        infos={m: e.info for m, e in estimates.items()},
        pixel_sigma_px=dict(zip(session.rig.names, pre.sigma_px.tolist(), strict=True)),
        pixel_noise=pre.noise, checks=figures, warnings=warned)
    session.warnings[:] = summary["warnings"]  # the run's warnings join the self-checks'
    return Run(session, traj_all, reproj_all, summary, estimates, dense=dense)


def with_scanned_offsets(session: Session, dense: DenseObservations, pre: checks.Preflight) -> tuple:
    """(session, dense, preflight) with each camera's offset as the lag scan finds it (batgraph.timing.scan_lags,
    to a fraction of a frame, relative to the first camera) added to its time offset and the observations put on
    that clock: the smoother's estimate starts there. As given where no whole-frame lag is found (a rig
    synchronised to the frame starts from its stated timing)."""
    scan = scan_lags(session.rig, pre.ideal, dense.frames, session.fps)
    found = np.isfinite(scan.table["lag_frames"].to_numpy(float))
    if not (scan.table["lag_frames"].to_numpy(float)[found] != scan.table["lag_frames"].iloc[0]).any():
        return session, dense, pre
    offsets = scan.table["offset_frames"].to_numpy(float)
    lags = np.where(found, offsets - (offsets[0] if found[0] else 0.0), 0.0)
    rig = type(session.rig)([dataclasses.replace(c, time_offset_s=c.time_offset_s + lag / c.frame_rate(session.fps))
                             for c, lag in zip(session.rig, lags, strict=True)], world_mirror=session.rig.world_mirror)
    session = retime(session, rig)
    dense = dense_observations(session, timing=True)
    return session, dense, checks.preflight(session, dense)


def timing_self_check(session: Session, ideal: IdealObservations, estimates: dict[str, Estimate]) -> tuple:
    """Each camera's residuals tested for a time offset or a rolling shutter (batgraph.timing.timing_check) at
    the smoother's estimate (else the triangulation's), with velocities by np.gradient: (the table's records,
    the warnings: one line per camera out of step, naming --sync estimate)."""
    est = estimates.get("smoother")
    xyz = est.xyz_m if est is not None else dlt_points(session.rig, ideal)
    vel = np.gradient(xyz, axis=0) * session.fps if len(xyz) > 1 else np.zeros_like(xyz)
    check = timing_check(session.rig, ideal, xyz, vel, session.fps)
    lines = [summary_mod.WarningLine(w, "the residuals of that camera's observations move with its markers' "
                                     "image velocity (batgraph.timing): see summary.json checks.timing")
             for w in check.warnings]
    return check.table.to_dict("records"), lines


def take_warnings(session: Session, dense: DenseObservations) -> list[summary_mod.WarningLine]:
    """One warning when the session splits into takes (batgraph.session.frame_axis): which, and why."""
    takes = dense.take_slices
    if len(takes) == 1:
        return []
    spans = [f"{dense.frames[sl][0]}" + (f"-{dense.frames[sl][-1]}" if sl.stop - sl.start > 1 else "")
             for sl in takes]
    listed = ", ".join(spans[:2]) + (f" +{len(spans) - 2}" if len(spans) > 2 else "")
    longest = max(takes, key=lambda sl: sl.stop - sl.start)
    return [summary_mod.WarningLine(
        f"{len(takes)} takes (frames {listed}), each solved on its own; C3D/TRC hold the longest: "
        "'batgraph export c3d OUT --take N' writes another",
        f"no camera sees any marker for more than {session.take_gap_frames} frames ([session] take_gap_s = "
        f"{session.take_gap_s:g} s) between the takes, and no motion model bridges such a gap; the takes span "
        f"frames {', '.join(spans)}; the longest is frames {dense.frames[longest][0]}-{dense.frames[longest][-1]}")]


def run_by_take(run: RunFunction, session: Session, dense: DenseObservations, ideal: IdealObservations,
                options: Options, on_frame=None) -> Estimate:
    """One method's Estimate over every take of ``dense``, each take solved on its own, joined along F.

    run: the method's run function (:data:`RUN`). on_frame(frame number, xyz (M, 3), cov (M, 3, 3)):
    the filter's per-frame callback (the live viewer), given the original frame number. Takes are runs
    of frames separated by long runs without observations (batgraph.session.frame_axis): no motion model
    bridges such a gap, and a stray frame costs only its own take. With several takes, ``info`` and ``rig`` (the
    timing and poses as estimated: OUT/rig.toml) are the longest take's, plus ``takes`` in info: each take's first
    and last frame and iterations where reported.
    """
    parts = []
    for sl in dense.take_slices:
        sub = dense if len(dense.take_slices) == 1 else dense.take(sl)
        sub_ideal = ideal if sub is dense else ideal.take(sl)
        extra = {} if on_frame is None else {
            "on_frame": lambda k, xyz, cov, frames=sub.frames: on_frame(int(frames[k]), xyz, cov)}
        parts.append(run(session, sub, sub_ideal, options, **extra))
    if len(parts) == 1:
        return parts[0]
    longest = int(np.argmax([len(dense.frames[sl]) for sl in dense.take_slices]))
    info = dict(parts[longest].info)
    info["takes"] = [{"first_frame": int(dense.frames[sl][0]), "last_frame": int(dense.frames[sl][-1]),
                      **({"iterations": p.info["iterations"]} if "iterations" in p.info else {})}
                     for sl, p in zip(dense.take_slices, parts, strict=True)]
    info["info_of_take"] = longest
    return Estimate(parts[0].method, np.concatenate([p.xyz_m for p in parts]),
                    np.concatenate([p.cov_m2 for p in parts]), np.concatenate([p.outlier for p in parts], axis=1),
                    sum(p.runtime_s for p in parts), info, rig=parts[longest].rig)
