"""Tests of batgraph.report: mm-at-depth and truth metrics on exact cases, and the HTML's structure.

The scene is built by hand (cameras from camera.py, a few markers moving like a flapping wing, a
few occlusion gaps); the methods' trajectories are truth plus seeded noise, so the report's numbers
can be checked against what went in.
"""

from __future__ import annotations

import re
from html.parser import HTMLParser

import cv2
import numpy as np
import pandas as pd
import pytest

from batgraph import evaluate
from batgraph.camera import Camera, Rig
from batgraph.motion import CHI2_3DOF_95
from batgraph.report import render_report, write_report
from batgraph.session import Session
from batgraph.summary import Summary, summarize

MARKERS = ["body2", "shoulder_r", "elbow_r", "wrist_r", "digit3_r", "tail"]


def look_at_camera(name: str, centre: np.ndarray, target=(0.0, 0.0, 0.0), f_px: float = 1000.0,
                   size_wh=(1280, 720)) -> Camera:
    """A distortion-free camera at ``centre`` [m, world] looking at ``target``; world z is up."""
    fwd = np.asarray(target, float) - centre
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])  # rows: camera axes in world (x right, y down, z forward)
    K = [[f_px, 0, size_wh[0] / 2 - 0.5], [0, f_px, size_wh[1] / 2 - 0.5], [0, 0, 1]]
    return Camera(name, size_wh, K, rvec=cv2.Rodrigues(R)[0].ravel(), tvec=-R @ centre)


def make_scene(n_cams=3, n_frames=48, markers=MARKERS, fps=120.0, methods=("smoother", "ekf", "ukf"),
               seed=0, name="flight_test"):
    """A session plus trajectories/reprojection tables as the pipeline would hand them to the report.

    Markers: a body moving along -x at 3 m/s through the origin and wing points flapping at 4 Hz. Occlusion: wrist_r is
    seen by one camera on frames 10-17 and by none on 18-25. Each method = truth + N(0, sigma) with
    its own sigma and its covariance set to sigma^2 I; triangulate has no estimate off 2+ views.
    """
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n_cams, endpoint=False)
    rig = Rig([look_at_camera(f"cam{i + 1}", np.array([4 * np.cos(a), 4 * np.sin(a), 0.8]))
               for i, a in enumerate(ang)])
    frames = np.arange(n_frames)
    t = frames / fps
    M = len(markers)
    span = np.linspace(0, 0.25, M)  # distance of each marker from the body along the wing [m]
    flap = np.sin(2 * np.pi * 4.0 * t)[:, None] * span[None, :] * 0.8
    xyz = np.stack([np.broadcast_to(3.0 * (t[-1] / 2 - t[:, None]), (n_frames, M)) + 0.01 * np.arange(M),
                    np.broadcast_to(-span, (n_frames, M)), flap], axis=-1)  # (F, M, 3) [m]
    truth = pd.DataFrame({"frame": np.repeat(frames, M), "marker": np.tile(markers, n_frames),
                          "x": xyz[..., 0].ravel(), "y": xyz[..., 1].ravel(), "z": xyz[..., 2].ravel()})
    uv = rig.project(xyz)  # (C, F, M, 2)
    seen = np.isfinite(uv[..., 0])
    if "wrist_r" in markers:
        j = markers.index("wrist_r")
        seen[1:, 10:18, j] = False
        seen[:, 18:26, j] = False
    uv_obs = uv + rng.normal(0, 0.5, uv.shape)
    c_i, f_i, m_i = np.nonzero(seen)
    obs = pd.DataFrame({"frame": frames[f_i], "camera": np.array(rig.names)[c_i],
                        "marker": np.array(markers)[m_i], "u": uv_obs[c_i, f_i, m_i, 0],
                        "v": uv_obs[c_i, f_i, m_i, 1], "weight": 1.0})
    n_views = seen.sum(axis=0)
    status = np.where(n_views >= 2, "observed", np.where(n_views == 1, "single_view", "unobserved"))
    trajs, reps = [], []
    for k, m in enumerate(methods):
        sigma = (0.002 + 0.001 * k) * np.where(status == "observed", 1.0, 4.0)  # (F, M) [m]
        est = xyz + rng.normal(size=xyz.shape) * sigma[..., None]
        if m == "triangulate":
            est[n_views < 2] = np.nan
        var = np.where(np.isfinite(est[..., 0]), sigma**2, np.nan)
        trajs.append(pd.DataFrame({
            "method": m, "frame": np.repeat(frames, M), "time_s": np.repeat(t, M),
            "marker": np.tile(markers, n_frames), "x": est[..., 0].ravel(), "y": est[..., 1].ravel(),
            "z": est[..., 2].ravel(), "cov_xx": var.ravel(), "cov_xy": 0.0, "cov_xz": 0.0,
            "cov_yy": var.ravel(), "cov_yz": 0.0, "cov_zz": var.ravel(), "n_views": n_views.ravel(),
            "status": status.ravel()}))
        uv_hat = rig.project(est)[c_i, f_i, m_i]
        rep = obs[["frame", "camera", "marker", "u", "v"]].assign(
            method=m, u_hat=uv_hat[:, 0], v_hat=uv_hat[:, 1])
        rep["err_px"] = np.hypot(rep["u_hat"] - rep["u"], rep["v_hat"] - rep["v"])
        rep["outlier"] = False
        rep.loc[rep.index[:2], "outlier"] = True
        reps.append(rep)
    session = Session(name=name, fps=fps, rig=rig, observations=obs, marker_names=list(markers),
                      skeleton=list(zip(markers[:-1], markers[1:], strict=True)), truth=truth)
    traj = evaluate.add_span(pd.concat(trajs, ignore_index=True))
    rep = pd.concat(reps, ignore_index=True)
    summary = summarize(session, traj, rep, runtimes={m: 0.1 * (k + 1) for k, m in enumerate(methods)})
    return session, traj, rep, summary


def typed(session, traj, rep, summary: dict | None = None) -> Summary:
    """The Summary the report draws: ``summary`` (summary.json's dict) typed, or computed from the tables."""
    return Summary.from_json(summary if summary is not None else summarize(session, traj, rep))


class _Collector(HTMLParser):
    """Collects figures (their SVG's aria-label), links, sections, table rows (as lists of cell texts) from the
    report."""

    def __init__(self):
        super().__init__()
        self.figures, self.imgs, self.hrefs, self.srcs, self.sections, self.tables = [], [], [], [], [], []
        self._row, self._cell, self._depth = None, None, 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.imgs.append(a.get("src", ""))
        if tag == "svg" and a.get("class") == "fig":
            self.figures.append(a.get("aria-label"))
        if "src" in a:
            self.srcs.append(a["src"])
        if "href" in a:
            self.hrefs.append(a["href"])
        if tag == "section":
            self.sections.append(a.get("id"))
        if tag == "table":
            self.tables.append((a.get("class"), []))
        if tag == "tr":
            self._row = []
        if tag in ("td", "th"):
            self._cell = []

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._row is not None:
            self._row.append("".join(self._cell or []).strip())
            self._cell = None
        if tag == "tr" and self._row is not None:
            self.tables[-1][1].append(self._row)
            self._row = None


def parse(text: str) -> _Collector:
    p = _Collector()
    p.feed(text)
    return p


def table(p: _Collector, cls: str) -> list[list[str]]:
    rows = [rows for c, rows in p.tables if c == cls]
    assert len(rows) == 1, f"expected one table of class {cls!r}"
    return rows[0]


# ----------------------------------------------------------------------------------------------
def test_mm_at_depth_is_exact_on_the_optical_axis():
    """A point 2 m in front of an f = 1000 px camera: 1 px = 2 mm, so 5 px (3, 4) -> 10 mm (6, 8)."""
    cam = Camera("c", (1280, 720), [[1000, 0, 640], [0, 1000, 360], [0, 0, 1]])
    rig = Rig([cam])
    traj = pd.DataFrame({"method": ["a", "b"], "frame": [0, 0], "marker": ["m", "m"],
                         "x": [0.0, np.nan], "y": [0.0, np.nan], "z": [2.0, np.nan]})
    rep = pd.DataFrame({"method": ["a", "b", "a", "a"], "frame": [0, 0, 0, 0], "camera": ["c", "c", "nope", "c"],
                        "marker": ["m", "m", "m", "m"], "u": [640.0] * 4, "v": [360.0] * 4,
                        "u_hat": [643.0, 643.0, 643.0, 700.0], "v_hat": [364.0, 364.0, 364.0, 360.0],
                        "err_px": [5.0, 5.0, 5.0, 60.0], "outlier": [False, False, False, True]})
    out = evaluate.reprojection_in_mm(rep, traj, rig)
    assert out["depth_m"].iloc[0] == pytest.approx(2.0, abs=1e-12)
    assert out[["err_mm", "du_mm", "dv_mm"]].iloc[0].tolist() == pytest.approx([10.0, 6.0, 8.0], abs=1e-9)
    # no estimate (method b) and a camera missing from the rig give NaN, not an exception
    assert out["err_mm"].iloc[1:3].isna().all()
    session = Session(name="s", fps=100.0, rig=rig, observations=pd.DataFrame())
    stats = evaluate.reprojection_stats(session, out[out["method"] == "a"])["c"]
    # the flagged observation (60 px) is counted but left out of every figure
    assert stats["n"] == 1 and stats["n_outliers"] == 1 and stats["outlier_fraction"] == 0.5
    assert stats["mean_mm_at_depth"] == pytest.approx(10.0) and stats["rms_px"] == pytest.approx(5.0)


def test_truth_metrics_on_a_known_offset():
    """Every estimate off by exactly 3 mm in x: RMSE = 3 mm; d^2 = (3/sigma)^2 is 9 for sigma = 1 mm
    (outside the 95 % ellipsoid, 7.815) and 2.25 for sigma = 2 mm (inside); no tolerance needed
    beyond float rounding. Groups follow status and span."""
    pts = pd.DataFrame({"frame": [0, 1, 2, 3], "marker": "m", "x": 0.0, "y": 0.0, "z": 1.0})
    rows = []
    for meth, sd in (("tight", 0.001), ("loose", 0.002)):
        rows.append(pts.assign(method=meth, x=0.003, cov_xx=sd**2, cov_xy=0.0, cov_xz=0.0, cov_yy=sd**2,
                               cov_yz=0.0, cov_zz=sd**2, n_views=[2, 2, 1, 0],
                               status=["observed", "observed", "single_view", "unobserved"]))
    traj = evaluate.add_span(pd.concat(rows, ignore_index=True))
    assert traj["span"].tolist()[:4] == ["inside", "inside", "outside", "outside"]
    traj.loc[3, ["x", "y", "z"]] = np.nan  # one missing estimate is skipped, not counted as an error
    err = evaluate.point_errors(traj, pts)
    assert len(err) == 7
    assert err["mahal2"].to_numpy() == pytest.approx(np.where(err["method"] == "tight", 9.0, 2.25))
    assert 9.0 > CHI2_3DOF_95 > 2.25
    tight = evaluate.truth_stats(traj[traj["method"] == "tight"], pts)
    loose = evaluate.truth_stats(traj[traj["method"] == "loose"], pts)
    assert tight["rmse_m"]["all"] == pytest.approx(0.003) and loose["rmse_m"]["outside"] == pytest.approx(0.003)
    assert tight["coverage95"]["all"] == 0.0 and loose["coverage95"]["all"] == 1.0
    assert tight["n_estimated"]["all"] == 3 and loose["n_estimated"]["all"] == 4 and tight["n"]["all"] == 4
    assert loose["n_estimated"]["observed/inside"] == 2 and loose["n_estimated"]["single_view/outside"] == 1
    assert tight["n_estimated"]["unobserved"] == 0 and tight["rmse_m"]["unobserved"] is None


def test_full_report_has_every_section_and_is_self_contained(tmp_path):
    """Truth and a reference present: 8 figures (the animal, the data map and 6 more), the verdict first,
    per-camera rows, no external links; every number in a table is summary.json's."""
    session, traj, rep, _ = make_scene(methods=("smoother", "ekf", "ukf", "triangulate"))
    session.reference = session.truth.assign(x=session.truth["x"] + 0.0005)  # a DLTdv-like reference
    summary = summarize(session, traj, rep)
    path = write_report(tmp_path / "out" / "report.html", session, traj, rep, typed(session, traj, rep, summary))
    text = path.read_text(encoding="utf-8")
    assert list(tmp_path.joinpath("out").iterdir()) == [path]  # atomic: no temporary left behind
    p = parse(text)
    assert p.sections == ["verdict", "overview", "trajectories", "ellipses", "features", "coordinates", "table",
                          "truth", "reference"]
    assert len(p.figures) == 8 and not p.imgs
    svgs = figure_svgs(text)
    assert len(svgs) == 8
    for fig in svgs:  # every figure draws something: paths (lines, points, bands) and texts (ticks, labels)
        assert len(fig.findall(".//path")) >= 5 and len(fig.findall(".//text")) >= 5
    clip_ids = re.findall(r'<clipPath id="([^"]+)"', text)
    assert len(clip_ids) == len(set(clip_ids))  # unique in the page, so each figure clips to its own panels
    assert set(re.findall(r'url\(#([^)]+)\)', text)) <= set(clip_ids)
    # self-contained: only embedded data and in-page anchors
    assert all(s.startswith("data:") for s in p.srcs)
    assert all(h.startswith("#") for h in p.hrefs)
    assert not re.search(r"<(script|link|iframe)\b", text, re.I)
    assert not re.search(r"(https?:)?//[a-z]", re.sub(r"data:[^\"]+", "", text), re.I)
    assert "Use the smoother result" in re.sub(r"<[^>]+>", "", text)

    cams = table(p, "cameras")
    header, body = cams[0], cams[1:]
    assert "mean [mm at depth]" in header and "paper (published)" not in header  # not declared a paper scene
    cam_rows = [r for r in body if r[0] in session.rig.names]  # first row of each camera's group
    assert [r[0] for r in cam_rows] == session.rig.names
    assert len(body) == 3 * 4  # every (camera, method) pair
    s1 = summary["methods"]["smoother"]["reprojection"]["cam1"]
    assert cam_rows[0][2] == f"{s1['n']}" and cam_rows[0][3] == "2"  # inliers, and the 2 flagged
    assert cam_rows[0][5] == f"{s1['mean_px']:.2f}"

    compare = table(p, "compare")
    rows = {r[0]: r for r in compare[1:]}
    c = summary["comparison"]["groups"]["observed/inside"]
    assert rows["seen by >= 2 cameras"][1] == str(c["n"])
    assert rows["seen by >= 2 cameras"][2].startswith(f"{1000 * c['values']['smoother']['rmse_m']:.2f}")
    assert rows["gaps seen by 1 camera"][-1] == "not estimated"  # triangulation: one camera is not enough

    status_tables = [rows for c, rows in p.tables if c == "status"]
    assert len(status_tables) == 2
    truth_rows = {r[0]: r for r in status_tables[0][1:]}
    assert set(truth_rows) == {"smoother", "ekf", "ukf", "triangulate"}
    t = summary["methods"]["smoother"]["truth"]
    assert truth_rows["smoother"][2] == f"{t['rmse_m']['observed/inside'] * 1000:.2f}"
    assert truth_rows["triangulate"][4] == "0"  # n of one-camera gaps: triangulation estimates none


def figure_svgs(text: str) -> list:
    """Every figure's <svg> element of the report, parsed as XML (so each is well-formed)."""
    import xml.etree.ElementTree as ET

    return [ET.fromstring(m) for m in re.findall(r'<svg class="fig".*?</svg>', text, re.S)]


def test_figures_keep_their_texts_inside_their_canvas():
    """Every text of every figure (ticks, labels, titles, legends), at its estimated width, lies inside its
    figure's canvas, also with 12 cameras and a long marker name, and with one marker (a figure as narrow as its
    one legend entry): nothing is cut off at the figure's edge."""
    from batgraph.svg import text_width

    for kw in ({}, {"n_cams": 12, "markers": MARKERS[:-1] + ["a_rather_long_marker_name_on_the_tail"]},
               {"markers": ["body2"]}):
        session, traj, rep, _ = make_scene(methods=("smoother", "ekf", "ukf", "triangulate"), **kw)
        session.reference = session.truth.assign(x=session.truth["x"] + 0.0005)
        svgs = figure_svgs(render_report(session, traj, rep, typed(session, traj, rep)))
        assert len(svgs) == 8
        for fig in svgs:
            w, h = float(fig.get("width")), float(fig.get("height"))
            for t in fig.iter("text"):
                x, y, size = float(t.get("x")), float(t.get("y")), float(t.get("font-size"))
                width = text_width(t.text or "", size)
                lo = {"start": 0.0, "middle": 0.5, "end": 1.0}[t.get("text-anchor")] * width
                if t.get("transform"):  # rotated by -90 degrees about (x, y): the text runs upward
                    box = (x - size, y - width + lo, x + 0.3 * size, y + lo)
                else:
                    box = (x - lo, y - size, x - lo + width, y + 0.3 * size)
                assert box[0] >= -1 and box[1] >= -1 and box[2] <= w + 1 and box[3] <= h + 1, \
                    (fig.get("aria-label"), t.text, box, (w, h))


def test_finite_runs_are_the_pieces_plot_draws():
    """NaN splits a track; single points between NaNs draw nothing (as with ``plot``) and are left out."""
    from batgraph.report import _finite_runs

    track = np.array([[0, 0], [1, 1], [np.nan, 2], [3, 3], [np.nan, 4], [5, 5], [6, 6], [7, 7]], float)
    runs = _finite_runs(np.stack([track, track[::-1]]))
    assert [r[:, 0].tolist() for r in runs] == [[0, 1], [5, 6, 7], [7, 6, 5], [1, 0]]


def test_paper_figures_only_for_a_declared_paper_scene(tmp_path):
    """A session named like the paper's ear experiment gets no paper column; one that declares
    ``[paper] experiment = "flight"`` gets the flight figures."""
    session, traj, rep, _ = make_scene(n_cams=2, methods=("smoother", "ekf"), name="ear_session")
    p = parse(render_report(session, traj, rep, typed(session, traj, rep)))
    assert "paper (published)" not in table(p, "cameras")[0]
    session.extra_toml = {"paper": {"experiment": "flight"}}
    p = parse(render_report(session, traj, rep, typed(session, traj, rep)))
    cams = [r for r in table(p, "cameras")[1:] if r[0] in session.rig.names]
    assert cams[0][-1] == "< 3 mm" and cams[1][-1] == "< 20 mm"


def test_report_without_truth_or_reference_omits_those_sections(tmp_path):
    """No truth, no reference, and a method with no estimate at all still render; the comparison is then
    on reprojection."""
    session, traj, rep, _ = make_scene(n_cams=2, methods=("filter", "triangulate"), name="ear_session")
    session.truth = None
    traj.loc[traj["method"] == "triangulate", ["x", "y", "z"]] = np.nan
    rep = rep[rep["method"] == "filter"]
    text = write_report(tmp_path / "report.html", session, traj, rep, typed(session, traj, rep)).read_text(
        encoding="utf-8")
    p = parse(text)
    assert p.sections == ["verdict", "overview", "trajectories", "ellipses", "features", "coordinates", "table"]
    assert len(p.figures) == 6
    assert "Errors against truth" not in text and "reference reconstruction" not in text.split("</nav>")[0]
    cams = table(p, "cameras")[1:]
    assert [r[0] for r in cams] == ["cam1", "cam2"]
    runs = {r[0]: r for r in table(p, "runs")[1:]}
    assert runs["triangulate"][2].startswith("0 / ")


def test_report_shows_summary_numbers_as_given(tmp_path):
    """The report draws summary.json's figures and recomputes none of them."""
    session, traj, rep, summary = make_scene(methods=("smoother", "ukf"))
    summary["methods"]["smoother"]["reprojection"]["cam2"]["mean_px"] = 123.456
    summary["methods"]["ukf"]["truth"]["rmse_m"]["observed/inside"] = 0.04321
    summary["methods"]["ukf"]["truth"]["coverage95"]["observed/inside"] = 0.5
    p = parse(render_report(session, traj, rep, typed(session, traj, rep, summary)))
    cams = table(p, "cameras")[1:]
    row = next(i for i, r in enumerate(cams) if r[0] == "cam2")
    assert cams[row][1] == "smoother" and cams[row][5] == "123.46"
    truth = {r[0]: r for r in table(p, "status")[1:]}
    assert truth["ukf"][2] == "43.21" and truth["ukf"][3] == "50.0 %"


def test_report_says_when_the_track_ends_were_widened(tmp_path):
    """The data map's caption gives the smoother's track-end check (summary.json info.track_ends) when it widened
    covariances, and says nothing of it otherwise."""
    session, traj, rep, summary = make_scene(methods=("smoother", "ukf"))
    info = summary["methods"]["smoother"].setdefault("info", {})
    info["track_ends"] = {"backtest_frames": 8, "markers": 14, "samples": 201, "median_ratio": 2.1887,
                          "p95_ratio": 3.0412, "growth_per_frame": 0.3678, "widened_points": 44, "ray_samples": 100,
                          "ray_p95_ratio": 2.7607, "ray_growth_per_frame": 0.3647, "widened_single_view_points": 67}
    text = re.sub(r"<[^>]+>", "", render_report(session, traj, rep, typed(session, traj, rep, summary)))
    assert ("checked its extrapolation on 14 tracks (their first and last 8 frames hidden) and widened the "
            "covariances of the 44 unseen points at the track ends by 1 + 0.368 h (the 95th percentile of the squared "
            "errors was 3.04x what its covariances said) and the variance along the ray of the 67 points seen by one "
            "camera there by 1 + 0.365 h (the errors along those cameras' rays: 2.76x), h the distance") in text
    info["track_ends"].update(depth_floored_points=12, ray_p95_ratio=None)  # floored; no backtest along the rays
    text = re.sub(r"<[^>]+>", "", render_report(session, traj, rep, typed(session, traj, rep, summary)))
    assert ("the variance along the ray of the 67 points seen by one camera there (12 of them first raised to the "
            "variance the solve gives them without that view) by 1 + 0.365 h, h the distance") in text
    info["track_ends"].update(widened_single_view_points=0)
    text = re.sub(r"<[^>]+>", "", render_report(session, traj, rep, typed(session, traj, rep, summary)))
    assert "said), h the distance" in text and "along the ray" not in text
    info["track_ends"].update(growth_per_frame=0.0, widened_points=0, widened_single_view_points=0)
    assert "checked its extrapolation" not in render_report(session, traj, rep, typed(session, traj, rep, summary))


def test_degenerate_inputs_still_render(tmp_path):
    """No reprojection rows and a single method without any estimate: every figure section says so,
    and the truth section (nothing to compare) is left out."""
    session, traj, rep, _ = make_scene(n_cams=2, n_frames=12, methods=("smoother",))
    traj[["x", "y", "z"]] = np.nan
    text = render_report(session, traj, rep.iloc[:0], typed(session, traj, rep.iloc[:0]))
    p = parse(text)
    assert p.sections == ["verdict", "overview", "trajectories", "ellipses", "features", "coordinates", "table"]
    assert len(p.figures) == 1  # the marker x frame map: where the data are, even without an estimate
    assert text.count("No data to draw") == 5  # the animal too
    assert "No reprojection errors." in text


def test_per_camera_figures_draw_at_most_ten_panels_and_say_which():
    """A 30-camera rig: the two per-camera figures draw 10 evenly spaced cameras (first and last included) and
    their captions name them; every camera keeps its row in the per-camera table."""
    from batgraph.report import MAX_CAMERA_PANELS, _panel_cameras

    names = [f"cam{i}" for i in range(1, 31)]
    drawn, note = _panel_cameras(names)
    assert len(drawn) == MAX_CAMERA_PANELS == 10 and drawn[0] == "cam1" and drawn[-1] == "cam30"
    assert len(set(drawn)) == 10 and "10 of the 30 cameras" in note and "cam30" in note
    assert _panel_cameras(names[:10]) == (names[:10], "")


def test_section_titles_are_unique_and_the_paper_is_cited_in_full():
    """Each section has its own title (the figure of residual ellipses and the per-camera table were both
    "Reprojection error per camera"), and the paper is cited by authors and title, never by a file name."""
    import html

    session, traj, rep, _ = make_scene(methods=("smoother", "ekf"))
    session.extra_toml = {"paper": {"experiment": "flight"}}
    text = render_report(session, traj, rep, typed(session, traj, rep))
    titles = [re.sub(r"\s*\(.*\)$", "", t) for t in re.findall(r"<h2>(.*?)</h2>", text)]  # without remarks
    assert len(titles) >= 7 and len(titles) == len(set(titles)), titles
    plain = html.unescape(re.sub(r"<[^>]+>", "", text))
    assert "M. J. Bender, H. G. McClelland, G. Bledt, A. Kurdila, T. Furukawa and R. Müller" in plain
    assert "Trajectory Estimation of Bat Flight Using a Multi-View Camera System" in plain and "AIAA" in plain
    assert not re.search(r"PAPER\.md|CONTRACT\.md", text)


def test_3d_panels_are_readable_with_26_markers():
    """26 markers: the 3D figure's panels are at least 500 px wide, its legend names every marker, and no two
    markers are drawn alike (colour and dash)."""
    from batgraph.report import _marker_styles

    names = [f"marker_{i:02d}" for i in range(26)]
    session, traj, rep, _ = make_scene(methods=("smoother", "ekf", "ukf"), markers=names)
    (fig,) = [f for f in figure_svgs(render_report(session, traj, rep, typed(session, traj, rep)))
              if f.get("aria-label") == "3D trajectories per method"]
    texts = {t.text for t in fig.iter("text")}
    assert set(names) <= texts
    widths = [float(r.get("width")) for clip in fig.iter("clipPath") for r in clip.iter("rect")]  # the panels
    assert len(widths) == 3 and min(widths) >= 500, widths
    styles = _marker_styles(names)
    assert len({(s["colour"], s["dash"]) for s in styles}) == 26


def test_the_first_screen_shows_the_animal_with_names_on_hover():
    """The verdict's section draws the verdict method's markers on the opening frame, each dot titled with its
    marker's name (a browser shows it on hover), beside the headlines."""
    session, traj, rep, summary = make_scene(methods=("smoother", "ekf"))
    s = typed(session, traj, rep, summary)
    assert s.opening_frame is not None
    text = render_report(session, traj, rep, s)
    verdict = text.split('<section id="overview">')[0]
    (fig,) = [f for f in figure_svgs(verdict) if f.get("aria-label") == "the animal on its first well-seen frame"]
    titles = [t.text for t in fig.iter("title")]
    assert set(titles) <= set(MARKERS) and len(titles) >= 4
    assert f"on frame {s.opening_frame} " in "".join(t.text or "" for t in fig.iter("text"))
