"""summary.json as types: every figure a user reads is computed here once, from the result tables.

The terminal (:func:`terminal_lines`), the report and batch read a :class:`Summary` (or its JSON) and never
recompute. summary.json (``Summary.to_json``; strict JSON, NaN -> null) holds: the session's facts (session,
fps, n_cameras, n_frames, n_markers, n_observations, views, spans, opening_frame: where a viewer opens);
pixel_sigma_px, pixel_noise, checks, world, import; warnings (one line each) and warning_details (line ->
figures and reasons); paper_experiment ("flight" / "ear" only when the session declares itself one of the
paper's scenes); methods (per method: runtime, counts, reprojection per camera, truth / reference per
group, info); comparison (every method on the points the verdict's method estimates, per group); verdict
(which result, why, one headline per kind of point); validation (batgraph.validation_table), when run.
Groups: ``all``; a status (observed / single_view / unobserved); a span (inside / outside); or
``status/span`` (e.g. ``single_view/inside``: gaps inside a track seen by one camera).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from . import methods as methods_registry
from .evaluate import (
    GROUPS,
    SPANS,
    STATUSES,
    add_span,
    coverage95,
    errors_by_method,
    group_masks,
    method_rows,
    method_summary,
    opening_frame,
    point_errors,
    rms,
)

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
    """The methods' figures on the points of one group that the verdict's method estimates.

    n: those points (truth/reference) or observations (reprojection); values: each method that estimates any
    of them -> its figures on all n ({"rmse_m", "coverage95"} against truth, {"rms_m"} against a reference,
    {"median_px", "mean_px"} for reprojection), or None when it estimates only ``estimated[method]`` of them;
    common: the same on the points every one of those methods estimates, when that is fewer than n.
    """

    n: int
    values: dict[str, dict[str, float | None] | None]
    estimated: dict[str, int] = field(default_factory=dict)
    common: GroupComparison | None = None

    def to_json(self) -> dict:
        return {"n": self.n, "values": self.values, "estimated": self.estimated,
                "common": self.common.to_json() if self.common else None}

    @classmethod
    def from_json(cls, d: dict) -> GroupComparison:
        values = d.get("values") or {}
        return cls(int(d["n"]), values, d.get("estimated") or {m: int(d["n"]) for m in values},
                   cls.from_json(d["common"]) if d.get("common") else None)


@dataclass
class Comparison:
    """``methods`` (registry order) on the points of the verdict's method ``use``, per group (GROUPS), ``against``
    truth, a reference or reprojection."""

    methods: list[str]
    against: str
    use: str | None = None
    groups: dict[str, GroupComparison] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"methods": self.methods, "against": self.against, "use": self.use,
                "groups": {g: c.to_json() for g, c in self.groups.items()}}

    @classmethod
    def from_json(cls, d: dict | None) -> Comparison | None:
        if not d:
            return None
        return cls(list(d["methods"]), d["against"], d.get("use"),
                   {g: GroupComparison.from_json(c) for g, c in d.get("groups", {}).items()})


@dataclass
class Verdict:
    """Which result to use, why, how good it is, and what to look at first.

    use: a method name; why: one sentence; headlines: one line per accuracy figure, each on one set of points
    named with its n (held-out cameras first when validated, then each kind of point of HEADLINE_GROUPS, seen
    by >= 2 cameras first), the same figures as the comparison table; warnings: lines that bear on this result.
    """

    use: str
    why: str
    headlines: list[str]
    warnings: list[str] = field(default_factory=list)

    @property
    def headline(self) -> str:
        """The headlines as one sentence."""
        return "; ".join(self.headlines)


@dataclass(frozen=True)
class WarningLine:
    """A warning: ``text``, one line (at most WARNING_CHARS) saying what is wrong and what to do; ``details``,
    the figures and reasons behind it (summary.json ``warning_details``, the report)."""

    text: str
    details: str = ""


WARNING_CHARS = 160
"""The longest warning line: a terminal shows it whole, and the details go to summary.json and the report."""


def _finite(x) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def compare(trajectories: pd.DataFrame, reprojection: pd.DataFrame, methods: list[str], use: str,
            truth: pd.DataFrame | None = None, reference: pd.DataFrame | None = None,
            joined: dict[str, pd.DataFrame] | None = None) -> Comparison | None:
    """Each method's figure on the points of each group that ``use`` (the verdict's method) estimates.

    trajectories, reprojection: the output tables (every method stacked). Against truth: RMSE [m] and
    95 % coverage; else against a reference: RMS difference [m]; else the reprojection error [px] of the
    observations of those points that no compared method flags as an outlier. None when ``use`` did not run.
    joined: per method, the trajectories joined with the truth (else the reference) where the caller has
    them (batgraph.evaluate.errors_by_method).
    """
    rows = method_rows(trajectories)
    methods = [m for m in methods_registry.ordered(methods) if m in rows]
    if use not in methods:
        return None
    points = truth if truth is not None else reference
    if points is not None:
        joined = errors_by_method(trajectories, points) if joined is None else joined
        tabs = {m: point_errors(trajectories.iloc[rows[m]], points, joined.get(m)).set_index(["frame", "marker"])
                for m in methods}
        out = Comparison(methods, "truth" if truth is not None else "reference", use)

        def figures(m, sel):
            return _point_figures(tabs[m].loc[sel], truth is not None)
    else:  # observations (frame, camera, marker) of the group a method reprojects and does not flag
        keys = ["frame", "camera", "marker"]
        tabs = {}
        rep_rows = method_rows(reprojection)
        for m in methods:
            t = (reprojection.iloc[rep_rows[m]] if m in rep_rows else reprojection.iloc[:0]).set_index(keys)
            ok = np.isfinite(t["err_px"].to_numpy(float)) & ~t["outlier"].fillna(False).astype(bool).to_numpy()
            tabs[m] = pd.concat([t[ok].reset_index(), _status_of_observations(trajectories, m, t.index[ok])],
                                axis=1).set_index(keys)
        out = Comparison(methods, "reprojection", use)

        def figures(m, sel):
            return _pixel_figures(tabs[m].loc[sel, "err_px"].to_numpy(float))
    masks = {m: group_masks(t) for m, t in tabs.items()}
    for g in GROUPS:
        group = _group(methods, use, {m: t.index[masks[m][g]] for m, t in tabs.items()}, figures)
        if group is not None:
            out.groups[g] = group
    return out


def _group(methods: list[str], use: str, index: dict[str, pd.Index], figures) -> GroupComparison | None:
    """One group: the points of ``use`` (index[use]), each method's figures on them when it estimates all, its
    count when it estimates some; and the figures on the points they all estimate when that is fewer."""
    base = index[use]
    if not len(base):
        return None
    shared = {m: index[m].intersection(base) for m in methods}
    shared = {m: i for m, i in shared.items() if len(i)}
    values = {m: figures(m, base) if len(i) == len(base) else None for m, i in shared.items()}
    common = None
    if any(len(i) < len(base) for i in shared.values()):
        both = base
        for i in shared.values():
            both = both.intersection(i)
        if len(both):
            common = GroupComparison(len(both), {m: figures(m, both) for m in shared}, {m: len(both) for m in shared})
    return GroupComparison(len(base), values, {m: len(i) for m, i in shared.items()}, common)


def _point_figures(e: pd.DataFrame, with_truth: bool) -> dict:
    err = rms(e["err_m"].to_numpy(float))
    if not with_truth:
        return {"rms_m": err}
    return {"rmse_m": err, "coverage95": coverage95(e["mahal2"].to_numpy(float))}


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


def outlier_warnings(method_summary: dict, method: str) -> list[WarningLine]:
    """One warning per camera where ``method`` flagged more than OUTLIER_WARN_FRACTION of the observations."""
    out = []
    for cam, s in (method_summary.get("reprojection") or {}).items():
        n, k = s.get("n", 0) or 0, s.get("n_outliers", 0) or 0
        if n + k and k / (n + k) > OUTLIER_WARN_FRACTION:
            out.append(WarningLine(
                f"camera {cam}: {100 * k / (n + k):.0f} % of its observations are outliers: check its calibration, "
                "synchronisation and marker labels",
                f"the {method} flagged {k} of the {n + k} observations of camera {cam} as outliers, more than "
                f"{100 * OUTLIER_WARN_FRACTION:.0f} %: their reprojection errors are far beyond the pixel noise"))
    return out




def smoother_warnings(info: dict | None) -> list[WarningLine]:
    """One warning per rigid segment (``[markers] rigid``) whose length scatters over the frames by more than
    RIGID_WARN_FACTOR x rigid_sigma_m RMS at the smoother's solution or, beyond the triangulation's noise, in the
    per-frame triangulation (solver.segments.triangulated_excess): the pair is not rigid, or a label is swapped."""
    info = info or {}
    sigma = info.get("rigid_sigma_m")
    out = []
    for name, s in (info.get("segments") or {}).items():
        scatter = max(s["scatter_rms_m"], s.get("triangulated_excess_m") or 0.0)
        if sigma and scatter > RIGID_WARN_FACTOR * sigma:
            out.append(WarningLine(
                f"segment {name}: its length varies by {1000 * scatter:.1f} mm RMS: the two markers are not on one "
                "rigid segment, or a label is swapped; check [markers] rigid",
                f"more than {RIGID_WARN_FACTOR:g} x [markers] rigid_sigma_m = {1000 * sigma:g} mm, at the smoother's "
                f"solution ({1000 * s['scatter_rms_m']:.1f} mm) or in the per-frame triangulation beyond its noise "
                f"({1000 * (s.get('triangulated_excess_m') or 0.0):.1f} mm); the segment factor pulls the two "
                "markers toward a length they do not keep"))
    return out


def _mm(x) -> str:
    return "-" if x is None else f"{1000 * x:.2f}"


def figure_text(against: str, v: dict | None) -> str:
    """A method's figure in a comparison cell: RMSE [mm] (95 % coverage) against truth, RMS [mm] against a
    reference, the median [px] of reprojection errors; "-" without one."""
    if not v:
        return "-"
    if against == "truth":
        cov = v.get("coverage95")
        return _mm(v.get("rmse_m")) + (f" ({100 * cov:.0f}%)" if cov is not None else "")
    if against == "reference":
        return _mm(v.get("rms_m"))
    return "-" if v.get("median_px") is None else f"{v['median_px']:.2f}"


UNITS = {"truth": "RMSE [mm] against truth (in brackets: truth inside the 95 % ellipsoid)",
         "reference": "RMS difference to the reference 3D [mm]",
         "reprojection": "median reprojection error of inlier observations [px]"}
"""What a comparison's figures are, by what they are against."""


def _headline(against: str, label: str, n: int, v: dict) -> str:
    """One headline: a kind of point, its n, the verdict method's figure on exactly those points."""
    if against == "truth":
        cov = v.get("coverage95")
        what = f"RMSE {_mm(v.get('rmse_m'))} mm against truth" + (
            f", {100 * cov:.0f} % inside the 95 % ellipsoid" if cov is not None else "")
    elif against == "reference":
        what = f"{_mm(v.get('rms_m'))} mm RMS from the reference 3D"
    else:
        what = f"reprojection error {figure_text(against, v)} px median"
    return f"{label} (n={n}{' observations' if against == 'reprojection' else ''}): {what}"


def headlines(summary: dict, use: str) -> list[str]:
    """The verdict's headlines for method ``use``: the held-out-camera error when validated, then per kind of point
    (HEADLINE_GROUPS, seen by >= 2 cameras first) its figure on the points it estimates there, as in the
    comparison table (summary["comparison"]): one set of points per line, with its n."""
    lines = []
    v = summary.get("validation") or {}
    rows = [r for r in v.get("table") or [] if r.get("held_out") == "all" and r.get("method") == use
            and r.get("status") == "observed" and r.get("subset") == "common"]
    if rows and rows[0].get("median_px") is not None:
        r = rows[0]
        lines.append(f"each camera predicted from the others, seen by >= 2 cameras (n={r['n']}): "
                     f"{r['median_px']:.2f} px median, {r['p90_px']:.2f} px p90")
    c = Comparison.from_json(summary.get("comparison"))
    if c is not None and c.use == use:
        for g, label in HEADLINE_GROUPS.items():
            gc = c.groups.get(g)
            if gc is not None and gc.values.get(use):
                lines.append(_headline(c.against, label, gc.n, gc.values[use]))
    return lines or ["no accuracy figure (no observation could be reprojected)"]


def verdict(summary: dict) -> Verdict:
    """The verdict from a summary dict whose methods, comparison (and validation, when run) are filled in."""
    methods = list(summary.get("methods") or {})
    use, why = recommended(methods)
    return Verdict(use, why, headlines(summary, use), list(summary.get("warnings") or []))


def comparison_rows(c: Comparison) -> list[tuple[str, int, dict[str, str]]]:
    """The comparison table's rows, one text for the terminal and the report: (label, n, method -> cell) per
    kind of point (HEADLINE_GROUPS), each followed, where a method estimates only some of its points, by a row
    on the points every method of that row estimates."""
    rows = []
    for g, label in HEADLINE_GROUPS.items():
        gc = c.groups.get(g)
        if gc is None:
            continue
        cells = {m: ("not estimated" if m not in gc.estimated else figure_text(c.against, gc.values[m])
                     if gc.values.get(m) else f"{gc.estimated[m]} estimated") for m in c.methods}
        rows.append((label, gc.n, cells))
        if gc.common is not None:
            rows.append(("  where every method estimates", gc.common.n,
                         {m: figure_text(c.against, gc.common.values.get(m)) if m in gc.common.values else ""
                          for m in c.methods}))
    return rows


def terminal_lines(summary: dict) -> list[str]:
    """The end-of-run text: the verdict and its headlines, the comparison table (the same figures on the same
    points, and the other methods beside them), then runtimes. Reads summary.json's figures; computes none."""
    s = Summary.from_json(summary)
    lines = []
    if s.verdict:
        lines += [f"use: {s.verdict.use} ({s.verdict.why})"] + [f"  {h}" for h in s.verdict.headlines]
    methods = list(s.methods)
    c = s.comparison
    width = max(len(label) for label in [*HEADLINE_GROUPS.values(), "  where every method estimates"]) + 2
    if c is not None and c.groups:
        lines.append(f"per kind of point, on the {c.use}'s points (n): {UNITS[c.against]}")
        lines.append(f"{'':<{width}}{'n':>7}" + "".join(f"{m:>16}" for m in c.methods))
        lines += [f"{label:<{width}}{n:>7}" + "".join(f"{cells[m]:>16}" for m in c.methods)
                  for label, n, cells in comparison_rows(c)]
    lines.append(f"{'runtime s':<{width + 7}}" + "".join(f"{_fmt_s(s.methods[m].get('runtime_s')):>16}"
                                                         for m in methods))
    return lines


def _fmt_s(x) -> str:
    return "-" if x is None else f"{x:.2f}"


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
    warning_details: dict[str, str] = field(default_factory=dict)
    opening_frame: int | None = None
    comparison: Comparison | None = None
    verdict: Verdict | None = None
    validation: dict | None = None
    association: dict | None = None

    def to_json(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("imported", "comparison",
                                                                               "verdict", "validation", "association")}
        d["import"] = self.imported
        d["comparison"] = self.comparison.to_json() if self.comparison else None
        d["verdict"] = ({"use": self.verdict.use, "why": self.verdict.why, "headlines": self.verdict.headlines,
                         "warnings": self.verdict.warnings} if self.verdict else None)
        if self.validation is not None:
            d["validation"] = self.validation
        if self.association is not None:
            d["association"] = self.association
        return clean(d)

    @classmethod
    def from_json(cls, d: dict) -> Summary:
        plain = {k: d.get(k) for k in cls.__dataclass_fields__
                 if k not in ("imported", "comparison", "verdict", "validation", "association")}
        for k in ("views", "spans", "pixel_sigma_px", "pixel_noise", "checks", "world", "methods", "warning_details"):
            plain[k] = plain[k] or {}
        plain["warnings"] = plain["warnings"] or []
        v = d.get("verdict")
        verdict_ = None
        if v:
            lines = v.get("headlines") or ([v["headline"]] if v.get("headline") else [])
            verdict_ = Verdict(v["use"], v["why"], list(lines), list(v.get("warnings") or []))
        return cls(**plain, imported=d.get("import") or {}, comparison=Comparison.from_json(d.get("comparison")),
                   verdict=verdict_, validation=d.get("validation"), association=d.get("association"))


def summarize(session, trajectories: pd.DataFrame, reprojection: pd.DataFrame, *,
              runtimes: dict[str, float] | None = None, infos: dict[str, dict] | None = None,
              pixel_sigma_px: dict[str, float] | None = None, pixel_noise: dict | None = None,
              checks: dict | None = None, warnings: list[WarningLine] = ()) -> dict:
    """summary.json (as a dict) computed once from the result tables: every method's figures, the comparison
    and the verdict, and the warnings: the session's, then ``warnings``, the outliers' (:func:`outlier_warnings`)
    and the smoother's (:func:`smoother_warnings`), with their details in ``warning_details``.

    session: batgraph.session.Session (rig, truth, reference, warnings, extra_toml); trajectories, reprojection:
    the output tables, every method stacked (trajectories with status and span); runtimes, infos: per
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
    found = list(warnings)
    if use is not None:
        found += outlier_warnings(per_method[use], use) + smoother_warnings((infos or {}).get(use))
    lines = list(session.warnings) + [w.text for w in found if w.text not in session.warnings]
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
        imported=session.extra_toml.get("import", {}), warnings=list(dict.fromkeys(lines)),
        warning_details={w.text: w.details for w in found if w.details},
        opening_frame=_opening_frame(first),
        paper_experiment=paper_experiment(session), methods=per_method,
        comparison=compare(trajectories, reprojection, methods, use, session.truth, session.reference,
                           joined=truth_errors if session.truth is not None else ref_errors),
    ).to_json()
    return refresh_verdict(summary)


def _opening_frame(traj: pd.DataFrame) -> int | None:
    """evaluate.opening_frame of one method's trajectories rows (frame, marker, n_views)."""
    if not len(traj):
        return None
    seen = (traj["n_views"] >= 2).groupby(traj["frame"].to_numpy()).sum()
    return opening_frame(seen.to_numpy(), seen.index.to_numpy())


def refresh_verdict(summary: dict) -> dict:
    """summary (a JSON dict) with its ``verdict`` recomputed, e.g. after validation was added."""
    v = verdict(summary)
    summary["verdict"] = {"use": v.use, "why": v.why, "headlines": v.headlines, "warnings": v.warnings}
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
