"""Synthetic sessions with ground truth: a bat flapping through a camera-lined tunnel, and a bat ear.

The scenes follow the paper (docs/method.md): a 0.5 m bat flapping at 4 Hz through 90 degrees while
flying at 3 m/s along -x, filmed at 120 fps by GoPro-like cameras on the wall of a cylindrical
tunnel; and a head with a bending 5 cm ear filmed by two low-distortion cameras at 250 fps.
Occlusion is physical: a marker is hidden from a camera exactly when the segment from the camera
centre to the marker crosses a wing-membrane triangle or a body ellipsoid (vectorised
Moller-Trumbore and ray-quadric tests). Noise, mislabelled observations and a calibration error
are added on request. All randomness comes from the ``np.random.Generator`` passed in.

World frame: x along the tunnel axis (the bat flies toward -x), z up, metres. This module only
renders scenes; it does not estimate anything and does not write files (see
:func:`batgraph.session.write_session`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from .camera import Camera, Rig
from .geometry import pose
from .session import MotionConfig, Session, exposure_frames, nearest_frame, to_session_clock

# ----- the paper's flight numbers (its motion model, docs/method.md) --------------------------------
FLIGHT_SPEED_MPS = 3.0
SPAN_M = 0.5
FLAP_HZ = 4.0
FLAP_ANGLE_DEG = 90.0  # peak to peak: the shoulder elevation swings +-45 deg
TUNNEL_RADIUS_M = 1.0
FLIGHT_IMAGE_WH = (1280, 720)
GOPRO_F_PX = 640.0
GOPRO_DIST = np.array([-0.25, 0.07, 0.0005, -0.0003, -0.008])  # strong barrel distortion

# ----- the paper's ear numbers -----------------------------------------------------------------
EAR_LENGTH_M = 0.05
EAR_HZ = 10.0
EAR_BEND_DEG = 90.0
EAR_IMAGE_WH = (1280, 720)
EAR_F_PX = 1500.0
EAR_DIST = np.array([-0.03, 0.01, 0.0, 0.0, 0.0])  # "minimal lens distortion"
EAR_N_POINTS = 6

MAX_FLIGHT_MARKERS = 180
HIT_EPS = 1e-6  # a blocker must cut the segment before t = 1 - HIT_EPS (t = 1 is the marker itself)

# ----- bat geometry, body frame (forward, right, up) [m]; the left side mirrors "right" ------------
_SHOULDER = (0.015, 0.022, 0.006)
_HIP = (-0.05, 0.016, -0.004)
_TAIL = (-0.10, 0.0, -0.010)
_BODY_MARKERS = {"body1": (0.010, 0.0, 0.0190), "body2": (-0.030, 0.0, 0.0168)}  # on the back
_BODY_CENTER = (-0.01, 0.0, 0.0)
_BODY_SEMI_AXES = np.array([0.05, 0.019, 0.017])
_HEAD_CENTER = (0.058, 0.0, 0.004)
_HEAD_SEMI_AXES = np.array([0.02, 0.015, 0.014])
_HUMERUS_M, _FOREARM_M = 0.055, 0.085
_DIGIT_M = {"digit3": 0.095, "digit4": 0.085, "digit5": 0.075}
_WING_JOINTS = ["shoulder", "elbow", "wrist", "digit3", "digit4", "digit5"]
# membrane triangles of one wing, by vertex name (hip is a vertex, not a marker)
_WING_TRIANGLES = [
    ("hip", "shoulder", "elbow"), ("hip", "elbow", "wrist"), ("hip", "wrist", "digit5"),  # plagiopatagium
    ("wrist", "digit3", "digit4"), ("wrist", "digit4", "digit5"),  # dactylopatagium
]


@dataclass
class Ellipsoid:
    """A solid ellipsoid moving with the scene.

    center_m: shape (F, 3) [m, world].
    axes: shape (F, 3, 3); column i is the unit direction (world) of semi-axis i.
    semi_axes_m: shape (3,) [m].
    """

    center_m: np.ndarray
    axes: np.ndarray
    semi_axes_m: np.ndarray


@dataclass
class Scene:
    """The ground-truth geometry of a simulated scene at every frame.

    marker_names: labels of the M markers.
    points_m: marker positions, shape (F, M, 3) [m, world].
    triangles_m: opaque membrane triangles, shape (F, T, 3, 3) [m, world] (T may be 0).
    ellipsoids: opaque solids (body, head).
    phase_rad: wingbeat (or ear) phase at each frame, shape (F,) [rad]; for the flight the
        shoulder elevation is ``45 deg * cos(phase)``, so ``sin(phase) > 0`` is the downstroke.
    """

    marker_names: list[str]
    points_m: np.ndarray
    triangles_m: np.ndarray
    ellipsoids: list[Ellipsoid]
    phase_rad: np.ndarray


def is_upstroke(phase_rad: np.ndarray) -> np.ndarray:
    """True where the wing (shoulder elevation ``cos(phase)``) is rising, shape of ``phase_rad``."""
    return np.sin(phase_rad) < 0


# ==================================================================================================
# occlusion
# ==================================================================================================
def segments_hit_triangles(origins_m: np.ndarray, points_m: np.ndarray, triangles_m: np.ndarray) -> np.ndarray:
    """Which segments origin -> point cross a triangle strictly before reaching the point.

    origins_m: segment starts (camera centres), shape (C, 3) [m].
    points_m: segment ends (markers), shape (M, 3) [m].
    triangles_m: shape (T, 3, 3) [m], vertex-major.
    Returns bool (C, M). Moller-Trumbore on the unnormalised direction, so the hit parameter t is
    a fraction of the segment; only 0 < t < 1 - HIT_EPS counts, which is why a triangle having
    the marker as a vertex or on its surface never hides it. Edge-on triangles (the segment in
    their plane) do not hide anything.
    """
    if len(triangles_m) == 0:
        return np.zeros((len(origins_m), len(points_m)), dtype=bool)
    O = origins_m[:, None, None, :]  # (C, 1, 1, 3)
    D = points_m[None, :, None, :] - O  # (C, M, 1, 3)
    v0 = triangles_m[None, None, :, 0]  # (1, 1, T, 3)
    e1 = triangles_m[None, None, :, 1] - v0
    e2 = triangles_m[None, None, :, 2] - v0
    p = np.cross(D, e2)  # (C, M, T, 3)
    det = np.einsum("...i,...i->...", e1, p)
    scale = np.linalg.norm(D, axis=-1) * np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1)
    ok = np.abs(det) > 1e-12 * scale
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = O - v0  # (C, 1, T, 3)
    u = np.einsum("...i,...i->...", s, p) * inv
    q = np.cross(s, e1)  # (C, 1, T, 3)
    v = np.einsum("...i,...i->...", D, q) * inv
    t = np.einsum("...i,...i->...", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > HIT_EPS) & (t < 1 - HIT_EPS)
    return hit.any(axis=-1)


def segments_hit_ellipsoid(
    origins_m: np.ndarray, points_m: np.ndarray, center_m: np.ndarray, axes: np.ndarray, semi_axes_m: np.ndarray
) -> np.ndarray:
    """Which segments origin (C, 3) -> point (M, 3) enter a solid ellipsoid before the point; bool (C, M).

    center_m (3,), axes (3, 3) (columns = semi-axis directions), semi_axes_m (3,): see
    :class:`Ellipsoid`. In the ellipsoid's unit-sphere coordinates the segment ``o + t d`` meets the
    surface where ``|o + t d|^2 = 1``; the segment is blocked when the first root lies in
    (0, 1 - HIT_EPS).
    """
    o = ((origins_m - center_m) @ axes) / semi_axes_m  # (C, 3)
    d = ((points_m[None] - origins_m[:, None]) @ axes) / semi_axes_m  # (C, M, 3)
    a = np.einsum("cmi,cmi->cm", d, d)
    b = np.einsum("ci,cmi->cm", o, d)
    c = np.einsum("ci,ci->c", o, o)[:, None] - 1.0
    disc = b * b - a * c
    t1 = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return (disc > 0) & (t1 > HIT_EPS) & (t1 < 1 - HIT_EPS)


def visibility(
    cam_centers_m: np.ndarray,
    points_m: np.ndarray,
    triangles_m: np.ndarray,
    ellipsoids: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = (),
) -> np.ndarray:
    """Clear line of sight from each camera centre to each point, bool (C, M).

    cam_centers_m: (C, 3) [m]; points_m: (M, 3) [m]; triangles_m: (T, 3, 3) [m];
    ellipsoids: (center (3,), axes (3, 3), semi_axes (3,)) per solid, at this frame.
    Only occlusion: the image border and the lens's field are the camera's business.
    """
    hidden = segments_hit_triangles(cam_centers_m, points_m, triangles_m)
    for center, axes, semi in ellipsoids:
        hidden |= segments_hit_ellipsoid(cam_centers_m, points_m, center, axes, semi)
    return ~hidden


def scene_visibility(scene: Scene, rig: Rig) -> np.ndarray:
    """Line of sight for every camera, frame and marker of a scene, bool (C, F, M)."""
    centers = np.stack([c.center_world for c in rig])
    F, M = scene.points_m.shape[:2]
    out = np.empty((len(rig), F, M), dtype=bool)
    for f in range(F):  # vectorised over (cameras, markers, blockers) inside one frame
        solids = [(e.center_m[f], e.axes[f], e.semi_axes_m) for e in scene.ellipsoids]
        out[:, f] = visibility(centers, scene.points_m[f], scene.triangles_m[f], solids)
    return out


# ==================================================================================================
# cameras
# ==================================================================================================
def look_at(center_m: np.ndarray, target_m: np.ndarray, right_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (rvec (3,), tvec (3,)) of a camera at ``center_m`` looking at ``target_m``
    (:func:`batgraph.geometry.pose.look_at`: world-up at the top of the image)."""
    R, t = pose.look_at(center_m, target_m, right_hint)
    return pose.rvec_from_R(R), t


def tunnel_rig(rng: np.random.Generator, n_cameras: int) -> Rig:
    """GoPro-like cameras on the wall of the flight tunnel, aimed at its axis.

    Cameras are spread evenly along x (over +-1.5 m, the middle of the ~4 m capture length) and
    around the wall by the golden angle starting at the top, so any consecutive few see the bat
    from well separated directions; image width runs along the flight path. Intrinsics and
    distortion vary slightly per camera (drawn from ``rng``).
    """
    n = int(n_cameras)
    xs = np.linspace(-1.5, 1.5, n) if n > 1 else np.zeros(1)
    angles = np.radians(90.0 + 137.50776 * np.arange(n))
    w, h = FLIGHT_IMAGE_WH
    cams = []
    for i in range(n):
        # lens slightly inside the wall; aimed at the axis a little toward the tunnel's middle so the
        # end cameras also cover the path beyond them
        r = 0.95 * TUNNEL_RADIUS_M
        center = np.array([xs[i], r * np.cos(angles[i]), r * np.sin(angles[i])])
        target = np.array([0.85 * xs[i], 0.0, 0.0])
        rvec, tvec = look_at(center, target, np.array([1.0, 0.0, 0.0]))
        f = GOPRO_F_PX * (1 + 0.01 * rng.standard_normal())
        K = np.array([[f, 0.0, (w - 1) / 2 + 3 * rng.standard_normal()],
                      [0.0, f * (1 + 0.002 * rng.standard_normal()), (h - 1) / 2 + 3 * rng.standard_normal()],
                      [0.0, 0.0, 1.0]])
        dist = GOPRO_DIST * (1 + 0.05 * rng.standard_normal(5))
        cams.append(Camera(f"cam{i + 1}", (w, h), K, dist, rvec, tvec))
    return Rig(cams)


def ear_rig(rng: np.random.Generator, target_m: np.ndarray) -> Rig:
    """Two low-distortion cameras 0.4 m from ``target_m`` (3,), 45 deg apart, 10 deg above, in front (+x)."""
    w, h = EAR_IMAGE_WH
    cams = []
    for i, az in enumerate(np.radians([-22.5, 22.5])):
        el = np.radians(10.0)
        center = target_m + 0.4 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        fwd = target_m - center
        rvec, tvec = look_at(center, target_m, np.cross(fwd, [0.0, 0.0, 1.0]))
        f = EAR_F_PX * (1 + 0.01 * rng.standard_normal())
        K = np.array([[f, 0.0, (w - 1) / 2 + 2 * rng.standard_normal()],
                      [0.0, f, (h - 1) / 2 + 2 * rng.standard_normal()], [0.0, 0.0, 1.0]])
        dist = EAR_DIST * (1 + 0.05 * rng.standard_normal(5))
        cams.append(Camera(f"cam{i + 1}", (w, h), K, dist, rvec, tvec))
    return Rig(cams)


# ==================================================================================================
# flight kinematics
# ==================================================================================================
def _segment_dir(elev_rad: np.ndarray, sweep_rad: np.ndarray) -> np.ndarray:
    """Unit vectors (F, 3) in the body frame (forward, right, up): elevation up, sweep forward."""
    c = np.cos(elev_rad)
    return np.stack([c * np.sin(sweep_rad), c * np.cos(sweep_rad), np.sin(elev_rad)], axis=-1)


def _wing_body_frame(phase_rad: np.ndarray) -> dict[str, np.ndarray]:
    """Right-wing joints and digit tips in the body frame, name -> (F, 3) [m].

    Smooth (C-infinity) in time. Distal segments lag in phase and swing further (0, 0.35, 0.7 rad
    behind the humerus); on the upstroke the wing folds (fold factor 0 mid-downstroke, 1
    mid-upstroke): the humerus swings back, the forearm forward, and the digits sweep back, which
    brings wrist and digit tips toward the body.
    """
    amp = math.radians(FLAP_ANGLE_DEG / 2)
    fold = ((1 - np.sin(phase_rad)) / 2) ** 2
    elev_h = amp * np.cos(phase_rad) + math.radians(5)
    elev_r = 1.05 * amp * np.cos(phase_rad - 0.35) + math.radians(5)
    elev_d = 1.15 * amp * np.cos(phase_rad - 0.7) + math.radians(5) - math.radians(15) * fold
    sweep = {
        "humerus": np.radians(-15 - 35 * fold), "forearm": np.radians(10 + 45 * fold),
        "digit3": np.radians(5 - 70 * fold), "digit4": np.radians(-30 - 60 * fold),
        "digit5": np.radians(-70 - 45 * fold),
    }
    F = len(phase_rad)
    j = {"shoulder": np.broadcast_to(np.asarray(_SHOULDER), (F, 3)), "hip": np.broadcast_to(np.asarray(_HIP), (F, 3))}
    j["elbow"] = j["shoulder"] + _HUMERUS_M * _segment_dir(elev_h, sweep["humerus"])
    j["wrist"] = j["elbow"] + _FOREARM_M * _segment_dir(elev_r, sweep["forearm"])
    for d, length in _DIGIT_M.items():
        j[d] = j["wrist"] + length * _segment_dir(elev_d, sweep[d])
    return j


def _membrane_barycentric(n: int, areas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fixed positions of n membrane markers on triangles of the given areas (T,).

    Returns triangle index (n,) and barycentric weights (n, 3). Triangles get markers in
    proportion to their area; positions follow the R2 low-discrepancy sequence folded into the
    triangle and shrunk 10 % toward its centroid (markers sit inside the membrane, off its
    edges). Deterministic: the marker layout is the same for every seed.
    """
    k = np.arange(n)
    cum = np.cumsum(areas) / areas.sum()
    tri = np.minimum(np.searchsorted(cum, (k + 0.5) / max(n, 1)), len(areas) - 1)
    g = 1.32471795724474602596  # plastic number: R2 sequence
    ab = np.mod(0.5 + np.outer(k + 1, [1 / g, 1 / g**2]), 1.0)
    flip = ab.sum(axis=1) > 1
    ab[flip] = 1 - ab[flip]
    bary = np.column_stack([1 - ab.sum(axis=1), ab])
    return tri, 0.9 * bary + 0.1 / 3


def flight_scene(
    n_frames: int, fps: float, n_markers: int = 14, phase0_rad: float = 0.0,
    offset_yz_m: tuple[float, float] = (0.0, 0.0), times_s: np.ndarray | None = None,
) -> Scene:
    """The flying bat: markers, membrane triangles and body/head ellipsoids at every frame.

    n_frames, fps: frame k is at time k / fps [s]; the flight path (3 m/s along -x) is centred on x = 0.
    n_markers: 14 named markers (body1, body2, shoulder/elbow/wrist/digit3-5 on each wing) plus
        n_markers - 14 membrane markers ("mem_r_001", ...) split between the wings.
    phase0_rad: wingbeat phase at frame 0; offset_yz_m: the flight line's offset from the tunnel axis [m].
    times_s: evaluate the same flight at these times [s] instead of the frames' (closed form: any instant).
    Deterministic (no randomness): :func:`simulate_flight` draws these arguments.
    """
    if not 14 <= n_markers <= MAX_FLIGHT_MARKERS:
        raise ValueError(f"n_markers must be in 14..{MAX_FLIGHT_MARKERS}, got {n_markers}")
    t = np.arange(n_frames) / fps if times_s is None else np.asarray(times_s, float)
    phase = phase0_rad + 2 * np.pi * FLAP_HZ * t
    # body: constant speed along -x, bob (up during the downstroke), slight sway and pitch oscillation
    x0 = FLIGHT_SPEED_MPS * (n_frames - 1) / fps / 2
    center = np.stack([x0 - FLIGHT_SPEED_MPS * t,
                       offset_yz_m[0] + 0.004 * np.sin(phase / 2),
                       offset_yz_m[1] - 0.008 * np.cos(phase)], axis=-1)
    pitch = np.radians(8 + 4 * np.sin(phase + 0.5))
    fwd = np.stack([-np.cos(pitch), np.zeros_like(pitch), np.sin(pitch)], axis=-1)
    up = np.stack([np.sin(pitch), np.zeros_like(pitch), np.cos(pitch)], axis=-1)
    right = np.broadcast_to([0.0, 1.0, 0.0], fwd.shape)  # flying toward -x with z up: right is +y
    B = np.stack([fwd, right, up], axis=-1)  # (F, 3, 3): body (forward, right, up) -> world

    def world(p_body):  # (F, 3) or (3,) body -> (F, 3) world
        return center + np.einsum("fij,fj->fi", B, np.broadcast_to(p_body, center.shape))

    wing = _wing_body_frame(phase)
    pts = {"body1": world(_BODY_MARKERS["body1"]), "body2": world(_BODY_MARKERS["body2"]), "tail": world(_TAIL)}
    mirror = np.array([1.0, -1.0, 1.0])
    for side, s in (("r", np.ones(3)), ("l", mirror)):
        for name, p in wing.items():
            pts[f"{name}_{side}"] = world(p * s)
    names = ["body1", "body2"] + [f"{j}_{s}" for s in "rl" for j in _WING_JOINTS]
    tri_names = [tuple(f"{v}_{s}" for v in tri) for s in "rl" for tri in _WING_TRIANGLES]
    tri_names.append(("hip_r", "tail", "hip_l"))  # tail membrane (uropatagium)
    triangles = np.stack([np.stack([pts[v] for v in tri], axis=1) for tri in tri_names], axis=1)  # (F, T, 3, 3)

    n_mem = n_markers - 14
    n_wing = len(_WING_TRIANGLES)
    # allocate by the membrane areas of an extended reference pose (mid-downstroke)
    ref = _wing_body_frame(np.array([np.pi / 2]))
    ref_tri = np.stack([np.stack([ref[v][0] for v in tri]) for tri in _WING_TRIANGLES])
    areas = 0.5 * np.linalg.norm(np.cross(ref_tri[:, 1] - ref_tri[:, 0], ref_tri[:, 2] - ref_tri[:, 0]), axis=-1)
    mem_points = []
    for w, (side, n_side) in enumerate((("r", n_mem - n_mem // 2), ("l", n_mem // 2))):
        tri, bary = _membrane_barycentric(n_side, areas)
        mem_points.append(np.einsum("fkvi,kv->fki", triangles[:, w * n_wing + tri], bary))
        names += [f"mem_{side}_{k + 1:03d}" for k in range(n_side)]
    points = np.concatenate([np.stack([pts[n] for n in names[:14]], axis=1)] + mem_points, axis=1)

    body = Ellipsoid(world(_BODY_CENTER), B, _BODY_SEMI_AXES)
    head = Ellipsoid(world(_HEAD_CENTER), B, _HEAD_SEMI_AXES)
    return Scene(names, points, triangles, [body, head], phase)


def flight_skeleton(marker_names: list[str]) -> list[tuple[str, str]]:
    """Edges body - shoulder - elbow - wrist - digits for each wing present in ``marker_names``: every one is a
    bone or fixed in the body frame, so the simulator also writes them as ``[markers] rigid``."""
    edges = [("body1", "body2")]
    for s in "rl":
        edges += [("body1", f"shoulder_{s}"), (f"shoulder_{s}", f"elbow_{s}"), (f"elbow_{s}", f"wrist_{s}")]
        edges += [(f"wrist_{s}", f"{d}_{s}") for d in _DIGIT_M]
    return [e for e in edges if e[0] in marker_names and e[1] in marker_names]


# ==================================================================================================
# ear kinematics
# ==================================================================================================
def ear_scene(
    n_frames: int, fps: float, phase0_rad: float = 0.0, drift_hz: tuple[float, ...] = (0.4, 0.7, 1.1),
    drift_phase_rad: tuple[float, ...] = (0.0, 0.0, 0.0), drift_amp_m: float = 2e-4,
    times_s: np.ndarray | None = None,
) -> Scene:
    """A bat head (3 markers) with one ear (6 markers) bending through 90 deg at 10 Hz.

    The head faces +x with its centre at the origin and drifts rigidly by a smooth sub-millimetre
    amount (one sinusoid of amplitude ``drift_amp_m`` per axis, frequencies ``drift_hz`` (3,),
    phases ``drift_phase_rad`` (3,)). The ear is a 0.05 m strip of constant curvature whose tip
    angle goes 0 -> 90 deg -> 0 each cycle, so distal points bend more; markers sit at 1/6 .. 6/6
    of its length. The head is an opaque ellipsoid. times_s: these times [s] instead of the frames'. Deterministic.
    """
    t = np.arange(n_frames) / fps if times_s is None else np.asarray(times_s, float)
    n_frames = len(t)
    phase = phase0_rad + 2 * np.pi * EAR_HZ * t
    drift = drift_amp_m * np.sin(2 * np.pi * np.outer(t, drift_hz) + np.asarray(drift_phase_rad))  # (F, 3)
    head_pts = np.array([[0.021, 0.0, 0.002], [0.008, 0.008, 0.0112], [0.008, -0.008, 0.0112]])
    base = np.array([-0.002, 0.010, 0.012])
    up = np.array([0.0, 0.26, 1.0])
    up /= np.linalg.norm(up)  # the ear stands up, tilted outward
    bend = np.array([1.0, 0.3, 0.0])
    bend -= (bend @ up) * up
    bend /= np.linalg.norm(bend)  # it bends forward and a little outward
    tip_angle = np.radians(EAR_BEND_DEG) * (1 - np.cos(phase)) / 2  # (F,)
    s = EAR_LENGTH_M * np.arange(1, EAR_N_POINTS + 1) / EAR_N_POINTS  # (E,)
    ks = np.outer(tip_angle / EAR_LENGTH_M, s)  # curvature * arc length = local angle, (F, E)
    # constant-curvature arc written with sinc so it stays exact and smooth at zero curvature
    along_up = s * np.sinc(ks / np.pi)  # sin(ks) / k
    along_bend = s * (ks / 2) * np.sinc(ks / (2 * np.pi)) ** 2  # (1 - cos(ks)) / k
    ear = base + along_up[..., None] * up + along_bend[..., None] * bend  # (F, E, 3)
    points = np.concatenate([np.broadcast_to(head_pts, (n_frames, 3, 3)), ear], axis=1) + drift[:, None, :]
    names = ["head1", "head2", "head3"] + [f"ear{k + 1}" for k in range(EAR_N_POINTS)]
    head = Ellipsoid(drift.copy(), np.broadcast_to(np.eye(3), (n_frames, 3, 3)), np.array([0.02, 0.014, 0.013]))
    return Scene(names, points, np.zeros((n_frames, 0, 3, 3)), [head], phase)


# ==================================================================================================
# rendering: scene + rig -> observations
# ==================================================================================================
def _seed_of(rng: np.random.Generator):
    """The integer seed ``rng`` was made from (for the record), or None if it is not a small int."""
    seq = getattr(rng.bit_generator, "seed_seq", None)
    ent = getattr(seq, "entropy", None)
    if isinstance(ent, int) and 0 <= ent < 2**63 and not getattr(seq, "spawn_key", ()):
        return ent
    return None


def perturb_rig(rng: np.random.Generator, rig: Rig, rot_deg: float, trans_mm: float, cameras: list[int]) -> Rig:
    """A copy of ``rig`` with each listed camera turned about its own centre by ``rot_deg`` about a
    random axis and its centre moved by ``trans_mm`` in a random direction (both uniform on the sphere).
    """
    out = []
    for i, cam in enumerate(rig):
        R, C = cam.R, cam.center_world
        if i in cameras:
            axis = rng.standard_normal(3)
            direction = rng.standard_normal(3)
            dR = pose.R_from_rvec(np.radians(rot_deg) * axis / np.linalg.norm(axis))
            R = R @ dR  # cam_from_world; the camera turns about its own centre by dR^T (world axes)
            C = C + trans_mm / 1000 * direction / np.linalg.norm(direction)
        R, t = pose.cam_from_world(R.T, C)  # orientation and centre -> cam_from_world
        out.append(Camera(cam.name, cam.size_wh, cam.K.copy(), cam.dist.copy(), pose.rvec_from_R(R), t))
    return Rig(out)


def render(
    scene: Scene, rig: Rig, pixel_sigma_px: float, outlier_rate: float,
    rng_noise: np.random.Generator, rng_outliers: np.random.Generator,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Observe a scene with a rig: (observations, mislabels) tables.

    A (camera, frame, marker) is observed when the marker is in front of the camera, inside the
    lens's valid field, unoccluded (:func:`scene_visibility`) and its noisy raw pixel lies inside
    the image. Noise: i.i.d. Gaussian ``pixel_sigma_px`` on raw (distorted) pixels, drawn for every
    slot so that the draw does not depend on visibility. Then ``round(outlier_rate * n_obs)``
    observations are mislabelled: their u, v become another marker's projection (plus this row's
    noise) that the same camera sees on the same frame, or a uniform pixel if there is none.
    """
    uv_true = rig.project(scene.points_m)  # (C, F, M, 2), raw pixels
    uv = uv_true + pixel_sigma_px * rng_noise.standard_normal(uv_true.shape)
    in_img = np.stack([cam.in_image(uv[c]) for c, cam in enumerate(rig)])
    seen = np.isfinite(uv_true[..., 0]) & in_img & scene_visibility(scene, rig)
    return _observe(rig, scene.marker_names, uv_true, uv, seen, outlier_rate, rng_outliers)


def _observe(rig: Rig, marker_names: list[str], uv_true: np.ndarray, uv: np.ndarray, seen: np.ndarray,
             outlier_rate: float, rng_outliers: np.random.Generator) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(observations, mislabels) from true and noisy raw pixels (C, F, M, 2) and what is seen (C, F, M); F is
    each camera's own frame number. Mislabels: see :func:`render`."""
    M = uv_true.shape[2]
    c_idx, f_idx, m_idx = np.nonzero(seen)
    obs_uv = uv[c_idx, f_idx, m_idx]
    n_bad = int(round(outlier_rate * len(c_idx)))
    bad = np.sort(rng_outliers.choice(len(c_idx), size=n_bad, replace=False)) if n_bad else np.zeros(0, int)
    if n_bad:
        # pick uniformly among the other markers this camera sees on this frame (vectorised r-th True)
        cand = seen[c_idx[bad], f_idx[bad]] & (np.arange(M) != m_idx[bad, None])  # (n_bad, M)
        n_cand = cand.sum(axis=1)
        r = np.floor(rng_outliers.random(n_bad) * n_cand)
        other = np.argmax(np.cumsum(cand, axis=1) > r[:, None], axis=1)
        wh = np.array([rig[int(c)].size_wh for c in c_idx[bad]], dtype=float)
        uniform = rng_outliers.random((n_bad, 2)) * wh - 0.5
        swapped = uv_true[c_idx[bad], f_idx[bad], other] + (obs_uv[bad] - uv_true[c_idx[bad], f_idx[bad], m_idx[bad]])
        obs_uv[bad] = np.where((n_cand > 0)[:, None], swapped, uniform)
    names, markers = np.array(rig.names), np.array(marker_names)
    obs = pd.DataFrame({"frame": f_idx.astype(np.int64), "camera": names[c_idx], "marker": markers[m_idx],
                        "u": obs_uv[:, 0], "v": obs_uv[:, 1], "weight": np.ones(len(c_idx))})
    mis = obs.iloc[bad][["frame", "camera", "marker"]]
    key = ["frame", "camera", "marker"]
    return (obs.sort_values(key, kind="stable").reset_index(drop=True),
            mis.sort_values(key, kind="stable").reset_index(drop=True))


# ==================================================================================================
# timing: cameras that are not synchronised, rolling shutters, mixed frame rates
# ==================================================================================================
@dataclass
class Timing:
    """How the simulated cameras really record (batgraph.camera.Camera's meaning of each value).

    time_offsets_s: per camera [s] (None: all 0): its frame j is exposed at ``j / fps_c + offset`` on the
        session clock (whole-frame lags are offsets of whole frames).
    readout_s: rolling-shutter readout [s], one value or one per camera (0: global shutter).
    camera_fps: per camera [Hz] (None: all at the session's fps), none faster than the session.
    known: the written calibration.toml states the true offsets and readouts; by default it states only what a
        user knows without estimating (each camera's fps), and the truth goes to truth_timing.toml.
    """

    time_offsets_s: tuple[float, ...] | None = None
    readout_s: float | tuple[float, ...] = 0.0
    camera_fps: tuple[float, ...] | None = None
    known: bool = False

    def cameras(self, n: int, fps: float) -> list[dict]:
        """Per camera the Camera keyword arguments fps, time_offset_s, readout_s (ValueError when invalid)."""
        offsets = np.zeros(n) if self.time_offsets_s is None else np.asarray(self.time_offsets_s, float)
        readout = np.broadcast_to(np.asarray(self.readout_s, float), (n,)) if np.ndim(self.readout_s) == 0 \
            else np.asarray(self.readout_s, float)
        rates = np.full(n, float(fps)) if self.camera_fps is None else np.asarray(self.camera_fps, float)
        for what, a in (("time_offsets_s", offsets), ("readout_s", readout), ("camera_fps", rates)):
            if a.shape != (n,) or not np.isfinite(a).all():
                raise ValueError(f"timing {what}: expected {n} finite values (one per camera), got {a.tolist()}")
        if (rates <= 0).any() or (rates > fps * (1 + 1e-9)).any():
            raise ValueError(f"timing camera_fps: each must be > 0 and at most the session's {fps:g} fps, "
                             f"got {rates.tolist()}")
        if (readout < 0).any() or (readout >= 1.0 / rates).any():
            raise ValueError(f"timing readout_s: must be >= 0 and shorter than a frame, got {readout.tolist()}")
        return [{"fps": None if r == fps else float(r), "time_offset_s": float(o), "readout_s": float(q)}
                for r, o, q in zip(rates, offsets, readout, strict=True)]

    def trivial(self, n: int, fps: float) -> bool:
        """True when every camera records the session's frames all at once (the plain renderer applies)."""
        return all(k["fps"] is None and k["time_offset_s"] == 0 and k["readout_s"] == 0 for k in self.cameras(n, fps))


def with_timing(rig: Rig, timing: list[dict]) -> Rig:
    """A copy of ``rig`` whose cameras carry ``timing`` (per camera: Camera keyword arguments)."""
    return Rig([dataclasses.replace(cam, **kw) for cam, kw in zip(rig, timing, strict=True)],
               world_mirror=rig.world_mirror)


def timing_table(rig: Rig, fps: float) -> pd.DataFrame:
    """camera, fps, time_offset_s, readout_s of a rig (what truth_timing.toml holds)."""
    return pd.DataFrame({"camera": rig.names, "fps": [c.frame_rate(fps) for c in rig],
                         "time_offset_s": [c.time_offset_s for c in rig], "readout_s": [c.readout_s for c in rig]})


class SceneSpline:
    """A scene between its frames: every coordinate (markers, membrane vertices, solids) as a cubic spline of
    time through the exact scene on a grid 16 times finer than the frames (its error: tests/test_timing_sim.py).

    scene_at(times (G,) [s]) -> Scene: the closed-form scene at any instant; t0_s, t1_s: the span to cover [s].
    """

    def __init__(self, scene_at, t0_s: float, t1_s: float, fps: float):
        from scipy.interpolate import CubicSpline

        step = 1.0 / (16.0 * fps)
        n = int(np.ceil((t1_s - t0_s) / step)) + 7
        grid = t0_s - 3 * step + step * np.arange(n)
        sc = scene_at(grid)
        self.marker_names, self.M = sc.marker_names, sc.points_m.shape[1]
        self.T, self.semi = sc.triangles_m.shape[1], [e.semi_axes_m for e in sc.ellipsoids]
        parts = [sc.points_m.reshape(n, -1), sc.triangles_m.reshape(n, -1)]
        parts += [np.concatenate([e.center_m, e.axes.reshape(n, 9)], axis=1) for e in sc.ellipsoids]
        self.grid, self.coef = grid, CubicSpline(grid, np.concatenate(parts, axis=1), axis=0).c  # (4, n - 1, D)

    def _at(self, t_s: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The spline at times (N,) for columns (N, K) or (K,): (N, K)."""
        i = np.clip(np.searchsorted(self.grid, t_s) - 1, 0, len(self.grid) - 2)
        dt = (t_s - self.grid[i])[:, None]
        cols = np.broadcast_to(cols, (len(t_s),) + np.shape(cols)[-1:])
        c = self.coef
        return ((c[0][i[:, None], cols] * dt + c[1][i[:, None], cols]) * dt + c[2][i[:, None], cols]) * dt \
            + c[3][i[:, None], cols]

    def points(self, t_s: np.ndarray, marker: np.ndarray) -> np.ndarray:
        """Marker ``marker[n]`` at time ``t_s[n]``, (N, 3) [m]."""
        return self._at(t_s, 3 * np.asarray(marker)[:, None] + np.arange(3))

    def visible(self, center_m: np.ndarray, t_s: np.ndarray, marker: np.ndarray) -> np.ndarray:
        """Clear line of sight from a camera centre (3,) to marker[n] at time t_s[n], with every blocker at that
        time too (the rows of an occluder and of the marker behind it are read together); bool (N,)."""
        pts = self.points(t_s, marker)
        base = 3 * self.M
        tri = self._at(t_s, base + np.arange(9 * self.T)).reshape(len(t_s), self.T, 3, 3)
        hidden = _segments_hit_triangles_each(center_m, pts, tri)
        base += 9 * self.T
        for semi in self.semi:
            e = self._at(t_s, base + np.arange(12))
            hidden |= _segments_hit_ellipsoid_each(center_m, pts, e[:, :3], e[:, 3:].reshape(-1, 3, 3), semi)
            base += 12
        return ~hidden


def _segments_hit_triangles_each(origin_m: np.ndarray, points_m: np.ndarray, triangles_m: np.ndarray) -> np.ndarray:
    """:func:`segments_hit_triangles` for one origin (3,), N points (N, 3), each with its own triangles (N, T, 3, 3)."""
    D = (points_m - origin_m)[:, None, :]  # (N, 1, 3)
    v0 = triangles_m[:, :, 0]
    e1, e2 = triangles_m[:, :, 1] - v0, triangles_m[:, :, 2] - v0
    p = np.cross(D, e2)
    det = np.einsum("...i,...i->...", e1, p)
    scale = np.linalg.norm(D, axis=-1) * np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1)
    ok = np.abs(det) > 1e-12 * scale
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin_m - v0
    u = np.einsum("...i,...i->...", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("...i,...i->...", D, q) * inv
    t = np.einsum("...i,...i->...", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > HIT_EPS) & (t < 1 - HIT_EPS)
    return hit.any(axis=-1)


def _segments_hit_ellipsoid_each(origin_m: np.ndarray, points_m: np.ndarray, center_m: np.ndarray,
                                 axes: np.ndarray, semi_axes_m: np.ndarray) -> np.ndarray:
    """:func:`segments_hit_ellipsoid` for one origin (3,), N points (N, 3), each with its own solid's centre (N, 3)
    and axes (N, 3, 3); bool (N,)."""
    o = np.einsum("ni,nij->nj", origin_m - center_m, axes) / semi_axes_m
    d = np.einsum("ni,nij->nj", points_m - origin_m, axes) / semi_axes_m
    a, b, c = (d * d).sum(-1), (o * d).sum(-1), (o * o).sum(-1) - 1.0
    disc = b * b - a * c
    t1 = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
    return (disc > 0) & (t1 > HIT_EPS) & (t1 < 1 - HIT_EPS)


def render_timed(
    scene_at, n_frames: int, fps: float, rig: Rig, pixel_sigma_px: float, outlier_rate: float,
    rng_noise: np.random.Generator, rng_outliers: np.random.Generator,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """:func:`render` for cameras with their own timing (rig: the cameras as they really record).

    Each observation is the projection of the marker at its exact capture time: camera c's own frame j starts at
    ``j / fps_c + offset_c`` and raw row v is read ``readout_c * v / height`` later, the row being that of the
    projection itself (fixed-point iterations, converged to 1e-9 s). Camera frames j in [0, n_frames) whose nearest
    session frame k (batgraph.session.session_frames) is one of the n_frames are rendered. The noise of (c, j, m)
    is the draw :func:`render` gives (c, k, m), so a synchronised twin with the same seed has the same noise.
    Returns tables in each camera's own frames.
    """
    C, F = len(rig), int(n_frames)
    span = SceneSpline(scene_at, -1.0 / fps, F / fps + 1.0 / min(c.frame_rate(fps) for c in rig), fps)
    M = span.M
    noise = pixel_sigma_px * rng_noise.standard_normal((C, F, M, 2))
    uv_true = np.full((C, F, M, 2), np.nan)
    uv = np.full((C, F, M, 2), np.nan)
    seen = np.zeros((C, F, M), bool)
    for c, cam in enumerate(rig):
        j = np.arange(F)
        k = nearest_frame(exposure_frames(j, cam, fps))
        j, k = j[(k >= 0) & (k < F)], k[(k >= 0) & (k < F)]
        jj, mm = np.repeat(j, M), np.tile(np.arange(M), len(j))
        start = jj / cam.frame_rate(fps) + cam.time_offset_s
        t = start.copy()
        for _ in range(20):
            px = cam.project(span.points(t, mm))
            t_new = start + cam.readout_s * np.nan_to_num(px[:, 1]) / cam.size_wh[1]
            done = np.max(np.abs(t_new - t), initial=0.0) < 1e-9
            t = t_new
            if done:
                break
        px = cam.project(span.points(t, mm))
        noisy = px + noise[c, np.repeat(k, M), mm]
        uv_true[c, jj, mm], uv[c, jj, mm] = px, noisy
        seen[c, jj, mm] = np.isfinite(px[:, 0]) & cam.in_image(noisy) & span.visible(cam.center_world, t, mm)
    return _observe(rig, span.marker_names, uv_true, uv, seen, outlier_rate, rng_outliers)


def observe(scene: Scene, scene_at, rig: Rig, fps: float, timing: Timing | None, pixel_sigma_px: float,
            outlier_rate: float, rng_noise: np.random.Generator, rng_outliers: np.random.Generator):
    """(observations, mislabels, rig as it records): :func:`render` when ``timing`` is None or trivial (the rig
    returned is ``rig``), else :func:`render_timed` with the rig given ``timing`` (tables in camera frames).
    scene_at(times (G,) [s]) -> Scene: the same scene at any instant."""
    if timing is None or timing.trivial(len(rig), fps):
        return (*render(scene, rig, pixel_sigma_px, outlier_rate, rng_noise, rng_outliers), rig)
    true_rig = with_timing(rig, timing.cameras(len(rig), fps))
    n_frames = scene.points_m.shape[0]
    return (*render_timed(scene_at, n_frames, fps, true_rig, pixel_sigma_px, outlier_rate, rng_noise, rng_outliers),
            true_rig)


def state_timing(session: Session, recording: Rig, known: bool, table: str) -> Session:
    """A session rendered by :func:`render_timed` (tables in each camera's own frames) as a user would load it.

    recording: the rig as it really records. The session's rig states each camera's fps, and its offset and
    readout only when ``known``; the observations and mislabels go on that rig's session clock; ``true_timing``
    and ``extra_toml[table]`` (the scene's parameters) record the truth.
    """
    fps = session.fps
    stated = [{"fps": c.fps, **({"time_offset_s": c.time_offset_s, "readout_s": c.readout_s} if known else {})}
              for c in recording]
    written = with_timing(session.rig, stated)
    obs, _ = to_session_clock(session.observations, written, fps, f"session {session.name!r}")
    mis, _ = to_session_clock(session.mislabels, written, fps, f"session {session.name!r}")
    params = dict(session.extra_toml[table], camera_fps=[c.frame_rate(fps) for c in recording],
                  time_offsets_s=[c.time_offset_s for c in recording], readout_s=[c.readout_s for c in recording],
                  timing_known=bool(known))
    true_rig = None if session.true_rig is None else with_timing(session.true_rig, stated)
    return dataclasses.replace(session, rig=written, observations=obs, mislabels=mis, true_rig=true_rig,
                               true_timing=timing_table(recording, fps),
                               extra_toml=dict(session.extra_toml, **{table: params}))


def truth_table(scene: Scene) -> pd.DataFrame:
    """frame, marker, x, y, z [m] for every frame and marker of a scene."""
    F, M = scene.points_m.shape[:2]
    xyz = scene.points_m.reshape(-1, 3)
    return pd.DataFrame({"frame": np.repeat(np.arange(F, dtype=np.int64), M),
                         "marker": np.tile(scene.marker_names, F), "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})


def _assemble(
    rng: np.random.Generator, streams: list[np.random.Generator], scene: Scene, rig: Rig, *, name: str,
    fps: float, motion: MotionConfig, skeleton: list[tuple[str, str]], pixel_sigma_px: float,
    outlier_rate: float, calib_rot_deg: float, calib_trans_mm: float, calib_cameras: list[int] | None,
    params: dict, rigid: list[tuple[str, str]] = (), timing: Timing | None = None, scene_at=None,
) -> Session:
    """Render, apply the calibration error, and pack a Session (shared by both scenes); with a timing that is not
    trivial, render each observation at its capture time (:func:`observe`, :func:`state_timing`)."""
    if not 0 <= outlier_rate <= 1:
        raise ValueError(f"outlier_rate must be in [0, 1], got {outlier_rate}")
    if pixel_sigma_px < 0:
        raise ValueError(f"pixel_sigma_px must be >= 0, got {pixel_sigma_px}")
    cams = list(range(1, len(rig))) if calib_cameras is None else [int(c) for c in calib_cameras]
    if any(not 0 <= c < len(rig) for c in cams):
        raise ValueError(f"calib_cameras must index the {len(rig)} cameras, got {cams}")
    rng_noise, rng_out, rng_calib = streams
    obs, mis, recording = observe(scene, scene_at, rig, fps, timing, pixel_sigma_px, outlier_rate, rng_noise, rng_out)
    written, true_rig = rig, None
    if calib_rot_deg or calib_trans_mm:
        written, true_rig = perturb_rig(rng_calib, rig, calib_rot_deg, calib_trans_mm, cams), rig
    seed = _seed_of(rng)
    sim = dict(params, pixel_sigma_px=float(pixel_sigma_px), outlier_rate=float(outlier_rate),
               calib_rot_deg=float(calib_rot_deg), calib_trans_mm=float(calib_trans_mm), calib_cameras=cams,
               n_observations=len(obs), n_mislabelled=len(mis))
    if seed is not None:
        sim["seed"] = seed
    session = Session(
        name=name, fps=float(fps), rig=written, observations=obs, motion=motion,
        pixel_sigma_px=float(pixel_sigma_px), marker_names=list(scene.marker_names), skeleton=skeleton,
        truth=truth_table(scene), true_rig=true_rig, mislabels=mis, extra_toml={"simulation": sim},
        rigid=list(rigid),
    )
    return session if recording is rig else state_timing(session, recording, timing.known, "simulation")


def simulate_flight(
    rng: np.random.Generator, *, n_cameras: int = 5, n_markers: int | None = None, n_frames: int = 160,
    fps: float = 120.0, pixel_sigma_px: float = 1.0, outlier_rate: float = 0.0, calib_rot_deg: float = 0.0,
    calib_trans_mm: float = 0.0, calib_cameras: list[int] | None = None, name: str | None = None,
    timing: Timing | None = None,
) -> Session:
    """The paper's flight scene as a Session with truth (see module docstring).

    n_cameras: cameras on the tunnel wall (5 in the paper, up to 30 in the facility).
    n_markers: 14 (None) to 180; beyond 14 they are wing-membrane markers.
    n_frames, fps: 160 frames at 120 fps = 1.33 s = 4 m of flight.
    pixel_sigma_px: std of the Gaussian noise on raw pixels [px].
    outlier_rate: fraction of observations given another marker's pixels (listed in ``mislabels``).
    calib_rot_deg, calib_trans_mm, calib_cameras: the written calibration is the rendering rig with
        these cameras (default all but the first) turned and shifted; ``true_rig`` keeps the truth.
    timing: how the cameras really record (:class:`Timing`: offsets, readout, frame rates); None = all at once.
        It draws nothing, so the same seed without it is the synchronised twin of the same scene.
    Random draws (independent streams, so e.g. adding outliers leaves the noise unchanged): wingbeat
    phase at frame 0, the flight line's offset (+-5 cm), per-camera intrinsics, noise, outliers,
    calibration error.
    """
    n_markers = 14 if n_markers is None else int(n_markers)
    if n_cameras < 1 or n_frames < 1 or fps <= 0:
        raise ValueError("n_cameras and n_frames must be >= 1 and fps > 0")
    rng_scene, rng_cams, *streams = rng.spawn(5)
    phase0 = float(rng_scene.uniform(0, 2 * np.pi))
    offset = [float(v) for v in rng_scene.uniform(-0.05, 0.05, 2)]
    scene = flight_scene(n_frames, fps, n_markers, phase0, offset)
    rig = tunnel_rig(rng_cams, n_cameras)
    motion = MotionConfig(flight_speed_mps=FLIGHT_SPEED_MPS, span_m=SPAN_M,
                          flap_hz=FLAP_HZ, flap_angle_deg=FLAP_ANGLE_DEG)
    params = {"scene": "flight", "n_cameras": int(n_cameras), "n_markers": n_markers, "n_frames": int(n_frames),
              "fps": float(fps), "phase0_rad": phase0, "offset_yz_m": offset,
              "flight_speed_mps": FLIGHT_SPEED_MPS, "span_m": SPAN_M, "flap_hz": FLAP_HZ,
              "flap_angle_deg": FLAP_ANGLE_DEG, "tunnel_radius_m": TUNNEL_RADIUS_M}
    return _assemble(rng, streams, scene, rig, name=name or f"flight_{n_cameras}cam", fps=fps, motion=motion,
                     skeleton=flight_skeleton(scene.marker_names), pixel_sigma_px=pixel_sigma_px,
                     outlier_rate=outlier_rate, calib_rot_deg=calib_rot_deg, calib_trans_mm=calib_trans_mm,
                     calib_cameras=calib_cameras, params=params, rigid=flight_skeleton(scene.marker_names),
                     timing=timing, scene_at=lambda t: flight_scene(n_frames, fps, n_markers, phase0, offset, t))


def simulate_ear(
    rng: np.random.Generator, *, n_frames: int = 250, fps: float = 250.0, pixel_sigma_px: float = 1.0,
    outlier_rate: float = 0.0, calib_rot_deg: float = 0.0, calib_trans_mm: float = 0.0,
    calib_cameras: list[int] | None = None, name: str | None = None, timing: Timing | None = None,
) -> Session:
    """The paper's ear scene (2 low-distortion cameras, 250 fps) as a Session with truth.

    Arguments (timing included) as in :func:`simulate_flight`. Random draws: ear phase at frame 0, the head's drift
    frequencies (0.2-1.5 Hz) and phases, per-camera intrinsics, noise, outliers, calibration error.
    """
    if n_frames < 1 or fps <= 0:
        raise ValueError("n_frames must be >= 1 and fps > 0")
    rng_scene, rng_cams, *streams = rng.spawn(5)
    phase0 = float(rng_scene.uniform(0, 2 * np.pi))
    drift_hz = [float(v) for v in rng_scene.uniform(0.2, 1.5, 3)]
    drift_phase = [float(v) for v in rng_scene.uniform(0, 2 * np.pi, 3)]
    scene = ear_scene(n_frames, fps, phase0, drift_hz, drift_phase)
    rig = ear_rig(rng_cams, np.array([0.0, 0.0, 0.02]))
    motion = MotionConfig(flight_speed_mps=0.0, span_m=EAR_LENGTH_M, flap_hz=EAR_HZ,
                          flap_angle_deg=EAR_BEND_DEG)
    names = scene.marker_names
    skeleton = [("head1", "head2"), ("head2", "head3"), ("head3", "head1"), ("head2", "ear1")]
    skeleton += list(zip(names[3:-1], names[4:], strict=True))
    params = {"scene": "ear", "n_frames": int(n_frames), "fps": float(fps), "phase0_rad": phase0,
              "drift_hz": drift_hz, "drift_phase_rad": drift_phase, "drift_amp_m": 2e-4,
              "ear_length_m": EAR_LENGTH_M, "ear_hz": EAR_HZ, "ear_bend_deg": EAR_BEND_DEG}
    return _assemble(rng, streams, scene, rig, name=name or "ear_2cam", fps=fps, motion=motion, skeleton=skeleton,
                     pixel_sigma_px=pixel_sigma_px, outlier_rate=outlier_rate, calib_rot_deg=calib_rot_deg,
                     calib_trans_mm=calib_trans_mm, calib_cameras=calib_cameras, params=params, timing=timing,
                     scene_at=lambda t: ear_scene(n_frames, fps, phase0, drift_hz, drift_phase, times_s=t))


def scene_from_session(session: Session) -> Scene:
    """Rebuild the exact scene geometry (membranes, solids, phase) of a simulated session.

    Reads the [simulation] table the simulators write; raises ValueError for other sessions.
    Useful to check occlusion, to draw membranes in a viewer, or to split frames by stroke.
    """
    sim = session.extra_toml.get("simulation")
    if not isinstance(sim, dict) or sim.get("scene") not in ("flight", "ear"):
        raise ValueError(f"session {session.name!r} has no [simulation] table from batgraph.simulate")
    if sim["scene"] == "flight":
        return flight_scene(sim["n_frames"], sim["fps"], sim["n_markers"], sim["phase0_rad"], tuple(sim["offset_yz_m"]))
    return ear_scene(sim["n_frames"], sim["fps"], sim["phase0_rad"], sim["drift_hz"], sim["drift_phase_rad"],
                     sim["drift_amp_m"])


WAND_LENGTH_M = 0.5


def wand_scene(n_frames: int, fps: float, rng: np.random.Generator, length_m: float = WAND_LENGTH_M) -> Scene:
    """A calibration wand (two end markers ``wand_a``, ``wand_b`` a fixed distance apart) waved through
    the tunnel's flight volume: its centre wanders smoothly along x in [-1.5, 1.5] m and within
    +-0.25 m of the axis, and it turns about all axes. Nothing occludes it (a thin wand)."""
    t = np.arange(n_frames) / fps
    dur = max(t[-1], 1e-9)
    f = rng.uniform(0.3, 1.2, (3, 3))  # Hz: three sinusoids per coordinate
    ph = rng.uniform(0, 2 * np.pi, (3, 3))
    wave = np.stack([np.sin(2 * np.pi * f[i][:, None] * t + ph[i][:, None]).mean(axis=0) for i in range(3)], -1)
    center = np.column_stack([1.5 * np.cos(np.pi * t / dur), 0.25 * wave[:, 1], 0.25 * wave[:, 2]])
    yaw = 2 * np.pi * 0.4 * t + ph[0, 0]
    pitch = 0.6 * np.sin(2 * np.pi * 0.3 * t + ph[1, 1])
    direction = np.column_stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    half = 0.5 * length_m * direction
    points = np.stack([center - half, center + half], axis=1)  # (F, 2, 3)
    return Scene(["wand_a", "wand_b"], points, np.zeros((n_frames, 0, 3, 3)), [], np.zeros(n_frames))


def simulate_wand(
    rng: np.random.Generator, *, n_cameras: int = 5, n_frames: int = 600, fps: float = 120.0,
    pixel_sigma_px: float = 1.0, outlier_rate: float = 0.0, calib_rot_deg: float = 0.0,
    calib_trans_mm: float = 0.0, calib_cameras: list[int] | None = None, name: str | None = None,
) -> Session:
    """A wand-calibration recording in the flight tunnel: the SAME rig and calibration error as
    :func:`simulate_flight` with the same seed and ``n_cameras`` (same random streams), so a wand
    session can calibrate the rig that films a flight. session.toml gets ``[wand] ends``, ``length_m``.
    """
    if n_cameras < 1 or n_frames < 2 or fps <= 0:
        raise ValueError("n_cameras must be >= 1, n_frames >= 2 and fps > 0")
    rng_scene, rng_cams, *streams = rng.spawn(5)
    scene = wand_scene(n_frames, fps, rng_scene)
    rig = tunnel_rig(rng_cams, n_cameras)
    motion = MotionConfig(flight_speed_mps=FLIGHT_SPEED_MPS, span_m=WAND_LENGTH_M,
                          flap_hz=1.0, flap_angle_deg=90.0)
    params = {"scene": "wand", "n_cameras": int(n_cameras), "n_frames": int(n_frames), "fps": float(fps),
              "wand_length_m": WAND_LENGTH_M}
    session = _assemble(rng, streams, scene, rig, name=name or f"wand_{n_cameras}cam", fps=fps, motion=motion,
                        skeleton=[("wand_a", "wand_b")], pixel_sigma_px=pixel_sigma_px,
                        outlier_rate=outlier_rate, calib_rot_deg=calib_rot_deg, calib_trans_mm=calib_trans_mm,
                        calib_cameras=calib_cameras, params=params)
    session.extra_toml["wand"] = {"ends": ["wand_a", "wand_b"], "length_m": WAND_LENGTH_M}
    return session
