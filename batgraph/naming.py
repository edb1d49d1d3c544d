"""Naming a folder of unlabelled detections, the step before the estimators: ``batgraph associate`` and the first
step of ``reconstruct`` on such a folder.

batgraph.associate names the detections on the cameras' clocks as calibration.toml states them. Free-running
cameras' clocks are rarely stated, and detections taken a few milliseconds apart are not paired (docs/associate.md,
Limits). With ``--sync estimate`` (or session.toml's ``[sync] estimate = true``) the clocks are measured from the
names: the smoother estimates each camera's time offset and rolling-shutter readout on them (batgraph.solver.shared),
and the detections are named again on that rig, once: a second pass did not name more (measured in
docs/associate.md). The second names are kept where they are more.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from . import atomic, inputs
from .associate import (
    AssociateOptions,
    Figures,
    associate_session,
    check_out,
    require_named,
    warning_texts,
    write_associated,
    write_observations,
)
from .result import SYNC, Options
from .runner import run_methods
from .session import calibration_toml, read_session

OBS_NAME = "observations.csv"  # the names, in the caller's scratch folder, for read_session


@dataclass
class Named:
    """A naming's result: observations (observations.csv's layout, the named detections), labels (one row per
    detection), figures (batgraph.associate.Figures; summary["clocks_estimated"]: whether the names are those given
    on the estimated clocks), calibration (the calibration.toml the names were given on; None: the folder's own)
    and shown_as (how warnings name the named detections)."""

    observations: pd.DataFrame
    labels: pd.DataFrame
    figures: Figures
    calibration: Path | None
    shown_as: str


def name_detections(folder: str | Path, scratch: Path, options: Options | None = None,
                    calibration: str | Path | None = None, associate: AssociateOptions | None = None) -> Named:
    """Name the detections of ``folder`` (batgraph.associate) and, where ``options`` (or session.toml) asks to
    estimate the timing, again on the clocks the smoother measures from those names (module docstring).

    scratch: a folder for the names' observations.csv (left in ``scratch``/OBS_NAME, for read_session) and the
    estimated rig (the result's ``calibration`` where its names were kept). InputError for bad input or no name.
    """
    folder = Path(folder)
    options = options or Options()
    associate = associate or AssociateOptions(progress=options.progress)
    calibration = None if calibration is None else Path(calibration)
    named = _name(folder, associate, calibration)
    write_observations(scratch / OBS_NAME, named.observations)
    if options.sync is False or (options.sync is None and "sync" not in inputs.read_toml(folder / "session.toml")):
        return named
    session = read_session(folder, calibration, scratch / OBS_NAME, named.shown_as)
    if not options.estimates_sync(session):
        return named
    rig = run_methods(session, ["smoother"], dataclasses.replace(options, sync=True)).estimates["smoother"].rig
    if rig is None:  # no timing variable was solved (schedule.run's est.rig): nothing measured to name again on
        return named
    clocks = scratch / "clocks.toml"
    atomic.write_text(clocks, calibration_toml(rig))
    again = _name(folder, associate, clocks)
    if len(again.observations) <= len(named.observations):
        return named
    again.figures.summary["clocks_estimated"] = True
    write_observations(scratch / OBS_NAME, again.observations)
    return again


def _name(folder: Path, associate: AssociateOptions | None, calibration: Path | None) -> Named:
    """One association on the clocks ``calibration`` states; InputError where nothing could be named."""
    obs, labels, figures = associate_session(folder, associate, calibration)
    require_named(folder, obs)
    figures.summary["clocks_estimated"] = False
    return Named(obs, labels, figures, calibration, f"{figures.summary['detections_file']} (the detections named)")


def associate_command(args, progress: bool = False) -> int:
    """``batgraph associate SESSION [--out DIR] [--pixel-sigma PX] [--calibration FILE] [--sync estimate]``: name
    the detections, write DIR (batgraph.associate.write_associated; with the estimated clocks as its
    calibration.toml where they were kept), print a summary. progress: show progress bars."""
    folder = Path(args.session)
    out = Path(args.out) if args.out else folder / "associated"
    check_out(folder, out)
    with tempfile.TemporaryDirectory(prefix="batgraph-names-") as scratch:
        named = name_detections(folder, Path(scratch), Options(sync=SYNC[args.sync], progress=progress),
                                args.calibration, AssociateOptions(pixel_sigma_px=args.pixel_sigma, progress=progress))
        write_associated(folder, out, named.observations, named.labels, named.figures, named.calibration)
    s = named.figures.summary
    print(f"{folder}: named {s['named']} of {s['detections']} detections ({100 * s['named_fraction']:.1f} %), "
          f"pixel noise {s['pixel_sigma_px']:.2f} px, {s['suspected_switches']} suspected identity switch(es)"
          + (f", {s['clock_rounds']} round(s) on the cameras' stated clocks" if s["clock_rounds"] else "")
          + (", named again on the clocks estimated from the first names" if s["clocks_estimated"] else ""))
    for text in warning_texts(s):
        print(f"batgraph: warning: {text}", file=sys.stderr)
    print(f"wrote observations.csv, labels.csv and association.json to {out} "
          f"(`batgraph reconstruct {out}` takes it as it is)")
    return 0
