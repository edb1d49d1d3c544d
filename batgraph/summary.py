"""summary.json as types: every figure a user reads is computed here once, from the result tables.

The terminal table (cli), the report and batch read a :class:`Summary` (or its JSON) and never recompute.
Layout of summary.json (``Summary.to_json``; strict JSON, NaN -> null):

* session facts: session, fps, n_cameras, n_frames, n_markers, n_observations, views, spans
* pixel_sigma_px, pixel_noise, checks, world, import, warnings (self-checks and noise-model warnings)
* paper_experiment: "flight" / "ear" when the session is one of the paper's scenes (session.toml
  ``[paper] experiment``, or the simulator's ``[simulation] scene``), else null: the paper's
  published figures are shown only then, never guessed from the session name.
* methods: per method (batgraph.evaluate.method_summary): runtime_s, n_estimated, n_points, reprojection
  (per camera, inlier statistics and outlier counts), truth / reference (per group: all, each status, each
  span, each status/span), info.
* comparison: like-for-like: per group, the points *every* compared method estimates, their count n, and
  each method's figure on exactly those points (against truth, else a reference, else reprojection).
* verdict: which result to use and why, its headline accuracy, and the warnings that bear on it.
* validation: leave-one-camera-out (batgraph.validate), when run.

Groups: ``all``; a status (observed / single_view / unobserved); a span (inside / outside); or
``status/span`` (e.g. ``single_view/inside``: gaps inside a track seen by one camera).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
import pandas as pd

from . import methods as methods_registry
from .evaluate import (
    GROUPS,
    SPANS,
    STATUSES,
    add_span,
    errors_by_method,
    group_masks,
    method_rows,
    method_summary,
    point_errors,
)
from .motion import CHI2_3DOF_95

OUTLIER_WARN_FRACTION = 0.05
"""A camera with more than this fraction of its observations flagged as outliers (by the recommended
method) gets a warning: the noise model or the calibration of that camera is suspect."""
RIGID_WARN_FACTOR = 3.0
"""A rigid segment whose length scatters by more than this x rigid_sigma_m RMS is warned about
(:func:`smoother_warnings`); measured on simulated bones (truly rigid, 1 px): 0.3-0.8 mm at 2 mm."""


HEADLINE_GROUPS = {
    "observed/inside": "seen by >= 2 cameras",
    "single_view/inside": "gaps seen by 1 camera",
    "unobserved/inside": "gaps seen by none",
    "outside": "track ends (extrapolated)",
}
"""The groups a user reads first (terminal table, report), with their plain names; together they cover every
point once (observed points are always inside a span)."""


@dataclass
class GroupComparison:
    """Methods compared on the same points of one group.

    n: points (truth/reference) or observations (reprojection) every compared method estimates.
    values: the compared methods (those with any estimate in the group) -> {"rmse_m", "coverage95"}
        (truth), {"rms_m"} (reference) or {"median_px", "mean_px"} (reprojection).
    """

    n: int
    values: dict[str, dict[str, float | None]]


@dataclass
class Comparison:
    """Like-for-like comparison of ``methods`` (registry order) ``against`` truth, reference or reprojection."""

    methods: list[str]
    against: str
    groups: dict[str, GroupComparison] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"methods": self.methods, "against": self.against,
                "groups": {g: asdict(c) for g, c in self.groups.items()}}

    @classmethod
    def from_json(cls, d: dict | None) -> Comparison | None:
        if not d:
            return None
        return cls(list(d["methods"]), d["against"],
                   {g: GroupComparison(int(c["n"]), c["values"]) for g, c in d.get("groups", {}).items()})


@dataclass
class Verdict:
    """Which result to use, why, how good it is, and what to look at first.

    use: a method name; why: one sentence; headline: one sentence with the accuracy figure and where it
    comes from (validation, truth, or reprojection); warnings: lines that bear on this result.
    """

    use: str
    why: str
    headline: str
    warnings: list[str] = field(default_factory=list)


def _finite(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def compare(trajectories: pd.DataFrame, reprojection: pd.DataFrame, methods: list[str],
            truth: pd.DataFrame | None = None, reference: pd.DataFrame | None = None,
            joined: dict[str, pd.DataFrame] | None = None) -> Comparison | None:
    """Each method's figure on the points every method in ``methods`` estimates, per group.

    trajectories, reprojection: the contract's tables (every method stacked). Against truth: RMSE [m] and
    95 % coverage; else against a reference: RMS difference [m]; else the reprojection error [px] of the
    observations of the common points that no compared method flags as an outlier. None for < 2 methods.
    joined: per method, the trajectories joined with the truth (else the reference) where the caller has
    them (batgraph.evaluate.errors_by_method).
    """
    rows = method_rows(trajectories)
    methods = [m for m in methods_registry.ordered(methods) if m in rows]
    if len(methods) < 2:
        return None
    points = truth if truth is not None else reference
    if points is not None:
        joined = errors_by_method(trajectories, points) if joined is None else joined
        errs = {m: point_errors(trajectories.iloc[rows[m]], points, joined.get(m)).set_index(["frame", "marker"])
                for m in methods}
        out = Comparison(methods, "truth" if truth is not None else "reference")
        masks = {m: group_masks(e) for m, e in errs.items()}
        for g in GROUPS:
            idx = {m: e.index[masks[m][g]] for m, e in errs.items()}
            _add_group(out, g, idx, lambda m, sel: _point_figures(errs[m].loc[sel], truth is not None))
        return out
    # reprojection: observations (frame, camera, marker) of the group a method reprojects and does not flag
    keys = ["frame", "camera", "marker"]
    tabs = {}
    rep_rows = method_rows(reprojection)
    for m in methods:
        t = (reprojection.iloc[rep_rows[m]] if m in rep_rows else reprojection.iloc[:0]).set_index(keys)
        ok = np.isfinite(t["err_px"].to_numpy(float)) & ~t["outlier"].fillna(False).astype(bool).to_numpy()
        tabs[m] = pd.concat([t[ok].reset_index(), _status_of_observations(trajectories, m, t.index[ok])],
                            axis=1).set_index(keys)
    out = Comparison(methods, "reprojection")
    masks = {m: group_masks(t) for m, t in tabs.items()}
    for g in GROUPS:
        idx = {m: t.index[masks[m][g]] for m, t in tabs.items()}
        _add_group(out, g, idx, lambda m, sel: _pixel_figures(tabs[m].loc[sel, "err_px"].to_numpy(float)))
    return out


def _add_group(out: Comparison, group: str, index: dict[str, pd.Index], figures) -> None:
    """Add ``group`` to ``out``: the methods with any point in it, compared on the points all of them have.

    A method that estimates nothing in the group (triangulation where one camera sees the marker) is left
    out of that group rather than shrinking it to nothing; the group lists the methods it compares.
    """
    present = [m for m in out.methods if len(index[m])]
    if len(present) < 2:
        return
    common = index[present[0]]
    for m in present[1:]:
        common = common.intersection(index[m])
    if len(common):
        out.groups[group] = GroupComparison(int(len(common)), {m: figures(m, common) for m in present})


def _point_figures(e: pd.DataFrame, with_truth: bool) -> dict:
    err = e["err_m"].to_numpy(float)
    rms = _finite(np.sqrt(np.mean(err**2)))
    if not with_truth:
        return {"rms_m": rms}
    d2 = e["mahal2"].to_numpy(float)
    has = np.isfinite(d2)
    return {"rmse_m": rms, "coverage95": float(np.mean(d2[has] <= CHI2_3DOF_95)) if has.any() else None}


def _pixel_figures(e: np.ndarray) -> dict:
    return {"median_px": _finite(np.median(e)), "mean_px": _finite(np.mean(e))}


def _status_of_observations(trajectories: pd.DataFrame, method: str, index: pd.MultiIndex) -> pd.DataFrame:
    """status and span of each (frame, camera, marker) observation's point, row-aligned with index."""
    t = trajectories[trajectories["method"] == method].set_index(["frame", "marker"])[["status", "span"]]
    fm = pd.MultiIndex.from_arrays([index.get_level_values("frame"), index.get_level_values("marker")])
    return t.reindex(fm).reset_index(drop=True)


def recommended(methods: list[str]) -> tuple[str, str]:
    """(method to use, why): the smoother when it ran, else the first of the registry's order."""
    if "smoother" in methods:
        return "smoother", ("it uses every frame and every camera at once (the filters only the past, "
                            "triangulation one frame), and it estimates the points seen by fewer than two "
                            "cameras with an honest covariance")
    first = methods_registry.ordered(methods)[0]
    return first, "the smoother did not run; this is the first of the methods that did, in batgraph's order"


def outlier_warnings(method_summary: dict, method: str) -> list[str]:
    """One line per camera where ``method`` flagged more than OUTLIER_WARN_FRACTION of the observations."""
    out = []
    for cam, s in (method_summary.get("reprojection") or {}).items():
        n, k = s.get("n", 0) or 0, s.get("n_outliers", 0) or 0
        if n + k and k / (n + k) > OUTLIER_WARN_FRACTION:
            out.append(f"camera {cam}: the {method} flagged {k} of its {n + k} observations "
                       f"({100 * k / (n + k):.0f} %) as outliers (more than {100 * OUTLIER_WARN_FRACTION:.0f} %): "
                       "check this camera's calibration, synchronisation and marker labels")
    return out


#: The smoother's own notes (its info) that summary.json lists as warnings, each one line of text.
SMOOTHER_NOTES = ("segments_left_out", "wingbeat_left_out", "wingbeat_advice")


def smoother_warnings(info: dict | None) -> list[str]:
    """One line per rigid segment (``[markers] rigid``) whose length scatters over the frames by more than
    RIGID_WARN_FACTOR x rigid_sigma_m RMS at the smoother's solution or, beyond the triangulation's noise, in the
    per-frame triangulation (graph.rigid.triangulated_excess): the pair is not rigid, or a label is
    swapped, and the segment factor is pulling the two markers toward a length they do not keep. Before
    them, the smoother's notes (:data:`SMOOTHER_NOTES`): why it left the segments out, or the wingbeat
    model's oscillation for want of a frequency, or that the tracks move periodically and its motion model
    does not follow that (batgraph.graph.schedule.periodic_advice)."""
    info = info or {}
    sigma = info.get("rigid_sigma_m")
    out = [info[key] for key in SMOOTHER_NOTES if info.get(key)]
    for name, s in (info.get("segments") or {}).items():
        scatter = max(s["scatter_rms_m"], s.get("triangulated_excess_m") or 0.0)
        if sigma and scatter > RIGID_WARN_FACTOR * sigma:
            out.append(f"segment {name}: its length varies by {1000 * scatter:.1f} mm RMS over the frames, "
                       f"more than {RIGID_WARN_FACTOR:g} x [markers] rigid_sigma_m = {1000 * sigma:g} mm: these two "
                       "markers are not on one rigid segment, or a label is swapped; check [markers] rigid")
    return out


def _mm(x) -> str:
    return "-" if x is None else f"{1000 * x:.2f} mm"


def headline(summary: dict, use: str) -> str:
    """The headline accuracy of method ``use``: held-out-camera error when validated, truth RMSE when known,
    the difference to a reference when there is one, and the inlier reprojection error (median over cameras
    of each camera's median)."""
    parts = []
    v = summary.get("validation") or {}
    rows = [r for r in v.get("table") or [] if r.get("held_out") == "all" and r.get("method") == use
            and r.get("status") == "observed" and r.get("subset") == "common"]
    if rows and rows[0].get("median_px") is not None:
        r = rows[0]
        parts.append(f"held-out-camera error {r['median_px']:.2f} px median, {r['p90_px']:.2f} px p90 "
                     f"(n={r['n']}, each camera predicted from the others)")
    m = (summary.get("methods") or {}).get(use) or {}
    t = m.get("truth")
    if t:
        parts.append("against truth: RMSE " + ", ".join(
            f"{_mm(t['rmse_m'].get(g))} {where} (n={t['n_estimated'].get(g, 0)})"
            for g, where in (("observed/inside", "where seen by >= 2 cameras"),
                             ("single_view/inside", "in one-camera gaps"), ("unobserved/inside", "in unseen gaps"),
                             ("outside", "at track ends"))
            if t["n_estimated"].get(g)))
    ref = m.get("reference") or {}
    if ref.get("n"):
        parts.append(f"{_mm(ref.get('rms_m'))} RMS from the reference 3D (reference_xyz.csv, n={ref['n']})")
    rep = [c for c in (m.get("reprojection") or {}).values() if c.get("median_px") is not None]
    if rep:
        med = float(np.median([c["median_px"] for c in rep]))
        mm = [c["median_mm_at_depth"] for c in rep if c.get("median_mm_at_depth") is not None]
        parts.append(f"reprojection error {med:.2f} px median over cameras"
                     + (f" (about {float(np.median(mm)):.2f} mm at the markers' depth)" if mm else ""))
    return "; ".join(parts) if parts else "no accuracy figure (no observation could be reprojected)"


def verdict(summary: dict) -> Verdict:
    """The verdict from a summary dict whose methods (and validation, when run) are filled in."""
    methods = list(summary.get("methods") or {})
    use, why = recommended(methods)
    warnings = list(summary.get("warnings") or [])
    return Verdict(use, why, headline(summary, use), warnings)


@dataclass
class Summary:
    """The typed summary.json (see the module docstring); ``to_json`` / ``from_json`` are exact inverses
    for the keys listed here (a JSON written by an older batgraph reads with the missing ones None/empty)."""

    session: str
    fps: float
    n_cameras: int
    n_frames: int
    n_markers: int
    n_observations: int
    views: dict[str, int]
    spans: dict[str, int]
    pixel_sigma_px: dict[str, float]
    pixel_noise: dict
    checks: dict
    world: dict
    imported: dict
    warnings: list[str]
    paper_experiment: str | None
    methods: dict[str, dict]
    comparison: Comparison | None = None
    verdict: Verdict | None = None
    validation: dict | None = None

    def to_json(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("imported", "comparison",
                                                                               "verdict", "validation")}
        d["import"] = self.imported
        d["comparison"] = self.comparison.to_json() if self.comparison else None
        d["verdict"] = asdict(self.verdict) if self.verdict else None
        if self.validation is not None:
            d["validation"] = self.validation
        return clean(d)

    @classmethod
    def from_json(cls, d: dict) -> Summary:
        plain = {k: d.get(k) for k in cls.__dataclass_fields__
                 if k not in ("imported", "comparison", "verdict", "validation")}
        for k in ("views", "spans", "pixel_sigma_px", "pixel_noise", "checks", "world", "methods"):
            plain[k] = plain[k] or {}
        plain["warnings"] = plain["warnings"] or []
        v = d.get("verdict")
        return cls(**plain, imported=d.get("import") or {}, comparison=Comparison.from_json(d.get("comparison")),
                   verdict=Verdict(**v) if v else None, validation=d.get("validation"))


def summarize(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame, *,
              runtimes: dict[str, float] | None = None, infos: dict[str, dict] | None = None,
              pixel_sigma_px: dict[str, float] | None = None, pixel_noise: dict | None = None,
              checks: dict | None = None) -> dict:
    """summary.json (as a dict) computed once from the result tables: every method's figures, the like-for-like
    comparison and the verdict. Adds a noise-model warning (:func:`outlier_warnings`) to the session's warnings.

    session: batgraph.session.Session (rig, truth, reference, warnings, extra_toml); trajectories, reprojection:
    the contract's tables, every method stacked (trajectories with status and span); runtimes, infos: per
    method, from the estimators; pixel_sigma_px, pixel_noise, checks: from the self-checks (batgraph.checks).
    """
    if "span" not in trajectories.columns:
        trajectories = add_span(trajectories)
    rows, rep_rows = method_rows(trajectories), method_rows(reprojection)
    methods = methods_registry.ordered(rows)
    # each method's rows by position, and the join with the truth / reference once for every method
    traj_of = {m: trajectories.iloc[rows[m]] for m in methods}
    rep_of = {m: reprojection.iloc[rep_rows[m]] if m in rep_rows else reprojection.iloc[:0] for m in methods}
    truth_errors = errors_by_method(trajectories, session.truth) if session.truth is not None else {}
    ref_errors = errors_by_method(trajectories, session.reference) if session.reference is not None else {}
    per_method = {}
    for m in methods:
        per_method[m] = method_summary(session, traj_of[m], rep_of[m], (runtimes or {}).get(m), (infos or {}).get(m),
                                       truth_errors=truth_errors.get(m), reference_errors=ref_errors.get(m))
    use = recommended(methods)[0] if methods else None
    warnings = list(session.warnings)
    if use is not None:
        warnings += [w for w in outlier_warnings(per_method[use], use) + smoother_warnings((infos or {}).get(use))
                     if w not in warnings]
    first = traj_of[methods[0]] if methods else trajectories
    reproj_first = rep_of[methods[0]] if methods else reprojection
    summary = Summary(
        session=session.name, fps=float(session.fps), n_cameras=len(session.rig),
        n_frames=int(first["frame"].nunique()), n_markers=int(first["marker"].nunique()),
        n_observations=int(len(reproj_first)),
        views={s: int((first["status"] == s).sum()) for s in STATUSES},
        spans={s: int((first["span"] == s).sum()) for s in SPANS},
        pixel_sigma_px=pixel_sigma_px or {}, pixel_noise=pixel_noise or {}, checks=checks or {},
        world={"units": "m", "world_mirror": session.world_mirror.tolist()},
        imported=session.extra_toml.get("import", {}), warnings=warnings,
        paper_experiment=paper_experiment(session), methods=per_method,
        comparison=compare(trajectories, reprojection, methods, session.truth, session.reference,
                           joined=truth_errors if session.truth is not None else ref_errors),
    ).to_json()
    return refresh_verdict(summary)


def refresh_verdict(summary: dict) -> dict:
    """summary (a JSON dict) with its ``verdict`` recomputed, e.g. after validation was added."""
    summary["verdict"] = asdict(verdict(summary))
    return summary


def paper_experiment(session) -> str | None:
    """'flight' or 'ear' when the session declares itself one of the paper's scenes, else None.

    Declared by session.toml ``[paper] experiment = "flight"|"ear"``, or by the simulator
    (``[simulation] scene``); never guessed from the session's name.
    """
    extra = getattr(session, "extra_toml", {}) or {}
    declared = (extra.get("paper") or {}).get("experiment")
    if declared in ("flight", "ear"):
        return declared
    sim = extra.get("simulation")
    if isinstance(sim, dict) and sim.get("scene") in ("flight", "ear"):
        return sim["scene"]
    return None


def clean(o):
    """NaN/inf -> None (recursively) so summary.json is strict JSON."""
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [clean(v) for v in o]
    if isinstance(o, float | np.floating) and not math.isfinite(o):
        return None
    if isinstance(o, np.integer | np.bool_):
        return o.item()
    if isinstance(o, np.floating):
        return float(o)
    return o
