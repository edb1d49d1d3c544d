"""Session folders <-> validated tables and a camera rig; the only module that knows file layouts.

A session folder (docs/formats.md) holds ``session.toml``, ``calibration.toml``
(aniposelib format), ``observations.csv`` or ``.parquet``, and optionally ``truth.csv`` (simulated
sessions), ``reference_xyz.csv`` (another tool's 3D, e.g. DLTdv's xyzpts, for comparison),
``calibration_true.toml`` (simulated sessions with a calibration error: the rig used to render),
``truth_mislabels.csv`` (simulated sessions: frame, camera, marker of deliberately mislabelled rows).

Every problem with user input raises :class:`batgraph.errors.InputError` with a one-line message
naming the file, the row (CSV line number, header = line 1) or key, and the problem. This module
does not estimate anything.
"""

from __future__ import annotations

import dataclasses
import difflib
import warnings as warnings_mod
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import tomli_w

from . import atomic, inputs
from .camera import Camera, Rig
from .errors import InputError
from .formats.csv_text import write_csv
from .geometry.dlt import UNITS_M
from .labels import Labels, factorize, text_column

OBS_COLUMNS = ["frame", "camera", "marker", "u", "v"]
TRUTH_COLUMNS = ["frame", "marker", "x", "y", "z"]
MOTION_MODELS = ("random_walk", "constant_velocity", "constant_acceleration", "auto")


DEFAULT_TAKE_GAP_S = 1.0
# [markers] rigid_sigma_m: the std of a rigid segment's length about its one estimated value [m]. Skin
# markers over a joint move a few millimetres relative to the bone (Cappozzo et al. 1996 measured
# soft-tissue artefacts of 2-20 mm on human limbs; a bat's thin skin over its wing bones is at the low
# end), so 2 mm: stiff enough to pin a single-view marker's depth, loose enough for real markers.
DEFAULT_RIGID_SIGMA_M = 0.002
# Its accepted range [m]: stiffer than 10 um the segment's information (1/sigma^2) swamps the pixels' by so many
# orders that the solve loses its precision (measured: 1e-9 m gave negative variances, 1e-300 a division by
# zero); looser than 1 m a segment constrains nothing on a bat (and 1e300 made the bordered system singular).
RIGID_SIGMA_RANGE_M = (1e-5, 1.0)
"""[session] take_gap_s: a run of more frames than this many seconds in which no camera sees any marker
separates two takes (see :func:`frame_axis`)."""

PAPER_PHYSICS = {"flight_speed_mps": 3.0, "span_m": 0.5, "flap_hz": 4.0, "flap_angle_deg": 90.0}
"""The paper's bat flight (v_f, l_w, f_f, alpha_f); the simulator and tests use it, nothing assumes it."""

TIMING_KEYS = ("fps", "time_offset_s", "readout_s", "time_offset_sd_s", "readout_sd_s")
"""A camera's timing in calibration.toml (see batgraph.camera.Camera and docs/timing.md)."""
CAMERA_KEYS = frozenset({
    "name", "size", "matrix", "distortions", "rotation", "translation", "fisheye",  # aniposelib, Anipose, Pose2Sim
    "pose_covariance", *TIMING_KEYS,  # batgraph
    # Caliscope
    "port", "cam_id", "rotation_count", "error", "exposure", "grid_count", "ignore", "verified_resolutions",
})
"""Keys a camera table of calibration.toml may hold: batgraph's and those the peer tools write."""
METADATA_KEYS = frozenset({
    "units", "world_mirror", "written_by", "gauge",  # batgraph
    "adjusted", "error",  # aniposelib / Anipose / Pose2Sim
    "charuco_square_size", "charuco_board_object", "charco_board_object", "path_to_recorded_videos",  # FreeMoCap
    "date_time_calibrated", "groundplane_calibration", "calibration_method", "camera_specs_file",
    "reprojection_error",
})
SESSION_KEYS = {
    "session": frozenset({"name", "fps", "take_gap_s"}),
    "motion": frozenset({"model", *PAPER_PHYSICS, "sigma_m", "accel_psd_m2_s3"}),
    "noise": frozenset({"pixel_sigma_px"}),
    "markers": frozenset({"names", "skeleton", "rigid", "rigid_sigma_m"}),
    "sync": frozenset({"estimate"}),
    "paper": frozenset({"experiment"}),
    "wand": frozenset({"ends", "length_m"}),
    # written by batgraph itself, free-form provenance: their keys are not checked
    "simulation": None, "wingbeat": None, "import": None,
}
"""session.toml's tables and the keys each may hold (None: any). Extend it with every new key."""
CLOSE_MATCH = 0.75
"""difflib ratio above which an unknown key is taken for a misspelt known one (an error, not a warning)."""


@dataclass
class MotionConfig:
    """[motion] of session.toml.

    flight_speed_mps, span_m, flap_hz, flap_angle_deg: the paper's physics (eq. 4-5); None = not given.
        Without them the random walk's sigma_m and the filter's q are measured from the triangulated
        track by ``reconstruct`` (batgraph.motion.noise_from_track): nothing assumes a bat.
    sigma_m: random-walk per-axis std per frame [m]; overrides the physics.
    accel_psd_m2_s3: for ``constant_velocity``, the power spectral density of the white-noise
        acceleration [m^2/s^3]; None means "choose it from the data" (see batgraph.motion).
    causal_accel_psd_m2_s3: the filter's q when the physics are not given (filled by reconstruct from
        the triangulated track; not read from session.toml).
    """

    model: str = "auto"  # or constant_velocity, random_walk, constant_acceleration (batgraph.solver.model)
    flight_speed_mps: float | None = None
    span_m: float | None = None
    flap_hz: float | None = None
    flap_angle_deg: float | None = None
    sigma_m: float | None = None
    accel_psd_m2_s3: float | None = None
    causal_accel_psd_m2_s3: float | None = None

    @property
    def has_physics(self) -> bool:
        """True when all four physics values are given."""
        return all(getattr(self, k) is not None for k in PAPER_PHYSICS)


@dataclass
class Session:
    """A loaded session.

    observations: columns frame (int64), camera (str), marker (str), u, v (float, raw pixels), weight (float in
        (0, 1]); only seen points. When the rig's timing puts a camera off the session clock
        (batgraph.camera.Camera.on_session_clock), ``frame`` is the session frame nearest each exposure and
        ``camera_frame`` the camera's own frame, as read (:func:`to_session_clock`).
    truth, reference: columns frame, marker, x, y, z [m, world], or None.
    pixel_sigma_px: std of one observation [px]: one value, one per camera name, or None = estimate it per
        camera from the data (batgraph.pixel_noise), as reconstruct does without ``[noise] pixel_sigma_px``.
    warnings: non-fatal remarks found while loading (e.g. points outside the image).
    take_gap_s: ``[session] take_gap_s`` [s]: a longer run with no observation splits takes (:func:`frame_axis`).
    rigid: ``[markers] rigid``, marker pairs on one rigid segment (a bone), whose distance the smoother ties to
        one estimated length per segment; rigid_sigma_m: the std of that distance about its length [m].
    true_timing: simulated sessions' truth_timing.toml (camera, fps, time_offset_s, readout_s), or None.
    """

    name: str
    fps: float
    rig: Rig
    observations: pd.DataFrame
    motion: MotionConfig = field(default_factory=MotionConfig)
    pixel_sigma_px: float | dict[str, float] | None = 1.0
    marker_names: list[str] = field(default_factory=list)
    skeleton: list[tuple[str, str]] = field(default_factory=list)
    truth: pd.DataFrame | None = None
    reference: pd.DataFrame | None = None
    true_rig: Rig | None = None
    mislabels: pd.DataFrame | None = None
    extra_toml: dict = field(default_factory=dict)
    path: Path | None = None
    warnings: list[str] = field(default_factory=list)
    take_gap_s: float = DEFAULT_TAKE_GAP_S
    rigid: list[tuple[str, str]] = field(default_factory=list)
    rigid_sigma_m: float = DEFAULT_RIGID_SIGMA_M
    true_timing: pd.DataFrame | None = None

    @property
    def markers(self) -> list[str]:
        """All marker labels: session.toml's order first, then the others as first seen."""
        named = set(self.marker_names)
        seen = [str(m) for m in pd.unique(self.observations["marker"])]  # in order of appearance
        return list(self.marker_names) + [m for m in seen if m not in named]

    @property
    def world_mirror(self) -> np.ndarray:
        """(3,) of +-1: user frame = world_mirror * the rig's (right-handed) world; see Rig."""
        return self.rig.world_mirror

    @property
    def take_gap_frames(self) -> int:
        """The longest run of frames without any observation inside one take (take_gap_s * fps, >= 1)."""
        return gap_frames(self.take_gap_s, self.fps)

    @property
    def frames(self) -> np.ndarray:
        """The frame axis the estimators work on, original frame numbers, shape (F,) (:func:`frame_axis`)."""
        return frame_axis(self.observations["frame"].to_numpy(), self.take_gap_frames)[0]

    @property
    def takes(self) -> list[slice]:
        """The takes as slices of :attr:`frames` (:func:`frame_axis`)."""
        return frame_axis(self.observations["frame"].to_numpy(), self.take_gap_frames)[1]


def gap_frames(take_gap_s: float, fps: float) -> int:
    """[session] take_gap_s [s] at ``fps`` [Hz] as a number of frames, at least 1 and at most
    inputs.MAX_FRAME (a huge take_gap_s means one take; the product may overflow to inf)."""
    return max(1, round(min(take_gap_s * fps, inputs.MAX_FRAME)))


def frame_axis(observed: np.ndarray, gap_frames: int) -> tuple[np.ndarray, list[slice]]:
    """The compacted frame axis: every frame of each take, with the original frame numbers kept.

    A take runs from an observed frame to the last observed frame before a run of more than
    ``gap_frames`` frames in which nothing is observed; the frames of such a run belong to no take, so a
    stray frame number far from the others costs one take of one frame, not memory for the frames in
    between. The estimators solve each take on its own (no motion model bridges a gap in which the
    animal may have left the volume): batgraph.pipeline.

    observed: frame numbers of the observations, any order, shape (N,) int. Returns (frames (F,) int64,
    sorted, contiguous within each take; takes: slices of ``frames``, in order); F = 0 when N = 0.
    """
    uniq = np.unique(np.asarray(observed, np.int64))
    if len(uniq) == 0:
        return np.zeros(0, np.int64), []
    cut = np.flatnonzero(np.diff(uniq) - 1 > gap_frames)
    first, last = np.r_[uniq[0], uniq[cut + 1]], np.r_[uniq[cut], uniq[-1]]
    edges = np.r_[0, np.cumsum(last - first + 1)]
    frames = np.concatenate([np.arange(a, b + 1) for a, b in zip(first, last, strict=True)])
    return frames, [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


@dataclass
class DenseObservations:
    """Observations as dense arrays, the layout estimators work on.

    uv_px: raw pixels, shape (C, F, M, 2), NaN where unseen.
    weight: shape (C, F, M), 0 where unseen.
    frames: frame numbers along F, shape (F,) (the session's compacted axis: :func:`frame_axis`);
    cameras, markers: names along C and M. takes: slices of F solved on their own; empty = one take.
    time_frac: (C, F, M) each observation's capture time minus its session frame's time, in session frames,
        from the rig's known timing (offset, and readout times the row: :func:`capture_fractions`); 0 where unseen.
    row_frac: (C, F, M) raw row / image height of each observation (0 where unseen): what a readout multiplies.
    Both None when every camera exposes the session's frames all at once (nothing to model).
    """

    cameras: list[str]
    frames: np.ndarray
    markers: list[str]
    uv_px: np.ndarray
    weight: np.ndarray
    takes: list[slice] = field(default_factory=list)
    time_frac: np.ndarray | None = None
    row_frac: np.ndarray | None = None

    @property
    def take_slices(self) -> list[slice]:
        """The takes as slices along F (one covering every frame when none were set)."""
        return list(self.takes) or [slice(0, len(self.frames))]

    def take(self, sl: slice) -> DenseObservations:
        """The frames ``sl`` (one take) as a DenseObservations of their own (views, not copies)."""
        return DenseObservations(self.cameras, self.frames[sl], self.markers, self.uv_px[:, sl], self.weight[:, sl],
                                 time_frac=None if self.time_frac is None else self.time_frac[:, sl],
                                 row_frac=None if self.row_frac is None else self.row_frac[:, sl])

    @property
    def seen(self) -> np.ndarray:
        """bool (C, F, M)."""
        return np.isfinite(self.uv_px[..., 0])

    @property
    def n_views(self) -> np.ndarray:
        """Cameras seeing each (frame, marker), shape (F, M)."""
        return self.seen.sum(axis=0)


def span_distance(n_views: np.ndarray) -> np.ndarray:
    """Frames from each (frame, marker)'s nearest span end, (F, M) int: 0 inside the span (first to last frame
    with n_views >= 2, both included), -1 for a marker never seen twice. n_views: (F, M) views per point."""
    F, M = n_views.shape
    two = n_views >= 2
    has = two.any(axis=0)
    first = np.where(has, two.argmax(axis=0), 0)
    last = np.where(has, F - 1 - two[::-1].argmax(axis=0), -1)
    f = np.arange(F)[:, None]
    dist = np.maximum(first - f, 0) + np.maximum(f - last, 0)
    return np.where(has, dist, -1)


def dense_observations(session: Session, timing: bool | None = None) -> DenseObservations:
    """Scatter the long observations table into (C, F, M) arrays (see :class:`DenseObservations`).

    timing: fill ``time_frac`` and ``row_frac`` (True), leave them None (False), or fill them only when the rig
    puts a camera off the session clock (None, the default). An estimator of the timing asks for True.
    Raises InputError, before allocating, when they would not fit in memory (batgraph.inputs.check_dense_memory).
    """
    obs = session.observations
    cams, markers = session.rig.names, session.markers
    C, M = len(cams), len(markers)
    frames, takes = frame_axis(obs["frame"].to_numpy(), session.take_gap_frames)
    F = len(frames)
    inputs.check_dense_memory(C, F, M, f"session {session.name!r}" if session.path is None else str(session.path))
    ci = factorize(obs["camera"]).positions(cams)
    fi = np.searchsorted(frames, obs["frame"].to_numpy())
    mi = factorize(obs["marker"]).positions(markers)
    if (ci < 0).any():
        raise ValueError(f"observations name camera {obs['camera'].iloc[int(np.argmax(ci < 0))]!r}, not in the rig")
    uv = np.full((C, F, M, 2), np.nan)
    w = np.zeros((C, F, M))
    uv[ci, fi, mi] = obs[["u", "v"]].to_numpy(float)
    w[ci, fi, mi] = obs["weight"].to_numpy(float)
    dense = DenseObservations(cams, frames, markers, uv, w, takes if len(takes) > 1 else [])
    if timing or (timing is None and not session.rig.on_session_clock(session.fps)):
        time_frac, row_frac = capture_fractions(session.rig, obs, ci, session.fps)
        dense.time_frac, dense.row_frac = np.zeros((C, F, M)), np.zeros((C, F, M))
        dense.time_frac[ci, fi, mi], dense.row_frac[ci, fi, mi] = time_frac, row_frac
    return dense


def exposure_frames(camera_frame: np.ndarray, camera: Camera, fps: float) -> np.ndarray:
    """When a camera's own frames (N,) int start their exposure, in session frames (float, session clock).

    Exact for a camera at the session's rate with no offset (the frames as given)."""
    rate = camera.frame_rate(fps)
    return np.asarray(camera_frame, np.int64) * (float(fps) / rate) + camera.time_offset_s * float(fps)


def nearest_frame(x_frames: np.ndarray) -> np.ndarray:
    """The session frame nearest each time ``x_frames`` [session frames], a half going to the earlier frame
    (so DLTdv's rows, which round a half up when they pick a camera's frame, come back as they were)."""
    return np.ceil(np.asarray(x_frames, float) - 0.5).astype(np.int64)


def capture_fractions(rig: Rig, obs: pd.DataFrame, cam_index: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per observation row: (capture time minus its session frame, in session frames; raw row / height).

    obs: the session's observations (frame = session frame; camera_frame = the camera's own, when present);
    cam_index (N,): each row's camera in ``rig``. The capture time adds readout_s * v / height to the exposure.
    """
    own = obs["camera_frame"].to_numpy(np.int64) if "camera_frame" in obs else obs["frame"].to_numpy(np.int64)
    v = obs["v"].to_numpy(float)
    time_frac, row_frac = np.zeros(len(obs)), np.zeros(len(obs))
    for c, cam in enumerate(rig):
        sel = cam_index == c
        row_frac[sel] = v[sel] / cam.size_wh[1]
        start = exposure_frames(own[sel], cam, fps) - obs["frame"].to_numpy(np.int64)[sel]
        time_frac[sel] = start + cam.readout_s * float(fps) * row_frac[sel]
    return time_frac, row_frac


def check_clock(rig: Rig, fps: float, where: str) -> None:
    """InputError when a camera cannot live on a session clock of ``fps``: it runs faster, or reads out for a
    frame or more. where: the calibration file, for the message."""
    for cam in rig:
        rate = cam.frame_rate(fps)
        if rate > float(fps) * (1 + 1e-9):
            raise InputError(f"{where}: camera {cam.name} runs at {rate:g} fps, faster than the session's {fps:g} "
                             f"fps: raise [session] fps in session.toml to at least {rate:g} (the session's frames "
                             f"must be as fine as its fastest camera's)")
        if cam.readout_s >= 1.0 / rate:
            raise InputError(f"{where}: camera {cam.name} readout_s {cam.readout_s:g} s is not shorter than one of "
                             f"its frames (1 / {rate:g} fps = {1.0 / rate:g} s)")


def session_frames(camera_frame: np.ndarray, camera: np.ndarray, rig: Rig, fps: float) -> np.ndarray:
    """The session frame (N,) int64 of each camera's own frame: ``nearest_frame((j / fps_c + time_offset_s) * fps)``.

    camera_frame (N,) int: the cameras' own frame numbers; camera (N,): their camera names (all in ``rig``)."""
    ci = factorize(pd.Series(camera)).positions(rig.names)
    own = np.asarray(camera_frame, np.int64)
    k = own.copy()
    for c, cam in enumerate(rig):
        sel = ci == c
        k[sel] = nearest_frame(exposure_frames(own[sel], cam, fps))
    return k


def to_session_clock(table: pd.DataFrame, rig: Rig, fps: float, where: str) -> tuple[pd.DataFrame, list[str]]:
    """A table with frame and camera columns (observations, mislabels) from each camera's own frames to the
    session's frames; (table, warnings).

    Camera c's frame j goes to :func:`session_frames`; the table keeps j as ``camera_frame``. A rig on the session
    clock returns the table as it is (or, for a table mapped before, with its camera frames back). Rows that land
    before session frame 0 are dropped, with a warning; the rows are sorted by frame, camera, marker.
    """
    check_clock(rig, fps, where)
    own = (table["camera_frame"] if "camera_frame" in table else table["frame"]).to_numpy(np.int64)
    if rig.on_session_clock(fps):
        if "camera_frame" not in table:
            return table, []
        back = table.assign(frame=own).drop(columns="camera_frame")
        return back.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True), []
    k = session_frames(own, table["camera"].to_numpy(), rig, fps)
    out = table.assign(frame=k, camera_frame=own)
    notes = []
    early = k < 0
    if early.any():
        per = pd.Series(table["camera"].to_numpy()[early]).value_counts(sort=False)
        notes.append(f"{where}: {int(early.sum())} observation(s) fall before session frame 0 with the cameras' "
                     f"time offsets ({', '.join(f'{n} of {c}' for c, n in per.items())}); dropped")
        out = out[~early]
    return out.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True), notes


def retime(session: Session, rig: Rig) -> Session:
    """The session with another rig (e.g. estimated time offsets), its observations put on that rig's clock."""
    where = f"session {session.name!r}" if session.path is None else str(session.path)
    obs, notes = to_session_clock(session.observations, rig, session.fps, where)
    return dataclasses.replace(session, rig=rig, observations=obs, warnings=list(session.warnings) + notes)


# ----------------------------------------------------------------------------------------------
# reading (every file through batgraph.inputs: encodings, permissions, CSV dialects, frame limits)
# ----------------------------------------------------------------------------------------------
def near_miss(key: str, known) -> str | None:
    """The known key that ``key`` most likely misspells (difflib ratio >= CLOSE_MATCH, or the same letters in
    another order), or None."""
    close = difflib.get_close_matches(key, sorted(known), n=1, cutoff=CLOSE_MATCH)
    swapped = [k for k in sorted(known) if sorted(k) == sorted(key)]
    return close[0] if close else (swapped[0] if swapped else None)


def check_keys(keys, known, where: str, warnings: list[str]) -> None:
    """Unknown keys of one TOML table: InputError for a near miss of a known key (:func:`near_miss`: a typo such as
    ``time_ofset_s`` would silently change the result), else one warning line naming them (keys other tools
    write must not stop a file from loading). where: the file and table, for the messages."""
    unknown = [k for k in keys if k not in known]
    for k in unknown:
        close = near_miss(k, known)
        if close:
            raise InputError(f"{where}: unknown key {k!r} (did you mean {close!r}?)")
    if unknown:
        warnings.append(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} ignored "
                        f"(known: {', '.join(sorted(known))})")


def _timing(tab: dict, where: str) -> dict:
    """A camera table's timing keys (TIMING_KEYS), validated: finite, fps > 0, readout and the sds >= 0, the
    readout shorter than one frame when the camera's fps is given (else checked against the session's: check_clock)."""
    out = {}
    for k in TIMING_KEYS:
        if k in tab:
            out[k] = inputs.number(tab[k], f"{where} {k}", positive=k != "time_offset_s",
                                   allow_zero=k in ("readout_s", "time_offset_sd_s", "readout_sd_s"))
    if "fps" in out and out.get("readout_s", 0.0) >= 1.0 / out["fps"]:
        raise InputError(f"{where} readout_s: {out['readout_s']:g} s is not shorter than one frame "
                         f"(1 / fps = {1.0 / out['fps']:g} s)")
    return out


def _pose_covariance(value, where: str) -> np.ndarray:
    """A 6x6 pose covariance: finite, symmetric and positive definite (the estimators invert it)."""
    cov = inputs.array(value, (6, 6), where)
    if not np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12 * max(float(np.abs(cov).max()), 1e-300)):
        i, j = np.unravel_index(int(np.argmax(np.abs(cov - cov.T))), cov.shape)
        raise InputError(f"{where}: not symmetric ([{i}][{j}] = {float(cov[i, j])!r} but [{j}][{i}] = "
                         f"{float(cov[j, i])!r})")
    try:
        np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        smallest = float(np.linalg.eigvalsh(cov).min())
        raise InputError(f"{where}: not positive definite (smallest eigenvalue {smallest:.3g}); a covariance "
                         f"needs every variance > 0") from None
    return cov


def read_calibration(path: Path, units: str | None = None, warnings: list[str] | None = None) -> Rig:
    """Read an aniposelib-style calibration.toml into a :class:`Rig` (order of the tables), in metres.

    Translations are in ``[metadata] units`` ("m" default, "cm", "mm"); ``units`` overrides it (an
    importer's --units). ``[metadata] world_mirror`` (three +-1) marks a left-handed user frame. A camera's
    timing (TIMING_KEYS) is optional. Unknown keys: :func:`check_keys`; their warnings are appended to
    ``warnings``, or issued as Python warnings when it is None (never silent).
    """
    notes = [] if warnings is None else warnings
    data = inputs.read_toml(path)
    meta = data.get("metadata", {})
    meta = meta if isinstance(meta, dict) else {}
    check_keys(meta, METADATA_KEYS, f"{path} [metadata]", notes)
    units = units if units is not None else meta.get("units", "m")
    if not isinstance(units, str) or units not in UNITS_M:
        raise InputError(f"{path} [metadata] units: {units!r} is not one of {', '.join(UNITS_M)}")
    scale = UNITS_M[units]  # translations [units] -> [m]
    mirror = np.ones(3)
    if "world_mirror" in meta:
        mirror = inputs.array(meta["world_mirror"], (3,), f"{path} [metadata] world_mirror")
        if not np.all(np.abs(mirror) == 1):
            raise InputError(f"{path} [metadata] world_mirror: expected three values of 1 or -1, got {mirror.tolist()}")
    loose = [k for k, v in data.items() if not isinstance(v, dict)]
    if loose:
        notes.append(f"{path}: top-level key(s) {', '.join(map(repr, loose))} outside any camera table ignored")
    cams = [_camera(tab, f"{path} [{key}]", key, scale, notes) for key, tab in data.items()
            if key != "metadata" and isinstance(tab, dict)]
    if not cams:
        raise InputError(f"{path}: no camera tables (expected [cam_0], [cam_1], ...)")
    names = [c.name for c in cams]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"{path}: camera name {dup[0]!r} appears more than once")
    if warnings is None:
        for line in notes:
            warnings_mod.warn(line, stacklevel=2)
    return Rig(cams, world_mirror=mirror)


def _camera(tab: dict, where: str, key: str, scale: float, notes: list[str]) -> Camera:
    """One camera table of calibration.toml (see :func:`read_calibration`); translations times ``scale``."""
    check_keys(tab, CAMERA_KEYS, where, notes)
    for k in ("size", "matrix", "rotation", "translation"):
        if k not in tab:
            raise InputError(f"{where}: missing key '{k}'")
    if tab.get("fisheye", False):
        raise InputError(f"{where}: fisheye calibrations are not supported (use the 5-parameter model)")
    name = tab.get("name", key)
    if not isinstance(name, str | int) or isinstance(name, bool) or not str(name).strip():
        raise InputError(f"{where} name: expected a camera name, got {name!r}")
    size = inputs.array(tab["size"], (2,), f"{where} size")
    if (size <= 0).any() or (size != np.round(size)).any() or (size > 100_000).any():
        raise InputError(f"{where} size: expected two positive integers [width, height], got {tab['size']!r}")
    K = inputs.array(tab["matrix"], (3, 3), f"{where} matrix")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise InputError(f"{where} matrix: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    dist = tab.get("distortions", [0.0] * 5)
    if not isinstance(dist, list) or len(dist) > 5:
        raise InputError(f"{where} distortions: expected up to 5 values [k1, k2, p1, p2, k3], got {dist!r}")
    dist = inputs.array(list(dist) + [0.0] * (5 - len(dist)), (5,), f"{where} distortions")
    rvec = inputs.array(tab["rotation"], (3,), f"{where} rotation")
    tvec = inputs.array(tab["translation"], (3,), f"{where} translation") * scale
    cov = None
    if "pose_covariance" in tab:
        s_t = np.diag([1.0, 1.0, 1.0, scale, scale, scale])  # tangent [rot rad, trans units]
        cov = s_t @ _pose_covariance(tab["pose_covariance"], f"{where} pose_covariance") @ s_t
    return Camera(str(name), (int(size[0]), int(size[1])), K, dist, rvec, tvec, cov, **_timing(tab, where))


def read_observations(path: Path, rig: Rig, calibration_name: str = "calibration.toml",
                      shown_as: str | None = None) -> tuple[pd.DataFrame, list[str]]:
    """Read and validate observations.csv/.parquet against ``rig`` (read from ``calibration_name``, named in
    errors). Returns (table, warnings; they name the file as ``shown_as`` where given). Frames obey
    batgraph.inputs' limits (MAX_FRAME, MAX_FRAME_GAP).

    The camera and marker columns are checked, matched and sorted as codes into their distinct names
    (batgraph.labels), not as text per row.
    """
    df, is_csv = inputs.read_table(path, OBS_COLUMNS, "observations")
    frame = inputs.frame_column(df, path, is_csv)
    camera = inputs.label_codes(df, "camera", path, is_csv)
    marker = inputs.label_codes(df, "marker", path, is_csv)
    u = inputs.numeric_column(df, "u", path, is_csv, allow_missing=True)
    v = inputs.numeric_column(df, "v", path, is_csv, allow_missing=True)
    if "weight" in df.columns:
        w = inputs.numeric_column(df, "weight", path, is_csv, allow_missing=True)
        w = np.where(np.isnan(w), 1.0, w)
        bad = ~((w > 0) & (w <= 1))
        if bad.any():
            i = int(np.argmax(bad))
            raise InputError(f"{path} {inputs.row_name(i, is_csv)}: weight {inputs.cell(df['weight'].iloc[i])} "
                             f"is not in (0, 1]")
    else:
        w = np.ones(len(df))
    cam = camera.positions(rig.names)  # (N,) index into the rig, -1 for a name not in it
    if (cam < 0).any():
        i = int(np.argmax(cam < 0))
        raise InputError(
            f"{path} {inputs.row_name(i, is_csv)}: camera {camera.names[camera.codes[i]]!r} is not in "
            f"{calibration_name} (cameras: {', '.join(rig.names)})"
        )
    half = np.isnan(u) != np.isnan(v)
    if half.any():
        i = int(np.argmax(half))
        raise InputError(f"{path} {inputs.row_name(i, is_csv)}: only one of u, v is given")
    rows = np.flatnonzero(~np.isnan(u))  # the file's data rows that hold an observation
    if len(rows) == 0:
        raise InputError(f"{path}: no observations (every u, v is empty)")
    inputs.check_frame_gaps(frame[rows], path, is_csv, rows=rows)
    # observations.csv's order: frame, then camera and marker names as text sort (stable: file order within a key)
    rows = rows[np.lexsort((marker.sort_keys()[rows], camera.sort_keys()[rows], frame[rows]))]
    _check_duplicates(rows, frame, camera, marker, path, is_csv)
    warnings = []
    n_out = 0
    for c, one in enumerate(rig):
        sel = rows[cam[rows] == c]
        n_out += int((~one.in_image(np.stack([u[sel], v[sel]], axis=1))).sum())
    if n_out:
        warnings.append(f"{shown_as or path}: {n_out} observation(s) lie outside their camera's image; kept")
    out = pd.DataFrame({"frame": frame[rows], "camera": text_column(camera.names, camera.codes[rows]),
                        "marker": text_column(marker.names, marker.codes[rows]),
                        "u": u[rows], "v": v[rows], "weight": w[rows]})
    return out, warnings


def _check_duplicates(rows: np.ndarray, frame: np.ndarray, camera: Labels, marker: Labels, path: Path,
                      is_csv: bool) -> None:
    """InputError naming the first row (in file order) whose frame, camera and marker another row repeats, and
    the next such row. rows: data rows sorted by (frame, camera, marker), file order within a key."""
    same = ((frame[rows[1:]] == frame[rows[:-1]]) & (camera.codes[rows[1:]] == camera.codes[rows[:-1]])
            & (marker.codes[rows[1:]] == marker.codes[rows[:-1]]))  # sorted row k + 1 repeats row k
    if not same.any():
        return
    k = np.flatnonzero(same)
    k = k[np.argmin(rows[k])]  # the repeated key whose first row comes first in the file
    a, b = int(rows[k]), int(rows[k + 1])
    raise InputError(f"{path} {inputs.row_name(a, is_csv)} and {inputs.row_name(b, is_csv)}: duplicate observation "
                     f"of frame {frame[a]}, camera {camera.names[camera.codes[a]]!r}, "
                     f"marker {marker.names[marker.codes[a]]!r}")


def read_points(path: Path) -> pd.DataFrame:
    """Read a frame, marker, x, y, z table (truth.csv, reference_xyz.csv); empty xyz rows dropped."""
    df, is_csv = inputs.read_table(path, TRUTH_COLUMNS, "points")
    out = pd.DataFrame({"frame": inputs.frame_column(df, path, is_csv),
                        "marker": inputs.label_column(df, "marker", path, is_csv)})
    for c in "xyz":
        out[c] = inputs.numeric_column(df, c, path, is_csv, allow_missing=True)
    return out.dropna().reset_index(drop=True)


def read_mislabels(path: Path) -> pd.DataFrame:
    """Read truth_mislabels.csv (frame, camera, marker of deliberately mislabelled rows); header-only is fine."""
    df, is_csv = inputs.read_table(path, ["frame", "camera", "marker"], "mislabelled rows", allow_empty=True)
    return pd.DataFrame({"frame": inputs.frame_column(df, path, is_csv),
                         "camera": inputs.label_column(df, "camera", path, is_csv).to_numpy(dtype=object),
                         "marker": inputs.label_column(df, "marker", path, is_csv).to_numpy(dtype=object)})


TRUTH_TIMING = "truth_timing.toml"
TRUTH_TIMING_COLUMNS = ["camera", "fps", "time_offset_s", "readout_s"]


def read_truth_timing(path: Path) -> pd.DataFrame:
    """truth_timing.toml (simulated sessions): one table per camera with name, fps, time_offset_s, readout_s."""
    rows = []
    for key, tab in inputs.read_toml(path).items():
        where = f"{path} [{key}]"
        if not isinstance(tab, dict) or not set(TRUTH_TIMING_COLUMNS[1:]) <= set(tab) or "name" not in tab:
            raise InputError(f"{where}: expected name, fps, time_offset_s and readout_s")
        rows.append({"camera": str(tab["name"]), "fps": inputs.number(tab["fps"], f"{where} fps", positive=True),
                     "time_offset_s": inputs.number(tab["time_offset_s"], f"{where} time_offset_s"),
                     "readout_s": inputs.number(tab["readout_s"], f"{where} readout_s", positive=True,
                                                allow_zero=True)})
    return pd.DataFrame(rows, columns=TRUTH_TIMING_COLUMNS)


def truth_timing_toml(table: pd.DataFrame) -> str:
    """The text of truth_timing.toml from a camera, fps, time_offset_s, readout_s table."""
    return tomli_w.dumps({f"cam_{i}": {"name": str(r.camera), "fps": float(r.fps),
                                       "time_offset_s": float(r.time_offset_s), "readout_s": float(r.readout_s)}
                          for i, r in enumerate(table.itertuples())})


def _session_config(path: Path, warnings: list[str]) -> dict:
    data = inputs.read_toml(path)
    for table, value in data.items():
        if table not in SESSION_KEYS:
            close = near_miss(table, SESSION_KEYS)
            if close:
                raise InputError(f"{path}: unknown table [{table}] (did you mean [{close}]?)")
            warnings.append(f"{path}: unknown table [{table}] ignored (known: {', '.join(sorted(SESSION_KEYS))})")
        elif SESSION_KEYS[table] is not None and isinstance(value, dict):
            check_keys(value, SESSION_KEYS[table], f"{path} [{table}]", warnings)
    sess = data.get("session")
    if not isinstance(sess, dict):
        raise InputError(f"{path}: missing table [session]")
    if "fps" not in sess:
        raise InputError(f"{path} [session]: missing key 'fps'")
    inputs.number(sess["fps"], f"{path} [session] fps", positive=True)
    if "take_gap_s" in sess:
        inputs.number(sess["take_gap_s"], f"{path} [session] take_gap_s", positive=True)
    for key in ("motion", "noise", "markers"):
        if not isinstance(data.get(key, {}), dict):
            raise InputError(f"{path}: '{key}' must be a table [{key}], got {data[key]!r}")
    markers = data.get("markers", {})
    inputs.unique_names(markers.get("names", []), f"{path} [markers] names", "marker name")
    for key in ("skeleton", "rigid"):
        pairs = markers.get(key, [])
        if not isinstance(pairs, list):
            raise InputError(f"{path} [markers] {key}: expected a list of [marker, marker] pairs, got {pairs!r}")
        for i, edge in enumerate(pairs):
            if not (isinstance(edge, list) and len(edge) == 2 and all(isinstance(e, str) for e in edge)):
                raise InputError(f"{path} [markers] {key}[{i}]: expected a pair of marker names, got {edge!r}")
            if key == "rigid" and edge[0] == edge[1]:
                raise InputError(f"{path} [markers] rigid[{i}]: a segment needs two different markers, got {edge!r}")
    if "rigid_sigma_m" in markers:
        sigma = inputs.number(markers["rigid_sigma_m"], f"{path} [markers] rigid_sigma_m", positive=True)
        lo, hi = RIGID_SIGMA_RANGE_M
        if not lo <= sigma <= hi:
            raise InputError(f"{path} [markers] rigid_sigma_m: {sigma:g} m is outside [{lo:g}, {hi:g}] m (the std of "
                             "a segment's length about its one value; default 0.002)")
    motion = data.get("motion", {})
    model = motion.get("model", MotionConfig.model)
    if model not in MOTION_MODELS:
        raise InputError(f"{path} [motion] model: {model!r} is not one of {', '.join(MOTION_MODELS)}")
    for k in ("flight_speed_mps", "span_m", "flap_hz", "flap_angle_deg", "sigma_m", "accel_psd_m2_s3"):
        if k in motion:
            inputs.number(motion[k], f"{path} [motion] {k}", positive=True, allow_zero=k == "flight_speed_mps")
    sync = data.get("sync", {})
    if "estimate" in sync and not isinstance(sync["estimate"], bool):
        raise InputError(f"{path} [sync] estimate: expected true or false, got {sync['estimate']!r}")
    noise = data.get("noise", {})
    if "pixel_sigma_px" in noise:
        inputs.number(noise["pixel_sigma_px"], f"{path} [noise] pixel_sigma_px", positive=True)
    return data


def read_session(folder: str | Path, calibration: str | Path | None = None,
                 observations: str | Path | None = None, observations_shown_as: str | None = None) -> Session:
    """Load and validate a session folder (see module docstring).

    calibration: a calibration.toml to use instead of the folder's own (e.g. one ``calibrate`` wrote
    from a wand recording of the same rig); observations: an observations.csv to use instead of the folder's (the
    names ``batgraph associate`` gave its detections), named in warnings as ``observations_shown_as`` where given
    (a scratch file's path means nothing to the user); the folder is not modified.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: session folder not found" if not folder.exists()
                         else f"{folder}: not a folder (a session is a folder holding session.toml, ...)")
    notes: list[str] = []
    cfg = _session_config(folder / "session.toml", notes)
    cal_path = Path(calibration) if calibration is not None else folder / "calibration.toml"
    rig = read_calibration(cal_path, warnings=notes)
    obs_path = folder / "observations.csv" if observations is None else Path(observations)
    if not obs_path.exists() and observations is None and (folder / "observations.parquet").exists():
        obs_path = folder / "observations.parquet"
    if not obs_path.exists():
        if any((folder / f"detections.{ext}").exists() for ext in ("csv", "parquet")):
            raise InputError(f"{obs_path}: file not found; the folder holds unlabelled detections: name them first "
                             f"with `batgraph associate {folder}` (docs/associate.md)")
        raise InputError(f"{obs_path}: file not found (nor observations.parquet)")
    observations, warnings = read_observations(obs_path, rig, cal_path.name if calibration is None else str(cal_path),
                                               observations_shown_as)
    sess, motion, noise = cfg["session"], cfg.get("motion", {}), cfg.get("noise", {})
    observations, clock_notes = to_session_clock(observations, rig, float(sess["fps"]), str(cal_path))
    warnings = notes + warnings + clock_notes
    known = {f for f in MotionConfig.__dataclass_fields__} - {"causal_accel_psd_m2_s3"}
    mcfg = MotionConfig(**{k: v for k, v in motion.items() if k in known})
    markers = cfg.get("markers", {})
    names = [str(n) for n in markers.get("names", [])]
    skeleton = [(str(a), str(b)) for a, b in markers.get("skeleton", [])]
    rigid = list(dict.fromkeys((str(a), str(b)) for a, b in markers.get("rigid", [])))
    observed = set(observations["marker"].unique())
    known_markers = set(names) | observed
    for key, pairs in (("skeleton", skeleton), ("rigid", rigid)):
        for i, edge in enumerate(pairs):
            for e in edge:
                if e not in known_markers:
                    raise InputError(f"{folder / 'session.toml'} [markers] {key}[{i}]: marker {e!r} is neither in "
                                     f"[markers] names nor observed in {obs_path.name}")
    take_gap_s = float(sess.get("take_gap_s", DEFAULT_TAKE_GAP_S))
    frames, _ = frame_axis(observations["frame"].to_numpy(), gap_frames(take_gap_s, float(sess["fps"])))
    n_markers = len(known_markers)
    inputs.check_dense_memory(len(rig), len(frames), n_markers, str(obs_path))
    truth = read_points(folder / "truth.csv") if (folder / "truth.csv").exists() else None
    ref = read_points(folder / "reference_xyz.csv") if (folder / "reference_xyz.csv").exists() else None
    true_rig = (read_calibration(folder / "calibration_true.toml")
                if (folder / "calibration_true.toml").exists() else None)
    mislabels = None
    if (folder / "truth_mislabels.csv").exists():  # header-only is fine: a clean simulation
        mislabels = read_mislabels(folder / "truth_mislabels.csv")
    if mislabels is not None:
        mislabels = to_session_clock(mislabels, rig, float(sess["fps"]), str(cal_path))[0]
    true_timing = read_truth_timing(folder / TRUTH_TIMING) if (folder / TRUTH_TIMING).exists() else None
    extra = {k: v for k, v in cfg.items() if k not in ("session", "motion", "noise", "markers")}
    return Session(
        name=str(sess.get("name", folder.name)), fps=float(sess["fps"]), rig=rig,
        observations=observations, motion=mcfg,
        pixel_sigma_px=float(noise["pixel_sigma_px"]) if "pixel_sigma_px" in noise else None,
        marker_names=names, skeleton=skeleton,
        truth=truth, reference=ref, true_rig=true_rig, mislabels=mislabels, extra_toml=extra, path=folder,
        warnings=warnings, take_gap_s=take_gap_s, rigid=rigid,
        rigid_sigma_m=float(markers.get("rigid_sigma_m", DEFAULT_RIGID_SIGMA_M)), true_timing=true_timing,
    )


# ----------------------------------------------------------------------------------------------
# writing
# ----------------------------------------------------------------------------------------------
def calibration_toml(rig: Rig) -> str:
    """The aniposelib-format text of a rig (plus batgraph's optional pose_covariance)."""
    doc = {}
    for i, c in enumerate(rig):
        tab = {
            "name": c.name,
            "size": [int(c.size_wh[0]), int(c.size_wh[1])],
            "matrix": c.K.tolist(),
            "distortions": c.dist.tolist(),
            "rotation": c.rvec.tolist(),
            "translation": c.tvec.tolist(),
        }
        if c.pose_cov is not None:
            tab["pose_covariance"] = c.pose_cov.tolist()
        for k in TIMING_KEYS:  # only what is stated: a rig without timing writes as it always did
            value = getattr(c, k)
            if value is not None and (value != 0 or k.endswith("_sd_s")):
                tab[k] = float(value)
        doc[f"cam_{i}"] = tab
    doc["metadata"] = {"written_by": "batgraph", "units": "m"}
    if rig.mirrored:
        doc["metadata"]["world_mirror"] = rig.world_mirror.tolist()
    return tomli_w.dumps(doc)


def session_toml(session: Session) -> str:
    """The text of session.toml: only what the session states (no physics, no noise it does not know)."""
    m = session.motion
    motion = {"model": m.model}
    for k in (*PAPER_PHYSICS, "sigma_m", "accel_psd_m2_s3"):
        if getattr(m, k) is not None:
            motion[k] = getattr(m, k)
    doc = {"session": {"name": session.name, "fps": session.fps}, "motion": motion}
    if session.take_gap_s != DEFAULT_TAKE_GAP_S:
        doc["session"]["take_gap_s"] = session.take_gap_s
    if isinstance(session.pixel_sigma_px, int | float):
        doc["noise"] = {"pixel_sigma_px": session.pixel_sigma_px}
    if session.marker_names or session.skeleton or session.rigid:
        doc["markers"] = {"names": list(session.marker_names), "skeleton": [list(e) for e in session.skeleton]}
        if session.rigid:
            doc["markers"]["rigid"] = [list(e) for e in session.rigid]
        if session.rigid_sigma_m != DEFAULT_RIGID_SIGMA_M:
            doc["markers"]["rigid_sigma_m"] = session.rigid_sigma_m
    doc.update(session.extra_toml)
    return tomli_w.dumps(doc)


def write_session(session: Session, folder: str | Path) -> Path:
    """Write a session folder (every file atomically). Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    atomic.write_text(folder / "session.toml", session_toml(session))
    atomic.write_text(folder / "calibration.toml", calibration_toml(session.rig))
    obs = session.observations
    if "camera_frame" in obs:  # the file holds each camera's own frame numbers (to_session_clock)
        obs = obs.assign(frame=obs["camera_frame"]).sort_values(["frame", "camera", "marker"], kind="stable")
    cols = OBS_COLUMNS + (["weight"] if "weight" in obs and not np.allclose(obs["weight"], 1.0) else [])
    write_csv(folder / "observations.csv", obs[cols], "%.6f")
    if session.truth is not None:
        write_csv(folder / "truth.csv", session.truth[TRUTH_COLUMNS], "%.9f")
    if session.reference is not None:
        write_csv(folder / "reference_xyz.csv", session.reference[TRUTH_COLUMNS], "%.9f")
    if session.true_rig is not None:
        atomic.write_text(folder / "calibration_true.toml", calibration_toml(session.true_rig))
    if session.mislabels is not None:
        mis = session.mislabels
        if "camera_frame" in mis:
            mis = mis.assign(frame=mis["camera_frame"]).sort_values(["frame", "camera", "marker"], kind="stable")
        atomic.write_text(folder / "truth_mislabels.csv", mis[["frame", "camera", "marker"]].to_csv(index=False))
    if session.true_timing is not None:
        atomic.write_text(folder / TRUTH_TIMING, truth_timing_toml(session.true_timing))
    return folder
