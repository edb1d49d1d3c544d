"""Ablation of the smoother's post-solve steps and floors (batgraph.solver): RMSE and 95 % coverage by status, span.

Each variant is the default smoother ("auto", Huber, outlier rejection, the session's segments) with one step
switched off: the flapping q floor (solver.schedule.flapping_floor), the segments' second depth
(solver.ends._second_depth), the track ends' backtest widening c (ends.growth_rate), the no-view floor
(ends._no_view_variances), the outlier-rejection schedule (Options.outlier_rejection), the segments' softer first
solve (schedule.SEGMENT_RELAX), and "bare": all of ends.widen off. They are switched off from outside, by
replacing those names for the run (unittest.mock): batgraph/ is unchanged. Scenes: the first generator's flight
(batgraph.simulate, with and without 5 % mislabels), three hold-out scenes of batgraph.wingbeat, and a
wing-occlusion scene written here from first principles (:func:`occlusion_scene`). Writes docs/ablation.md: per
scene, variant and group (status within span) the RMSE over seeds and the 95 % coverage pooled over seeds with
its exact interval and verdict on [90, 98] % (scripts/accuracy_study.pooled_coverage), and the verdicts each step
changes, which scripts/accuracy_study.py copies into docs/accuracy.md. Run by ``make ablation``. Nothing is asserted.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import fnmatch
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

import accuracy_study as study  # noqa: E402

from batgraph import atomic  # noqa: E402
from batgraph.camera import Camera, Rig  # noqa: E402
from batgraph.result import Options  # noqa: E402
from batgraph.runner import run_methods  # noqa: E402
from batgraph.session import MotionConfig, Session  # noqa: E402
from batgraph.simulate import simulate_flight  # noqa: E402
from batgraph.solver import ends, schedule  # noqa: E402
from batgraph.wingbeat import simulate_wingbeat  # noqa: E402

GROUPS = ("observed/inside", "single_view/inside", "single_view/outside", "unobserved/inside", "unobserved/outside")
TARGET = (90.0, 98.0)  # 95 % coverage target [%]
DEFAULT_SEEDS = "1,2,3"


# ==================================================================================================
# the switches
# ==================================================================================================
def _no_flapping_floor(xyz_m: np.ndarray, fps: float) -> float:
    return 0.0


def _no_second_depth(setup, backend, models, levels, fit, cov) -> tuple[np.ndarray, int]:
    return cov, 0


def _zero_rate(*args, **kwargs) -> float:
    return 0.0


def _no_view_floor(solve, setup, fit, rays, u, units) -> np.ndarray:
    return np.zeros(len(u))


def _exclude_none(rejected: np.ndarray, seen: np.ndarray) -> np.ndarray:
    return np.zeros_like(rejected)


def _no_widening(setup, backend, models, levels, fit) -> tuple[np.ndarray, dict]:
    return fit.cov, {}


@dataclass(frozen=True)
class Variant:
    """One row of the ablation: which names of batgraph.solver are replaced (functions or constants), and which
    Options change."""

    key: str
    what: str
    patches: tuple[tuple[object, str, object], ...] = ()
    options: tuple[tuple[str, object], ...] = ()


VARIANTS = (
    Variant("default", "every step on (the default smoother)"),
    Variant("no_flap_floor", "1. no flapping q floor (schedule.flapping_floor returns 0)",
            ((schedule, "flapping_floor", _no_flapping_floor),)),
    Variant("no_ambiguity", "2. no segments' second depth (ends._second_depth adds nothing)",
            ((ends, "_second_depth", _no_second_depth),)),
    Variant("no_ends_c", "3. no backtest widening c (ends.growth_rate returns 0)",
            ((ends, "growth_rate", _zero_rate),)),
    Variant("no_view_floor", "4. no no-view floor (ends._no_view_variances returns 0)",
            ((ends, "_no_view_variances", _no_view_floor),)),
    Variant("no_rejection", "5. no outlier-rejection schedule (Options.outlier_rejection=False)",
            options=(("outlier_rejection", False),)),
    Variant("no_exclusion", "5'. the rejection schedule's cleaning solve kept, nothing excluded (schedule.to_exclude "
            "returns none)", ((schedule, "to_exclude", _exclude_none),)),
    Variant("no_segment_relax", "6. no softer first solve with the segments (schedule.SEGMENT_RELAX = 1)",
            ((schedule, "SEGMENT_RELAX", 1.0),)),
    Variant("bare", "7. steps 2-4 off together (ends.widen returns the solve's covariances)",
            ((ends, "widen", _no_widening),)),
)


def run_variant(session: Session, variant: Variant) -> dict:
    """The default smoother on ``session`` with ``variant``'s switches: summary.json's smoother entry, its info,
    and the flapping floor the schedule computed (q [m^2/s^3]; 0 when no wingbeat was found)."""
    floors = []
    with contextlib.ExitStack() as stack:
        for module, name, value in variant.patches:
            stack.enter_context(mock.patch.object(module, name, value))
        floor_fn = schedule.flapping_floor

        def spy(xyz_m, fps):
            floors.append(floor_fn(xyz_m, fps))
            return floors[-1]

        stack.enter_context(mock.patch.object(schedule, "flapping_floor", spy))
        options = dataclasses.replace(Options(progress=False), **dict(variant.options))
        res = run_methods(session, ["smoother"], options)
    return {"summary": res.summary["methods"]["smoother"], "info": res.estimates["smoother"].info,
            "floor_q": floors[-1] if floors else None}


# ==================================================================================================
# the wing-occlusion scene: a bat written from first principles (not batgraph.simulate / batgraph.wingbeat)
# ==================================================================================================
BODY_MARKERS = {"head": (1.0, 0.0, 0.25), "back": (0.1, 0.0, 1.0), "rump": (-1.0, 0.0, 0.3),
                "sternum": (0.3, 0.0, -1.0)}  # directions from the body centre (forward, left, up) to the skin
WING_JOINTS = ("shoulder", "elbow", "wrist", "tip3", "tip5")
OCC_MARKERS = tuple(BODY_MARKERS) + tuple(f"{s}_{j}" for s in "LR" for j in WING_JOINTS)
OCC_BONES = ([("head", "back"), ("back", "rump"), ("back", "sternum")]
             + [pair for s in "LR" for pair in ((("back", f"{s}_shoulder"), (f"{s}_shoulder", f"{s}_elbow"),
                                                 (f"{s}_elbow", f"{s}_wrist"), (f"{s}_wrist", f"{s}_tip3"),
                                                 (f"{s}_wrist", f"{s}_tip5")))])
G_MPS2 = 9.81


def _rot(axis: int, angle: np.ndarray) -> np.ndarray:
    """Rotations about a coordinate axis (0 x, 1 y, 2 z) by ``angle`` (n,) [rad]: (n, 3, 3)."""
    return Rotation.from_euler("xyz"[axis], np.asarray(angle, float).reshape(-1, 1)).as_matrix()


def _draw_bat(rng: np.random.Generator) -> dict:
    """The scene's parameters, drawn per seed: sizes [m], angles [rad], rates [Hz], speeds [m/s]."""
    d = np.deg2rad
    s = rng.uniform(0.9, 1.1)
    return {"flap_hz": rng.uniform(8.0, 12.0), "phase0": rng.uniform(0, 2 * np.pi), "speed": rng.uniform(3.0, 4.5),
            "stroke": d(rng.uniform(80, 120)), "stroke_mean": d(rng.uniform(0, 20)),
            "sweep": d(rng.uniform(5, 15)), "pitch": d(rng.uniform(8, 20)), "heave": rng.uniform(0.002, 0.006),
            "wander": rng.uniform(0.05, 0.15), "wander_hz": rng.uniform(0.3, 0.8), "wander_phase": rng.uniform(0, 6.3),
            "climb": rng.uniform(-0.3, 0.3), "yaw": d(rng.uniform(-10, 10)), "hand_lag": rng.uniform(0.3, 0.9),
            "body_axes": s * np.array([0.035, 0.014, 0.012]), "shoulder": s * np.array([0.012, 0.013, 0.006]),
            "hip": s * np.array([-0.030, 0.012, -0.002]), "bones": s * np.array([0.030, 0.055, 0.085, 0.060])}


def _body_pose(p: dict, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Body centre (F, 3) [m], world_from_body rotations (F, 3, 3) and stroke phase (F,) [rad] at times t (F,) [s].

    Forward along +x through the tunnel's section at t = mid-take, a slow lateral wander, a climb, a heave driven by
    the downstroke's lift (z = -A sin phase: upward acceleration at mid-downstroke), heading along the velocity,
    nose up by the body pitch (+-3 deg with the stroke) and banked into the lateral acceleration."""
    ph = 2 * np.pi * p["flap_hz"] * t + p["phase0"]
    tc = t - t.mean()
    w = 2 * np.pi * p["wander_hz"]
    y = p["wander"] * np.sin(w * tc + p["wander_phase"])
    x = p["speed"] * tc * np.cos(p["yaw"]) - 0.0015 * np.sin(ph + 0.5)
    y = y + p["speed"] * tc * np.sin(p["yaw"])
    z = p["climb"] * tc - p["heave"] * np.sin(ph)
    vy = p["wander"] * w * np.cos(w * tc + p["wander_phase"]) + p["speed"] * np.sin(p["yaw"])
    ay = -p["wander"] * w * w * np.sin(w * tc + p["wander_phase"])
    yaw = np.arctan2(vy, p["speed"] * np.cos(p["yaw"]))
    pitch = p["pitch"] + np.deg2rad(3.0) * np.sin(ph)
    bank = -np.arctan(ay / G_MPS2)
    R = _rot(2, yaw) @ _rot(1, -pitch) @ _rot(0, bank)
    return np.stack([x, y, z], axis=-1), R, ph


def _wing(p: dict, ph: np.ndarray, side: float) -> dict[str, np.ndarray]:
    """One wing's joints in the body frame (F, 3) [m] (side +1 left, -1 right), and the hip anchor of its membrane.

    Stroke: elevation about the body's forward axis, phi = mean + stroke/2 cos(phase) + a second harmonic; sweep
    back about the up axis; pitch (leading edge down on the downstroke) about the lateral axis. In the wing's plane
    the humerus points back, the forearm forward, digits III and V back, every angle opening on the downstroke and
    folding on the upstroke (fold = (1 - sin phase) / 2); the hand wing bends about the forearm, lagging the stroke.
    """
    d = np.deg2rad
    fold = 0.5 * (1.0 - np.sin(ph))
    phi = p["stroke_mean"] + 0.5 * p["stroke"] * np.cos(ph) + 0.08 * p["stroke"] * np.cos(2 * ph)
    sweep = p["sweep"] + d(10.0) * np.sin(ph)
    W = _rot(0, side * phi) @ _rot(2, side * sweep) @ _rot(1, d(10.0) + d(15.0) * np.sin(ph))

    def plane(angle: np.ndarray) -> np.ndarray:  # a unit vector in the wing's plane, ``angle`` forward of lateral
        return np.einsum("fij,fj->fi", W, np.stack([np.sin(angle), side * np.cos(angle), 0 * angle], -1))

    L1, L2, L3, L5 = p["bones"]
    shoulder = np.broadcast_to(p["shoulder"] * [1, side, 1], (len(ph), 3))
    elbow = shoulder + L1 * plane(-(d(20.0) + d(15.0) * fold))
    forearm = plane(d(15.0) + d(40.0) * fold)
    wrist = elbow + L2 * forearm
    hand = Rotation.from_rotvec(forearm * (side * d(20.0) * np.sin(ph - p["hand_lag"]))[:, None]).as_matrix()
    tip3 = wrist + L3 * np.einsum("fij,fj->fi", hand, plane(-(d(10.0) + d(35.0) * fold)))
    tip5 = wrist + L5 * np.einsum("fij,fj->fi", hand, plane(-(d(55.0) + d(20.0) * fold)))
    hip = np.broadcast_to(p["hip"] * [1, side, 1], (len(ph), 3))
    return {"shoulder": shoulder, "elbow": elbow, "wrist": wrist, "tip3": tip3, "tip5": tip5, "hip": hip}


def _skin(axes: np.ndarray, direction: tuple[float, float, float], lift_m: float = 0.0015) -> np.ndarray:
    """The point of the body ellipsoid (semi-axes ``axes`` [m]) along ``direction``, ``lift_m`` out along its normal."""
    d = np.asarray(direction, float)
    s = d / np.sqrt(np.sum((d / axes) ** 2))
    n = s / axes**2
    return s + lift_m * n / np.linalg.norm(n)


def _bat(p: dict, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Markers (F, M, 3) [m] in OCC_MARKERS' order, membrane triangles (F, K, 3, 3) [m], their vertex markers (K, 3)
    (-1: the hip, no marker), and the body's centre (F, 3) and world_from_body rotations (F, 3, 3)."""
    centre, R, ph = _body_pose(p, t)
    F = len(t)
    local = {name: np.broadcast_to(_skin(p["body_axes"], d), (F, 3)) for name, d in BODY_MARKERS.items()}
    tri_names = []
    for s, side in (("L", 1.0), ("R", -1.0)):
        for joint, xyz in _wing(p, ph, side).items():
            local[f"{s}_{joint}"] = xyz
        tri_names += [(f"{s}_shoulder", f"{s}_elbow", f"{s}_tip5"), (f"{s}_elbow", f"{s}_wrist", f"{s}_tip5"),
                      (f"{s}_wrist", f"{s}_tip3", f"{s}_tip5"), (f"{s}_shoulder", f"{s}_tip5", f"{s}_hip")]

    def world(x: np.ndarray) -> np.ndarray:
        return centre + np.einsum("fij,fj->fi", R, x)

    markers = np.stack([world(local[m]) for m in OCC_MARKERS], axis=1)
    tris = np.stack([np.stack([world(local[v]) for v in tri], axis=1) for tri in tri_names], axis=1)
    index = {m: i for i, m in enumerate(OCC_MARKERS)}
    vertex = np.array([[index.get(v, -1) for v in tri] for tri in tri_names])
    return markers, tris, vertex, centre, R


def _tunnel_rig(rng: np.random.Generator, n_cameras: int) -> Rig:
    """Cameras around a tunnel along x (axis through the origin): evenly spread around it (random offset, +-15 deg),
    0.9-1.3 m from the axis, spread along it over +-1.2 m, each aimed at a point of the axis within 0.4 m of its own
    station; 1920 x 1080 px, focal 1000 px, mild barrel distortion."""
    cams = []
    around = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_cameras) / n_cameras
    along = rng.permutation(np.linspace(-1.2, 1.2, n_cameras))
    for i in range(n_cameras):
        a = around[i] + np.deg2rad(rng.uniform(-15, 15))
        r = rng.uniform(0.9, 1.3)
        centre = np.array([along[i], r * np.cos(a), r * np.sin(a)])
        target = np.array([along[i] + rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1)])
        fwd = (target - centre) / np.linalg.norm(target - centre)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right = right / np.linalg.norm(right) if np.linalg.norm(right) > 0.1 else np.array([0.0, -1.0, 0.0])
        R = np.stack([right, np.cross(fwd, right), fwd])  # cam_from_world: x right, y down, z along the view
        K = np.array([[1000.0, 0, 959.5], [0, 1000.0, 539.5], [0, 0, 1]])
        cams.append(Camera(f"t{i + 1}", (1920, 1080), K, np.array([-0.05, 0.01, 0, 0, 0]),
                           Rotation.from_matrix(R).as_rotvec(), -R @ centre))
    return Rig(cams)


def _membrane_hides(origin: np.ndarray, points: np.ndarray, tris: np.ndarray, vertex: np.ndarray) -> np.ndarray:
    """(F, M) bool: the segment from a camera centre ``origin`` (3,) to each marker (F, M, 3) crosses a membrane
    triangle (F, K, 3, 3) that does not have that marker as a vertex (``vertex`` (K, 3)). Moeller-Trumbore."""
    d = points - origin  # (F, M, 3): the whole segment, so a hit at parameter t < 1 lies between them
    v0, e1, e2 = tris[:, :, 0], tris[:, :, 1] - tris[:, :, 0], tris[:, :, 2] - tris[:, :, 0]  # (F, K, 3)
    pvec = np.cross(d[:, :, None], e2[:, None])  # (F, M, K, 3)
    det = np.einsum("fkj,fmkj->fmk", e1, pvec)
    ok = np.abs(det) > 1e-15
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = origin - v0  # (F, K, 3)
    u = np.einsum("fkj,fmkj->fmk", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)  # (F, K, 3)
    v = np.einsum("fmj,fkj->fmk", d, qvec) * inv
    t = np.einsum("fkj,fkj->fk", e2, qvec)[:, None] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1 - 1e-9)
    own = (vertex[None, :, :] == np.arange(points.shape[1])[:, None, None]).any(-1)  # (M, K)
    return (hit & ~own[None]).any(axis=-1)


def _body_hides(origin: np.ndarray, points: np.ndarray, centre: np.ndarray, R: np.ndarray,
                axes: np.ndarray) -> np.ndarray:
    """(F, M) bool: the segment from ``origin`` (3,) to each marker (F, M, 3) [m] passes through the body
    ellipsoid (centre (F, 3), world_from_body (F, 3, 3), semi-axes (3,) [m])."""
    o = np.einsum("fji,fj->fi", R, origin - centre) / axes  # (F, 3): the camera in the unit-sphere frame
    q = np.einsum("fji,fmj->fmi", R, points - centre[:, None]) / axes
    dq = q - o[:, None]
    a, b, c = np.sum(dq * dq, -1), 2 * np.einsum("fmi,fi->fm", dq, o), np.sum(o * o, -1)[:, None] - 1.0
    disc = b * b - 4 * a * c
    t1 = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    return (disc > 0) & (t1 > 0) & (t1 < 1)


def occlusion_scene(rng: np.random.Generator, n_cameras: int = 5, fps: float = 120.0, n_frames: int = 120,
                    pixel_sigma_px: float = 1.0) -> Session:
    """The wing-occlusion scene: a bat (4 body, 2 x 5 wing markers; body ellipsoid; two articulated wings flapping at
    8-12 Hz) flying through a tunnel rig. A marker is seen by a camera when it projects into the image (after 1 px
    Gaussian noise on the raw pixel) and neither a membrane triangle nor the body lies between them. Bones and
    body-fixed pairs are written as ``[markers] rigid``. extra_toml["occlusion"]: the draws and the counts of
    (camera, frame, marker) slots hidden by the membrane, by the body, and outside the image."""
    p = _draw_bat(rng)
    rig = _tunnel_rig(rng, n_cameras)
    t = np.arange(n_frames) / fps
    points, tris, vertex, centre, R = _bat(p, t)
    F, M = points.shape[:2]
    uv_true = np.stack([cam.project(points) for cam in rig])  # (C, F, M, 2) raw pixels, NaN behind / off the lens
    uv = uv_true + pixel_sigma_px * rng.standard_normal(uv_true.shape)
    in_image = np.isfinite(uv_true[..., 0]) & np.stack([cam.in_image(uv[c]) for c, cam in enumerate(rig)])
    membrane = np.stack([_membrane_hides(cam.center_world, points, tris, vertex) for cam in rig])
    body = np.stack([_body_hides(cam.center_world, points, centre, R, p["body_axes"]) for cam in rig])
    seen = in_image & ~membrane & ~body
    c, f, m = np.nonzero(seen)
    obs = pd.DataFrame({"frame": f.astype(np.int64), "camera": np.array(rig.names)[c],
                        "marker": np.array(OCC_MARKERS)[m], "u": uv[c, f, m, 0], "v": uv[c, f, m, 1],
                        "weight": np.ones(len(c))})
    truth = pd.DataFrame({"frame": np.repeat(np.arange(F, dtype=np.int64), M), "marker": np.tile(OCC_MARKERS, F),
                          "x": points[..., 0].ravel(), "y": points[..., 1].ravel(), "z": points[..., 2].ravel()})
    info = {"flap_hz": float(p["flap_hz"]), "speed_mps": float(p["speed"]),
            "hidden_by_membrane": int((in_image & membrane).sum()), "hidden_by_body": int((in_image & body).sum()),
            "outside_image": int((~in_image).sum())}
    return Session(name="wing_occlusion", fps=fps, rig=rig, observations=obs, motion=MotionConfig(),
                   pixel_sigma_px=pixel_sigma_px, marker_names=list(OCC_MARKERS), skeleton=list(OCC_BONES),
                   truth=truth, extra_toml={"occlusion": info}, rigid=list(OCC_BONES))


# ==================================================================================================
# scenes and runs
# ==================================================================================================
@dataclass(frozen=True)
class Scene:
    """One scene of the ablation: its key, how it is made for a seed, and which variants run on it."""

    key: str
    params: str
    make: Callable[[int], Session]
    variants: tuple[str, ...] = tuple(v.key for v in VARIANTS)


def _wb(**kw) -> Callable[[int], Session]:
    return lambda s: simulate_wingbeat(np.random.default_rng(s), **kw)


SCENES = (
    Scene("flight5", "`simulate_flight(n_cameras=5)` (14 markers, 160 frames, 120 fps, 1 px)",
          lambda s: simulate_flight(np.random.default_rng(s), n_cameras=5)),
    Scene("flight5_out", "`simulate_flight(n_cameras=5, outlier_rate=0.05)` (same seeds as flight5)",
          lambda s: simulate_flight(np.random.default_rng(s), n_cameras=5, outlier_rate=0.05),
          ("default", "no_rejection", "no_exclusion", "no_segment_relax")),
    Scene("wingbeat", "`simulate_wingbeat(flight=\"straight\", n_cameras=5, fps=120, n_frames=72, flap_hz=10, "
          "pixel_sigma_px=1)`", _wb(flight="straight", n_cameras=5, fps=120.0, n_frames=72, flap_hz=10.0,
                                    pixel_sigma_px=1.0)),
    Scene("wingbeat_dorsal", "`simulate_wingbeat(flight=\"straight\", n_cameras=4, fps=120, n_frames=96, flap_hz=8, "
          "pixel_sigma_px=2, marker_side=\"dorsal\")`",
          _wb(flight="straight", n_cameras=4, fps=120.0, n_frames=96, flap_hz=8.0, pixel_sigma_px=2.0,
              marker_side="dorsal")),
    Scene("wingbeat_glide", "`simulate_wingbeat(flight=\"glide\", n_cameras=5, fps=60, n_frames=60, "
          "pixel_sigma_px=2)`", _wb(flight="glide", n_cameras=5, fps=60.0, n_frames=60, pixel_sigma_px=2.0)),
    Scene("occlusion", "`occlusion_scene(n_cameras=5, fps=120, n_frames=120, pixel_sigma_px=1)` (this script)",
          lambda s: occlusion_scene(np.random.default_rng(s))),
)


def step_figures(run: dict) -> dict:
    """What each step did on one run, from the smoother's info: the flapping floor (q, markers raised), points
    given a second depth, the ends' c and the points it widened, points raised to the no-view floor, observations
    rejected."""
    info = run["info"]
    ends_ = info.get("track_ends") or {}
    floor = info.get("accel_psd_floor") or {}
    return {"floor_q": run["floor_q"], "floor_markers": len(floor.get("markers", [])),
            "ambiguous": info.get("depth_ambiguous_points", 0), "c": ends_.get("growth_per_frame"),
            "widened": ends_.get("widened_points"), "floored": ends_.get("depth_floored_points"),
            "rejected": info.get("rejected")}


def record(scene: str, seed: int, variant: str, run: dict, seconds: float) -> dict:
    """One flat row: RMSE, coverage and count per group, outlier detection, the steps' figures, the run time."""
    s = run["summary"]
    t = s["truth"]
    out = {"scene": scene, "seed": seed, "method": variant, "runtime_s": seconds}
    for g in ("all", *GROUPS):
        out[f"rmse_{g}"], out[f"cov_{g}"], out[f"n_{g}"] = t["rmse_m"].get(g), t["coverage95"].get(g), t["n"].get(g)
    od = s.get("outlier_detection") or {}
    out.update({f"od_{k}": od.get(k) for k in ("planted", "flagged", "flagged_planted")})
    out.update(step_figures(run))
    return out


def pick(items, patterns: str | None, what: str) -> list:
    """The items whose key matches one of the comma-separated shell patterns (all when None)."""
    if not patterns:
        return list(items)
    pats = [p.strip() for p in patterns.split(",") if p.strip()]
    out = [x for x in items if any(fnmatch.fnmatchcase(x.key, p) for p in pats)]
    if not out:
        raise SystemExit(f"--{what} {patterns!r} matches none of {', '.join(x.key for x in items)}")
    return out


def run_all(scenes: list[Scene], variants: list[Variant], seeds: list[int]) -> tuple[pd.DataFrame, dict]:
    """Every variant of every scene and seed: (records, per scene the points by group and seed, and the
    occlusion scene's hidden-slot counts). Progress goes to stderr, one line per run."""
    recs, facts = [], {}
    chosen = {v.key for v in variants}
    for scene in scenes:
        for seed in seeds:
            session = scene.make(seed)
            for v in VARIANTS:
                if v.key not in scene.variants or v.key not in chosen:
                    continue
                t0 = time.perf_counter()
                run = run_variant(session, v)
                dt = time.perf_counter() - t0
                recs.append(record(scene.key, seed, v.key, run, dt))
                print(f"{scene.key} seed {seed} {v.key}: {dt:.1f} s", file=sys.stderr, flush=True)
            f = facts.setdefault(scene.key, {})
            f[seed] = {g: run["summary"]["truth"]["n"].get(g, 0) for g in GROUPS}
            f[seed]["frames"] = run["summary"]["n_points"] // max(1, len(session.markers))
            f[seed].update(session.extra_toml.get("occlusion", {}))
    return pd.DataFrame(recs), facts


def verdict_of(pooled: str) -> str:
    """The verdict at the end of study.pooled_coverage's text ('PASS', 'FAIL', 'not resolved'), or '—'."""
    return pooled.rsplit(": ", 1)[-1] if ": " in pooled else "—"


def coverage_cells(df: pd.DataFrame, variant: str) -> dict[str, str]:
    """Per group, the coverage pooled over seeds with its exact 95 % interval and verdict on TARGET."""
    return {g: study.pooled_coverage(df, g, *TARGET, method=variant) for g in GROUPS}


def rmse_values(df: pd.DataFrame, variant: str, group: str) -> np.ndarray:
    """RMSE [mm] per seed (seed order), NaN where the group has no point."""
    g = df[df["method"] == variant].sort_values("seed")
    return 1000 * pd.to_numeric(g[f"rmse_{group}"], errors="coerce").to_numpy(float)


RMSE_TOL = 0.01  # an RMSE change smaller than this share of the default's is not counted (one seed has no spread)


def rmse_changed(base: np.ndarray, other: np.ndarray) -> bool:
    """An RMSE change beyond the seeds' spread: the variant's median over seeds outside the default's [min, max],
    widened by RMSE_TOL of the default's median."""
    b, o = base[np.isfinite(base)], other[np.isfinite(other)]
    if not (len(b) and len(o)):
        return False
    tol = RMSE_TOL * np.median(b)
    return bool(not b.min() - tol <= np.median(o) <= b.max() + tol)


def scene_section(key: str, params: str, df: pd.DataFrame, facts: dict) -> list[str]:
    """One scene's tables: pooled coverage with verdicts, RMSE per group, and the points per seed."""
    variants = [v for v in VARIANTS if v.key in set(df["method"])]
    cov_rows, rmse_rows = [], []
    for v in variants:
        cells = coverage_cells(df, v.key)
        cov_rows.append([v.key] + [cells[g] for g in GROUPS])
        rmse_rows.append([v.key] + [study.spread(rmse_values(df, v.key, g)) for g in GROUPS + ("all",)])
    counts = ", ".join(f"{g} {study.spread(np.array([facts[s][g] for s in sorted(facts)], float), 1, 0)}"
                       for g in GROUPS)
    out = [f"## {key}", "", params + ".", "", f"Points per seed (median [min, max]): {counts}.", "",
           "95 % coverage pooled over seeds: k/n = rate [exact 95 % interval]: verdict on [90, 98] %.", "",
           study.markdown_table(["variant", *GROUPS], cov_rows), "",
           "RMSE [mm], median [min, max] over seeds.", "",
           study.markdown_table(["variant", *GROUPS, "all"], rmse_rows), ""]
    if "od_planted" in df and (pd.to_numeric(df["od_planted"], errors="coerce") > 0).any():
        rows = [[v.key] + [study.spread(pd.to_numeric(df[df["method"] == v.key][f"od_{k}"]).to_numpy(float), 1, 0)
                           for k in ("planted", "flagged", "flagged_planted")] for v in variants]
        out += ["Mislabelled observations: planted, flagged as outliers, both (per seed).", "",
                study.markdown_table(["variant", "planted", "flagged", "flagged & planted"], rows), ""]
    return out


STEP_COLUMNS = (("floor_q", "flapping floor q [m^2/s^3]", 2), ("floor_markers", "markers raised to it", 0),
                ("ambiguous", "second-depth points", 0), ("c", "c [1/frame]", 3), ("widened", "c-widened points", 0),
                ("floored", "no-view-floored points", 0), ("rejected", "observations rejected", 0))


def steps_table(df: pd.DataFrame, scenes: list[str]) -> str:
    """What each step did in the default run, per scene: median [min, max] over seeds."""
    rows = []
    for key in scenes:
        g = df[(df["scene"] == key) & (df["method"] == "default")]
        rows.append([key] + [study.spread(pd.to_numeric(g[c], errors="coerce").to_numpy(float), 1, d)
                             for c, _, d in STEP_COLUMNS])
    return study.markdown_table(["scene", *(h for _, h, _ in STEP_COLUMNS)], rows)


def time_ratio(df: pd.DataFrame, variant: str) -> str:
    """The variant's run time over the default's on the same scene and seed: median [min, max] over them."""
    t = df.pivot_table(index=["scene", "seed"], columns="method", values="runtime_s")
    return study.spread((t[variant] / t["default"]).to_numpy(float)) if variant in t else "—"


def changes_table(df: pd.DataFrame, scenes: list[str]) -> tuple[str, str]:
    """Every verdict a variant changes against the default (coverage verdict, or RMSE beyond the seeds' spread), and
    a one-row-per-variant count with the run time against the default's."""
    rows, counts = [], []
    for v in (v for v in VARIANTS[1:] if v.key in set(df["method"])):
        n_cov = n_rmse = 0
        for key in scenes:
            d = df[df["scene"] == key]
            if v.key not in set(d["method"]):
                continue
            base, other = coverage_cells(d, "default"), coverage_cells(d, v.key)
            for g in GROUPS:
                if verdict_of(base[g]) != verdict_of(other[g]):
                    rows.append([v.key, key, f"coverage {g}", base[g], other[g]])
                    n_cov += 1
            for g in GROUPS + ("all",):
                b, o = rmse_values(d, "default", g), rmse_values(d, v.key, g)
                if rmse_changed(b, o):
                    rows.append([v.key, key, f"RMSE {g} [mm]", study.spread(b), study.spread(o)])
                    n_rmse += 1
        counts.append([v.key, v.what, str(n_cov), str(n_rmse), time_ratio(df, v.key)])
    head = ["variant", "scene", "figure", "default", "variant"]
    return (study.markdown_table(head, rows) if rows else "No verdict changes.",
            study.markdown_table(["variant", "step off", "coverage verdicts changed", "RMSE changes",
                                  "run time / default's"], counts))


RULES = ("Groups: status (observed >= 2 views, single_view, unobserved) within span (inside: from a marker's first "
         "to its last frame with >= 2 views; outside: the track's ends). A coverage verdict: PASS when the rate "
         "pooled over seeds lies in [90, 98] %, FAIL when its exact 95 % interval lies wholly outside, \"not "
         "resolved\" otherwise. An RMSE change counts when the variant's median over seeds lies outside the "
         "default's [min, max] over seeds widened by 1 % of its median. Run time: the whole run (preflight and "
         "smoother) against the default's on the same scene and seed, median [min, max] over them (a shared "
         "machine: a rough figure).")


def occlusion_table(facts: dict) -> list[str]:
    """The wing-occlusion scene's draws and hidden slots per seed."""
    rows = [[str(seed)] + [str(f.get(k, "—")) if not isinstance(f.get(k), float) else f"{f[k]:.2f}"
                           for k in ("flap_hz", "speed_mps", "frames", *GROUPS, "hidden_by_membrane",
                                     "hidden_by_body", "outside_image")]
            for seed, f in sorted(facts.items())]
    return ["## The wing-occlusion scene per seed", "",
            "Draws, frames, points per status within span, and (camera, frame, marker) slots hidden by the wing "
            "membrane, by the body, or outside the image.", "",
            study.markdown_table(["seed", "flap [Hz]", "speed [m/s]", "frames", *GROUPS, "hidden by membrane",
                                  "hidden by body", "outside image"], rows), ""]


def build_report(df: pd.DataFrame, facts: dict, scenes: list[Scene], command: str, started: str,
                 elapsed_s: float) -> str:
    """The markdown report (docs/ablation.md); its section study.ABLATION_SUMMARY is what docs/accuracy.md embeds."""
    keys = [s.key for s in scenes if s.key in set(df["scene"])]
    changed, counts = changes_table(df, keys)
    out = ["# Ablation of the smoother's post-solve steps and floors", "",
           "Generated by `make ablation` (`scripts/ablation.py`); do not edit by hand.", "",
           f"* command: `{command}`", f"* date: {started} (wall time {elapsed_s / 60:.1f} min)",
           f"* machine: {study.machine()}", f"* code: git {study.git_state()}", "",
           "Variants (each the default smoother, \"auto\", Huber, segments as the generator writes them, with one "
           "step off; the steps are replaced from outside for the run, batgraph/ unchanged):", ""]
    out += [f"* `{v.key}`: {v.what}" for v in VARIANTS]
    out += ["", study.ABLATION_SUMMARY, "", RULES, "", counts, "", changed, "",
            "## What each step did in the default run", "", steps_table(df, keys), ""]
    for s in scenes:
        if s.key in keys:
            out += scene_section(s.key, s.params, df[df["scene"] == s.key], facts[s.key])
    if "occlusion" in facts:
        out += occlusion_table(facts["occlusion"])
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", help=f"comma-separated seeds (default {DEFAULT_SEEDS})")
    p.add_argument("--scenes", metavar="PATTERNS", help="scene keys or shell patterns, comma-separated (keys: "
                   + ", ".join(s.key for s in SCENES) + ")")
    p.add_argument("--variants", metavar="PATTERNS", help="variant keys or patterns (keys: "
                   + ", ".join(v.key for v in VARIANTS) + "); 'default' is always run")
    p.add_argument("--out", type=Path, help="report path (default docs/ablation.md; with --seeds, --scenes or "
                   "--variants out/ablation_partial.md)")
    p.add_argument("--csv", type=Path, help="also write the per-run records here")
    args = p.parse_args(argv)
    partial = bool(args.seeds or args.scenes or args.variants)
    out = args.out or (ROOT / "out" / "ablation_partial.md" if partial else study.ABLATION_MD)
    seeds = [int(s) for s in (args.seeds or DEFAULT_SEEDS).split(",") if s.strip()]
    scenes = pick(SCENES, args.scenes, "scenes")
    variants = pick(VARIANTS, args.variants, "variants")
    variants = [VARIANTS[0]] + [v for v in variants if v.key != "default"]
    command = " ".join(["python scripts/ablation.py", *(sys.argv[1:] if argv is None else argv)])
    started = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    t0 = time.perf_counter()
    df, facts = run_all(scenes, variants, seeds)
    text = build_report(df, facts, scenes, command, started, time.perf_counter() - t0)
    print(text)
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        df.to_csv(args.csv, index=False)
    atomic.write_text(out, text + "\n")
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
