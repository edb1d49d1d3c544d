"""The one registry of estimation methods as a user sees them: name, order, colour, line style, past-only.

The CLI builds its help and checks ``--methods`` here, and the report and the viewer draw each method in the
colour and line style given here, so a method looks the same everywhere. The functions that run the methods
are registered beside the code that runs them (batgraph.runner), so that reading this registry (the CLI's
help) loads no estimator. Imports nothing of batgraph but ``errors``.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass

from .errors import InputError


@dataclass(frozen=True)
class Method:
    """One estimation method.

    name: as in ``--methods`` and the ``method`` column of every table.
    colour: hex RGB used by the report and the viewer; line: matplotlib line style.
    past_only: the estimate of frame k uses frames <= k only (a filter), so it can run live.
    summary: one line for the CLI help and the report.
    """

    name: str
    colour: str
    line: str
    past_only: bool
    summary: str


# In display order. The paper draws the EKF dashed and the UKF solid (Fig. 5); batgraph's own methods
# get their own colours so that the two solid lines (ukf, smoother) stay distinguishable.
METHODS: dict[str, Method] = {m.name: m for m in (
    Method("smoother", "#1f77b4", "-", False,
           "factor-graph smoother: every frame uses every other (Levenberg-Marquardt over the whole recording)"),
    Method("filter", "#ff7f0e", "-.", True,
           "factor-graph filter: frame k uses frames <= k (the same model, one frame at a time)"),
    Method("ekf", "#d62728", "--", True, "the paper's extended Kalman filter"),
    Method("ukf", "#2ca02c", "-", True, "the paper's unscented Kalman filter"),
    Method("triangulate", "#7f7f7f", ":", False, "per-frame linear multi-view triangulation (DLT), no motion model"),
)}
ALL_METHODS = tuple(METHODS)
DEFAULT_METHODS = ("smoother", "filter")
_FALLBACK = ("#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22")


def get(name: str) -> Method:
    """The registered method ``name``; InputError naming the closest name and the choices otherwise."""
    if name not in METHODS:
        close = difflib.get_close_matches(name.lower(), ALL_METHODS, n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]}?" if close else ""
        raise InputError(f"--methods: unknown method {name!r}{hint} (choose from {', '.join(ALL_METHODS)})")
    return METHODS[name]


def parse(text: str | None, compare: bool = False) -> list[str]:
    """``--methods a,b`` (+ ``--compare``) -> ordered unique method names; validates each."""
    names = [m.strip() for m in (text or ",".join(DEFAULT_METHODS)).split(",") if m.strip()]
    if compare:
        names += [m for m in ALL_METHODS if m not in names]
    for n in names:
        get(n)
    return list(dict.fromkeys(names))


def ordered(names) -> list[str]:
    """Method names in registry order; unknown names (e.g. from an older result) after, sorted."""
    found = set(names)
    return [m for m in ALL_METHODS if m in found] + sorted(found - set(ALL_METHODS))


def style(name: str) -> tuple[str, str]:
    """(hex colour, line style) of a method; an unknown name gets a stable fallback colour, solid."""
    if name in METHODS:
        return METHODS[name].colour, METHODS[name].line
    return _FALLBACK[sum(map(ord, name)) % len(_FALLBACK)], "-"


def rgb(name: str) -> tuple[int, int, int]:
    """(r, g, b) 0-255 colour of a method (see :func:`style`)."""
    h = style(name)[0].lstrip("#")
    return int(h[0:2], 16), int(h[2:4], 16), int(h[4:6], 16)


def help_text() -> str:
    """The ``--methods`` help: every method with its one-line summary."""
    return "comma-separated, any of: " + "; ".join(
        f"{m.name} ({m.summary}{'; past frames only' if m.past_only else ''})" for m in METHODS.values()) + \
        f" (default {','.join(DEFAULT_METHODS)})"
