"""``reconstruct``: load a session, run the chosen methods (batgraph.runner), write a result folder.

The one place that knows which files a result folder holds; the CLI only parses arguments and calls
:func:`reconstruct` (batgraph.batch: many sessions).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm.auto import tqdm

from . import associate as associate_mod
from . import atomic, forked, inputs, naming
from . import methods as methods_registry
from . import report as report_mod
from . import summary as summary_mod
from . import validation_table as validation_mod
from .errors import InputError
from .evaluate import REPROJ_COLUMNS, TRAJ_COLUMNS, add_span
from .formats.c3d_trc import write_c3d, write_trc
from .formats.csv_text import write_csv
from .result import Options
from .runner import Run, run_methods
from .session import calibration_toml, dense_observations, read_session
from .validate import validate_session
from .viewer import RECORDING_NAME, LiveViewer, preload_rerun, write_recording

DEFAULT_METHODS = methods_registry.DEFAULT_METHODS
ALL_METHODS = methods_registry.ALL_METHODS
parse_methods = methods_registry.parse


@dataclass
class Result(Run):
    """What one reconstruct run produced: a :class:`batgraph.runner.Run` and where it was written."""

    out_dir: Path = Path()
    files: list[Path] = field(default_factory=list)


def _json_default(o):
    if isinstance(o, np.integer | np.bool_):
        return o.item()
    if isinstance(o, np.floating):
        return None if not math.isfinite(o) else float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def export_method(result: Run) -> str:
    """The method whose trajectories go to C3D/TRC: the verdict's (the smoother when it ran)."""
    return summary_mod.recommended(list(result.estimates))[0]


#: The files of one result folder: a folder holds one result,
#: so one of these that a run does not write is not carried over from the previous result.
OUTPUT_FILES = ("trajectories.csv", "reprojection.csv", "summary.json", "report.html", "trajectories.c3d",
                "trajectories.trc", "recording.rrd", "validation.csv", "rig.toml", "labels.csv", "association.json")


def write_outputs(result: Run, out_dir: str | Path, viewer: str = "save", options: Options | None = None,
                  validation_table: pd.DataFrame | None = None, report: forked.Standby | None = None,
                  association: tuple[pd.DataFrame, dict] | None = None) -> list[Path]:
    """Write a result folder's files (:data:`OUTPUT_FILES`) into ``out_dir`` as one atomic replacement.

    viewer: "save" or "spawn" write recording.rrd; "none" skips it. validation_table: also write validation.csv
    (batgraph.validate). association: (labels table, counts) of the names ``reconstruct`` gave unlabelled
    detections, written as labels.csv and association.json (as ``batgraph associate`` does). Every file is written
    into a staging folder beside ``out_dir`` that then replaces ``out_dir`` (batgraph.atomic.result_folder): a crash
    or kill leaves the previous complete result or the new one, never a mix; files in ``out_dir`` that are not in
    :data:`OUTPUT_FILES` are carried over. report.html is drawn in a child process while this process writes the
    other files, and waited for before the swap: ``report``, a :func:`report_standby` made earlier, or one forked
    here (here, in this process, where no child can be made).
    Returns the paths written (under ``out_dir``).
    """
    out_dir = Path(out_dir)
    session_dir = result.session.path
    # the session folder itself (--out SESSION) or a folder holding it is not swapped: file by file there
    in_place = session_dir is not None and Path(os.path.realpath(out_dir)) in (
        Path(os.path.realpath(session_dir)), *Path(os.path.realpath(session_dir)).parents)
    with atomic.result_folder(out_dir, OUTPUT_FILES, in_place=in_place) as stage:
        files = _write_files(result, stage, viewer, options, report or report_standby(viewer))
        if validation_table is not None:
            validation_mod.write_csv(validation_table, stage / validation_mod.CSV_NAME)
            files.append(stage / validation_mod.CSV_NAME)
        if association is not None:
            write_csv(stage / "labels.csv", association[0].reset_index(drop=True), "%.6f")
            atomic.write_text(stage / "association.json", json.dumps(association[1], indent=2) + "\n")
            files += [stage / "labels.csv", stage / "association.json"]
    return [out_dir / p.name for p in files]


def _report_writer(recording: bool = True):
    """The report child's preparation: imports Rerun when a recording will be written (0.2-1.4 s, while the
    estimators run; a missing rerun-sdk says so when the recording is written) and returns the writer of report.html
    and, when given a path, recording.rrd."""
    if recording:
        with contextlib.suppress(InputError):
            preload_rerun()

    def write(report_path, session, trajectories, reprojection, summary, recording_path=None, dense=None):
        report_mod.write_report(report_path, session, trajectories, reprojection, summary)
        if recording_path is not None:
            write_recording(recording_path, session, dense, trajectories, reprojection)

    return write


def report_standby(viewer: str = "save") -> forked.Standby:
    """A child process that prepares now (Rerun imported unless ``viewer`` is "none") and draws report.html (and
    writes recording.rrd) when :func:`write_outputs` hands it the result (batgraph.forked.Standby). Cancel it if
    unused."""
    return forked.Standby(partial(_report_writer, viewer != "none"), "report")


def _write_files(result: Run, out_dir: Path, viewer: str, options: Options | None,
                 report: forked.Standby) -> list[Path]:
    """Write every output file into the (staging) folder ``out_dir``: the two CSV tables
    by a child forked here (batgraph.forked.Standby) and report.html by ``report``, beside this process's writing
    of the others (at 30 x 180 x 160 the CSVs take 1.3 s, the rest ~0.8 s)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    s = result.session
    report_path = out_dir / "report.html"
    files = [out_dir / "trajectories.csv", out_dir / "reprojection.csv", out_dir / "summary.json"]

    def write_tables():
        write_csv(files[0], result.trajectories, "%.9g")
        write_csv(files[1], result.reprojection, "%.6f")

    tables = forked.Standby(lambda: write_tables, "CSV tables").run()  # a child forked now: nothing is pickled
    recording = out_dir / RECORDING_NAME if viewer != "none" else None
    try:
        pending = report.run(report_path, s, result.trajectories, result.reprojection,
                             summary_mod.Summary.from_json(result.summary), recording, result.dense)
        atomic.write_text(files[2], json.dumps(result.summary, indent=2, default=_json_default, allow_nan=False))
        method = export_method(result)
        one = result.trajectories[result.trajectories["method"] == method]
        steps = [("trajectories.c3d", lambda p: write_c3d(p, one, s.fps, result.dense.markers, keep="span",
                                                          reprojection=result.reprojection, cameras=s.rig.names)),
                 ("trajectories.trc", lambda p: write_trc(p, one, s.fps, result.dense.markers, keep="span"))]
        rig = next((e.rig for e in result.estimates.values() if e.rig is not None), None)
        if rig is not None:  # the rig as a method estimated it (timing, poses): reusable with --calibration
            steps.append(("rig.toml", lambda p: atomic.write_text(p, calibration_toml(rig))))
        progress = options.progress if options else False
        for name, write in tqdm(steps, desc=f"{s.name}: writing", disable=not progress, leave=False):
            write(out_dir / name)
            files.append(out_dir / name)
        tables.wait()
        pending.wait()
    finally:  # the parent failed: no child may write into a staging folder being removed
        tables.cancel()
        report.cancel()
    files.insert(3, report_path)
    return files + ([recording] if recording is not None else [])


def reconstruct(session_dir: str | Path, out_dir: str | Path | None = None,
                methods: list[str] | None = None, options: Options | None = None,
                viewer: str = "save", calibration: str | Path | None = None,
                validate: bool = False, validate_workers: int | None = None) -> Result:
    """The ``reconstruct`` command for one session folder. Raises InputError on bad input.

    viewer: "spawn" streams the filter live to a Rerun window (and saves recording.rrd), "save"
    writes recording.rrd, "none" neither. calibration: a calibration.toml to use instead of the
    session's own (see batgraph.session.read_session). validate: also run leave-one-camera-out
    validation (batgraph.validate) of every method: summary.json gets a "validation" section (and the
    report its table), and validation.csv is written; validate_workers: its processes (None: one per core).
    """
    options = options or Options()
    out = Path(out_dir) if out_dir is not None else Path(session_dir) / "out"
    inputs.check_output_dir(out)  # before any work (a batch item fails alone; the CLI checks too)
    # the report's child, forked before the estimators' memory grows; cancelled on failure
    with report_standby(viewer) as report, contextlib.ExitStack() as names_dir:
        named = None
        if _detections_only(Path(session_dir)):  # a scratch folder for the names only then (a killed run leaves it)
            scratch = Path(names_dir.enter_context(tempfile.TemporaryDirectory(prefix="batgraph-names-")))
            named = naming.name_detections(Path(session_dir), scratch, options, calibration)
        session = (read_session(session_dir, calibration) if named is None else
                   read_session(session_dir, calibration, scratch / naming.OBS_NAME, named.shown_as))
        if named is not None:
            session.warnings.append(_association_warning(named.figures.summary))
        methods = list(methods or DEFAULT_METHODS)
        if viewer == "spawn":
            with LiveViewer(session, dense_observations(session), method="filter") as live:
                run = run_methods(session, methods, options, live=live)
        else:
            run = run_methods(session, methods, options)
        result = Result(**vars(run), out_dir=out)
        if named is not None:
            result.summary["association"] = named.figures.to_summary()
        validation = None
        if validate:
            validation = validate_session(session, methods, options, summary=result.summary, workers=validate_workers)
            result.summary["validation"] = validation.to_summary()
            summary_mod.refresh_verdict(result.summary)
        # one atomic replacement of the whole folder; without --validate a previous validation.csv is not kept
        # (it would be read as this result's)
        result.files = write_outputs(result, out, viewer, options,
                                     validation_table=None if validation is None else validation.table, report=report,
                                     association=None if named is None else (named.labels, named.figures.summary))
        return result


def _detections_only(folder: Path) -> bool:
    """Whether a session folder holds unlabelled detections (detections.csv or .parquet) and no observations: its
    detections are named first (batgraph.naming; again on estimated clocks where the timing is estimated)."""
    has = [(folder / f"{stem}.{ext}").exists() for stem in ("observations", "detections") for ext in ("csv", "parquet")]
    return not any(has[:2]) and any(has[2:])


def _association_warning(counts: dict) -> str:
    """The warning every run on names from unlabelled detections carries: how many, where to check them, the frames
    that hold names where they are fewer than half, the cameras whose detections were moved out of step, and a noise
    assumed where it could not be measured."""
    more = associate_mod.warning_texts(counts)
    return (f"the markers were named from unlabelled detections (batgraph associate, experimental): "
            f"{counts['named']} of {counts['detections']} detections named ({100 * counts['named_fraction']:.1f} %), "
            f"{counts['suspected_switches']} suspected identity switch(es), but most wrong names are not among them: "
            "check the 3D paths where a marker reappears after a gap before relying on them"
            + "".join(f"; {t}" for t in more))


_TEXT_COLUMNS = ("method", "marker", "camera", "status", "span")


def _typed_result_table(path: Path, required: list[str]) -> pd.DataFrame:
    """One result CSV through batgraph.inputs: text columns as str, frame as checked int64 (limits and gaps
    as observations'), outlier as bool, every other column as float; InputError naming the line otherwise."""
    raw, is_csv = inputs.read_table(path, required, "rows")
    df = pd.DataFrame(index=raw.index)
    for c in raw.columns:
        if c in _TEXT_COLUMNS:
            df[c] = raw[c].astype(str).str.strip()
        elif c == "frame":
            df[c] = inputs.frame_column(raw, path, is_csv)
            inputs.check_frame_gaps(df[c].to_numpy(), path, is_csv)
        elif c == "outlier":
            text = raw[c].astype(str).str.strip().str.lower()
            flags = text.map({"true": True, "false": False, "1": True, "0": False})
            if flags.isna().any():
                i = int(np.argmax(flags.isna().to_numpy()))
                raise InputError(f"{path} {inputs.row_name(i, is_csv)}: outlier {raw[c].iloc[i]!r} is not True/False")
            df[c] = flags.astype(bool)
        elif c in required:
            df[c] = inputs.numeric_column(raw, c, path, is_csv, allow_missing=True)
        else:  # a column this version does not know: numbers if they all are, else text
            num = pd.to_numeric(raw[c], errors="coerce")
            df[c] = num if num.notna().sum() == (raw[c].str.strip() != "").sum() else raw[c]
    if "n_views" in df and df["n_views"].notna().all():
        df["n_views"] = df["n_views"].astype(np.int64)
    return df


def read_result_tables(out_dir: str | Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read trajectories.csv and reprojection.csv of a reconstruct output folder (for ``export``).

    A trajectories.csv written before the ``span`` column existed gets it computed from n_views.
    """
    out_dir = Path(out_dir)
    tables = []
    for name, cols in (("trajectories.csv", [c for c in TRAJ_COLUMNS if c != "span"]),
                       ("reprojection.csv", REPROJ_COLUMNS)):
        path = out_dir / name
        if not path.exists():
            raise InputError(f"{path}: file not found (is {out_dir} a reconstruct output folder?)")
        tables.append(_typed_result_table(path, cols))
    if "span" not in tables[0].columns:
        tables[0] = add_span(tables[0])
    return tables[0], tables[1]
