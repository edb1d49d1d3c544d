"""The typed summary (batgraph.summary): like-for-like comparisons, spans, the verdict, and one set of numbers
shown the same way by the terminal and the report.

The scene is the simulator's bat flight (its own truth), small enough to run every method in a few seconds;
the figures are checked against a direct recomputation from trajectories.csv's rows, not against the
summary's own code path.
"""

from __future__ import annotations

import re
from html.parser import HTMLParser

import numpy as np
import pandas as pd
import pytest

from batgraph import evaluate, simulate
from batgraph.cli import summary_lines
from batgraph.pipeline import run_methods
from batgraph.report import render_report
from batgraph.result import Options
from batgraph.summary import HEADLINE_GROUPS, OUTLIER_WARN_FRACTION, Summary, outlier_warnings, paper_experiment


@pytest.fixture(scope="module")
def flight():
    """A 4-camera simulated flight run through smoother, filter, ekf and triangulate."""
    session = simulate.simulate_flight(np.random.default_rng(3), n_cameras=4, n_markers=14, n_frames=60)
    result = run_methods(session, ["smoother", "filter", "ekf", "triangulate"], Options(progress=False))
    return session, result


def test_span_is_first_to_last_frame_seen_twice():
    n_views = np.array([[0, 2], [1, 0], [2, 1], [0, 0], [3, 1], [1, 0]])  # (F=6, M=2)
    assert evaluate.span_of(n_views)[:, 0].tolist() == ["outside", "outside", "inside", "inside", "inside",
                                                        "outside"]
    assert evaluate.span_of(n_views)[:, 1].tolist() == ["inside"] + ["outside"] * 5
    assert evaluate.span_of(np.ones((3, 1))).tolist() == [["outside"]] * 3  # never seen twice: no span


def in_group(t, group: str) -> np.ndarray:
    """The rows of ``t`` in a summary group, by the groups' definition: "all", a status, a span, "status/span"."""
    if group == "all":
        return np.ones(len(t), bool)
    if "/" in group:
        status, span = group.split("/")
        return ((t["status"] == status) & (t["span"] == span)).to_numpy()
    column = "span" if group in evaluate.SPANS else "status"
    assert group in (evaluate.SPANS if column == "span" else evaluate.STATUSES)
    return (t[column] == group).to_numpy()


def _keys(traj, method: str, group: str) -> set:
    t = traj[traj["method"] == method]
    t = t[in_group(t, group) & np.isfinite(t["x"].to_numpy())]
    return set(zip(t["frame"], t["marker"], strict=True))


def _rmse(traj, truth, method: str, keys: set) -> float:
    t = traj[traj["method"] == method].set_index(["frame", "marker"]).loc[sorted(keys)]
    d = t[["x", "y", "z"]].to_numpy() - truth.loc[sorted(keys), ["x", "y", "z"]].to_numpy()
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def test_comparison_is_on_the_points_of_the_verdicts_method(flight):
    """Each group's n is the smoother's points there; a method that estimates all of them has its RMSE on exactly
    those, one that estimates some has its count; and the common row is every method on the points they all
    estimate. Each figure equals a direct recomputation from the trajectories' rows."""
    session, result = flight
    traj, truth = result.trajectories, session.truth.set_index(["frame", "marker"])
    comp = result.summary["comparison"]
    assert comp["against"] == "truth" and comp["use"] == "smoother"
    checked = partial = 0
    for group, gc in comp["groups"].items():
        base = _keys(traj, "smoother", group)
        assert gc["n"] == len(base), group
        for m, v in gc["values"].items():
            mine = _keys(traj, m, group) & base
            assert gc["estimated"][m] == len(mine) > 0, (group, m)
            if v is None:
                assert len(mine) < len(base)
                partial += 1
                continue
            assert mine == base
            assert v["rmse_m"] == pytest.approx(_rmse(traj, truth, m, base), rel=1e-9), (group, m)
            checked += 1
        if gc["common"] is not None:
            both = set.intersection(*(_keys(traj, m, group) & base for m in gc["values"]))
            assert gc["common"]["n"] == len(both) < len(base)
            for m, v in gc["common"]["values"].items():
                assert v["rmse_m"] == pytest.approx(_rmse(traj, truth, m, both), rel=1e-9), (group, m)
    assert checked >= 10 and partial >= 1
    # triangulation estimates no point seen by one camera: it is left out of that group, not zeroed
    if "single_view/inside" in comp["groups"]:
        assert "triangulate" not in comp["groups"]["single_view/inside"]["values"]
    assert set(comp["groups"]["observed/inside"]["values"]) == {"smoother", "filter", "ekf", "triangulate"}


def test_each_headline_is_the_tables_figure_on_the_same_points(flight):
    """One headline per kind of point, seen by >= 2 cameras first, each with the n and the figure of the verdict
    method's own truth statistics and of the comparison table (track ends: the smoother's n, not the points every
    method estimates)."""
    _, result = flight
    s = Summary.from_json(result.summary)
    truth = result.summary["methods"]["smoother"]["truth"]
    lines = s.verdict.headlines
    labels = [g for g in HEADLINE_GROUPS if truth["n_estimated"][g]]
    assert len(lines) == len(labels) and lines[0].startswith("seen by >= 2 cameras")
    for line, g in zip(lines, labels, strict=True):
        n, rmse = truth["n_estimated"][g], truth["rmse_m"][g]
        assert line.startswith(f"{HEADLINE_GROUPS[g]} (n={n}): RMSE {1000 * rmse:.2f} mm"), line
        gc = s.comparison.groups[g]
        assert gc.n == n and gc.values["smoother"]["rmse_m"] == pytest.approx(rmse, rel=1e-12)


def test_summary_json_round_trip(flight):
    _, result = flight
    s = Summary.from_json(result.summary)
    assert s.to_json() == result.summary
    assert s.verdict.use == "smoother" and "RMSE" in s.verdict.headline


class _Tables(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tables, self._cls, self._row, self._cell = {}, None, None, None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "table":
            self._cls = a.get("class")
            self.tables[self._cls] = []
        elif tag == "tr" and self._cls:
            self._row = []
        elif tag in ("td", "th") and self._row is not None:
            self._cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append(self._cell.strip())
            self._cell = None
        elif tag == "tr" and self._row is not None:
            self.tables[self._cls].append(self._row)
            self._row = None
        elif tag == "table":
            self._cls = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell += data


def _ranking(values: dict[str, float]) -> list[str]:
    return sorted(values, key=values.get)


def test_terminal_and_report_show_the_same_rows(flight):
    """The terminal's comparison table and the report's are the same rows, cell for cell (one text for both,
    batgraph.summary.comparison_rows), and the verdict's headlines appear in both."""
    session, result = flight
    lines = summary_lines(result.summary)
    methods = result.summary["comparison"]["methods"]
    header = next(i for i, line in enumerate(lines) if line.split()[:1] == ["n"])
    assert lines[header].split() == ["n", *methods]
    terminal = [re.split(r"\s{2,}", line.strip()) for line in lines[header + 1:] if not line.startswith("runtime")]
    p = _Tables()
    p.feed(render_report(session, result.trajectories, result.reprojection, Summary.from_json(result.summary)))
    report = [[c for c in row if c != ""] for row in p.tables["compare"][1:]]
    assert terminal == report
    assert any(r[0] == "track ends (extrapolated)" for r in terminal)
    for h in result.summary["verdict"]["headlines"]:
        assert f"  {h}" in lines
    # on points seen twice the smoother ranks first on this scene (the point of comparing on the same points)
    observed = dict(zip(methods, terminal[0][2:], strict=True))
    assert min(observed, key=lambda m: float(observed[m].split()[0])) == "smoother"


def test_outlier_warning_above_five_percent():
    ok = {"reprojection": {"a": {"n": 96, "n_outliers": 4}, "b": {"n": 90, "n_outliers": 10}}}
    w = outlier_warnings(ok, "smoother")
    assert len(w) == 1 and w[0].text.startswith("camera b: 10 % of its observations are outliers: check")
    assert "flagged 10 of the 100 observations" in w[0].details
    assert 4 / 100 < OUTLIER_WARN_FRACTION < 10 / 100


def test_paper_experiment_is_declared_never_guessed_from_the_name():
    class S:
        name = "flight_paper_ear"
        extra_toml: dict = {}
    assert paper_experiment(S()) is None
    S.extra_toml = {"paper": {"experiment": "ear"}}
    assert paper_experiment(S()) == "ear"
    S.extra_toml = {"simulation": {"scene": "flight"}}
    assert paper_experiment(S()) == "flight"


def test_span_column_in_trajectories_and_counts_in_summary(flight):
    _, result = flight
    traj = result.trajectories
    one = traj[traj["method"] == "smoother"]
    assert set(one["span"]) <= {"inside", "outside"}
    assert (one.loc[one["status"] == "observed", "span"] == "inside").all()
    assert result.summary["spans"] == one["span"].value_counts().reindex(["inside", "outside"], fill_value=0).to_dict()
    assert pd.api.types.is_string_dtype(one["span"]) or one["span"].dtype == object


def test_add_span_from_a_table_equals_the_span_written_by_reconstruct(flight):
    """export reads old trajectories.csv files without a span column: the recomputed one must be the same."""
    _, result = flight
    traj = result.trajectories
    again = evaluate.add_span(traj.drop(columns="span").sample(frac=1.0, random_state=0)).sort_index()
    assert (again["span"] == traj["span"]).all()
    assert (traj["span"] == "outside").any() and (traj["span"] == "inside").any()
