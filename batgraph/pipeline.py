"""``reconstruct``: load a session, run the chosen methods, write the contract's outputs.

The only place that knows which estimators exist and which files a result folder holds; the CLI
only parses arguments and calls :func:`reconstruct` / :func:`reconstruct_many`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from . import atomic, evaluate
from .errors import InputError
from .measurement import ideal_observations
from .result import Estimate, Options
from .session import Session, dense_observations, read_session

DEFAULT_METHODS = ("smoother", "filter")
ALL_METHODS = ("smoother", "filter", "ekf", "ukf", "triangulate")


def _estimator(name: str) -> Callable:
    """The run function of a method, imported lazily so that a slow import is paid only when used."""
    if name == "smoother":
        from .graph.smoother import run_smoother
        return run_smoother
    if name == "filter":
        from .graph.filter import run_filter
        return run_filter
    if name == "ekf":
        from .filters.ekf import run_ekf
        return run_ekf
    if name == "ukf":
        from .filters.ukf import run_ukf
        return run_ukf
    if name == "triangulate":
        from .triangulate import run
        return run
    raise InputError(f"--methods: unknown method {name!r} (choose from {', '.join(ALL_METHODS)})")


def parse_methods(text: str | None, compare: bool) -> list[str]:
    """``--methods a,b`` (+ ``--compare``) -> ordered unique method names; validates each."""
    names = [m.strip() for m in (text or ",".join(DEFAULT_METHODS)).split(",") if m.strip()]
    if compare:
        names += [m for m in ALL_METHODS if m not in names]
    for n in names:
        if n not in ALL_METHODS:
            raise InputError(f"--methods: unknown method {n!r} (choose from {', '.join(ALL_METHODS)})")
    return list(dict.fromkeys(names))


@dataclass
class Result:
    """What one reconstruct run produced (tables are also written to ``out_dir``)."""

    session: Session
    out_dir: Path
    trajectories: pd.DataFrame
    reprojection: pd.DataFrame
    summary: dict
    estimates: dict[str, Estimate] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)


def _json_default(o):
    if isinstance(o, np.integer | np.bool_):
        return o.item()
    if isinstance(o, np.floating):
        return None if not math.isfinite(o) else float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _clean(o):
    """NaN/inf -> None so summary.json is strict JSON."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_clean(v) for v in o]
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def run_methods(session: Session, methods: list[str], options: Options) -> Result:
    """Run ``methods`` on a loaded session; returns tables and summary (nothing written)."""
    dense = dense_observations(session)
    ideal = ideal_observations(session.rig, dense, session.pixel_sigma_px)
    estimates, trajs, reprojs, per_method = {}, [], [], {}
    for name in tqdm(methods, desc=f"{session.name}: methods", disable=not options.progress, leave=False):
        run = _estimator(name)
        t0 = time.perf_counter()
        est = run(session, dense, ideal, options)
        est.runtime_s = est.runtime_s or time.perf_counter() - t0
        traj = evaluate.trajectories_table(session, dense, est)
        reproj = evaluate.reprojection_table(session, dense, est)
        estimates[name], per_method[name] = est, evaluate.method_summary(session, est, traj, reproj)
        trajs.append(traj)
        reprojs.append(reproj)
    summary = {
        "session": session.name, "fps": session.fps, "n_cameras": len(session.rig),
        "n_frames": int(len(dense.frames)), "n_markers": len(dense.markers),
        "n_observations": int(dense.seen.sum()), "pixel_sigma_px": session.pixel_sigma_px,
        "views": {s: int((evaluate.status_of(dense.n_views) == s).sum()) for s in evaluate.STATUSES},
        "warnings": list(session.warnings), "methods": per_method,
    }
    return Result(session, Path(), pd.concat(trajs, ignore_index=True), pd.concat(reprojs, ignore_index=True),
                  _clean(summary), estimates)


def write_outputs(result: Result, out_dir: Path) -> list[Path]:
    """Write trajectories.csv, reprojection.csv and summary.json atomically into ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = [out_dir / "trajectories.csv", out_dir / "reprojection.csv", out_dir / "summary.json"]
    atomic.write_text(files[0], result.trajectories.to_csv(index=False, float_format="%.9g"))
    atomic.write_text(files[1], result.reprojection.to_csv(index=False, float_format="%.6f"))
    atomic.write_text(files[2], json.dumps(result.summary, indent=2, default=_json_default, allow_nan=False))
    return files


def reconstruct(session_dir: str | Path, out_dir: str | Path | None = None,
                methods: list[str] | None = None, options: Options | None = None) -> Result:
    """The ``reconstruct`` command for one session folder. Raises InputError on bad input."""
    options = options or Options()
    session = read_session(session_dir)
    out = Path(out_dir) if out_dir is not None else Path(session_dir) / "out"
    result = run_methods(session, list(methods or DEFAULT_METHODS), options)
    result.out_dir = out
    result.files = write_outputs(result, out)
    return result
