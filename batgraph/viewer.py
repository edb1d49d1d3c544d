"""Rerun recordings of a session and its results (saved .rrd, live viewer, opening a file); estimates nothing.

Rerun is imported inside functions, so ``import batgraph`` never loads it. Timelines: ``frame`` (the frame
number) and ``time`` (frame / fps s). Entities ({cam}, {method} escaped): ``world`` (annotation context:
class id i = marker i, its name on hover); ``world/cameras/{cam}`` (pose, static) and its ``image`` (Pinhole
K and size) holding ``border``, ``detections`` (raw pixels per frame) and ``reproj/{method}`` (predicted
raw pixels, outliers red; ``residuals`` lines); ``world/{method}/`` ``markers`` and ``ellipsoids`` (95 %)
inside each marker's span, ``names`` (a few markers named), ``skeleton`` (session.toml's edges),
``trails`` (last positions) and ``track_ends/`` (the markers and ellipsoids outside the spans: hidden).
Every per-frame entity has a row on every frame (Rerun shows the latest row at the cursor). A recording
opens (:func:`default_blueprint`) aimed at the animal on its opening frame; ``batgraph view`` also moves
the time cursor there. The 2D entities are raw (distorted) pixels where the marker is in the image;
Rerun's Pinhole is ideal, so in 3D their rays are off by the lens's distortion, not by an error.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from . import methods
from .atomic import atomic_path
from .errors import InputError
from .evaluate import add_span, dense_from_table, opening_frame
from .motion import CHI2_3DOF_95

#: chi-square quantile, 3 degrees of freedom, 0.95: a 3D Gaussian's 95 % ellipsoid is
#: ``(x - mu)^T cov^-1 (x - mu) <= CHI2_3D_95``, i.e. half-axes ``sqrt(CHI2_3D_95 * eigenvalue)``.
CHI2_3D_95 = CHI2_3DOF_95  # 95 % quantile of chi-square, 3 DOF (ellipsoid half-axes)

RECORDING_NAME = "recording.rrd"
APPLICATION_ID = "batgraph"

DETECTION_COLOR = (255, 255, 255)
OUTLIER_COLOR = (214, 39, 40)
BORDER_COLOR = (110, 110, 110)
TRACK_END_COLOR = (150, 150, 150)
NAMED_MARKERS = 5
"""Markers whose names the 3D view shows (chosen far apart, :func:`named_markers`); the others' on hover."""


class ViewerUnavailable(InputError):
    """The Rerun viewer cannot be shown here (no display, or no rerun executable); one-line message."""


def _rr():
    try:
        import rerun as rr
    except ImportError:  # the viewer is optional for a library user; say what to install
        raise InputError("the Rerun viewer needs the rerun-sdk package (pip install rerun-sdk)") from None
    return rr


def preload_rerun() -> None:
    """Import Rerun now (1.4 s on a 2-core machine), where a later write would otherwise wait for it."""
    _rr()


def method_color(method: str) -> tuple[int, int, int]:
    """RGB colour of a method, from the method registry (the report uses the same)."""
    return methods.rgb(method)


def display_available() -> bool:
    """False on Linux/BSD without an X11 or Wayland display (where a viewer window cannot open)."""
    if sys.platform.startswith(("win", "darwin")):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _rerun_executable() -> str:
    """Path of the rerun viewer binary shipped with rerun-sdk (works when the venv's bin is not on PATH)."""
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
    if sys.platform == "darwin":
        bundled = exe.parent / "Rerun.app" / "Contents" / "MacOS" / "Rerun"
        exe = bundled if bundled.exists() else exe
    if not exe.exists():
        raise ViewerUnavailable(f"the rerun viewer executable is missing ({exe}); reinstall rerun-sdk")
    return str(exe)


def _port_open(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def _require_display(what: str, hint: str | None = None) -> None:
    """Raise ViewerUnavailable without a display; ``hint`` says what to do instead (default: reconstruct's)."""
    if not display_available():
        hint = hint or (f"use --viewer save and open {RECORDING_NAME} on a machine with a screen "
                        f"(batgraph view OUT_DIR or rerun {RECORDING_NAME})")
        raise ViewerUnavailable(f"cannot {what}: no display (DISPLAY / WAYLAND_DISPLAY unset); {hint}")


def shown_method(names) -> str | None:
    """The method a recording opens with: the smoother when it ran, else the first (the others are hidden)."""
    names = [str(n) for n in names]
    return "smoother" if "smoother" in names else (names[0] if names else None)


# ----------------------------------------------------------------------------------------------
# geometry helpers (pure numpy)
# ----------------------------------------------------------------------------------------------
def ellipsoid_axes(cov: np.ndarray, chi2: float = CHI2_3D_95) -> tuple[np.ndarray, np.ndarray]:
    """Half-axes and orientation of the confidence ellipsoids of 3x3 covariances.

    cov: covariances, shape (N, 3, 3) [m^2], symmetric.
    chi2: the ellipsoid's squared Mahalanobis radius (default: 95 % for 3 degrees of freedom).
    Returns (half_sizes (N, 3) [m], quaternions_xyzw (N, 4)): the ellipsoid is
    ``R diag(half_sizes) unit_sphere`` with ``R`` the rotation of the quaternion, whose columns
    are the eigenvectors of ``cov``, so ``cov = R diag(half_sizes**2 / chi2) R^T``.
    """
    cov = np.asarray(cov, dtype=float)
    if cov.ndim != 3 or cov.shape[1:] != (3, 3):
        raise ValueError(f"cov must have shape (N, 3, 3), got {cov.shape}")
    if len(cov) == 0:
        return np.zeros((0, 3)), np.zeros((0, 4))
    eigval, eigvec = np.linalg.eigh(0.5 * (cov + cov.transpose(0, 2, 1)))
    # eigenvectors are defined up to sign: flip one to make a proper rotation (det +1)
    eigvec[..., 2] *= np.sign(np.linalg.det(eigvec))[:, None]
    half = np.sqrt(chi2 * np.clip(eigval, 0.0, None))  # round-off can make a flat direction slightly < 0
    return half, quaternions_xyzw(eigvec)


def quaternions_xyzw(rot: np.ndarray) -> np.ndarray:
    """Unit quaternions (x, y, z, w), Rerun's order, of rotation matrices ``rot`` (N, 3, 3).

    Shepperd's method: per matrix, the largest of |w|, |x|, |y|, |z| comes from the diagonal and the others
    from off-diagonal sums divided by it, so nothing is divided by a small number. The same rotations as
    scipy's ``Rotation.from_matrix(rot).as_quat()`` (up to the sign of q), without importing scipy.spatial
    (~70 ms of a recording's write).
    """
    m = np.asarray(rot, dtype=float)
    m00, m11, m22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):  # the cases not chosen may divide by ~0
        x = 0.5 * np.sqrt(np.clip(1 + m00 - m11 - m22, 0, None))
        y = 0.5 * np.sqrt(np.clip(1 - m00 + m11 - m22, 0, None))
        z = 0.5 * np.sqrt(np.clip(1 - m00 - m11 + m22, 0, None))
        w = 0.5 * np.sqrt(np.clip(1 + m00 + m11 + m22, 0, None))
        s_x, s_y, s_z = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
        xy, xz, yz = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
        cases = np.stack([  # (4 cases, N, 4): the largest component is x, y, z or w
            np.stack([x, xy / (4 * x), xz / (4 * x), s_x / (4 * x)], -1),
            np.stack([xy / (4 * y), y, yz / (4 * y), s_y / (4 * y)], -1),
            np.stack([xz / (4 * z), yz / (4 * z), z, s_z / (4 * z)], -1),
            np.stack([s_x / (4 * w), s_y / (4 * w), s_z / (4 * w), w], -1)])
    q = cases[np.argmax(np.stack([x, y, z, w]), axis=0), np.arange(len(m))]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _trail_windows(xyz: np.ndarray, n: int) -> np.ndarray:
    """Windows of the last ``n`` positions per frame: xyz (F, M, 3) -> (F, M, n, 3), oldest first.

    Before the first frame the window repeats frame 0 (zero-length segments draw nothing).
    """
    F = len(xyz)
    idx = np.clip(np.arange(F)[:, None] - (n - 1) + np.arange(n)[None, :], 0, None)  # (F, n)
    return xyz[idx].transpose(0, 2, 1, 3)


def _window_strips(win: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fill the gaps of trail windows and keep those whose newest point exists.

    win: (F, M, n, 3), NaN where a marker was not estimated.
    Returns (strips (S, n, 3), keep (F, M) bool): a missing point takes the newest earlier point of
    its window (or the oldest later one), so a trail jumps over a gap instead of breaking it.
    """
    valid = np.isfinite(win).all(axis=-1)  # (F, M, n)
    n = win.shape[2]
    last = np.maximum.accumulate(np.where(valid, np.arange(n), -1), axis=-1)
    first = np.argmax(valid, axis=-1)[..., None]
    src = np.where(last < 0, first, last)
    keep = valid[..., -1]
    filled = np.take_along_axis(win[keep], src[keep][..., None], axis=1)
    return filled, keep


def _dense_results(table: pd.DataFrame, frames: np.ndarray, markers: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """One method's trajectory rows -> xyz (F, M, 3) [m] and cov (F, M, 3, 3) [m^2], NaN where absent."""
    xyz, cov, _, _ = dense_from_table(table, frames, markers)
    return xyz, cov


# ----------------------------------------------------------------------------------------------
# logging
# ----------------------------------------------------------------------------------------------
def _path(*parts: str) -> str:
    rr = _rr()
    return "/".join(rr.escape_entity_path_part(str(p)) for p in parts)


def _time_columns(frames: np.ndarray, fps: float) -> list:
    rr = _rr()
    frames = np.asarray(frames, dtype=np.int64)
    return [rr.TimeColumn("frame", sequence=frames), rr.TimeColumn("time", duration=frames / float(fps))]


def _marker_list(session, *names) -> list[str]:
    """Class ids of the recording: session.toml's markers, then the observed ones, then any in ``names``.

    names: marker-name sequences or columns (e.g. a table's ``marker``), appended in first-seen order.
    The same as ``session.markers`` followed by extras, but vectorised (it runs on million-row tables).
    """
    out = dict.fromkeys(map(str, session.marker_names))
    for seq in (session.observations["marker"], *names):
        if seq is not None and len(seq):
            out.update(dict.fromkeys(map(str, pd.unique(pd.Series(seq)))))
    return list(out)


def _class_ids(keep: np.ndarray) -> np.ndarray:
    """Marker index of every kept (frame, marker) cell, keep (F, M) -> (n,) uint16."""
    return np.broadcast_to(np.arange(keep.shape[1], dtype=np.uint16), keep.shape)[keep]


def _image_plane_distance(rig) -> float:
    """Frustum depth for drawing: a tenth of the rig's spread (cameras 5 m apart -> ~0.5 m)."""
    c = np.array([cam.center_world for cam in rig])
    spread = float(np.median(np.linalg.norm(c - c.mean(axis=0), axis=1))) if len(c) > 1 else 0.0
    return 0.1 * spread if spread > 0 else 0.3


def log_session(rec, session, dense=None) -> None:
    """Log the static rig and (if given) every frame's 2D detections.

    rec: a ``rerun.RecordingStream``.
    session: :class:`batgraph.session.Session` (rig, markers, fps).
    dense: :class:`batgraph.session.DenseObservations` with uv_px (C, F, M, 2) raw pixels, NaN
        where unseen; None logs the cameras only.
    """
    rr = _rr()
    markers = _marker_list(session, None if dense is None else dense.markers)
    rec.log("world", rr.AnnotationContext([(i, m) for i, m in enumerate(markers)]), static=True)
    depth = _image_plane_distance(session.rig)
    for cam in session.rig:
        R_wc, t_wc = cam.world_from_cam()
        rec.log(_path("world", "cameras", cam.name), rr.Transform3D(translation=t_wc, mat3x3=R_wc), static=True)
        # camera axes x right, y down, z forward (batgraph.camera) = Rerun's RDF
        rec.log(_path("world", "cameras", cam.name, "image"),
                rr.Pinhole(image_from_camera=cam.K, resolution=list(cam.size_wh), camera_xyz=rr.ViewCoordinates.RDF,
                           image_plane_distance=depth), static=True)
        w, h = cam.size_wh
        rec.log(_path("world", "cameras", cam.name, "image", "border"),
                rr.LineStrips2D([[(-0.5, -0.5), (w - 0.5, -0.5), (w - 0.5, h - 0.5), (-0.5, h - 0.5), (-0.5, -0.5)]],
                                colors=BORDER_COLOR, radii=rr.Radius.ui_points(1.0)), static=True)
    if dense is None:
        return
    uv = np.asarray(dense.uv_px)
    C, F, M = len(dense.cameras), len(dense.frames), len(dense.markers)
    if uv.shape != (C, F, M, 2):
        raise ValueError(f"dense.uv_px must have shape {(C, F, M, 2)}, got {uv.shape}")
    col = {m: i for i, m in enumerate(markers)}
    ids_all = np.array([col[m] for m in dense.markers], dtype=np.uint16)
    times = _time_columns(dense.frames, session.fps)
    for c, name in enumerate(dense.cameras):
        path = _path("world", "cameras", name, "image", "detections")
        seen = np.isfinite(uv[c]).all(axis=-1)  # (F, M)
        rec.log(path, rr.Points2D.from_fields(colors=DETECTION_COLOR, radii=rr.Radius.ui_points(3.0),
                                              show_labels=False), static=True)
        rec.send_columns(path, indexes=times, columns=rr.Points2D.columns(
            positions=uv[c][seen].astype(np.float32),
            class_ids=np.broadcast_to(ids_all, seen.shape)[seen]).partition(seen.sum(axis=1)))


def _send_method_frames(rec, method: str, frames: np.ndarray, fps: float, xyz: np.ndarray, cov: np.ndarray,
                        edges: np.ndarray, windows: np.ndarray | None, named: list[int] | None = None) -> None:
    """Log one method's 3D entities on the given frames.

    xyz (F, M, 3) [m]; cov (F, M, 3, 3) [m^2] (NaN: no ellipsoid); edges (E, 2) marker indices;
    windows (F, M, n, 3) trail windows or None (no trails); named: the markers (indices) whose names are shown
    (one method only, so that names are not drawn once per method on top of each other).
    """
    rr = _rr()
    color = method_color(method)
    times = _time_columns(frames, fps)
    line = rr.Radius.ui_points(1.0)
    _send_points(rec, _path("world", method), times, xyz, cov, color)
    if named:
        path = _path("world", method, "names")
        ok = np.zeros(xyz.shape[:2], bool)
        ok[:, named] = np.isfinite(xyz[:, named]).all(axis=-1)
        rec.log(path, rr.Points3D.from_fields(colors=color, radii=rr.Radius.ui_points(1.0), show_labels=True),
                static=True)
        rec.send_columns(path, indexes=times, columns=rr.Points3D.columns(
            positions=xyz[ok], class_ids=_class_ids(ok)).partition(ok.sum(axis=1)))

    if len(edges):
        path = _path("world", method, "skeleton")
        seg = xyz[:, edges]  # (F, E, 2, 3)
        oks = np.isfinite(seg).all(axis=(-2, -1))
        rec.log(path, rr.LineStrips3D.from_fields(colors=color, radii=line), static=True)
        rec.send_columns(path, indexes=times, columns=[_strips_column(rr.LineStrips3D, seg[oks], oks.sum(axis=1))])

    if windows is not None:
        path = _path("world", method, "trails")
        strips, keep = _window_strips(windows)
        rec.log(path, rr.LineStrips3D.from_fields(colors=(*color, 128), radii=line), static=True)
        rec.send_columns(path, indexes=times, columns=[_strips_column(rr.LineStrips3D, strips, keep.sum(axis=1))])


def _send_points(rec, base: str, times: list, xyz: np.ndarray, cov: np.ndarray, color) -> None:
    """``base``/markers (Points3D, names on hover) and ``base``/ellipsoids (95 %) of xyz (F, M, 3) [m] and cov
    (F, M, 3, 3) [m^2] on every frame of ``times``; NaN draws nothing."""
    rr = _rr()
    path = f"{base}/markers"
    ok = np.isfinite(xyz).all(axis=-1)  # (F, M)
    rec.log(path, rr.Points3D.from_fields(colors=color, radii=rr.Radius.ui_points(4.0), show_labels=False),
            static=True)
    rec.send_columns(path, indexes=times, columns=rr.Points3D.columns(
        positions=xyz[ok], class_ids=_class_ids(ok)).partition(ok.sum(axis=1)))

    path = f"{base}/ellipsoids"
    okc = ok & np.isfinite(cov).all(axis=(-2, -1))
    half, quat = ellipsoid_axes(cov[okc])
    rec.log(path, rr.Ellipsoids3D.from_fields(colors=(*color[:3], 160), line_radii=rr.Radius.ui_points(0.5),
                                              show_labels=False), static=True)
    rec.send_columns(path, indexes=times, columns=rr.Ellipsoids3D.columns(
        centers=xyz[okc], half_sizes=half, quaternions=quat, class_ids=_class_ids(okc)).partition(okc.sum(axis=1)))


def named_markers(xyz: np.ndarray, n: int = NAMED_MARKERS) -> list[int]:
    """Up to ``n`` markers far apart (indices): the first estimated one, then each time the marker farthest from
    those chosen (xyz (M, 3) [m], one frame; NaN: not estimated), so that their names do not overlap."""
    ok = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    if not len(ok):
        return []
    chosen = [int(ok[0])]
    while len(chosen) < min(n, len(ok)):
        d = np.min(np.linalg.norm(xyz[ok][:, None] - xyz[chosen][None], axis=-1), axis=1)
        chosen.append(int(ok[np.argmax(d)]))
    return chosen


def _strips_column(archetype, strips: np.ndarray, lengths: np.ndarray):
    """Equal-length line strips as a Rerun column, built in Arrow directly.

    archetype: ``rr.LineStrips2D`` or ``rr.LineStrips3D``; strips: (S, L, D) with D = 2 or 3;
    lengths: strips per row (frame), shape (F,), summing to S. (Rerun's own numpy path loops in
    Python over the strips: 0.4 s per million points.)
    """
    import pyarrow as pa

    rr = _rr()
    S, L, D = strips.shape
    batch = rr.components.LineStrip3DBatch if D == 3 else rr.components.LineStrip2DBatch
    points = pa.FixedSizeListArray.from_arrays(pa.array(np.ascontiguousarray(strips, np.float32).ravel()),
                                               type=batch._ARROW_DATATYPE.value_type)
    arr = pa.ListArray.from_arrays(pa.array(np.arange(S + 1, dtype=np.int32) * L), points,
                                   type=batch._ARROW_DATATYPE)
    return rr.ComponentColumn(archetype.descriptor_strips(), batch(arr), lengths=lengths)


def _edges(session, markers: list[str]) -> np.ndarray:
    """Skeleton edges of session.toml as marker indices, shape (E, 2); edges naming unknown markers are skipped."""
    idx = {m: i for i, m in enumerate(markers)}
    e = [(idx[a], idx[b]) for a, b in session.skeleton if a in idx and b in idx]
    return np.array(e, dtype=np.int64).reshape(-1, 2)


def _codes(values, categories: list[str]) -> np.ndarray:
    """Index of each label in ``categories`` (all present), shape (n,).

    In Arrow: pandas' own routes convert Arrow-backed strings to Python objects first (2 s for 6M rows).
    """
    import pyarrow as pa
    import pyarrow.compute as pc

    arr = pc.cast(pa.array(values), pa.string())
    return pc.index_in(arr, value_set=pa.array(categories, pa.string())).fill_null(-1).to_numpy().astype(np.int64)


def _flags(col: pd.Series) -> np.ndarray:
    """A boolean column that may have been read from CSV as text ("True"/"False") or have gaps -> bool (n,)."""
    if pd.api.types.is_bool_dtype(col) or pd.api.types.is_numeric_dtype(col):
        return col.fillna(0).to_numpy(dtype=float) != 0
    return col.astype(str).str.strip().str.lower().isin(["true", "1", "yes"]).to_numpy()


def _send_reprojection(rec, method: str, camera: str, frames: np.ndarray, fps: float, frame_idx: np.ndarray,
                       class_ids: np.ndarray, uv: np.ndarray, uv_hat: np.ndarray, outlier: np.ndarray) -> None:
    """One (method, camera) slice of the reprojection table -> predicted points and residual lines per frame.

    frames (F,) the recording's frames; frame_idx (n,) row -> index into frames, non-decreasing;
    class_ids (n,) marker ids; uv, uv_hat (n, 2) observed and predicted raw pixels; outlier (n,) bool.
    """
    rr = _rr()
    times = _time_columns(frames, fps)
    color = np.array(method_color(method), dtype=np.uint8)

    path = _path("world", "cameras", camera, "image", "reproj", method)
    ok = np.isfinite(uv_hat).all(axis=1)
    colors = np.where(outlier[ok, None], np.array(OUTLIER_COLOR, np.uint8), color)
    rec.log(path, rr.Points2D.from_fields(radii=rr.Radius.ui_points(2.5), show_labels=False), static=True)
    rec.send_columns(path, indexes=times, columns=rr.Points2D.columns(
        positions=uv_hat[ok].astype(np.float32), class_ids=class_ids[ok].astype(np.uint16), colors=colors,
    ).partition(np.bincount(frame_idx[ok], minlength=len(frames))))

    path = _path("world", "cameras", camera, "image", "reproj", method, "residuals")
    okr = ok & np.isfinite(uv).all(axis=1)
    rec.log(path, rr.LineStrips2D.from_fields(colors=color, radii=rr.Radius.ui_points(1.0)), static=True)
    rec.send_columns(path, indexes=times, columns=[_strips_column(
        rr.LineStrips2D, np.stack([uv[okr], uv_hat[okr]], axis=1), np.bincount(frame_idx[okr], minlength=len(frames)))])


def _inside_span(table: pd.DataFrame, frames: np.ndarray, markers: list[str]) -> np.ndarray:
    """(F, M) bool: one method's (frame, marker) cells inside the marker's span (the table's ``span`` column,
    computed from n_views where absent; everything inside without either)."""
    if "span" not in table:
        if "n_views" not in table:
            return np.ones((len(frames), len(markers)), bool)
        table = add_span(table)
    inside = np.zeros((len(frames), len(markers)), bool)
    fi = np.searchsorted(frames, table["frame"].to_numpy(np.int64))
    mi = _codes(table["marker"], markers)
    ok = (mi >= 0) & (fi < len(frames))
    inside[fi[ok], mi[ok]] = (table["span"].to_numpy() == "inside")[ok]
    return inside


@dataclass(frozen=True)
class Focus:
    """Where a recording opens: ``frame`` (batgraph.evaluate.opening_frame) and, in the rig's world [m], the
    ``centre`` of the animal's estimated markers there and ``radius``, their largest distance from it (with
    fewer than 3 markers, of the box their paths fill)."""

    frame: int
    centre: np.ndarray
    radius: float


def focus(session, trajectories: pd.DataFrame) -> Focus | None:
    """The :class:`Focus` of the shown method's rows of ``trajectories`` (frame, marker, x, y, z, n_views,
    span), or None when nothing is estimated inside a span."""
    shown = shown_method(pd.unique(trajectories["method"].astype(str))) if len(trajectories) else None
    if shown is None or "n_views" not in trajectories:
        return None
    t = trajectories[trajectories["method"].astype(str) == shown]
    if "span" in t:
        t = t[t["span"] == "inside"]
    seen = (t["n_views"] >= 2).groupby(t["frame"].to_numpy()).sum()
    frame = opening_frame(seen.to_numpy(), seen.index.to_numpy())
    every = t[["x", "y", "z"]].to_numpy(float)
    every = every[np.isfinite(every).all(axis=1)]
    xyz = t.loc[t["frame"] == frame, ["x", "y", "z"]].to_numpy(float)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if frame is None or not len(xyz):
        return None
    if len(xyz) < 3:  # a point or two make no shape: show where they go (1st-99th percentile of their path)
        xyz = np.percentile(every, [1, 99], axis=0)
    xyz = session.rig.to_user(xyz)  # the user's frame -> the rig's world (the mirror is its own inverse)
    centre = xyz.mean(axis=0)
    return Focus(int(frame), centre, float(np.linalg.norm(xyz - centre, axis=1).max()))


def _eye(session, f: Focus):
    """The 3D view's eye on the animal of ``f``: from the side its cameras see it from (the mean of the directions
    to them), at a distance where its markers fill about half the view."""
    import rerun.blueprint as rrb

    to_cams = np.array([cam.center_world for cam in session.rig]) - f.centre
    to_cams /= np.maximum(np.linalg.norm(to_cams, axis=1, keepdims=True), 1e-12)
    way = to_cams.mean(axis=0)
    way = way / np.linalg.norm(way) if np.linalg.norm(way) > 0.3 else to_cams[0]
    return rrb.EyeControls3D(position=f.centre + max(2.5 * f.radius, 0.3) * way, look_target=f.centre)


def log_results(rec, session, trajectories: pd.DataFrame, reprojection: pd.DataFrame | None = None,
                *, trail_frames: int = 10) -> None:
    """Log every method's 3D markers, 95 % ellipsoids, skeleton, trails and 2D reprojections.

    trajectories, reprojection: the result's tables (reprojection may be None).
    trail_frames: positions per trail (the current frame and the ``trail_frames - 1`` before it);
        0 or 1 logs no trails.
    Positions are metres in the world frame; frames are those of the two tables together.
    """
    rr = _rr()
    markers = _marker_list(session, trajectories["marker"], None if reprojection is None else reprojection["marker"])
    # re-logged because the tables may name markers the session does not (same prefix, same ids)
    rec.log("world", rr.AnnotationContext([(i, m) for i, m in enumerate(markers)]), static=True)
    frame_sets = [t["frame"].to_numpy(np.int64) for t in (trajectories, reprojection) if t is not None and len(t)]
    if not frame_sets:
        return
    frames = np.unique(np.concatenate(frame_sets))
    edges = _edges(session, markers)
    shown = shown_method(pd.unique(trajectories["method"].astype(str)))
    opening = focus(session, trajectories)
    times = _time_columns(frames, session.fps)
    for method, table in trajectories.groupby("method", sort=False):
        # the table is in the user's frame; the cameras are logged in the rig's (right-handed) world
        xyz, cov = session.rig.to_user(*_dense_results(table, frames, markers))
        inside = _inside_span(table, frames, markers)
        ends_xyz, ends_cov = np.where(inside[..., None], np.nan, xyz), np.where(inside[..., None, None], np.nan, cov)
        xyz, cov = np.where(inside[..., None], xyz, np.nan), np.where(inside[..., None, None], cov, np.nan)
        windows = _trail_windows(xyz, trail_frames) if trail_frames > 1 else None
        named = None
        if str(method) == shown and opening is not None:
            named = named_markers(xyz[int(np.searchsorted(frames, opening.frame)) % len(frames)])
        _send_method_frames(rec, str(method), frames, session.fps, xyz, cov, edges, windows, named)
        _send_points(rec, _path("world", str(method), "track_ends"), times, ends_xyz, ends_cov, TRACK_END_COLOR)
    if reprojection is None or not len(reprojection):
        return
    rp = reprojection
    methods = list(pd.unique(rp["method"].astype(str)))
    cameras = list(pd.unique(rp["camera"].astype(str)))
    mc = _codes(rp["method"], methods) * len(cameras) + _codes(rp["camera"], cameras)
    fi = np.searchsorted(frames, rp["frame"].to_numpy(np.int64))
    order = np.lexsort((fi, mc))  # by (method, camera), then frame: each slice is one entity's rows in time order
    ids = _codes(rp["marker"], markers)
    uv, uv_hat = rp[["u", "v"]].to_numpy(float), rp[["u_hat", "v_hat"]].to_numpy(float)
    outlier = _flags(rp["outlier"]) if "outlier" in rp else np.zeros(len(rp), bool)
    for sl in np.split(order, np.flatnonzero(np.diff(mc[order])) + 1):
        k = mc[sl[0]]
        _send_reprojection(rec, methods[k // len(cameras)], cameras[k % len(cameras)], frames, session.fps,
                           fi[sl], ids[sl], uv[sl], uv_hat[sl], outlier[sl])


def default_blueprint(session, methods=(), *, live: bool = False, focus: Focus | None = None,
                      camera: str | None = None):
    """How a recording opens: the 3D world on the left, one tab per camera image on the right.

    methods: the methods in the recording. Only :func:`shown_method` (the smoother when it ran) is
    visible, its track ends hidden; the others are in the recording, hidden (tick them in the blueprint
    panel), in 3D and in the camera views, where each camera shows its detections and the shown method's
    reprojections. focus: the 3D view's eye is aimed at the animal on the opening frame (:func:`focus`);
    camera: the camera tab shown first (e.g. the one that sees the most there). The time panel is on the
    ``frame`` timeline at the session's frame rate, paused; live: following the newest frame instead.
    """
    import rerun.blueprint as rrb

    shown = shown_method(methods)
    hidden = [str(m) for m in methods if str(m) != shown]
    world = {_path("world", m): rrb.EntityBehavior(visible=False) for m in hidden}
    if shown is not None:
        world[_path("world", shown, "track_ends")] = rrb.EntityBehavior(visible=False)
    cams = [rrb.Spatial2DView(
        origin=_path("world", "cameras", c.name, "image"), name=c.name,
        overrides={_path("world", "cameras", c.name, "image", "reproj", m): rrb.EntityBehavior(visible=False)
                   for m in hidden}) for c in session.rig]
    time_panel = rrb.TimePanel(timeline="frame", fps=float(session.fps), state="expanded",
                               play_state="following" if live else "paused")
    view = rrb.Spatial3DView(origin="world", name="3D", overrides=world,
                             **({"eye_controls": _eye(session, focus)} if focus is not None else {}))
    tabs = rrb.Tabs(*cams, active_tab=session.rig.names.index(camera) if camera in session.rig.names else None)
    return rrb.Blueprint(rrb.Horizontal(view, tabs, column_shares=[2, 1]), time_panel, collapse_panels=False)


def write_recording(path: str | os.PathLike, session, dense, trajectories: pd.DataFrame,
                    reprojection: pd.DataFrame | None = None, *, trail_frames: int = 10) -> Path:
    """Write the whole result as a Rerun recording (atomically); returns the path.

    path: the .rrd file (``OUT_DIR/recording.rrd`` by convention).
    session, dense: see :func:`log_session`; trajectories, reprojection, trail_frames: see
    :func:`log_results`.
    """
    rr = _rr()
    path = Path(path)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
    methods = list(pd.unique(trajectories["method"].astype(str))) if len(trajectories) else []
    opening = focus(session, trajectories)
    camera = None
    if opening is not None and dense is not None and opening.frame in dense.frames:
        seen = dense.seen[:, int(np.searchsorted(dense.frames, opening.frame))].sum(axis=1)  # (C,)
        camera = dense.cameras[int(np.argmax(seen))]
    with atomic_path(path) as tmp:
        rec.save(tmp, default_blueprint=default_blueprint(session, methods, focus=opening, camera=camera))
        try:
            rec.send_recording_name(session.name)
            if opening is not None:  # shown in the viewer's recording properties; `batgraph view` goes there
                rec.send_property("batgraph", rr.AnyValues(opening_frame=opening.frame))
            log_session(rec, session, dense)
            log_results(rec, session, trajectories, reprojection, trail_frames=trail_frames)
            rec.flush()
        finally:
            rec.disconnect()  # closes the file (and writes its footer) before the rename
    return path


# ----------------------------------------------------------------------------------------------
# live viewer and opening a file
# ----------------------------------------------------------------------------------------------
class LiveViewer:
    """Stream one method's estimate, frame by frame, to a Rerun viewer while a filter runs.

    session, dense: as for :func:`log_session` (cameras and all 2D detections are logged at once).
    method: entity name of the streamed estimate (``world/{method}/...``).
    mode: ``"spawn"`` (start a viewer window; needs a display), ``"connect"`` (to a running viewer
        at ``url``, default ``rerun+http://127.0.0.1:9876/proxy``) or ``"save"`` (to the .rrd file
        ``path``, e.g. to watch with ``rerun path`` while it grows).
    Raises :class:`ViewerUnavailable` when a viewer cannot be spawned.
    """

    def __init__(self, session, dense=None, *, method: str = "filter", mode: str = "spawn",
                 url: str | None = None, path: str | os.PathLike | None = None, port: int = 9876,
                 trail_frames: int = 10):
        rr = _rr()
        if mode not in ("spawn", "connect", "save"):
            raise ValueError(f"mode must be spawn, connect or save, got {mode!r}")
        self.session, self.method, self.trail_frames = session, method, int(trail_frames)
        self.markers = list(dense.markers) if dense is not None else _marker_list(session)
        markers = _marker_list(session, self.markers)
        index = {m: i for i, m in enumerate(markers)}
        # LiveViewer's xyz follows self.markers; class ids follow the annotation context's order
        self._order = np.array([index[m] for m in self.markers])
        self._n_class = len(markers)
        self._edges = _edges(session, markers)
        self._history = np.full((max(self.trail_frames, 1), self._n_class, 3), np.nan)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
        blueprint = default_blueprint(session, [method], live=True)
        if mode == "spawn":
            _require_display("spawn the Rerun viewer")
            try:
                rr.spawn(port=port, recording=self.rec, executable_path=_rerun_executable(),
                         default_blueprint=blueprint)
            except ViewerUnavailable:
                raise
            except Exception as e:  # e.g. the binary fails to start
                raise ViewerUnavailable(f"cannot spawn the Rerun viewer: {str(e).splitlines()[0]}") from None
            if not _port_open(port):  # rr.spawn only warns when the viewer dies (e.g. a broken DISPLAY)
                self.rec.disconnect()
                raise ViewerUnavailable(f"the Rerun viewer did not start (nothing listens on port {port}); "
                                        "is the display working? Use --viewer save instead")
        elif mode == "connect":
            self.rec.connect_grpc(url, default_blueprint=blueprint)
        else:
            if path is None:
                raise ValueError("mode='save' needs a path")
            self.rec.save(path, default_blueprint=blueprint)
        self.rec.send_recording_name(session.name)
        log_session(self.rec, session, dense)

    def update(self, frame_index: int, xyz: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Log the estimate of one frame.

        frame_index: the frame number (as in observations.csv).
        xyz: positions of ``self.markers``, shape (M, 3) [m, world]; NaN rows are not drawn.
        cov: their covariances, shape (M, 3, 3) [m^2], or None (no ellipsoids).
        """
        M = len(self.markers)
        xyz = np.asarray(xyz, dtype=float)
        if xyz.shape != (M, 3):
            raise ValueError(f"xyz must have shape {(M, 3)}, got {xyz.shape}")
        full = np.full((1, self._n_class, 3), np.nan)
        full[0, self._order] = xyz
        full_cov = np.full((1, self._n_class, 3, 3), np.nan)
        if cov is not None:
            cov = np.asarray(cov, dtype=float)
            if cov.shape != (M, 3, 3):
                raise ValueError(f"cov must have shape {(M, 3, 3)}, got {cov.shape}")
            full_cov[0, self._order] = cov
        self._history = np.concatenate([self._history[1:], full])
        windows = self._history.transpose(1, 0, 2)[None] if self.trail_frames > 1 else None
        _send_method_frames(self.rec, self.method, np.array([frame_index]), self.session.fps, full, full_cov,
                            self._edges, windows)

    def close(self) -> None:
        """Flush what is buffered and close the connection or file.

        A viewer window closed by the user is not an error of the reconstruction: it only warns.
        """
        try:
            self.rec.flush()
        except RuntimeError as e:
            warnings.warn(f"Rerun viewer: {str(e).splitlines()[0]}", stacklevel=2)
        finally:
            self.rec.disconnect()

    def __enter__(self) -> LiveViewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_recording(path: str | os.PathLike, *, wait: bool = True) -> subprocess.Popen | int:
    """Open a saved recording in the Rerun viewer (``batgraph view OUT_DIR``).

    path: an output folder (its ``recording.rrd`` is opened) or an .rrd file.
    wait: block until the viewer window is closed and return its exit code; False returns the
        running process. While waiting, SIGINT and SIGTERM are passed on to the viewer, which is then
        given 5 s to exit and killed after that: it never outlives this process. A signal ends the wait
        as it would have ended this process: KeyboardInterrupt for SIGINT, SystemExit(128 + 15) for SIGTERM.
    Raises :class:`InputError` if there is no recording, :class:`ViewerUnavailable` without a display.
    """
    path = Path(path)
    rrd = path / RECORDING_NAME if path.is_dir() else path
    if not rrd.is_file():
        where = f"{path}: no {RECORDING_NAME} (run batgraph reconstruct with --viewer save)" if path.is_dir() else \
            f"{path}: file not found"
        raise InputError(where)
    _require_display(f"open {rrd}", hint=f"show it in a browser with Rerun's web viewer: rerun --web-viewer {rrd} "
                                         "(over ssh, forward ports 9090 and 9876), or open it on a machine with a "
                                         "screen")
    port = _free_port()
    cmd = [_rerun_executable(), "--port", str(port), str(rrd)]
    env = {**os.environ, "RERUN_APP_ONLY": "true"}
    frame = _opening_frame_beside(rrd)
    if not wait:
        return subprocess.Popen(cmd, env=env)
    return run_child(cmd, env=env, on_start=None if frame is None else lambda: move_cursor(port, frame))


def _free_port() -> int:
    """A TCP port free on this machine now (for the viewer's server, which :func:`move_cursor` talks to)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _opening_frame_beside(rrd: Path) -> int | None:
    """The opening frame of the result folder holding ``rrd`` (its summary.json), or None."""
    try:
        frame = json.loads((rrd.parent / "summary.json").read_text(encoding="utf-8")).get("opening_frame")
    except (OSError, ValueError, AttributeError):
        return None
    return frame if isinstance(frame, int) else None


def move_cursor(port: int, frame: int, timeout_s: float = 30.0) -> bool:
    """Move the time cursor of the viewer listening on ``port`` to ``frame`` (paused) once it shows a recording;
    False when that cannot be done within ``timeout_s`` (a viewer without the control API, or gone)."""
    try:
        from rerun.experimental import ViewerClient
    except ImportError:  # an older rerun: the recording opens on its first frame
        return False
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            client = ViewerClient.connect(f"rerun+http://127.0.0.1:{port}/proxy")
            if client.get_state().recordings:
                client.set_time("frame", sequence=int(frame), play_state="paused")
                return True
        except Exception:  # noqa: BLE001 - the viewer is still starting or loading: ask again
            pass
        time.sleep(0.25)
    return False


def run_child(cmd: list[str], env: dict | None = None, grace_s: float = 5.0, on_start=None) -> int:
    """Run ``cmd`` to completion, passing SIGINT/SIGTERM on to it; it is always reaped, never orphaned.

    The child gets its own process group, so a Ctrl-C in the terminal reaches it once, through this
    process. On a signal the child has ``grace_s`` to exit, then it is killed; then the signal takes
    effect here (KeyboardInterrupt for SIGINT, SystemExit(128 + signum) otherwise). Returns the
    child's exit code when it ends by itself. (Signal handlers can only be set from the main thread;
    elsewhere the child is still killed when the wait is interrupted.) on_start: called once the child runs,
    in a thread of its own (e.g. :func:`move_cursor`).
    """
    import signal
    import threading

    received: list[int] = []
    proc: subprocess.Popen | None = None

    def forward(signum, _frame):
        received.append(signum)
        try:
            if proc is not None:
                proc.send_signal(signum)
        except (ProcessLookupError, OSError):
            pass

    sigs = [signal.SIGINT, signal.SIGTERM]
    previous = {}
    if threading.current_thread() is threading.main_thread():  # before the child starts: no signal goes unseen
        previous = {sig: signal.signal(sig, forward) for sig in sigs}
    try:
        proc = subprocess.Popen(cmd, env=env, start_new_session=True)
        if received:  # a signal while it was starting
            proc.send_signal(received[0])
        if on_start is not None:
            threading.Thread(target=on_start, name="batgraph viewer control", daemon=True).start()
        deadline = None
        while True:
            try:
                rc = proc.wait(timeout=0.2)
                break
            except subprocess.TimeoutExpired:
                if received and deadline is None:
                    deadline = time.monotonic() + grace_s
                if deadline is not None and time.monotonic() > deadline:
                    proc.kill()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if proc is not None and proc.poll() is None:  # an exception (e.g. from another thread's interrupt)
            proc.kill()
            proc.wait()
    if received:
        if received[0] == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + received[0])
    return rc
