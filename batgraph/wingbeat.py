"""A second, independent generator of bat flight with ground truth: a joint-angle wing chain.

:mod:`batgraph.simulate` is one world (the paper's 0.5 m bat, a sinusoidal elevation per wing segment, GoPro
cameras on a tunnel wall). This module builds scenes to test batgraph on data it was not tuned on: another
parameterisation of the wing, other bats, paths, frame rates, noise levels and cameras. It only renders
scenes (it estimates nothing and writes no files) and nothing in it comes from batgraph's motion models: the
session it returns states no motion physics. Each wing is a rigid chain (humerus, radius, digits III-V)
driven by stroke, deviation, pronation, elbow, wrist and spread angles over the wingbeat, with representative
values for small bats from the literature; the body flies straight, turns banked or glides through a flight
section filmed by :func:`section_rig`'s random cameras; occlusion by membrane triangles and body and head
ellipsoids reuses :mod:`batgraph.simulate`'s ray tests; noise is Gaussian on raw pixels. All randomness
comes from the ``np.random.Generator`` passed in. docs/simulation.md gives every angle, length, range and
source.
"""

from __future__ import annotations

import math

import numpy as np

from .camera import Camera, Rig
from .geometry import pose
from .session import MotionConfig, Session
from .simulate import Ellipsoid, Scene, Timing, observe, state_timing, truth_table

G_MPS2 = 9.81
FLIGHTS = ("straight", "turn", "glide")
MARKER_SIDES = ("both", "dorsal")

# ----- ranges the generator draws from (and accepts) -------------------------------------------------
FLAP_HZ_RANGE = (4.0, 15.0)
SPEED_MPS_RANGE = (2.0, 6.0)
STROKE_AMPLITUDE_DEG_RANGE = (80.0, 120.0)
DOWNSTROKE_FRACTION_RANGE = (0.5, 0.6)
STROKE_PLANE_TILT_DEG_RANGE = (15.0, 35.0)
BODY_PITCH_DEG_RANGE = (5.0, 20.0)
SIZE_SCALE_RANGE = (0.85, 1.2)
PIXEL_SIGMA_PX_RANGE = (2.0, 8.0)
YAW_RATE_DEG_S_RANGE = (60.0, 150.0)  # magnitude; the sign is drawn
SENSORS_WH = ((1024, 1024), (1280, 800), (1280, 1024), (1920, 1080))
SECTION_HEIGHT_M = 1.2  # height of the flight path's middle above the floor

# ----- the bat (metres; wing frame: forward, outward, up; body frame: forward, left, up) -----------
BONES_M = {"humerus": 0.027, "radius": 0.037, "digit3": 0.070, "digit4": 0.052, "digit5": 0.045}
_SHOULDER_W = (0.012, 0.011, 0.004)
_HIP_W = (-0.040, 0.010, -0.004)
_TAIL_B = (-0.075, 0.0, -0.008)
_HEAD_MARKER_B = (0.030, 0.0, 0.013)
_RUMP_MARKER_B = (-0.035, 0.0, 0.0105)
_BODY_CENTER_B, _BODY_SEMI_M = (-0.012, 0.0, 0.0), np.array([0.035, 0.013, 0.012])
_HEAD_CENTER_B, _HEAD_SEMI_M = (0.030, 0.0, 0.002), np.array([0.014, 0.010, 0.010])
WING_JOINTS = ("shoulder", "elbow", "wrist", "tip3", "tip4", "tip5")
_WING_TRIANGLES = (  # by joint name; "hip" is a membrane vertex, not a marker
    ("shoulder", "elbow", "wrist"),  # propatagium
    ("hip", "shoulder", "elbow"), ("hip", "elbow", "wrist"), ("hip", "wrist", "tip5"),  # plagiopatagium
    ("wrist", "tip4", "tip5"), ("wrist", "tip3", "tip4"),  # dactylopatagium
)
_SIDES = (("R", -1.0), ("L", 1.0))  # marker prefix, sign of the body's left axis for "outward"


def marker_names() -> list[str]:
    """The 14 markers: head, rump, then per wing (R, L) shoulder, elbow, wrist and the tips of digits III-V."""
    return ["head", "rump"] + [f"{side}_{j}" for side, _ in _SIDES for j in WING_JOINTS]


def skeleton() -> list[tuple[str, str]]:
    """Edges to draw: head - rump, head - shoulder, and each wing's bones."""
    edges = [("head", "rump")]
    for side, _ in _SIDES:
        edges += [("head", f"{side}_shoulder"), (f"{side}_shoulder", f"{side}_elbow"),
                  (f"{side}_elbow", f"{side}_wrist")] + [(f"{side}_wrist", f"{side}_tip{d}") for d in (3, 4, 5)]
    return edges


def rigid_pairs() -> list[tuple[str, str]]:
    """Marker pairs whose distance never changes: the bones and the body (head, rump, both shoulders)."""
    body = ["head", "rump", "R_shoulder", "L_shoulder"]
    pairs = [(a, b) for i, a in enumerate(body) for b in body[i + 1:]]
    for side, _ in _SIDES:
        pairs += [(f"{side}_shoulder", f"{side}_elbow"), (f"{side}_elbow", f"{side}_wrist")]
        pairs += [(f"{side}_wrist", f"{side}_tip{d}") for d in (3, 4, 5)]
    return pairs


# ==================================================================================================
# wing kinematics
# ==================================================================================================
def _rot(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotations about a fixed unit axis (3,) by angles (F,): shape (F, 3, 3) (Rodrigues)."""
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    th = np.asarray(angle_rad, float)[:, None, None]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


_X, _Y, _Z = np.eye(3)


def stroke_phase(cycles: np.ndarray, downstroke_fraction: float) -> np.ndarray:
    """Stroke phase s (F,) [cycles] at wingbeat time ``cycles`` (F,) [cycles since the top of a stroke].

    Inverts the C-infinity warp ``p(s) = s + c (1 - cos 2 pi s) / (2 pi)``, ``c = pi (D - 1/2)``, which
    maps s = 1/2 (bottom of the stroke) to p = D: the downstroke lasts the fraction D of the cycle.
    """
    D = float(downstroke_fraction)
    if not 0.2 < D < 0.8:
        raise ValueError(f"downstroke_fraction must be in (0.2, 0.8), got {D}")
    c = math.pi * (D - 0.5)
    p = np.asarray(cycles, float)
    s = p.copy()
    for _ in range(50):  # Newton; p'(s) = 1 + c sin(2 pi s) >= 1 - |c| > 0.05
        step = (s + c * (1 - np.cos(2 * np.pi * s)) / (2 * np.pi) - p) / (1 + c * np.sin(2 * np.pi * s))
        s -= step
        if np.max(np.abs(step), initial=0.0) < 1e-15:
            break
    return s


def fold_of(s: np.ndarray) -> np.ndarray:
    """Wing folding (F,): 0 at mid-downstroke (s = 1/4), 1 at mid-upstroke (s = 3/4), smooth."""
    return ((1 - np.cos(2 * np.pi * (s - 0.25))) / 2) ** 2


def wing_angles(s: np.ndarray, stroke_amplitude_deg: float, glide: bool = False,
                dihedral_deg: np.ndarray | float = 5.0) -> dict[str, np.ndarray]:
    """Joint angles [rad], each (F,), at stroke phases s (F,) (module docstring).

    glide: the wing held extended (the mid-downstroke shape) at stroke angle ``dihedral_deg`` (F,) or scalar.
    """
    s = np.asarray(s, float)
    r = np.radians
    if glide:
        s = np.full_like(s, 0.25)
        phi = np.broadcast_to(r(np.asarray(dihedral_deg, float)), s.shape).copy()
    else:
        phi = r(5.0) + r(stroke_amplitude_deg) / 2 * np.cos(2 * np.pi * s)
    fold = fold_of(s)
    sin1 = np.sin(2 * np.pi * s)
    return {
        "stroke": phi,
        "deviation": r(15.0) + r(8.0) * np.sin(4 * np.pi * s) + r(25.0) * fold,
        "pronation": r(5.0) + r(20.0) * sin1,
        "elbow": r(50.0) + r(55.0) * fold,
        "elbow_bend": r(10.0) * sin1,
        "wrist": r(45.0) + r(80.0) * fold,
        "wrist_bend": r(15.0) * sin1 - r(25.0) * fold,
        "spread34": r(25.0) * (1 - 0.65 * fold),
        "spread45": r(30.0) * (1 - 0.65 * fold),
    }


def wing_chain(angles: dict[str, np.ndarray], stroke_plane_tilt_deg: float,
               scale: float = 1.0) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Joint positions of one wing in its wing frame (forward, outward, up) [m], name -> (F, 3), and the
    dorsal unit normal of the wing at each marker, name -> (F, 3).

    angles: :func:`wing_angles`; stroke_plane_tilt_deg: tilt of the stroke axis back from the body's
    forward axis (raising the wing also moves it back); scale: bone-length factor. Positions include
    "hip" (a membrane vertex). Normals: the body's up at the shoulder, the humerus's dorsal axis at the
    elbow, the forearm's at the wrist, each digit's at its tip.
    """
    g = math.radians(stroke_plane_tilt_deg)
    a = np.array([math.cos(g), 0.0, math.sin(g)])  # stroke axis, in the sagittal plane
    m = np.array([-math.sin(g), 0.0, math.cos(g)])  # in the stroke plane, perpendicular to the span axis
    L = {k: v * scale for k, v in BONES_M.items()}
    H = _rot(a, angles["stroke"]) @ _rot(m, angles["deviation"]) @ _rot(_Y, angles["pronation"])
    E = H @ _rot(_Z, -angles["elbow"]) @ _rot(_X, angles["elbow_bend"])  # forearm turns forward
    W = E @ _rot(_Z, angles["wrist"]) @ _rot(_X, angles["wrist_bend"])  # hand turns back
    F = len(angles["stroke"])
    out = {"shoulder": np.broadcast_to(np.asarray(_SHOULDER_W) * scale, (F, 3)).copy(),
           "hip": np.broadcast_to(np.asarray(_HIP_W) * scale, (F, 3)).copy()}
    out["elbow"] = out["shoulder"] + L["humerus"] * H[:, :, 1]
    out["wrist"] = out["elbow"] + L["radius"] * E[:, :, 1]
    normals = {"shoulder": np.broadcast_to(_Z, (F, 3)).copy(), "elbow": H[:, :, 2], "wrist": E[:, :, 2]}
    zero = np.zeros(F)
    fans = {"tip3": (zero, zero), "tip4": (angles["spread34"], zero),
            "tip5": (angles["spread34"] + angles["spread45"], np.full(F, math.radians(-10.0)))}
    for tip, (spread, bend) in fans.items():
        D = W @ _rot(_Z, spread) @ _rot(_X, bend)
        out[tip] = out["wrist"] + L[f"digit{tip[-1]}"] * D[:, :, 1]
        normals[tip] = D[:, :, 2]
    return out, normals


# ==================================================================================================
# body path
# ==================================================================================================
def body_path(t_s: np.ndarray, speed_mps: float, yaw_rate_rad_s: float, heading_mid_rad: float,
              climb_rad: float, s: np.ndarray | None, flap_hz: float) -> tuple[np.ndarray, tuple]:
    """Body centre (F, 3) [m, world] and (heading (F,), pitch wobble (F,), roll) [rad] at times ``t_s`` (F,)
    [s] measured from the path's middle (orientation: :func:`body_frames`).

    The centre moves at ``speed_mps`` horizontally with heading ``heading_mid_rad + yaw_rate t`` and climbs
    at angle ``climb_rad`` (negative = descends); at t = 0 it is at (0, 0, SECTION_HEIGHT_M). A turn is
    banked (roll toward the turn's centre, ``atan(v r / g)``). s: stroke phase (F,) for the wingbeat's
    bob (+-3 mm), surge (+-1.5 % of the speed at ``flap_hz``) and pitch wobble (+-3 deg); None: gliding.
    """
    t = np.asarray(t_s, float)
    h = heading_mid_rad + yaw_rate_rad_s * t
    v = speed_mps
    if abs(yaw_rate_rad_s) > 1e-12:
        xy = np.stack([np.sin(h) - math.sin(heading_mid_rad), -(np.cos(h) - math.cos(heading_mid_rad))], -1)
        xy *= v / yaw_rate_rad_s
    else:
        xy = v * t[:, None] * np.array([math.cos(heading_mid_rad), math.sin(heading_mid_rad)])
    center = np.column_stack([xy, SECTION_HEIGHT_M + v * math.tan(climb_rad) * t])
    bank = math.atan(v * yaw_rate_rad_s / G_MPS2)  # coordinated turn: lift tilts toward the turn's centre
    pitch = np.full_like(t, 0.0)
    if s is not None:
        w = 2 * np.pi * s
        fwd_h = np.column_stack([np.cos(h), np.sin(h), np.zeros_like(h)])
        center = center + (0.015 * v / (2 * np.pi * flap_hz)) * np.sin(w)[:, None] * fwd_h  # surge
        center[:, 2] += 0.003 * np.sin(w - 1.0)  # bob: up during the downstroke
        pitch = np.radians(3.0) * np.sin(w + 0.5)
    return center, (h, pitch, -bank)


def body_frames(heading_rad: np.ndarray, pitch_rad: np.ndarray, roll_rad: float) -> np.ndarray:
    """Body-to-world rotations (F, 3, 3): yaw about z, then nose-up pitch, then roll about forward."""
    return _rot(_Z, heading_rad) @ _rot(_Y, -pitch_rad) @ _rot(_X, np.full(len(heading_rad), roll_rad))


# ==================================================================================================
# cameras
# ==================================================================================================
def section_rig(rng: np.random.Generator, n_cameras: int, path_m: np.ndarray, half_span_m: float) -> Rig:
    """Cameras on both sides of a flight section at random but sensible poses (module docstring).

    path_m: body centre per frame (F, 3) [m, world]; half_span_m: margin around it that must stay in view.
    Camera i sits on side (-1)^i of the flight direction, at an azimuth stratified over 30-150 deg from
    it per side, 1.2-2.2 m from the path's middle and 0.8 m below to 1.2 m above it; it aims at a point
    of the path's middle 40 % and its focal length (400-8000 px) fits a random 50-100 % of the path
    around that point, plus the margin, into 90 % of the image: the bat may leave some views.
    """
    n = int(n_cameras)
    mid = path_m[len(path_m) // 2]
    chord = path_m[-1] - path_m[0]
    chord[2] = 0.0
    fwd = chord / np.linalg.norm(chord) if np.linalg.norm(chord) > 1e-6 else np.array([1.0, 0.0, 0.0])
    left = np.cross(_Z, fwd)
    offsets = np.array([[0, 0, 0]] + [list(sgn * half_span_m * e) for e in np.eye(3) for sgn in (1, -1)])
    F = len(path_m)
    per_side = [(n + 1) // 2, n // 2]
    cams = []
    for i in range(n):
        side, k = (1.0 if i % 2 == 0 else -1.0), i // 2
        az = np.radians(30.0 + 120.0 * (k + rng.uniform(0.15, 0.85)) / per_side[i % 2])
        dist = rng.uniform(1.2, 2.2)
        center = mid + dist * (np.cos(az) * fwd + side * np.sin(az) * left) + rng.uniform(-0.8, 1.2) * _Z
        aim, cover = rng.uniform(0.3, 0.7), rng.uniform(0.5, 1.0)  # aim point and share of the path to fit
        target = path_m[int(aim * (F - 1))] + rng.normal(0.0, 0.05, 3)
        R, t = pose.look_at(center, target, np.cross(target - center, _Z))
        w, h = SENSORS_WH[int(rng.integers(len(SENSORS_WH)))]
        lo, hi = int(max(aim - cover / 2, 0.0) * (F - 1)), int(np.ceil(min(aim + cover / 2, 1.0) * (F - 1)))
        cloud = (path_m[lo:hi + 1, None, :] + offsets[None]).reshape(-1, 3)
        xc = cloud @ R.T + t
        xn = xc[:, :2] / np.maximum(xc[:, 2:], 1e-3)
        f = float(np.clip(min(0.45 * w / np.abs(xn[:, 0]).max(), 0.45 * h / np.abs(xn[:, 1]).max()), 400.0, 8000.0))
        K = np.array([[f, 0.0, (w - 1) / 2 + 0.01 * w * rng.uniform(-1, 1)],
                      [0.0, f * (1 + 0.002 * rng.standard_normal()), (h - 1) / 2 + 0.01 * h * rng.uniform(-1, 1)],
                      [0.0, 0.0, 1.0]])
        dist_coefs = np.array([rng.uniform(-0.12, 0.02), rng.uniform(0.0, 0.04), 2e-4 * rng.standard_normal(),
                               2e-4 * rng.standard_normal(), 0.0])
        cams.append(Camera(f"hs{i + 1}", (w, h), K, dist_coefs, pose.rvec_from_R(R), t))
    return Rig(cams)


# ==================================================================================================
# scene
# ==================================================================================================
def wingbeat_scene(params: dict, times_s: np.ndarray | None = None) -> Scene:
    """The flying bat of a parameter set (what :func:`simulate_wingbeat` records under ``[wingbeat]``).

    Deterministic. Returns markers (F, 14, 3), membrane triangles (F, 13, 3, 3; then one skin patch per wing
    marker with ``marker_side = "dorsal"``), body and head solids,
    and the stroke phase as ``phase_rad`` (2 pi s; sin > 0 on the downstroke; constant when gliding).
    times_s: evaluate it at these times [s] instead of frame k's k / fps (closed form: any instant).
    """
    n, fps, flight = int(params["n_frames"]), float(params["fps"]), params["flight"]
    t = np.arange(n) / fps if times_s is None else np.asarray(times_s, float)
    t_mid = t - (n - 1) / fps / 2
    glide = flight == "glide"
    cycles = params["phase0_cycles"] + params["flap_hz"] * t
    s = stroke_phase(cycles, params["downstroke_fraction"])
    center, (heading, pitch_wobble, roll) = body_path(
        t_mid, params["speed_mps"], math.radians(params["yaw_rate_deg_s"]), math.radians(params["heading_deg"]),
        math.radians(-params["glide_angle_deg"]) if glide else 0.0, None if glide else s, params["flap_hz"])
    pitch = math.radians(params["body_pitch_deg"]) + pitch_wobble
    B = body_frames(heading, pitch, roll)

    def world(p_body):  # (F, 3) or (3,) body frame -> (F, 3) world
        return center + np.einsum("fij,fj->fi", B, np.broadcast_to(p_body, center.shape))

    scale = params["size_scale"]
    pts = {"head": world(np.asarray(_HEAD_MARKER_B) * scale), "rump": world(np.asarray(_RUMP_MARKER_B) * scale),
           "tail": world(np.asarray(_TAIL_B) * scale)}
    dorsal = {}
    dihedral = 5.0 + 3.0 * np.sin(2 * np.pi * 2.0 * t + 2 * np.pi * params["phase0_cycles"])
    inner = np.sign(params["yaw_rate_deg_s"])  # +1: turning left (the left wing is inside), -1 right, 0 none
    for side, sign in _SIDES:
        amp = params["stroke_amplitude_deg"] * (1 - params["inner_wing_reduction"] * (sign == inner))
        joints, normals = wing_chain(wing_angles(s, amp, glide, dihedral), params["stroke_plane_tilt_deg"], scale)
        flip = np.array([1.0, sign, 1.0])  # wing frame (forward, outward, up) -> body (forward, left, up)
        for j, p in joints.items():
            pts[f"{side}_{j}"] = world(p * flip)
        for j, nrm in normals.items():  # a reflection maps the dorsal normal to the mirrored wing's dorsal normal
            dorsal[f"{side}_{j}"] = np.einsum("fij,fj->fi", B, nrm * flip)
    names = marker_names()
    points = np.stack([pts[m] for m in names], axis=1)
    tri = [tuple(f"{side}_{v}" for v in tri) for side, _ in _SIDES for tri in _WING_TRIANGLES]
    tri.append(("R_hip", "tail", "L_hip"))  # uropatagium
    triangles = np.stack([np.stack([pts[v] for v in tr], axis=1) for tr in tri], axis=1)
    if params["marker_side"] == "dorsal":
        patches = [_skin_patch(pts[m], nrm) for m, nrm in dorsal.items()]
        triangles = np.concatenate([triangles, np.stack(patches, axis=1)], axis=1)
    solids = [Ellipsoid(world(np.asarray(c) * scale), B, semi * scale)
              for c, semi in ((_BODY_CENTER_B, _BODY_SEMI_M), (_HEAD_CENTER_B, _HEAD_SEMI_M))]
    return Scene(names, points, triangles, solids, 2 * np.pi * s)


SKIN_PATCH_DEPTH_M, SKIN_PATCH_RADIUS_M = 0.001, 0.006


def _skin_patch(point_m: np.ndarray, dorsal: np.ndarray) -> np.ndarray:
    """An opaque triangle (F, 3, 3) [m] 1 mm beneath a marker on the dorsal skin, perpendicular to the wing's
    dorsal normal (F, 3), circumradius 6 mm: the bone and skin under the marker. It hides the marker from
    cameras on the ventral side except at grazing angles (more than ~72 deg from the normal)."""
    n = dorsal / np.linalg.norm(dorsal, axis=-1, keepdims=True)
    ref = np.where(np.abs(n[:, :1]) < 0.9, _X, _Y)
    u1 = np.cross(n, ref)
    u1 /= np.linalg.norm(u1, axis=-1, keepdims=True)
    u2 = np.cross(n, u1)
    c = point_m - SKIN_PATCH_DEPTH_M * n
    ang = 2 * np.pi * np.arange(3) / 3
    rim = np.cos(ang)[None, :, None] * u1[:, None] + np.sin(ang)[None, :, None] * u2[:, None]  # (F, 3, 3)
    return c[:, None] + SKIN_PATCH_RADIUS_M * rim


def _draw(rng: np.random.Generator, value, lo_hi: tuple[float, float]) -> float:
    """``value`` as a float, or a uniform draw in ``lo_hi`` when it is None."""
    return float(rng.uniform(*lo_hi)) if value is None else float(value)


def simulate_wingbeat(
    rng: np.random.Generator, *, n_cameras: int = 5, fps: float = 120.0, n_frames: int = 72,
    flap_hz: float | None = None, pixel_sigma_px: float | None = 1.0, flight: str = "straight",
    speed_mps: float | None = None, stroke_amplitude_deg: float | None = None,
    downstroke_fraction: float | None = None, yaw_rate_deg_s: float | None = None, marker_side: str = "both",
    outlier_rate: float = 0.0, name: str | None = None, timing: Timing | None = None,
) -> Session:
    """A bat from the joint-angle generator filmed by a random flight-section rig, as a Session with truth.

    n_cameras: >= 2; fps: frame rate [Hz] (60-1000 typical); n_frames: frames to render.
    flap_hz: wingbeat frequency [Hz] (None: drawn in 4-15; ignored when gliding). pixel_sigma_px: std of the
        Gaussian pixel noise [px] (None: drawn in 2-8); the session states it.
    flight: "straight", "turn" (yaw rate drawn in +-60-150 deg/s unless given) or "glide" (no flapping).
    speed_mps (2-6), stroke_amplitude_deg (80-120), downstroke_fraction (0.5-0.6): None = drawn.
    marker_side: "both" (a wing marker is seen from either side of the wing unless something is in the way) or
        "dorsal" (painted on the dorsal skin: also hidden from the wing's ventral side, :func:`_skin_patch`).
    outlier_rate: fraction of observations relabelled to another marker (see simulate.render). timing: how the
        cameras really record (batgraph.simulate.Timing); None = all at once; the same seed without it gives the
        synchronised twin. Also drawn: the wingbeat phase, stroke-plane tilt, body pitch, bat size, heading, cameras.
    ``extra_toml`` holds ``[wingbeat]`` (every parameter, enough to rebuild the scene with :func:`wingbeat_scene`);
    ``rigid`` (``[markers] rigid``) the marker pairs at a constant distance (:func:`rigid_pairs`).
    """
    if flight not in FLIGHTS:
        raise ValueError(f"flight must be one of {FLIGHTS}, got {flight!r}")
    if marker_side not in MARKER_SIDES:
        raise ValueError(f"marker_side must be one of {MARKER_SIDES}, got {marker_side!r}")
    if n_cameras < 2 or n_frames < 2 or fps <= 0:
        raise ValueError("n_cameras and n_frames must be >= 2 and fps > 0")
    rng_scene, rng_cams, rng_noise, rng_out = rng.spawn(4)
    p = {"scene": "wingbeat", "flight": flight, "n_cameras": int(n_cameras), "n_frames": int(n_frames),
         "fps": float(fps)}
    p["flap_hz"] = 0.0 if flight == "glide" else _draw(rng_scene, flap_hz, FLAP_HZ_RANGE)
    p["speed_mps"] = _draw(rng_scene, speed_mps, SPEED_MPS_RANGE)
    p["stroke_amplitude_deg"] = _draw(rng_scene, stroke_amplitude_deg, STROKE_AMPLITUDE_DEG_RANGE)
    p["downstroke_fraction"] = _draw(rng_scene, downstroke_fraction, DOWNSTROKE_FRACTION_RANGE)
    p["stroke_plane_tilt_deg"] = _draw(rng_scene, None, STROKE_PLANE_TILT_DEG_RANGE)
    p["body_pitch_deg"] = _draw(rng_scene, None, BODY_PITCH_DEG_RANGE)
    p["size_scale"] = _draw(rng_scene, None, SIZE_SCALE_RANGE)
    p["phase0_cycles"] = _draw(rng_scene, None, (0.0, 1.0))
    p["heading_deg"] = _draw(rng_scene, None, (-180.0, 180.0))
    yaw = 0.0
    if flight == "turn":
        yaw = yaw_rate_deg_s if yaw_rate_deg_s is not None else (
            float(rng_scene.uniform(*YAW_RATE_DEG_S_RANGE)) * float(rng_scene.choice([-1.0, 1.0])))
    p["yaw_rate_deg_s"] = float(yaw)
    p["inner_wing_reduction"] = 0.1 if flight == "turn" else 0.0  # the inner wing's stroke amplitude: 10 % less
    p["glide_angle_deg"] = 8.0 if flight == "glide" else 0.0
    p["marker_side"] = marker_side
    p["pixel_sigma_px"] = _draw(rng_noise, pixel_sigma_px, PIXEL_SIGMA_PX_RANGE)
    p["outlier_rate"] = float(outlier_rate)
    if not 0 <= p["outlier_rate"] <= 1 or p["pixel_sigma_px"] < 0:
        raise ValueError("outlier_rate must be in [0, 1] and pixel_sigma_px >= 0")
    scene = wingbeat_scene(p)
    half_span = 0.16 * p["size_scale"]
    body = scene.points_m[:, 1]  # the rump follows the body
    rig = section_rig(rng_cams, n_cameras, body, half_span)
    obs, mis, recording = observe(scene, lambda t: wingbeat_scene(p, t), rig, fps, timing, p["pixel_sigma_px"],
                                  p["outlier_rate"], rng_noise, rng_out)
    p["n_observations"] = len(obs)
    session = Session(
        name=name or f"wingbeat_{flight}_{n_cameras}cam", fps=float(fps), rig=rig, observations=obs,
        motion=MotionConfig(), pixel_sigma_px=p["pixel_sigma_px"],
        marker_names=list(scene.marker_names), skeleton=skeleton(), truth=truth_table(scene), mislabels=mis,
        extra_toml={"wingbeat": p}, rigid=rigid_pairs(),
    )
    return session if recording is rig else state_timing(session, recording, timing.known, "wingbeat")
