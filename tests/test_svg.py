"""Tests of batgraph.svg, the report's chart layer: ticks, the data -> pixel mapping, broken lines, equal axes,
and the 3D view against matplotlib's own orthographic projection."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from batgraph import svg


@pytest.mark.parametrize("lo,hi,n", [(0, 1, 5), (-0.0731, 0.0412, 4), (1.5, 1.5004, 3), (-2.1, 2.2, 5),
                                     (0, 1330, 5), (0.93, 1.07, 3)])
def test_nice_ticks_are_round_inside_the_range_and_few(lo, hi, n):
    ticks, labels = svg.nice_ticks(lo, hi, n)
    assert 2 <= len(ticks) <= n + 1
    assert ticks.min() >= lo - 1e-12 and ticks.max() <= hi + 1e-12
    step = np.diff(ticks)
    assert np.allclose(step, step[0])
    mantissa = step[0] / 10 ** np.floor(np.log10(step[0]))
    assert any(np.isclose(mantissa, m) for m in (1, 2, 2.5, 5))
    assert [float(s) for s in labels] == pytest.approx(ticks.tolist(), abs=step[0] * 1e-6)  # labels say the value
    assert len(set(labels)) == len(labels)


def test_log_ticks_are_decades_or_their_2_and_5_multiples():
    assert svg.log_ticks(0.5, 2000)[1] == ["1", "10", "100", "1000"]
    ticks, labels = svg.log_ticks(0.8, 30)
    assert labels == ["1", "2", "5", "10", "20"]


def test_axes_map_data_to_its_box():
    fig = svg.Figure(200, 100)
    ax = fig.add_axes((10, 20, 100, 50), (0, 10), (-1, 1))
    assert ax.px([0, 10]).tolist() == [10, 110]
    assert ax.py([-1, 1]).tolist() == [70, 20]  # y up: the low limit at the box's bottom
    down = fig.add_axes((10, 20, 100, 50), (0, 10), (0, 720), y_down=True)
    assert down.py([0, 720]).tolist() == [20, 70]  # image rows: v grows downward
    log = fig.add_axes((0, 0, 100, 100), (0, 1), (1, 100), ylog=True)
    assert log.py([1, 10, 100]).tolist() == pytest.approx([100, 50, 0])


def test_equal_axes_shrink_the_box_to_the_data_proportions():
    fig = svg.Figure(400, 400)
    ax = fig.add_axes((0, 0, 300, 300), (0, 3), (0, 1), equal=True)
    assert ax.box == pytest.approx((0, 100, 300, 100))  # centred, one data unit = 100 px on both axes
    assert np.ptp(ax.px([0, 1])) == pytest.approx(np.ptp(ax.py([0, 1])))


def test_a_line_breaks_at_nan_and_drops_lone_points():
    fig = svg.Figure(100, 100)
    ax = fig.add_axes((0, 0, 100, 100), (0, 10), (0, 10))
    ax.line([0, 1, np.nan, 3, np.nan, 5, 6, 7], [0, 1, 2, 3, 4, 5, 6, 7], "#000")
    d = re.search(r'd="([^"]+)"', ax.parts[0]).group(1)
    pieces = d.split("M")[1:]
    assert [len(p.split()) for p in pieces] == [2, 3]  # [0, 1] and [5, 6, 7]; the lone point 3 is not drawn


def test_a_figure_is_well_formed_svg_with_its_own_clip_ids():
    fig = svg.Figure(300, 200)
    ax = fig.add_axes((40, 10, 250, 150), (0, 1), (0, 1))
    ax.points([0.2, 0.5], [0.3, np.nan], "#f00", hollow=True)
    ax.rects(np.array([0.1]), np.array([0.2]), np.array([0.0]), np.array([1.0]), "#0f0")
    ax.frame("x & more", "y < 1", "title")
    root = ET.fromstring(fig.svg("k7", "a <test>"))
    assert root.get("aria-label") == "a <test>"
    assert [c.get("id") for c in root.iter("clipPath")] == ["k7c0"]
    texts = [t.text for t in root.iter("text")]
    assert "x & more" in texts and "y < 1" in texts and "title" in texts


def test_the_3d_view_is_matplotlibs_orthographic_view():
    """svg.View3D projects like matplotlib's 3D axes with the same limits, box aspect, elevation and azimuth
    (orthographic): the two agree up to one scale and a shift."""
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d import proj3d

    lo, hi, aspect = np.array([-2.0, -0.4, 0.1]), np.array([2.5, 0.6, 0.5]), np.array([4.5, 1.2, 1.1])
    rng = np.random.default_rng(3)
    pts = lo + (hi - lo) * rng.random((50, 3))
    view = svg.View3D(lo, hi, aspect, elev=22, azim=-65)
    X, Y = view.project(pts)
    ax = Figure().add_subplot(projection="3d", proj_type="ortho")
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
    ax.set_box_aspect(aspect)
    ax.view_init(elev=22, azim=-65)
    mx, my, _ = proj3d.proj_transform(*pts.T, ax.get_proj())
    (sx, cx), (sy, cy) = np.polyfit(X, mx, 1), np.polyfit(Y, my, 1)
    assert np.allclose(sx * X + cx, mx, atol=1e-9) and np.allclose(sy * Y + cy, my, atol=1e-9)
    assert sx == pytest.approx(sy, rel=1e-6)  # one scale for both axes: the same picture, not a stretched one
