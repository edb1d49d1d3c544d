"""The accuracy study: every method against simulated truth, by point status, with 95 % coverage.

Scenes (batgraph.simulate): the flight with 5 cameras (simulate_flight defaults: 14 markers, 160 frames
at 120 fps, 1 px noise), the same flight with 5 % mislabelled observations, a 30-camera flight (60
markers, 160 frames) and the ear (simulate_ear defaults). Hold-out scenes from a second, independent
generator (batgraph.wingbeat: joint-angle wing chain, random flight-section rigs; batgraph is not tuned
on them): straight flight as the user's hold-out (5 cameras, 120 fps, 72 frames, 1 px), dorsal skin
markers with 4 cameras, a banked turn at 250 fps / 3 px, a glide at 60 fps / 2 px and a 15 Hz wingbeat
at 1000 fps / 8 px. ``--scenes`` picks scenes by key (shell patterns, e.g. ``--scenes 'wingbeat*'``).
Rows: the smoother with its default "auto" (each marker's model, constant velocity or constant acceleration,
and its noise by marginal likelihood), with constant velocity on every marker (q per marker by marginal
likelihood), without the segments, and with the paper's random walk; the filter with constant velocity (its
default) and with the random walk; the paper's EKF and UKF, per-frame triangulation, and triangulation linearly
interpolated through gaps (batgraph.solver.schedule.initial_track, no covariance). Prints the tables and writes them to
docs/accuracy.md with a checklist of the project's accuracy targets (measured value, pass/fail) and the summary
of docs/ablation.md (scripts/ablation.py). Run by ``make study``. Nothing is asserted: it reports what it measures.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import fnmatch
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from batgraph import atomic, evaluate  # noqa: E402
from batgraph.motion import CHI2_3DOF_95  # noqa: E402
from batgraph.pipeline import run_methods  # noqa: E402
from batgraph.result import Estimate, Options  # noqa: E402
from batgraph.session import Session  # noqa: E402
from batgraph.simulate import simulate_ear, simulate_flight  # noqa: E402
from batgraph.solver.schedule import initial_track  # noqa: E402
from batgraph.wingbeat import simulate_wingbeat  # noqa: E402

STATUSES = evaluate.STATUSES
GROUPS = ("all", *STATUSES)
SPLIT_GROUPS = tuple(f"{st}/{sp}" for st in STATUSES for sp in evaluate.SPANS)
# (row name, pipeline method, Options.motion_model); None = the method's default (constant velocity for the
# filter, the paper's random walk for EKF/UKF). The smoother's rows name the model ("auto" is the default).
METHOD_ROWS = (
    ("smoother", "smoother", "auto"),
    ("smoother_cv", "smoother", "constant_velocity"),
    ("smoother_noseg", "smoother", "auto"),
    ("smoother_rw", "smoother", "random_walk"),
    ("filter", "filter", None),
    ("filter_rw", "filter", "random_walk"),
    ("ekf", "ekf", None),
    ("ukf", "ukf", None),
    ("triangulate", "triangulate", None),
)
NO_SEGMENT_ROWS = ("smoother_noseg",)  # rows run on the session without its [markers] rigid segments
INTERPOLATION = "interpolation"  # triangulation interpolated through gaps (derived from the triangulate row)
ROW_NAMES = tuple(r[0] for r in METHOD_ROWS) + (INTERPOLATION,)
PAPER_STEREO_MM = 1.0  # paper: EKF/UKF within 1 mm of stereo triangulation on the ear
PAPER_REPROJ_PX = 5.0  # paper: reprojection errors within 5 px
ABLATION_MD = ROOT / "docs" / "ablation.md"  # written by scripts/ablation.py (make ablation)
ABLATION_SUMMARY = "## Verdicts each step changes"  # its section copied into docs/accuracy.md


@dataclass(frozen=True)
class StudyScene:
    """One simulated scene of the study: how to make it for a seed, and which seeds."""

    key: str
    title: str
    params: str  # human-readable scene parameters for the report
    make: Callable[[int], Session]
    seeds: tuple[int, ...]


def scenes(quick: bool) -> list[StudyScene]:
    """The study's scenes; ``quick`` shrinks them (fewer frames/markers, one seed) for a smoke run."""
    f5 = {"n_frames": 80} if quick else {}
    f30 = {"n_markers": 20, "n_frames": 40} if quick else {"n_markers": 60, "n_frames": 160}
    ear = {"n_frames": 60} if quick else {}
    s5 = (1,) if quick else (1, 2, 3)
    s30 = (1,) if quick else (1, 2)
    se = (1,) if quick else (1, 2)
    def call(fn: str, kw: dict) -> str:
        return f"`{fn}(" + ", ".join(f"{k}={v}" for k, v in kw.items()) + ")`, other arguments default"

    f5o = dict(f5, outlier_rate=0.05)
    # the second generator (batgraph.wingbeat), 3 seeds each; parameters not listed are drawn per seed
    sw = (1,) if quick else (1, 2, 3)
    short = (lambda n: max(n // 2, 36)) if quick else (lambda n: n)
    wingbeat = [
        ("wingbeat", "Hold-out wingbeat, straight, 5 cameras",
         dict(flight="straight", n_cameras=5, fps=120.0, n_frames=short(72), flap_hz=10.0, pixel_sigma_px=1.0)),
        ("wingbeat_dorsal", "Hold-out wingbeat, straight, dorsal skin markers, 4 cameras",
         dict(flight="straight", n_cameras=4, fps=120.0, n_frames=short(96), flap_hz=8.0, pixel_sigma_px=2.0,
              marker_side="dorsal")),
        ("wingbeat_turn", "Hold-out wingbeat, banked turn, 5 cameras",
         dict(flight="turn", n_cameras=5, fps=250.0, n_frames=short(150), flap_hz=12.0, pixel_sigma_px=3.0)),
        ("wingbeat_glide", "Hold-out glide, 5 cameras",
         dict(flight="glide", n_cameras=5, fps=60.0, n_frames=short(60), pixel_sigma_px=2.0)),
        ("wingbeat_fast", "Hold-out wingbeat, 15 Hz at 1000 fps, 6 cameras",
         dict(flight="straight", n_cameras=6, fps=1000.0, n_frames=short(200), flap_hz=15.0, pixel_sigma_px=8.0)),
    ]
    return [
        StudyScene("flight5", "Flight, 5 cameras", call("simulate_flight", dict(n_cameras=5, **f5)),
                   lambda s: simulate_flight(np.random.default_rng(s), n_cameras=5, **f5), s5),
        StudyScene("flight5_out", "Flight, 5 cameras, 5 % mislabelled",
                   call("simulate_flight", dict(n_cameras=5, **f5o)) + " (same seeds as the clean flight, hence the "
                   "same scene and pixel noise)",
                   lambda s: simulate_flight(np.random.default_rng(s), n_cameras=5, **f5o), s5),
        StudyScene("flight30", "Flight, 30 cameras", call("simulate_flight", dict(n_cameras=30, **f30)),
                   lambda s: simulate_flight(np.random.default_rng(s), n_cameras=30, **f30), s30),
        StudyScene("ear", "Ear, 2 cameras", call("simulate_ear", ear),
                   lambda s: simulate_ear(np.random.default_rng(s), **ear), se),
    ] + [StudyScene(key, title, call("batgraph.wingbeat.simulate_wingbeat", kw),
                    lambda s, kw=kw: simulate_wingbeat(np.random.default_rng(s), **kw), sw)
         for key, title, kw in wingbeat]


def pick_scenes(scene_list: list[StudyScene], patterns: str | None) -> list[StudyScene]:
    """The scenes whose key matches one of the comma-separated shell patterns (all when None)."""
    if not patterns:
        return scene_list
    pats = [p.strip() for p in patterns.split(",") if p.strip()]
    out = [s for s in scene_list if any(fnmatch.fnmatchcase(s.key, p) for p in pats)]
    if not out:
        raise SystemExit(f"--scenes {patterns!r} matches none of {', '.join(s.key for s in scene_list)}")
    return out


# ==================================================================================================
# measuring
# ==================================================================================================
def interpolation_estimate(tri: Estimate, fps: float) -> Estimate:
    """Triangulation linearly interpolated through gaps (constant at the ends); no covariance, no flags."""
    xyz = initial_track(tri.xyz_m, fps)[0]
    return Estimate(INTERPOLATION, xyz, np.full(xyz.shape + (3,), np.nan), np.zeros_like(tri.outlier), 0.0)


def inside_gaps(n_views: np.ndarray) -> np.ndarray:
    """Points inside a marker's span (batgraph.evaluate.inside_span: from its first to its last frame with
    >= 2 views), bool (F, M); single-view and unobserved points there lie inside occlusion gaps, with data on
    both sides, while outside it (the track ends) interpolation is a constant and a motion model extrapolates."""
    return evaluate.inside_span(n_views)


def partner_mask(session: Session, markers: list[str], n_views: np.ndarray) -> np.ndarray | None:
    """Single-view points inside a marker's span with a rigid segment partner (session.toml's ``[markers] rigid``,
    batgraph.wingbeat) observed (>= 2 views) on the same frame, bool (F, M); None without segments."""
    pairs = session.rigid
    if not pairs:
        return None
    idx = {m: i for i, m in enumerate(markers)}
    observed = n_views >= 2
    partner = np.zeros_like(observed)
    for a, b in pairs:
        if a in idx and b in idx:
            partner[:, idx[a]] |= observed[:, idx[b]]
            partner[:, idx[b]] |= observed[:, idx[a]]
    return (n_views == 1) & inside_gaps(n_views) & partner


def record(scene: str, seed: int, row: str, s: dict, traj: pd.DataFrame, truth: pd.DataFrame,
           inside: np.ndarray, xyz: np.ndarray, tri_xyz: np.ndarray, partner: np.ndarray | None = None) -> dict:
    """One flat row of figures from a method's summary entry ``s`` (pipeline.method_summary).

    traj: its trajectories table (rows in frame-major (F, M) order); inside: :func:`inside_gaps` (F, M).
    xyz, tri_xyz: this method's and triangulation's positions (F, M, 3) [m] for the stereo comparison.
    partner: :func:`partner_mask` (F, M) or None: figures ``*_partner`` for those points.
    """
    out = {"scene": scene, "seed": seed, "method": row, "runtime_s": s.get("runtime_s")}
    parts = [("", s["truth"])] + [(f"_{w}", evaluate.truth_stats(traj[mask], truth))
                                  for w, mask in (("gap", inside.reshape(-1)), ("end", ~inside.reshape(-1)))]
    for suffix, t in parts:
        for g in GROUPS if not suffix else ("single_view", "unobserved"):
            out[f"rmse_{g}{suffix}"] = t["rmse_m"][g]
            out[f"cov_{g}{suffix}"] = t["coverage95"][g]
            out[f"n_{g}{suffix}"] = t["n"][g]
            out[f"est_{g}{suffix}"] = t["n_estimated"][g]
    for g in SPLIT_GROUPS:  # status within span (evaluate.GROUPS), e.g. "single_view/inside"
        out[f"rmse_{g}"], out[f"cov_{g}"], out[f"n_{g}"] = (s["truth"][k].get(g) for k in ("rmse_m", "coverage95", "n"))
    if partner is not None:
        t = evaluate.truth_stats(traj[partner.reshape(-1)], truth)
        out["rmse_partner"], out["cov_partner"], out["n_partner"] = (t[k]["single_view"]
                                                                     for k in ("rmse_m", "coverage95", "n"))
    for cam, r in s["reprojection"].items():
        out[f"reproj_median_{cam}"] = r.get("median_px")
        out[f"reproj_p95_{cam}"] = r.get("p95_px")
    od = s.get("outlier_detection") or {}
    out.update({f"od_{k}": od.get(k) for k in ("planted", "flagged", "flagged_planted")})
    both = np.isfinite(tri_xyz).all(-1) & np.isfinite(xyz).all(-1)
    d = np.linalg.norm(xyz[both] - tri_xyz[both], axis=-1)
    out["stereo_n"] = int(both.sum())
    out["stereo_mean_m"] = float(d.mean()) if len(d) else None
    out["stereo_max_m"] = float(d.max()) if len(d) else None
    return out


def run_scene(scene: StudyScene, seed: int, bar: tqdm) -> tuple[list[dict], dict]:
    """All method rows on one seed of a scene: (records, scene facts: point counts by status, cameras)."""
    session = scene.make(seed)
    summaries, estimates, trajs = {}, {}, {}
    for row, method, motion_model in METHOD_ROWS:
        bar.set_postfix_str(f"{scene.key} seed {seed} {row}")
        res = run_methods(dataclasses.replace(session, rigid=[]) if row in NO_SEGMENT_ROWS else session, [method],
                          Options(motion_model=motion_model, progress=False))
        summaries[row], estimates[row] = res.summary["methods"][method], res.estimates[method]
        trajs[row] = res.trajectories
        bar.update()
    interp = interpolation_estimate(estimates["triangulate"], session.fps)
    trajs[INTERPOLATION] = evaluate.trajectories_table(session, res.dense, interp)
    reproj = evaluate.reprojection_table(session, res.dense, interp)
    summaries[INTERPOLATION] = evaluate.method_summary(session, trajs[INTERPOLATION], reproj, runtime_s=0.0)
    estimates[INTERPOLATION] = interp
    bar.update()
    tri, inside = estimates["triangulate"].xyz_m, inside_gaps(res.dense.n_views)
    partner = partner_mask(session, res.dense.markers, res.dense.n_views)
    recs = [record(scene.key, seed, row, summaries[row], trajs[row], session.truth, inside, estimates[row].xyz_m,
                   tri, partner) for row in ROW_NAMES]
    facts = {"views": res.summary["views"], "cameras": list(session.rig.names),
             "n_observations": res.summary["n_observations"], "n_markers": res.summary["n_markers"],
             "n_frames": res.summary["n_frames"], "fps": session.fps, "pixel_sigma_px": session.pixel_sigma_px}
    return recs, facts


# ==================================================================================================
# formatting
# ==================================================================================================
def _values(df: pd.DataFrame, col: str) -> np.ndarray:
    return pd.to_numeric(df[col], errors="coerce").to_numpy(float) if col in df else np.array([])


def spread(v: np.ndarray, scale: float = 1.0, digits: int = 2) -> str:
    """'median [min, max]' of the finite values times ``scale`` (just the value for one seed); '—' if none."""
    v = v[np.isfinite(v)] * scale
    if not len(v):
        return "—"
    med = f"{np.median(v):.{digits}f}"
    return med if len(v) == 1 or np.ptp(v) == 0 else f"{med} [{v.min():.{digits}f}, {v.max():.{digits}f}]"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def rmse_table(df: pd.DataFrame) -> str:
    """RMSE [mm] by status, per method: median [min, max] over seeds; runtime [s]."""
    rows = []
    for m in ROW_NAMES:
        g = df[df["method"] == m]
        rows.append([m] + [spread(_values(g, f"rmse_{s}"), 1000) for s in GROUPS]
                    + [spread(_values(g, "runtime_s"), 1, 1)])
    return markdown_table(["method", "RMSE all [mm]", "observed", "single_view", "unobserved", "runtime [s]"], rows)


def coverage_table(df: pd.DataFrame) -> str:
    """95 % ellipsoid coverage [%] by status and the share of points estimated [%]."""
    rows = []
    for m in ROW_NAMES:
        g = df[df["method"] == m]
        with np.errstate(all="ignore"):  # 0 / 0 where a status has no point: '—'
            est = [spread(100 * _values(g, f"est_{s}") / _values(g, f"n_{s}"), 1, 1) for s in GROUPS]
        rows.append([m] + [spread(_values(g, f"cov_{s}"), 100, 1) for s in GROUPS] + est)
    head = ["method", "coverage all [%]", "observed", "single_view", "unobserved",
            "estimated all [%]", "observed", "single_view", "unobserved"]
    return markdown_table(head, rows)


def reprojection_table(df: pd.DataFrame, cameras: list[str], per_camera: bool) -> str:
    """Reprojection error [px] per camera (or the worst camera's), median and p95 of each seed's figure."""
    rows = []
    for m in ROW_NAMES:
        g = df[df["method"] == m]
        med = np.stack([_values(g, f"reproj_median_{c}") for c in cameras])  # (C, seeds)
        p95 = np.stack([_values(g, f"reproj_p95_{c}") for c in cameras])
        if per_camera:
            rows.append([m] + [x for i in range(len(cameras)) for x in (spread(med[i]), spread(p95[i]))])
        else:
            with np.errstate(all="ignore"):
                rows.append([m, spread(np.nanmax(med, axis=0)), spread(np.nanmax(p95, axis=0))])
    head = (["method"] + [x for c in cameras for x in (f"{c} median [px]", f"{c} p95 [px]")] if per_camera
            else ["method", "worst camera's median [px]", "worst camera's p95 [px]"])
    return markdown_table(head, rows)


def gap_table(df: pd.DataFrame) -> str:
    """RMSE [mm] and coverage [%] of single-view and unobserved points inside occlusion gaps vs at the ends."""
    subs = [f"{st}_{w}" for st in ("single_view", "unobserved") for w in ("gap", "end")]
    rows = []
    for m in ROW_NAMES:
        g = df[df["method"] == m]
        rows.append([m] + [spread(_values(g, f"rmse_{x}"), 1000) for x in subs]
                    + [spread(_values(g, f"cov_{x}"), 100, 1) for x in subs])
    names = ["single_view in gaps", "single_view at ends", "unobserved in gaps", "unobserved at ends"]
    head = ["method"] + [f"RMSE {n} [mm]" for n in names] + [f"coverage {n} [%]" for n in names]
    counts = ", ".join(f"{n} {spread(_values(df[df['method'] == 'smoother'], f'n_{x}'), 1, 0)}"
                       for n, x in zip(names, subs, strict=True))
    return markdown_table(head, rows) + f"\n\nPoints per seed (median [min, max]): {counts}."


SPLIT_SHOWN = tuple(g for g in SPLIT_GROUPS if g != "observed/outside")  # observed points are inside by definition


def split_table(df: pd.DataFrame) -> str:
    """RMSE [mm] and 95 % coverage [%] by status within span (evaluate.GROUPS), per method."""
    rows = []
    for m in ROW_NAMES:
        g = df[df["method"] == m]
        rows.append([m] + [spread(_values(g, f"rmse_{x}"), 1000) for x in SPLIT_SHOWN]
                    + [spread(_values(g, f"cov_{x}"), 100, 1) for x in SPLIT_SHOWN])
    head = ["method"] + [f"RMSE {x} [mm]" for x in SPLIT_SHOWN] + [f"coverage {x} [%]" for x in SPLIT_SHOWN]
    counts = ", ".join(f"{x} {spread(_values(df[df['method'] == 'smoother'], f'n_{x}'), 1, 0)}" for x in SPLIT_SHOWN)
    return markdown_table(head, rows) + f"\n\nPoints per seed (median [min, max]): {counts}."


def stereo_table(df: pd.DataFrame) -> str:
    """Distance to per-frame stereo triangulation [mm] where triangulation exists."""
    rows = []
    for m in ROW_NAMES:
        if m in ("triangulate", INTERPOLATION):
            continue
        g = df[df["method"] == m]
        mx = _values(g, "stereo_max_m")
        ok = np.isfinite(mx).any() and np.nanmax(mx) * 1000 <= PAPER_STEREO_MM
        rows.append([m, spread(_values(g, "stereo_mean_m"), 1000, 3), spread(mx, 1000, 3),
                     spread(_values(g, "stereo_n"), 1, 0), "yes" if ok else "no"])
    return markdown_table(["method", "mean distance [mm]", "max distance [mm]", "points",
                           f"max within {PAPER_STEREO_MM:g} mm"], rows)


def robust_table(clean: pd.DataFrame, dirty: pd.DataFrame) -> str:
    """RMSE [mm] by status, clean vs 5 % mislabelled, and the outlier flags on the mislabelled run."""
    rows = []
    for m in ROW_NAMES:
        a, b = clean[clean["method"] == m], dirty[dirty["method"] == m]
        cells = [spread(_values(d, f"rmse_{s}"), 1000) for s in GROUPS for d in (a, b)]
        cells += [spread(_values(a, "cov_all"), 100, 1), spread(_values(b, "cov_all"), 100, 1)]
        cells += [spread(_values(b, f"od_{k}"), 1, 0) for k in ("planted", "flagged", "flagged_planted")]
        rows.append([m] + cells)
    head = ["method"] + [f"{s} {w} [mm]" for s in GROUPS for w in ("clean", "5 %")]
    head += ["coverage clean [%]", "coverage 5 % [%]", "planted", "flagged", "flagged & planted"]
    return markdown_table(head, rows)


# ==================================================================================================
# targets (5-camera flight, clean)
# ==================================================================================================
def per_seed(df: pd.DataFrame, method: str, col: str) -> pd.Series:
    """Column ``col`` of ``method`` indexed by seed (float, NaN where missing)."""
    g = df[df["method"] == method].set_index("seed")
    return pd.to_numeric(g[col], errors="coerce")


def pooled_coverage(df: pd.DataFrame, group: str, lo: float, hi: float, method: str = "smoother") -> str:
    """The smoother's 95 % coverage of ``group`` pooled over the seeds: k of n points inside their ellipsoid,
    the exact (Clopper-Pearson, scipy.stats.binomtest) 95 % interval of the true rate, and a verdict on the
    target [lo, hi] % that a small group can give: PASS (pooled rate inside), FAIL (the whole interval
    outside) or "not resolved" (outside, but the interval reaches into the target: too few points to tell).
    A group of 7 points can only show 85.7 % or 100 %, neither in [90, 98]. k = coverage x n is exact for the
    smoother, which estimates every point with a covariance."""
    from scipy.stats import binomtest

    c, n = per_seed(df, method, f"cov_{group}"), per_seed(df, method, f"n_{group}")
    ok = c.notna() & (n > 0)
    k, total = int(round(float((c[ok] * n[ok]).sum()))), int(n[ok].sum())
    if total == 0:
        return "— (no such points)"
    ci = binomtest(k, total).proportion_ci(0.95, method="exact")
    rate, c_lo, c_hi = 100 * k / total, 100 * ci.low, 100 * ci.high
    verdict = "PASS" if lo <= rate <= hi else "FAIL" if c_hi < lo or c_lo > hi else "not resolved"
    return f"{k}/{total} = {rate:.1f} % [{c_lo:.1f}, {c_hi:.1f}]: {verdict}"


def target_rows(df: pd.DataFrame) -> list[list[str]]:
    """The targets on the clean 5-camera flight: [target, measured (median over seeds), seeds, verdict,
    pooled over seeds (coverage rows)].

    A target passes only when it holds on every seed (seeds where a status has no points are skipped).
    """
    rows = []

    def add(target: str, measured: str, ok: pd.Series, pooled: str = "—"):
        rows.append(verdict_row(target, measured, ok, pooled))

    def seeds(x: pd.Series, digits: int) -> str:
        return "per seed " + ", ".join(f"{k}: {v:.{digits}f}" for k, v in x.items() if np.isfinite(v))

    def mm(a: pd.Series, b: pd.Series) -> str:
        return " vs ".join("—" if np.isnan(x.median()) else f"{x.median():.2f}" for x in (a, b)) + " mm"

    def less(a: pd.Series, b: pd.Series) -> pd.Series:
        return (a < b).where(a.notna() & b.notna())

    r = {m: {g: per_seed(df, m, f"rmse_{g}") * 1000 for g in GROUPS} for m in ROW_NAMES}
    n_all, est_all = per_seed(df, "smoother", "n_all"), per_seed(df, "smoother", "est_all")
    add("smoother estimates every marker on every frame",
        f"{int(est_all.median())} of {int(n_all.median())} points", est_all == n_all)
    a, b = r["smoother_rw"]["observed"], r["triangulate"]["observed"]
    add("smoother_rw RMSE observed <= triangulate", mm(a, b),
        (a <= b).where(a.notna()))
    ratio = r["smoother"]["observed"] / r["triangulate"]["observed"]
    add("smoother RMSE observed <= 0.6 x triangulate", f"ratio {ratio.median():.2f} ({seeds(ratio, 2)})",
        (ratio <= 0.6).where(ratio.notna()))
    for other in ("ekf", "ukf"):
        a, b = r["smoother"]["observed"], r[other]["observed"]
        add(f"smoother RMSE observed < {other}", mm(a, b), less(a, b))
    gap = {m: {st: per_seed(df, m, f"rmse_{st}_gap") * 1000 for st in ("single_view", "unobserved")}
           for m in ("smoother", "smoother_rw", INTERPOLATION)}
    for status in ("single_view", "unobserved"):
        for other in ("smoother_rw", INTERPOLATION):
            a, b = gap["smoother"][status], gap[other][status]
            add(f"smoother RMSE {status} inside occlusion gaps < {other}",
                mm(a, b), less(a, b))
        for other in ("smoother_rw", INTERPOLATION):
            a, b = r["smoother"][status], r[other][status]
            add(f"(stricter) smoother RMSE {status}, all such points incl. sequence ends, < {other}",
                mm(a, b), less(a, b))
    cov = {g: per_seed(df, "smoother", f"cov_{g}") * 100 for g in GROUPS}
    add("smoother coverage95 overall in [90, 99] %", f"{cov['all'].median():.1f} % ({seeds(cov['all'], 1)})",
        ((cov["all"] >= 90) & (cov["all"] <= 99)).where(cov["all"].notna()), pooled_coverage(df, "all", 90, 99))
    for status in STATUSES:
        c = cov[status]
        n = per_seed(df, "smoother", f"n_{status}")
        measured = (f"{c.median():.1f} % ({seeds(c, 1)}; " if c.notna().any() else "— (") + \
            f"median {int(n.median())} points)"
        add(f"smoother coverage95 {status} >= 85 %", measured, (c >= 85).where(c.notna()),
            pooled_coverage(df, status, 85, 100))
    return rows


def verdict_row(target: str, measured: str, ok: pd.Series, pooled: str = "—") -> list[str]:
    """[target, measured, seeds holding, verdict, pooled]: a target passes only when it holds on every seed
    (seeds where ``ok`` is NaN, e.g. no such points, are skipped); ``pooled``: :func:`pooled_coverage`'s text
    for a coverage target."""
    ok = ok.dropna()
    n, good = len(ok), int(ok.astype(bool).sum())
    verdict = "n/a (no such points)" if not n else "PASS" if good == n else "FAIL"
    bad = [str(k) for k, v in ok.items() if not v]
    return [target, measured, f"{good}/{n}" + (f" (fails on seed {', '.join(bad)})" if bad else ""), verdict,
            pooled]


def holdout_target_rows(df: pd.DataFrame, row: str = "smoother") -> list[list[str]]:
    """The wings-and-bones targets on one scene (each of the second generator's, batgraph.wingbeat, and the
    first's flight5), for the smoother's row ``row``: observed RMSE <= 0.6 x triangulation; single-view points
    inside the span whose rigid segment partner is observed on the frame <= 3 x the observed RMSE; 95 % coverage
    in [90, 98] % in every status and span."""
    def per_seed_txt(x: pd.Series, digits: int) -> str:
        return ", ".join(f"{k}: {v:.{digits}f}" for k, v in x.items() if np.isfinite(v))

    sm_obs = per_seed(df, row, "rmse_observed")
    ratio = sm_obs / per_seed(df, "triangulate", "rmse_observed")
    rows = [verdict_row(f"{row} RMSE observed <= 0.6 x triangulate",
                        f"ratio {ratio.median():.2f} (per seed {per_seed_txt(ratio, 2)})",
                        (ratio <= 0.6).where(ratio.notna()))]
    if "rmse_partner" in df:
        r = per_seed(df, row, "rmse_partner") / sm_obs
        n = per_seed(df, row, "n_partner")
        rows.append(verdict_row(f"{row} RMSE single_view inside span, rigid partner observed, <= 3 x observed",
                                (f"ratio {r.median():.2f} (per seed {per_seed_txt(r, 2)}; " if r.notna().any()
                                 else "— (") + f"median {n.median():.0f} points)", (r <= 3).where(r.notna())))
    for g in SPLIT_SHOWN:
        c = per_seed(df, row, f"cov_{g}") * 100
        n = per_seed(df, row, f"n_{g}")
        rows.append(verdict_row(f"{row} coverage95 {g} in [90, 98] %",
                                (f"{c.median():.1f} % (per seed {per_seed_txt(c, 1)}; " if c.notna().any() else "— (")
                                + f"median {n.median():.0f} points)", ((c >= 90) & (c <= 98)).where(c.notna()),
                                pooled_coverage(df, g, 90, 98, method=row)))
    return rows


# ==================================================================================================
# report
# ==================================================================================================
def machine() -> str:
    """'N cores, CPU model' from /proc/cpuinfo."""
    cpu = platform.processor() or "unknown CPU"
    try:
        cpu = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                   if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{os.cpu_count()} cores (nproc), {cpu}, Python {platform.python_version()}"


def git_state() -> str:
    """HEAD commit and whether the working tree differs from it (the study runs the tree as it is)."""
    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return ""
    head = git("rev-parse", "HEAD") or "unknown"
    status = [line for line in git("status", "--porcelain", "--", "batgraph").splitlines() if line]
    untracked = sum(line.startswith("??") for line in status)
    if not status:
        return head + " (batgraph/ as committed)"
    return head + (f" plus uncommitted changes in batgraph/ ({len(status) - untracked} modified, "
                   f"{untracked} untracked files)")


def ablation_section(path: Path = ABLATION_MD) -> list[str]:
    """The section "Ablation": the summary of ``path`` (scripts/ablation.py's report, its ABLATION_SUMMARY section,
    headings one level down) with the date and commit it was generated at; a line saying so when it is absent."""
    out, name = ["## Ablation", ""], path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    if not path.exists():
        return out + [f"{name} has not been generated: run `make ablation`.", ""]
    lines = path.read_text().splitlines()
    meta = {k: line.split(":", 1)[1].strip() for line in lines for k in ("date", "code", "command")
            if line.startswith(f"* {k}:")}
    try:
        start = lines.index(ABLATION_SUMMARY) + 1
    except ValueError:
        return out + [f"{name} has no section '{ABLATION_SUMMARY[3:]}': run `make ablation`.", ""]
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    out += ["The smoother's post-solve steps and floors switched off one at a time (scenes, variants and every "
            f"table in {name}), generated by {meta.get('command', '—')} on "
            f"{meta.get('date', '—')}, code {meta.get('code', '—')}. The verdicts each step changes:", ""]
    body = "\n".join("#" + line if line.startswith("#") else line for line in lines[start:end]).strip()
    return out + [body, ""]


def build_report(df: pd.DataFrame, facts: dict, scene_list: list[StudyScene], command: str, started: str,
                 elapsed_s: float) -> str:
    """The whole docs/accuracy.md text."""
    by = {s.key: df[df["scene"] == s.key] for s in scene_list}
    out = [
        "# Accuracy study",
        "",
        "Every estimator against simulated ground truth. Generated by `make study` "
        "(`scripts/accuracy_study.py`); do not edit by hand.",
        "",
        f"* command: `{command}`",
        f"* date: {started} (wall time {elapsed_s / 60:.1f} min)",
        f"* machine: {machine()}",
        f"* code: git {git_state()}",
        "",
        "## Definitions",
        "",
        "* RMSE = sqrt(mean ||xyz - truth||^2) over the (frame, marker) points a method estimates, in mm; "
        "the share of points each method estimates is in the coverage tables.",
        f"* coverage = share of estimated points whose truth lies inside the 95 % ellipsoid: "
        f"(x - t)^T Sigma^-1 (x - t) <= {CHI2_3DOF_95} (chi-square, 3 DOF).",
        "* status of a point, from the input observations: observed (>= 2 cameras), single_view (1), unobserved (0).",
        "* each cell: median over seeds [min, max] (one value when all seeds agree or there is one seed); "
        "'—' = no such point or no figure (interpolation has no covariance; the filters and triangulation "
        "give no estimate before a marker's first triangulation).",
        "* rows: `smoother` = the default motion model, \"auto\": per marker (per segment group) constant velocity "
        "or constant acceleration (white-noise jerk), whichever has the larger marginal likelihood, each with its "
        "noise chosen from the data by the same marginal likelihood, with the session's segment-length factors "
        "(both generators write their bones as `[markers] rigid`; default stiffness rigid_sigma_m = 2 mm) "
        "(batgraph.solver); `smoother_cv` = the same with constant velocity for every marker; `smoother_noseg` = "
        "`smoother` without the segments; `filter` = "
        "constant velocity with q from the motion config (its default; \"auto\" filters with constant "
        "velocity); `smoother_rw` / `filter_rw` = the paper's random walk "
        "(Options.motion_model='random_walk'); `ekf` / `ukf` = the paper's filters (random walk); "
        "`triangulate` = per-frame DLT, with the DLT's own first-order covariance (batgraph.triangulate); "
        "`interpolation` = triangulation linearly interpolated through gaps, "
        "constant before the first and after the last triangulated frame (solver.schedule.initial_track).",
        "* robust loss: the defaults of Options (Huber) for smoother and filter; EKF, UKF and triangulation have none.",
        "",
        "## Scenes",
        "",
    ]
    for s in scene_list:
        v = facts[s.key]
        out.append(f"* **{s.title}** (`{s.key}`): {s.params}; seeds {list(s.seeds)}. {len(v['cameras'])} cameras, "
                   f"{v['n_markers']} markers, {v['n_frames']} frames at {v['fps']:g} fps, pixel noise "
                   f"{v['pixel_sigma_px']:g} px; seed {s.seeds[0]}: {v['n_observations']} observations, points by "
                   "status " + ", ".join(f"{k} {n}" for k, n in v["views"].items()) + ".")
    target_head = ["target", "measured (median over seeds)", "seeds holding", "verdict",
                   "coverage pooled over seeds [exact 95 % interval]"]
    if "flight5" in by:
        out += ["", "## Targets (clean 5-camera flight; a target passes when it holds on every seed)", "",
                markdown_table(target_head, target_rows(by["flight5"])), "",
                "The single-view/unobserved targets are for points inside occlusion gaps; the stricter "
                "rows include the points before a marker's first and after its last triangulable frame. How many "
                "points each group has is under the split table of the 5-camera flight below (small groups make "
                "their RMSE noisy).", "",
                "The wings-and-bones targets (the hold-out generator's, below: RMSE against triangulation, the "
                "single-view points beside an observed segment partner, 95 % coverage in [90, 98] % in every status "
                "and span) on this first generator:", "",
                markdown_table(target_head, holdout_target_rows(by["flight5"])), "",
                "The same targets for constant velocity on every marker (`smoother_cv`):", "",
                markdown_table(target_head, holdout_target_rows(by["flight5"], "smoother_cv")), ""]
    held = [s for s in scene_list if s.key.startswith("wingbeat")]
    if held:
        out += ["", "## Targets on the hold-out generator (batgraph.wingbeat; a target passes when it holds on every "
                "seed)", "", "Scenes from a second, independent generator that batgraph was not tuned on (joint-angle "
                "wing chain, random flight-section rigs; see docs/simulation.md). The single-view row counts the "
                "single-view points inside a marker's span whose rigid segment partner (`[markers] rigid`) is "
                "observed on the same frame. The last column pools a coverage target's points over the seeds "
                "and gives the exact 95 % interval of the true rate: a group of a handful of points per seed "
                "cannot show a rate inside [90, 98] % (7 points give 85.7 % or 100 %), so \"not resolved\" marks "
                "a miss that the points cannot tell from a pass, and FAIL one they can.", ""]
        for s in held:
            out += [f"### {s.title} (`{s.key}`)", "", markdown_table(target_head, holdout_target_rows(by[s.key])), "",
                    "The same targets for constant velocity on every marker (`smoother_cv`):", "",
                    markdown_table(target_head, holdout_target_rows(by[s.key], "smoother_cv")), ""]
    else:
        out.append("")
    for s in scene_list:
        if s.key == "flight5_out":
            continue
        g = by[s.key]
        cams = facts[s.key]["cameras"]
        out += [f"## {s.title}", "", "RMSE against truth [mm] by status; runtime [s] of the estimation.", "",
                rmse_table(g), "", "95 % coverage [%] and share of points estimated [%], by status.", "",
                coverage_table(g), ""]
        if s.key == "ear":
            out += [f"Paper: EKF/UKF within {PAPER_STEREO_MM:g} mm of stereo triangulation. Distance of each "
                    "method's position to the triangulated one, over the points both estimate (mean and max per "
                    "seed; median [min, max] over seeds).", "", stereo_table(g), "",
                    f"Paper: reprojection errors within {PAPER_REPROJ_PX:g} px. Per camera, median and 95th "
                    "percentile of the reprojection error [px] (distorted pixels) over the observations.", "",
                    reprojection_table(g, cams, per_camera=True), ""]
        elif np.nansum(_values(g, "n_single_view")) + np.nansum(_values(g, "n_unobserved")):
            out += ["Single-view and unobserved points split by where they are: inside an occlusion gap "
                    "(strictly between the marker's first and last frame with >= 2 views) or at the "
                    "sequence ends (before the first / after the last such frame, where interpolation is a "
                    "constant and a motion model extrapolates).", "", gap_table(g), ""]
            if s.key.startswith("wingbeat"):
                out += ["RMSE [mm] and 95 % coverage [%] by status within span (inside = from a marker's first to "
                        "its last frame with >= 2 views).", "", split_table(g), ""]
        if s.key != "ear":
            out += ["Reprojection error [px] of the worst camera (paper: within "
                    f"{PAPER_REPROJ_PX:g} px).", "", reprojection_table(g, cams, per_camera=False), ""]
    if "flight5" not in by or "flight5_out" not in by:
        return "\n".join(out + ablation_section())
    out += ["## Robust loss: 5-camera flight, clean vs 5 % mislabelled", "",
            "Same seeds and noise; 5 % of the observations carry another marker's pixels. RMSE [mm] by status, "
            "overall coverage, and on the mislabelled run the observations planted as mislabels, flagged as "
            "outliers by the method (its Estimate.outlier; EKF, UKF and triangulation flag none), and both.", "",
            robust_table(by["flight5"], by["flight5_out"]), "",
            "Coverage by status on the mislabelled run:", "", coverage_table(by["flight5_out"]), "",
            "Single-view and unobserved points of the mislabelled run, inside gaps vs at the sequence ends:", "",
            gap_table(by["flight5_out"]), ""]
    return "\n".join(out + ablation_section())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="small scenes and one seed (a smoke run, ~1 min)")
    p.add_argument("--scenes", metavar="PATTERNS",
                   help="only the scenes whose key matches one of these comma-separated shell patterns, e.g. "
                        "'wingbeat*' (keys: flight5, flight5_out, flight30, ear, wingbeat, wingbeat_dorsal, "
                        "wingbeat_turn, wingbeat_glide, wingbeat_fast); the report then has only their sections and "
                        "goes to out/accuracy_scenes.md unless --out is given")
    p.add_argument("--out", type=Path,
                   help="report path (default docs/accuracy.md; with --quick out/accuracy_quick.md)")
    args = p.parse_args(argv)
    default = "out/accuracy_quick.md" if args.quick else "out/accuracy_scenes.md" if args.scenes else "docs/accuracy.md"
    out = args.out or ROOT / default
    flags = (" --quick" if args.quick else "") + (f" --scenes '{args.scenes}'" if args.scenes else "")
    command = ("make study  (= .venv/bin/python scripts/accuracy_study.py" + flags + ")" if not args.scenes
               else ".venv/bin/python scripts/accuracy_study.py" + flags)
    scene_list = pick_scenes(scenes(args.quick), args.scenes)
    started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    t0 = time.perf_counter()
    recs, facts = [], {}
    total = sum(len(s.seeds) for s in scene_list) * len(ROW_NAMES)
    with tqdm(total=total, desc="accuracy study (scenes x seeds x methods)") as bar:
        for s in scene_list:
            for seed in s.seeds:
                r, f = run_scene(s, seed, bar)
                recs += r
                facts.setdefault(s.key, f)
    df = pd.DataFrame(recs)
    text = build_report(df, facts, scene_list, command, started, time.perf_counter() - t0)
    print(text)
    atomic.write_text(out, text + "\n")
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
