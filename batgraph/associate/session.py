"""Association of a session folder: read its detections, seed and rig, name every detection, and write a session
every estimator takes as it is (observations.csv with the named detections, labels.csv with all of them).

``associate_session`` is the library entry (the ``associate`` command and, for a session holding detections.csv
instead of observations.csv, ``reconstruct`` call it); ``write_associated`` writes the result folder.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd

from .. import atomic, inputs
from ..errors import InputError
from ..formats.csv_text import write_csv
from ..session import OBS_COLUMNS
from .core import HOW, AssociateOptions, Association, associate
from .detections import Detections, SessionSetup, read_inputs, read_seed
from .tracks import DOUBT_BELOW

SEED_FILE = "seed_labels.csv"
LABEL_COLUMNS = ["frame", "camera", "u", "v", "marker", "track", "confidence", "how"]
OUTPUT_FILES = ("observations.csv", "labels.csv", "association.json")
HOW_CODES = ".STRP"  # summary.json's map of how: not named, seed, tracked, ray, reprojection (core.HOW's order)
NOT_COPIED = ("detections.csv", "detections.parquet", "observations.csv", "observations.parquet", SEED_FILE)


@dataclass
class Figures:
    """What the report shows of an association: ``how`` (M, F) int8 per marker and frame the HOW index by which
    most of its detections got its name (0: none), over ``frames`` (F,) and ``markers`` (M); ``switches``: a table
    (frame, marker, confidence) of the places where a marker's track splits and its name is carried on with a
    confidence below ``suspect_below``: the suspected identity switches; ``summary``: counts and figures."""

    frames: np.ndarray
    markers: list[str]
    how: np.ndarray
    switches: pd.DataFrame
    summary: dict
    suspect_below: float = DOUBT_BELOW

    def to_summary(self) -> dict:
        """summary.json's ``association``: the counts, the suspected switches (frame, marker, confidence; below
        ``suspect_below``) and the map of how, one string per marker with a character per frame from
        ``first_frame`` on (HOW_CODES)."""
        return {**self.summary, "suspect_below": self.suspect_below,
                "first_frame": int(self.frames[0]) if len(self.frames) else 0,
                "how_codes": dict(zip(HOW_CODES, (h or "none" for h in HOW), strict=True)),
                "how": {m: "".join(HOW_CODES[i] for i in row) for m, row in zip(self.markers, self.how, strict=True)},
                "switches": [{"frame": int(f), "marker": str(m), "confidence": round(float(c), 4)} for f, m, c in
                             self.switches[["frame", "marker", "confidence"]].itertuples(index=False)]}


def _markers(setup: SessionSetup, seed: pd.DataFrame, path: Path) -> list[str]:
    """The marker names: session.toml's [markers] names, else the seed's in order of first click."""
    if setup.marker_names:
        return list(setup.marker_names)
    names = list(dict.fromkeys(seed["marker"].tolist()))
    if not names:
        raise InputError(f"{path}: names no marker (and session.toml has no [markers] names)")
    return names


def associate_session(folder: str | Path, options: AssociateOptions | None = None,
                      calibration: str | Path | None = None) -> tuple[pd.DataFrame, pd.DataFrame, Figures]:
    """Name the detections of a session folder holding detections.csv (or .parquet) and seed_labels.csv.

    Returns (observations, labels, figures): observations in observations.csv's layout (frame, camera, marker, u,
    v, weight; the named detections only, weight = the detector's score where it has one in (0, 1], else 1);
    labels with one row per detection (LABEL_COLUMNS; marker empty where unnamed, track -1 where in no track);
    figures for the report (:class:`Figures`). InputError for bad input (see batgraph.associate.detections).
    calibration: a calibration.toml to use instead of the folder's own.
    """
    folder = Path(folder)
    setup, rig, dets, det_path = read_inputs(folder, None if calibration is None else Path(calibration))
    seed_path = folder / SEED_FILE
    if not seed_path.exists():
        raise InputError(f"{seed_path}: file not found; name the markers once: frame, camera, marker, u, v for the "
                         "markers of one frame (or a few clicks)")
    seed = read_seed(seed_path, rig, setup.fps, dets, setup.marker_names)
    markers = _markers(setup, seed, seed_path)
    index = {m: i for i, m in enumerate(markers)}
    pairs = [(index[a], index[b]) for a, b in dict.fromkeys(setup.rigid + setup.skeleton) if a in index and b in index]
    opt = options or AssociateOptions()
    if opt.pixel_sigma_px is None and setup.pixel_sigma_px is not None:
        opt = replace(opt, pixel_sigma_px=setup.pixel_sigma_px)
    res = associate(rig, dets, seed["detection"].to_numpy(), seed["marker"].map(index).to_numpy(), len(markers),
                    pairs, setup.fps, opt)
    labels = _labels_table(dets, rig.names, markers, res)
    named = labels[labels["marker"] != ""]
    weight = pd.Series(dets.weight, index=dets.row)[named.index].to_numpy()  # by file row, as labels is indexed
    obs = pd.DataFrame({"frame": named["frame"].to_numpy(), "camera": named["camera"].to_numpy(),
                        "marker": named["marker"].to_numpy(), "u": named["u"].to_numpy(), "v": named["v"].to_numpy(),
                        "weight": weight})
    obs = obs.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True)
    return obs, labels, _figures(dets, rig.names, markers, res, det_path)


def _labels_table(dets: Detections, cameras: list[str], markers: list[str], res: Association) -> pd.DataFrame:
    """One row per detection in the file's order (see LABEL_COLUMNS)."""
    names = np.array(markers + [""], dtype=object)
    out = pd.DataFrame({
        "frame": dets.own_frame, "camera": np.asarray(cameras, dtype=object)[dets.camera], "u": dets.uv_px[:, 0],
        "v": dets.uv_px[:, 1], "marker": names[np.where(res.label >= 0, res.label, -1)],
        "track": res.track, "confidence": np.round(np.where(res.label >= 0, res.confidence, 0.0), 4),
        "how": np.asarray(HOW, dtype=object)[res.how]})
    if dets.size is not None:
        out["size"] = dets.size
    if dets.score is not None:
        out["score"] = dets.score
    out.index = dets.row  # the file's row of each detection
    return out.sort_index()


def _modes(group: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each group's most frequent value, the first seen among equally frequent ones (as pandas' value_counts()
    .idxmax() per group): group (n,) and value (n,) integers; returns the groups (G,) ascending and their modes."""
    order = np.lexsort((value, group))  # stable: a run of one (group, value) keeps its rows' order
    g, v = group[order], value[order]
    start = np.flatnonzero(np.r_[True, (g[1:] != g[:-1]) | (v[1:] != v[:-1])])
    count = np.diff(np.r_[start, len(g)])
    pick = np.lexsort((order[start], -count, g[start]))  # per group: most rows, then the earliest row
    first = pick[np.r_[True, g[start][pick][1:] != g[start][pick][:-1]]]
    return g[start][first], v[start][first]


def _figures(dets: Detections, cameras: list[str], markers: list[str], res: Association, det_path: Path,
             suspect_below: float = DOUBT_BELOW) -> Figures:
    """The marker x frame map of how names were obtained, and the suspected switches (see :class:`Figures`)."""
    first = int(dets.frame.min())
    F = int(dets.frame.max()) - first + 1
    M = len(markers)
    how = np.zeros((M, F), np.int8)
    named = res.label >= 0
    if named.any():
        cell, h = _modes(res.label[named] * F + dets.frame[named] - first, res.how[named])
        how[cell // F, cell % F] = h
    sw = res.sweep
    starts = (sw.kind[1:] > 0) & (sw.kind[:-1] == 0)  # a marker placed again after a frame without it
    k, m = np.nonzero(starts)
    conf = sw.conf[k + 1, m]
    suspect = conf < suspect_below
    switches = pd.DataFrame({"frame": first + k[suspect] + 1, "marker": np.asarray(markers, dtype=object)[m[suspect]],
                             "confidence": conf[suspect]})
    n = len(dets.frame)
    summary = {"detections": n, "named": int(named.sum()), "named_fraction": float(named.mean()) if n else 0.0,
               "pixel_sigma_px": res.pixel_sigma_px, "pixel_sigma_source": res.sigma_source,
               "tracks": int(res.track.max()) + 1 if n else 0,
               "suspected_switches": int(suspect.sum()), "detections_file": str(det_path)}
    for i, h in enumerate(HOW):
        summary[f"how_{h or 'none'}"] = int((res.how == i).sum())
    summary["out_of_step"] = _out_of_step(dets, cameras, res)
    summary["clock_rounds"] = res.clock_rounds
    summary["frames"] = int(len(np.unique(dets.frame)))  # frames without a detection (between takes) do not count
    summary["named_spans"] = _spans(np.unique(dets.frame[named]))
    return Figures(np.arange(first, first + F), markers, how, switches, summary, suspect_below)


def _out_of_step(dets: Detections, cameras: list[str], res: Association) -> dict:
    """{camera: {frames, of_frames, median_px}} for the cameras whose detections were moved on some frames
    (batgraph.associate.jitter): on how many of the frames it has detections, and the median move there [px]."""
    if res.moved is None:
        return {}
    first = int(dets.frame.min())
    out = {}
    for c in np.flatnonzero(res.moved.any(axis=0)):
        mine = dets.camera == c
        on = res.moved[dets.frame[mine] - first, c]
        out[cameras[c]] = {"frames": int(res.moved[:, c].sum()), "of_frames": int(len(np.unique(dets.frame[mine]))),
                           "median_px": round(float(np.median(res.moved_px[mine][on])), 2)}
    return out


def _spans(frames: np.ndarray) -> list[list[int]]:
    """Runs of consecutive frames [[first, last], ...] of sorted unique frames."""
    if not len(frames):
        return []
    cut = np.flatnonzero(np.diff(frames) > 1)
    return [[int(a), int(b)] for a, b in zip(frames[np.r_[0, cut + 1]], frames[np.r_[cut, len(frames) - 1]],
                                             strict=True)]


SPANS_SHOWN = 3


def coverage_text(summary: dict) -> str:
    """One sentence where the names lie on fewer than half of the frames that hold detections ('' elsewhere): the
    tracker lost the markers near the labelled frame (wing markers that turn faster than their motion predicts,
    frames sampled too far apart to track), and the estimators would take the few names left without a word."""
    spans, frames = summary.get("named_spans"), summary.get("frames")
    if spans is None or not frames:
        return ""
    n = sum(b - a + 1 for a, b in spans)
    if 2 * n >= frames:
        return ""
    shown = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in spans[:SPANS_SHOWN])
    return (f"names on {n} of the {frames} frames only ({shown}{', ...' if len(spans) > SPANS_SHOWN else ''}): the "
            "markers were lost on the others (they moved or turned faster than the tracker predicts, or the frames "
            "lie too far apart to track); to name them, label a frame where they are lost (seed_labels.csv)")


def out_of_step_text(summary: dict) -> str:
    """One sentence on the cameras found out of step or shaken ('' where none)."""
    moved = summary.get("out_of_step") or {}
    if not moved:
        return ""
    each = ", ".join(f"{c} on {m['frames']} of {m['of_frames']} frames ({m['median_px']:.1f} px)"
                     for c, m in moved.items())
    return (f"detections out of step with the other cameras (a free-running or shaken camera) were moved to be "
            f"named: {each}; the estimators take them as they are (where a camera's offset is constant, "
            "--sync estimate measures it from the names and names the detections again on it)")


def noise_text(summary: dict) -> str:
    """One sentence where the detections' noise was assumed, for no point had views enough to measure it ('' else)."""
    if summary.get("pixel_sigma_source") != "assumed":
        return ""
    return ("the detections' noise could not be measured (no point is seen by 3 cameras or more; in a rig of more "
            f"than 8, no seed click in 4): {summary['pixel_sigma_px']:g} px assumed for the gates; state it "
            "(session.toml's [noise] pixel_sigma_px, or --pixel-sigma)")


def warning_texts(summary: dict) -> list[str]:
    """The association's warnings, each one sentence: the names' coverage, cameras out of step, the noise assumed."""
    return [t for t in (coverage_text(summary), out_of_step_text(summary), noise_text(summary)) if t]


def check_out(folder: Path, out: Path) -> None:
    """InputError where ``out`` cannot take an associated session: the session folder itself, or not a folder that
    can be written (batgraph.inputs.check_output_dir). Before any work: a naming can take minutes."""
    if out.resolve() == folder.resolve():
        raise InputError(f"{out}: is the session folder itself; give another --out (inputs are never modified)")
    inputs.check_output_dir(out)


def write_associated(folder: str | Path, out: str | Path, observations: pd.DataFrame, labels: pd.DataFrame,
                     figures: Figures, calibration: str | Path | None = None) -> Path:
    """Write the associated session into ``out`` (atomically, as one result): the session's other files copied
    (session.toml, calibration.toml, truth.csv, ...; not the detections, the seed or an earlier observations.csv),
    observations.csv, labels.csv and association.json (figures.summary). calibration: the file the association
    used instead of the session's, written as calibration.toml."""
    import json

    folder, out = Path(folder), Path(out)
    check_out(folder, out)
    copied = [p for p in sorted(folder.iterdir()) if p.is_file() and p.name not in NOT_COPIED]
    names = {p.name for p in copied} | set(OUTPUT_FILES) | ({"calibration.toml"} if calibration is not None else set())
    with atomic.result_folder(out, sorted(names)) as stage:
        for p in copied:
            shutil.copy2(p, stage / p.name)
        if calibration is not None:
            shutil.copy2(calibration, stage / "calibration.toml")
        write_observations(stage / "observations.csv", observations)
        write_csv(stage / "labels.csv", labels.reset_index(drop=True), "%.6f")
        (stage / "association.json").write_text(json.dumps(figures.summary, indent=2) + "\n")
    return out


def write_observations(path: Path, observations: pd.DataFrame) -> None:
    """The named detections as observations.csv (the weight column only where a weight is not 1)."""
    cols = OBS_COLUMNS + (["weight"] if not np.allclose(observations["weight"], 1.0) else [])
    write_csv(path, observations[cols], "%.6f")


def require_named(folder: Path, observations: pd.DataFrame) -> None:
    """InputError when the seed named no detection at all (nothing for an estimator to take)."""
    if not len(observations):
        raise InputError(f"{folder}: no detection could be named from the seed (check that seed_labels.csv's clicks "
                         "are on this session's frames and that the markers are seen by two cameras there)")
