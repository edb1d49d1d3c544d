"""The leave-one-camera-out validation's table: its columns, statistics, verdict and text (no estimation).

batgraph.validate runs the folds and hands their per-observation errors here; summary.json keeps the table
(``validation``), and the terminal (batgraph.cli) and the report draw it from there. Definitions:

* status of a held-out observation: that of its (frame, marker) *in the fold*, i.e. the number of views
  without camera c: ``observed`` (>= 2), ``single_view`` (1), ``unobserved`` (0).
* subset ``common``: observations every method estimates (methods compared on the same points; with
  triangulation among the methods, these are observed points only).
* subset ``smoother_only``: observations the smoother estimates and triangulation cannot (fewer than two
  other views, or triangulation failed there); every other method that estimates all of them is reported
  on them too. Absent without the smoother.
* held_out ``all``: every camera's held-out observations pooled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from .evaluate import STATUSES
from .formats import csv_text

SUBSETS = ("common", "smoother_only")
COLUMNS = ["held_out", "method", "status", "subset", "n", "median_px", "p90_px"]
POOLED = "all"  # held_out value of the rows that pool every camera
CSV_NAME = "validation.csv"


@dataclass
class Validation:
    """The outcome of a validation (batgraph.validate.validate_session).

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
# statistics
# ----------------------------------------------------------------------------------------------
def empty_points(methods: list[str]) -> pd.DataFrame:
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
    csv_text.write_csv(path, table[COLUMNS], "%.4f")
