"""The ``associate`` command: parse-free glue between the CLI's arguments and :func:`associate_session`."""

from __future__ import annotations

import sys
from pathlib import Path

from .core import AssociateOptions
from .session import associate_session, out_of_step_text, require_named, write_associated


def run(args) -> int:
    """``batgraph associate SESSION --out DIR [--pixel-sigma PX] [--calibration FILE]``: name the detections, write
    DIR, print a summary."""
    folder = Path(args.session)
    out = Path(args.out) if args.out else folder / "associated"
    opt = AssociateOptions(pixel_sigma_px=args.pixel_sigma)
    calibration = Path(args.calibration) if args.calibration else None
    obs, labels, fig = associate_session(folder, opt, calibration)
    require_named(folder, obs)
    write_associated(folder, out, obs, labels, fig, calibration)
    s = fig.summary
    print(f"{folder}: named {s['named']} of {s['detections']} detections ({100 * s['named_fraction']:.1f} %), "
          f"pixel noise {s['pixel_sigma_px']:.2f} px, {s['suspected_switches']} suspected identity switch(es)"
          + (f", {s['clock_rounds']} round(s) on the cameras' stated clocks" if s["clock_rounds"] else ""))
    moved = out_of_step_text(s)
    if moved:
        print(f"batgraph: warning: {moved}", file=sys.stderr)
    print(f"wrote observations.csv, labels.csv and association.json to {out} "
          f"(`batgraph reconstruct {out}` takes it as it is)")
    return 0
