"""Small charts as inline SVG text: the report's figures (batgraph.report), drawn by the browser.

Why not matplotlib: it builds a Python object per tick, label and line and rasterises them, seconds of
CPU for a report's figures; here a figure is a few strings per panel, each line or point cloud one SVG
element whose coordinates numpy formats in one call, and the figures stay sharp at any zoom. Why not a
JavaScript plotting library: the report is one self-contained file without scripts, and the figures need
only lines, bands, points, ellipses, rectangles and text.

Units: pixels of the figure's own canvas (``width`` x ``height``; SVG's y axis points down). A
:class:`Figure` holds :class:`Axes` panels, each mapping data coordinates into its box (linear or log10
axes; ``y_down`` for image coordinates). A NaN in a line breaks it, as in matplotlib's ``plot``. Colours
are CSS colour strings; ``dash`` is a matplotlib line style ("-", "--", "-.", ":").
"""

from __future__ import annotations

import html
import itertools
import math

import numpy as np

FONT = "-apple-system,Segoe UI,Helvetica,Arial,sans-serif"
TAB10 = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
         "#17becf")
TAB20 = ("#1f77b4", "#aec7e8", "#ff7f0e", "#ffbb78", "#2ca02c", "#98df8a", "#d62728", "#ff9896", "#9467bd",
         "#c5b0d5", "#8c564b", "#c49c94", "#e377c2", "#f7b6d2", "#7f7f7f", "#c7c7c7", "#bcbd22", "#dbdb8d",
         "#17becf", "#9edae5")
DASHES = {"-": "", "solid": "", "--": "6,3", "dashed": "6,3", "-.": "7,2.5,1.5,2.5", "dashdot": "7,2.5,1.5,2.5",
          ":": "1.5,2", "dotted": "1.5,2"}
CHAR_WIDTH = 0.58  # mean width of a character of FONT, in font sizes (for layout only: legends, margins)


def colours(n: int) -> list[str]:
    """``n`` distinct colours (matplotlib's tab10, or tab20 beyond 10, repeating past 20)."""
    table = TAB10 if n <= 10 else TAB20
    return [table[i % len(table)] for i in range(n)]


def text_width(s: str, size: float) -> float:
    """The approximate width [px] of ``s`` at font ``size`` [px] (for layout)."""
    return CHAR_WIDTH * size * len(s)


def _num(v: float) -> str:
    return f"{v:.1f}".rstrip("0").rstrip(".") if math.isfinite(v) else "0"


def _coords(x: np.ndarray, y: np.ndarray) -> str:
    """'x,y x,y ...' with one decimal, formatted in one call."""
    xy = np.empty(2 * len(x))
    xy[0::2], xy[1::2] = x, y
    return ("%.1f,%.1f " * len(x) % tuple(xy.tolist())).rstrip()


def _dash(ls: str | None, width: float) -> str:
    d = DASHES.get(ls or "-", "")
    if not d:
        return ""
    return f' stroke-dasharray="{",".join(_num(float(p) * max(width, 0.8)) for p in d.split(","))}"'


def nice_ticks(lo: float, hi: float, n: int = 5) -> tuple[np.ndarray, list[str]]:
    """At most about ``n`` round tick values in [lo, hi] (steps of 1, 2, 2.5 or 5 x 10^k) and their labels."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo]), [f"{lo:g}"]
    raw = (hi - lo) / max(n, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw * 0.999)
    ticks = np.arange(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1) * step
    decimals = max(0, -math.floor(math.log10(step) + 1e-9) + (1 if round(step / mag, 6) == 2.5 else 0))
    labels = [f"{0.0 if abs(t) < step * 1e-9 else t:.{decimals}f}" for t in ticks]
    return ticks, labels


def log_ticks(lo: float, hi: float) -> tuple[np.ndarray, list[str]]:
    """Ticks of a log10 axis over [lo, hi] (> 0): the powers of ten, with 2 and 5 between them when the range
    spans less than two decades; labels as plain numbers ("0.1", "20")."""
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    mult = (1,) if math.log10(hi / lo) >= 2 else (1, 2, 5)
    ticks = np.array([m * 10.0 ** k for k in range(k0, k1 + 1) for m in mult])
    ticks = ticks[(ticks >= lo * (1 - 1e-9)) & (ticks <= hi * (1 + 1e-9))]
    return ticks, [f"{t:g}" for t in ticks]


class Axes:
    """One panel: data (x, y) mapped into the box (left, top, width, height) [px] of its :class:`Figure`.

    xlim, ylim: (low, high) data limits; xlog / ylog: log10 axes; y_down: y grows downward (image pixels).
    equal: one data unit is as long on both axes (the box shrinks to the limits' proportions, centred).
    Every drawing is clipped to the box.
    """

    def __init__(self, fig: Figure, box: tuple[float, float, float, float], xlim, ylim, xlog: bool = False,
                 ylog: bool = False, y_down: bool = False, equal: bool = False):
        self.fig, self.box = fig, tuple(float(b) for b in box)
        self.xlog, self.ylog, self.y_down = xlog, ylog, y_down
        xlim, ylim = self._limits(xlim, xlog), self._limits(ylim, ylog)
        if equal:  # the box shrinks to the data's proportions, centred in the space given (matplotlib's "box")
            left, top, w, h = self.box
            dx, dy = self._span(xlim, xlog), self._span(ylim, ylog)
            if dx / dy > w / h:
                self.box = (left, top + (h - w * dy / dx) / 2, w, w * dy / dx)
            else:
                self.box = (left + (w - h * dx / dy) / 2, top, h * dx / dy, h)
        self.xlim, self.ylim = xlim, ylim
        self.parts: list[str] = []
        self.index = len(fig.axes)
        fig.axes.append(self)

    @staticmethod
    def _span(lim: tuple[float, float], log: bool) -> float:
        return math.log10(lim[1] / lim[0]) if log else lim[1] - lim[0]

    @staticmethod
    def _limits(lim, log: bool) -> tuple[float, float]:
        lo, hi = float(lim[0]), float(lim[1])
        if log:
            lo, hi = max(lo, 1e-300), max(hi, 1e-300)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            lo, hi = 0.0, 1.0
        if hi <= lo:
            pad = abs(lo) * 0.1 if lo else 1.0
            lo, hi = (lo / 2, lo * 2) if log else (lo - pad, hi + pad)
        return lo, hi

    @staticmethod
    def _fraction(v, lim: tuple[float, float], log: bool) -> np.ndarray:
        """Data values v -> their fraction of the axis range lim (0 at lim[0], 1 at lim[1]; log10 scale if log)."""
        v = np.asarray(v, float)
        lo, hi = lim
        if log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v, lo, hi = np.log10(v), math.log10(lo), math.log10(hi)
        return (v - lo) / (hi - lo)

    def px(self, x) -> np.ndarray:
        """Data x -> figure px (array)."""
        return self.box[0] + self._fraction(x, self.xlim, self.xlog) * self.box[2]

    def py(self, y) -> np.ndarray:
        """Data y -> figure px (array)."""
        frac = self._fraction(y, self.ylim, self.ylog)
        return self.box[1] + (frac if self.y_down else 1.0 - frac) * self.box[3]

    # --- drawing (data coordinates)
    def line(self, x, y, colour: str, width: float = 1.0, dash: str | None = "-", opacity: float = 1.0) -> None:
        """A polyline through (x, y), broken at non-finite points (single points between breaks draw nothing)."""
        X, Y = self.px(x), self.py(y)
        ok = np.isfinite(X) & np.isfinite(Y)
        if ok.sum() < 2:
            return
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        d = "".join(f"M{_coords(X[a:b], Y[a:b])}" for a, b in zip(edges[0::2], edges[1::2], strict=True)
                    if b - a >= 2)
        self.parts.append(f'<path d="{d}" fill="none" stroke="{colour}" stroke-width="{_num(width)}"'
                          f'{_dash(dash, width)}{_opacity(opacity, "stroke")} stroke-linejoin="round"/>')

    def band(self, x, lo, hi, colour: str, opacity: float = 0.15) -> None:
        """The area between lo and hi over x, one polygon per finite run."""
        X, L, H = self.px(x), self.py(lo), self.py(hi)
        ok = np.isfinite(X) & np.isfinite(L) & np.isfinite(H)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        d = "".join(f"M{_coords(np.concatenate([X[a:b], X[a:b][::-1]]), np.concatenate([L[a:b], H[a:b][::-1]]))}Z"
                    for a, b in zip(edges[0::2], edges[1::2], strict=True) if b - a >= 2)
        if d:
            self.parts.append(f'<path d="{d}" fill="{colour}"{_opacity(opacity, "fill")} stroke="none"/>')

    def polygon(self, x, y, fill: str, stroke: str = "none", width: float = 0.6) -> None:
        """A closed polygon through the data points (x, y)."""
        self.parts.append(f'<path d="M{_coords(self.px(x), self.py(y))}Z" fill="{fill}" stroke="{stroke}" '
                          f'stroke-width="{_num(width)}"/>')

    def points(self, x, y, colour: str, size: float = 2.0, opacity: float = 1.0, hollow: bool = False) -> None:
        """A dot (diameter ``size`` px) or, ``hollow``, a ring at each finite (x, y); one element for all."""
        X, Y = self.px(x), self.py(y)
        ok = np.isfinite(X) & np.isfinite(Y)
        X, Y = X[ok], Y[ok]
        if not len(X):
            return
        if hollow:  # two half-circle arcs per ring
            r = size / 2
            xy = np.empty(2 * len(X))
            xy[0::2], xy[1::2] = X - r, Y
            arc = f"a{_num(r)},{_num(r)} 0 1,0 {_num(2 * r)},0a{_num(r)},{_num(r)} 0 1,0 {_num(-2 * r)},0"
            d = ("M%.1f,%.1f" + arc) * len(X) % tuple(xy.tolist())
            self.parts.append(f'<path d="{d}" fill="none" stroke="{colour}" stroke-width="0.8"'
                              f'{_opacity(opacity, "stroke")}/>')
        else:  # zero-length strokes with round caps: a dot each
            xy = np.empty(2 * len(X))
            xy[0::2], xy[1::2] = X, Y
            d = "M%.1f,%.1fh0" * len(X) % tuple(xy.tolist())
            self.parts.append(f'<path d="{d}" stroke="{colour}" stroke-width="{_num(size)}" stroke-linecap="round"'
                              f'{_opacity(opacity, "stroke")}/>')

    def marks(self, x, y, colours: list[str], size: float, titles: list[str]) -> None:
        """A dot (diameter ``size`` px) at each (x, y) in its own colour, its title shown on hover (a browser's
        tooltip: the names of many points without a label on each)."""
        X, Y = self.px(x), self.py(y)
        for xi, yi, c, t in zip(X, Y, colours, titles, strict=True):
            if math.isfinite(xi) and math.isfinite(yi):
                self.parts.append(f'<circle cx="{_num(xi)}" cy="{_num(yi)}" r="{_num(size / 2)}" fill="{c}" '
                                  f'stroke="#222" stroke-width="0.6"><title>{html.escape(t)}</title></circle>')

    def rects(self, x0, x1, y0, y1, colour: str, opacity: float = 1.0) -> None:
        """Filled rectangles [x0, x1] x [y0, y1] (arrays of one length), one element for all."""
        X0, X1, Y0, Y1 = self.px(x0), self.px(x1), self.py(y0), self.py(y1)
        if not np.size(X0):
            return
        left, top = np.minimum(X0, X1), np.minimum(Y0, Y1)
        w, h = np.abs(X1 - X0), np.abs(Y1 - Y0)
        v = np.stack([left, top, w, h, -w], axis=1).ravel()
        d = "M%.2f,%.2fh%.2fv%.2fh%.2fz" * len(left) % tuple(v.tolist())
        self.parts.append(f'<path d="{d}" fill="{colour}"{_opacity(opacity, "fill")} stroke="none"/>')

    def vspan(self, x0, x1, colour: str) -> None:
        """Full-height spans [x0, x1] (arrays) in data x."""
        y = np.broadcast_to(self.ylim[0], np.shape(x0)), np.broadcast_to(self.ylim[1], np.shape(x0))
        self.rects(x0, x1, *y, colour)

    def hline(self, y: float, colour: str = "#b3b3b3", width: float = 0.5, dash: str = "-") -> None:
        self.line(self.xlim, [y, y], colour, width, dash)

    def vline(self, x: float, colour: str = "#b3b3b3", width: float = 0.5, dash: str = "-") -> None:
        self.line([x, x], self.ylim, colour, width, dash)

    def text(self, x: float, y: float, s: str, size: float = 10, colour: str = "#222", anchor: str = "start",
             dx: float = 0, dy: float = 0, weight: str = "normal") -> None:
        """Text at data (x, y), shifted by (dx, dy) px."""
        X, Y = float(self.px(x)), float(self.py(y))
        if math.isfinite(X) and math.isfinite(Y):
            self.parts.append(_text(X + dx, Y + dy, s, size, colour, anchor, weight=weight))

    # --- decoration (outside the clip)
    def frame(self, xlabel: str = "", ylabel: str = "", title: str = "", title_colour: str = "#222",
              xticks: bool = True, yticks: bool = True, n_xticks: int = 5, n_yticks: int = 5,
              yticklabels: tuple[np.ndarray, list[str]] | None = None) -> None:
        """The box, ticks with labels (nice_ticks / log_ticks unless given), axis labels and a title."""
        left, top, w, h = self.box
        out = self.fig.decor
        out.append(f'<rect x="{_num(left)}" y="{_num(top)}" width="{_num(w)}" height="{_num(h)}" fill="none" '
                   'stroke="#333" stroke-width="0.8"/>')
        if xticks:
            ticks, labels = log_ticks(*self.xlim) if self.xlog else nice_ticks(*self.xlim, n_xticks)
            X = self.px(ticks)
            out.append(_ticks(X, np.full(len(X), top + h), 0, 4))
            out.extend(_text(x, top + h + 15, lab, 10, anchor="middle") for x, lab in zip(X, labels, strict=True))
        ylabels: list[str] = []
        if yticks:
            ticks, ylabels = yticklabels if yticklabels is not None else (
                log_ticks(*self.ylim) if self.ylog else nice_ticks(*self.ylim, n_yticks))
            Y = self.py(ticks)
            out.append(_ticks(np.full(len(Y), left), Y, -4, 0))
            out.extend(_text(left - 6, y + 3.5, lab, 10, anchor="end") for y, lab in zip(Y, ylabels, strict=True))
        if xlabel:
            out.append(_text(left + w / 2, top + h + (33 if xticks else 16), xlabel, 11, anchor="middle"))
        if ylabel:
            room = max((text_width(lab, 10) + 14 for lab in ylabels), default=6)
            out.append(_text(left - room, top + h / 2, ylabel, 11, anchor="middle", rotate=True))
        if title:
            out.append(_text(left + w / 2, top - 7, title, 13, title_colour, "middle"))


def _opacity(a: float, what: str) -> str:
    return "" if a >= 1 else f' {what}-opacity="{a:.2f}"'


def _ticks(X: np.ndarray, Y: np.ndarray, dx: float, dy: float) -> str:
    xy = np.empty(2 * len(X))
    xy[0::2], xy[1::2] = X, Y
    d = (f"M%.1f,%.1fl{_num(dx)},{_num(dy)}" * len(X)) % tuple(xy.tolist())
    return f'<path d="{d}" stroke="#333" stroke-width="0.8"/>'


def _text(x: float, y: float, s: str, size: float, colour: str = "#222", anchor: str = "start",
          rotate: bool = False, weight: str = "normal") -> str:
    rot = f' transform="rotate(-90 {_num(x)} {_num(y)})"' if rotate else ""
    bold = ' font-weight="bold"' if weight == "bold" else ""
    return (f'<text x="{_num(x)}" y="{_num(y)}" font-size="{_num(size)}" fill="{colour}" text-anchor="{anchor}"'
            f'{bold}{rot}>{html.escape(str(s))}</text>')


class Figure:
    """An SVG canvas ``width`` x ``height`` [px] of :class:`Axes` panels, texts and legends."""

    def __init__(self, width: float, height: float):
        self.width, self.height = float(width), float(height)
        self.axes: list[Axes] = []
        self.decor: list[str] = []  # outside every panel's clip: frames, ticks, labels, legends

    def text(self, x: float, y: float, s: str, size: float = 11, colour: str = "#222", anchor: str = "start",
             rotate: bool = False, weight: str = "normal") -> None:
        self.decor.append(_text(x, y, s, size, colour, anchor, rotate, weight))

    def add_axes(self, box: tuple[float, float, float, float], xlim, ylim, **kw) -> Axes:
        """A panel in ``box`` (left, top, width, height) [px]; keywords as :class:`Axes`'s."""
        return Axes(self, box, xlim, ylim, **kw)

    def line(self, x, y, colour: str, width: float = 1.0, dash: str | None = "-", opacity: float = 1.0) -> None:
        """A polyline in figure px, outside every panel (e.g. a 3D panel's box)."""
        self.decor.append(f'<path d="M{_coords(np.asarray(x, float), np.asarray(y, float))}" fill="none" '
                          f'stroke="{colour}" stroke-width="{_num(width)}"{_dash(dash, width)}'
                          f'{_opacity(opacity, "stroke")}/>')

    def legend(self, items: list[tuple[str, dict]], x: float, y: float, ncol: int | None = None,
               anchor: str = "middle", size: float = 11) -> float:
        """A legend of ``items`` (label, style) in rows of ``ncol`` (default: as many as fit the figure's
        width), its top edge at y and
        its middle (anchor "middle") or left edge ("start") at x. A style is a line (colour, dash, width), a
        patch (colour, patch=True, opacity) or points (colour, points=True, hollow). Returns its height [px]."""
        if not items:
            return 0.0
        cell = max(text_width(lab, size) for lab, _ in items) + 40
        ncol = ncol or max(1, min(len(items), int((self.width - 20) // cell)))
        total_w = cell * min(ncol, len(items))
        x0 = x - total_w / 2 if anchor == "middle" else x
        for i, (lab, st) in enumerate(items):
            cx, cy = x0 + (i % ncol) * cell, y + (i // ncol) * (size + 7) + size / 2 + 2
            colour = st.get("colour", "#333")
            if st.get("patch"):
                self.decor.append(f'<rect x="{_num(cx)}" y="{_num(cy - 5)}" width="24" height="10" fill="{colour}"'
                                  f'{_opacity(st.get("opacity", 1.0), "fill")}/>')
            elif st.get("points"):
                r = 3.0
                fill = "none" if st.get("hollow") else colour
                self.decor.append(f'<circle cx="{_num(cx + 12)}" cy="{_num(cy)}" r="{r}" fill="{fill}" '
                                  f'stroke="{colour}" stroke-width="0.9"/>')
            else:
                w = st.get("width", 1.6)
                self.decor.append(f'<path d="M{_num(cx)},{_num(cy)}h24" stroke="{colour}" stroke-width="{_num(w)}"'
                                  f'{_dash(st.get("dash"), w)}{_opacity(st.get("opacity", 1.0), "stroke")}/>')
            self.decor.append(_text(cx + 30, cy + size * 0.35, lab, size))
        return math.ceil(len(items) / ncol) * (size + 7) + 4

    def svg(self, key: str, label: str) -> str:
        """The figure as one ``<svg>`` element; ``key`` makes its clip ids unique in the page, ``label`` is read
        by screen readers (aria-label)."""
        defs, body = [], []
        for ax in self.axes:
            cid = f"{key}c{ax.index}"
            left, top, w, h = ax.box
            defs.append(f'<clipPath id="{cid}"><rect x="{_num(left)}" y="{_num(top)}" width="{_num(w)}" '
                        f'height="{_num(h)}"/></clipPath>')
            body.append(f'<g clip-path="url(#{cid})">' + "".join(ax.parts) + "</g>")
        return (f'<svg class="fig" viewBox="0 0 {_num(self.width)} '
                f'{_num(self.height)}" width="{_num(self.width)}" height="{_num(self.height)}" role="img" '
                f'aria-label="{html.escape(label)}" font-family="{FONT}">'
                f'<rect width="100%" height="100%" fill="#fff"/><defs>{"".join(defs)}</defs>'
                + "".join(body) + "".join(self.decor) + "</svg>")


class View3D:
    """An orthographic view of the box [lo, hi] (3,) (data units, e.g. m), its sides drawn in the proportions
    ``aspect`` (3,), seen from elevation ``elev`` and azimuth ``azim`` [deg] (as matplotlib's ``view_init``).

    Draw on an :class:`Axes` made with :meth:`limits` and ``equal=True``: :meth:`project` maps points (..., 3)
    to its (x, y); :meth:`draw_box` draws the three back faces, and ticks on the three front-bottom edges.
    """

    def __init__(self, lo, hi, aspect, elev: float = 22.0, azim: float = -65.0):
        self.lo, self.hi = np.asarray(lo, float), np.asarray(hi, float)
        self.scale = np.asarray(aspect, float) / np.max(aspect) / np.maximum(self.hi - self.lo, 1e-300)
        e, a = math.radians(elev), math.radians(azim)
        self.right = np.array([-math.sin(a), math.cos(a), 0.0])
        self.up = np.array([-math.sin(e) * math.cos(a), -math.sin(e) * math.sin(a), math.cos(e)])
        self.toward = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])  # to the eye
        self.corners = self.lo + (self.hi - self.lo) * np.array(list(itertools.product((0.0, 1.0), repeat=3)))

    def project(self, xyz) -> tuple[np.ndarray, np.ndarray]:
        """Points (..., 3) -> their view coordinates (x (...), y (...)); NaN stays NaN."""
        n = (np.asarray(xyz, float) - (self.lo + self.hi) / 2) * self.scale
        return n @ self.right, n @ self.up

    def limits(self, pad: float = 0.1) -> tuple[tuple[float, float], tuple[float, float]]:
        """(xlim, ylim) of the box in view coordinates, with room for the tick labels."""
        X, Y = self.project(self.corners)
        p = pad * max(np.ptp(X), np.ptp(Y))
        return (X.min() - p, X.max() + p), (Y.min() - p, Y.max() + p)

    def _near(self, k: int) -> float:
        """The end of axis k nearer the eye."""
        return self.hi[k] if self.toward[k] > 0 else self.lo[k]

    def draw_box(self, ax: Axes, labels=("x [m]", "y [m]", "z [m]"), n_ticks: int = 4) -> None:
        """The back faces (light grey), and on the x and y edges at the floor nearest the eye and the leftmost
        vertical edge: ticks with labels and the axis's label."""
        for k in range(3):  # the face at the far end of axis k
            far = self.lo[k] if self.toward[k] > 0 else self.hi[k]
            i, j = [d for d in range(3) if d != k]
            quad = np.zeros((4, 3))
            quad[:, k] = far
            quad[:, i] = [self.lo[i], self.hi[i], self.hi[i], self.lo[i]]
            quad[:, j] = [self.lo[j], self.lo[j], self.hi[j], self.hi[j]]
            ax.polygon(*self.project(quad), "#f2f2f2", "#c8c8c8")
        floor = self.lo[2] if self.toward[2] > 0 else self.hi[2]
        verticals = [np.array([x, y]) for x in (self.lo[0], self.hi[0]) for y in (self.lo[1], self.hi[1])]
        left = min(verticals, key=lambda xy: float(self.project(np.array([*xy, self.lo[2]]))[0]))
        centre = np.array([float(ax.px(0.0)), float(ax.py(0.0))])
        for k in range(3):
            base = np.array([self._near(0), self._near(1), floor]) if k < 2 else np.array([*left, 0.0])
            ends = np.repeat(base[None], 2, axis=0)
            ends[:, k] = self.lo[k], self.hi[k]
            ex, ey = ax.px(self.project(ends)[0]), ax.py(self.project(ends)[1])  # the edge's ends [px]
            ax.fig.line(ex, ey, "#555", 0.8)
            length = float(np.hypot(ex[1] - ex[0], ey[1] - ey[0]))
            ticks, text = nice_ticks(self.lo[k], self.hi[k], int(min(max(length // 55, 2), n_ticks)))
            pts = np.repeat(base[None], len(ticks), axis=0)
            pts[:, k] = ticks
            X, Y = self.project(pts)
            mid = np.array([ex.mean(), ey.mean()])
            out = mid - centre
            out /= max(float(np.hypot(*out)), 1e-9)
            # labels away from the box, by half their width where the way out is sideways
            gap = 8 + 0.5 * max(text_width(t, 9) for t in text) * abs(out[0]) + 4 * abs(out[1])
            for x, y, t in zip(ax.px(X), ax.py(Y), text, strict=True):  # outside the panel's clip
                ax.fig.text(x + gap * out[0], y + gap * out[1] + 3, t, 9, "#333", "middle")
            gap2 = 2 * gap + 6 + 0.5 * text_width(labels[k], 10) * abs(out[0])
            ax.fig.text(mid[0] + gap2 * out[0], mid[1] + gap2 * out[1] + 3, labels[k], 10, "#222", "middle")
