"""OpenPose-style JSON keypoints (one folder per camera, as Pose2Sim reads them) + Pose2Sim's calibration
-> a batgraph session; no person association or tracking is done here.

Each folder holds one JSON file per frame (OpenPose's ``<video>_<frame:012d>_keypoints.json``,
Pose2Sim's ``cam01.0000.json``): the frame index is the last run of digits in the file name.
``people[person]["pose_keypoints_2d"]`` is a flat list ``x0, y0, c0, x1, y1, c1, ...`` in raw image
pixels (top-left origin, OpenCV's convention) with confidence c; c = 0 means "not detected". Frames
with no such person, or without the key, give no observations. Keypoint names follow Pose2Sim's
skeletons (:data:`KEYPOINT_MODELS`); the real demo data of Pose2Sim are OpenPose BODY_25B.

Pose2Sim's ``Calib_*.toml`` is in aniposelib format (Rodrigues world->camera, metres) and is read as
it is. Pose2Sim's own .trc output is Y-up: ``xyz_world = xyz_trc[..., [2, 0, 1]]``, in metres, and
its ``Frame#`` n is JSON frame n - 1 (checked on Pose2Sim's demo: tests/test_imports.py; read it with
:func:`batgraph.formats.c3d_trc.read_trc`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pandas as pd

from ..errors import InputError
from ..inputs import MAX_FRAME, check_frame_gaps, read_json, read_text
from ..session import Session
from .c3d_trc import read_trc
from .keypoints2d import check_fps, load_rig, make_session, match_cameras, observations_from_arrays

_COCO17 = ["Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
           "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle"]
KEYPOINT_MODELS: dict[str, list[str]] = {
    # OpenPose experimental BODY_25B; ids as in Pose2Sim's skeletons.py (Neck 17, Head 18, feet 19-24)
    "BODY_25B": _COCO17 + ["Neck", "Head", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"],
    # OpenPose standard BODY_25 (mid-hip is Pose2Sim's "CHip")
    "BODY_25": ["Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "CHip",
                "RHip", "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar",
                "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"],
    # AlphaPose / RTMPose HALPE_26
    "HALPE_26": _COCO17 + ["Head", "Neck", "Hip", "LBigToe", "RBigToe", "LSmallToe", "RSmallToe",
                           "LHeel", "RHeel"],
    # OpenPose COCO (18 points)
    "COCO": ["Nose", "Neck", "RShoulder", "RElbow", "RWrist", "LShoulder", "LElbow", "LWrist", "RHip",
             "RKnee", "RAnkle", "LHip", "LKnee", "LAnkle", "REye", "LEye", "REar", "LEar"],
    # MMPose / RTMPose COCO_17
    "COCO_17": _COCO17,
}

_ARMS_LEGS_FACE = [("RShoulder", "RElbow"), ("RElbow", "RWrist"), ("LShoulder", "LElbow"), ("LElbow", "LWrist"),
                   ("RHip", "RKnee"), ("RKnee", "RAnkle"), ("LHip", "LKnee"), ("LKnee", "LAnkle"),
                   ("Nose", "REye"), ("REye", "REar"), ("Nose", "LEye"), ("LEye", "LEar")]
_FEET = [("RAnkle", "RBigToe"), ("RBigToe", "RSmallToe"), ("RAnkle", "RHeel"),
         ("LAnkle", "LBigToe"), ("LBigToe", "LSmallToe"), ("LAnkle", "LHeel")]
_NECK = [("Neck", "RShoulder"), ("Neck", "LShoulder")]
KEYPOINT_SKELETONS: dict[str, list[tuple[str, str]]] = {
    # the bones each model's keypoints are drawn with (Pose2Sim's trees; a hip centre the model lacks, as
    # BODY_25B's, becomes the triangle of the hips and the neck)
    "BODY_25B": _ARMS_LEGS_FACE + _FEET + _NECK + [("Neck", "Head"), ("Head", "Nose"), ("RHip", "LHip"),
                                                   ("Neck", "RHip"), ("Neck", "LHip")],
    "BODY_25": _ARMS_LEGS_FACE + _FEET + _NECK + [("Neck", "Nose"), ("CHip", "RHip"), ("CHip", "LHip"),
                                                  ("CHip", "Neck")],
    "HALPE_26": _ARMS_LEGS_FACE + _FEET + _NECK + [("Neck", "Head"), ("Head", "Nose"), ("Hip", "RHip"),
                                                   ("Hip", "LHip"), ("Hip", "Neck")],
    "COCO": _ARMS_LEGS_FACE + _NECK + [("Neck", "Nose"), ("Neck", "RHip"), ("Neck", "LHip")],
    "COCO_17": _ARMS_LEGS_FACE + [("LShoulder", "RShoulder"), ("RHip", "LHip"), ("RShoulder", "RHip"),
                                  ("LShoulder", "LHip"), ("REar", "RShoulder"), ("LEar", "LShoulder")],
}
"""Each model's bones, written as session.toml's [markers] skeleton: the report and the viewer draw them, and
``batgraph associate`` takes them as segments (their lengths tell keypoints apart where motion cannot)."""


def keypoint_skeleton(keypoints: str | list[str]) -> list[tuple[str, str]]:
    """The bones of a model in :data:`KEYPOINT_SKELETONS` (case-insensitive); none for a custom list of names."""
    return list(KEYPOINT_SKELETONS.get(keypoints.upper(), [])) if isinstance(keypoints, str) else []


def keypoint_names(keypoints: str | list[str]) -> list[str]:
    """Names of a model in :data:`KEYPOINT_MODELS` (case-insensitive), or a custom list as given."""
    if isinstance(keypoints, str):
        key = keypoints.upper()
        if key not in KEYPOINT_MODELS:
            raise InputError(f"keypoints: unknown model {keypoints!r} (known: {', '.join(KEYPOINT_MODELS)}; "
                             f"or pass a list of names)")
        return list(KEYPOINT_MODELS[key])
    names = [str(k) for k in keypoints]
    if len(set(names)) != len(names):
        raise InputError("keypoints: a name appears more than once")
    return names


def _frame_number(path: Path) -> int:
    digits = re.findall(r"\d+", path.name[: -len(".json")])
    if not digits:
        raise InputError(f"{path}: no frame number in the file name")
    if int(digits[-1]) > MAX_FRAME:
        raise InputError(f"{path}: frame number {digits[-1]} in the file name is larger than {MAX_FRAME:,}")
    return int(digits[-1])


def read_openpose_folder(folder: str | Path, names: list[str], person: int = 0,
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read one camera's folder of OpenPose JSON.

    names: keypoint names, length K (the JSON must hold 3 K numbers per person).
    Returns frames (F,), uv_px (F, K, 2) [raw px, NaN where the person is absent] and
    confidence (F, K) (0 where absent).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: folder not found")
    files = sorted(folder.glob("*.json"))
    if not files:
        raise InputError(f"{folder}: no .json files")
    frames = np.array([_frame_number(p) for p in files], np.int64)
    check_frame_gaps(frames, folder, False, where=lambda i: str(files[i]))
    if len(set(frames)) != len(frames):
        dup = frames[np.argmax(np.unique(frames, return_counts=True)[1] > 1)]
        raise InputError(f"{folder}: frame {dup} appears in two file names")
    K = len(names)
    flat = np.full((len(files), 3 * K), np.nan)
    for i, p in enumerate(files):
        doc = read_json(p)
        people = doc.get("people") if isinstance(doc, dict) else None
        if not isinstance(people, list):
            raise InputError(f"{p}: missing key 'people' (not OpenPose JSON)")
        if person < len(people) and not isinstance(people[person], dict):
            raise InputError(f"{p}: people[{person}] is not an object {{...}} (not OpenPose JSON)")
        if person >= len(people) or "pose_keypoints_2d" not in people[person]:
            continue  # nobody (or not this person) on this frame
        kp = people[person]["pose_keypoints_2d"]
        if not isinstance(kp, list):
            raise InputError(f"{p}: people[{person}].pose_keypoints_2d is not a list of numbers")
        if len(kp) == 0:
            continue
        if len(kp) != 3 * K:
            raise InputError(f"{p}: people[{person}].pose_keypoints_2d has {len(kp)} numbers, expected "
                             f"3 x {K} for {K} keypoints (wrong keypoints model?)")
        try:
            if any(isinstance(x, bool) for x in kp):
                raise TypeError
            flat[i] = np.asarray(kp, dtype=float)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{p}: people[{person}].pose_keypoints_2d holds a non-number") from None
    order = np.argsort(frames, kind="stable")
    vals = flat[order].reshape(len(files), K, 3)
    conf = np.nan_to_num(vals[..., 2], nan=0.0)
    return frames[order], vals[..., :2], conf


def import_pose2sim(json_dirs: list[str | Path] | str | Path, calibration: str | Path, fps: float,
                    out: str | Path | None, keypoints: str | list[str] = "BODY_25B", threshold: float = 0.3,
                    camera_names: list[str] | None = None, person: int = 0, name: str | None = None,
                    reference_trc: str | Path | None = None, pixel_sigma_px: float | None = None,
                    units: str | None = None) -> Session:
    """Import per-camera folders of OpenPose JSON (Pose2Sim's pose/ or pose-associated/) into a session.

    json_dirs: one folder per camera, or one folder whose sub-folders (sorted) are the cameras.
    calibration: Pose2Sim's Calib_*.toml (aniposelib format). fps: frame rate [Hz].
    keypoints: a model name of :data:`KEYPOINT_MODELS` or the list of names in JSON order.
    threshold: minimum confidence kept (Pose2Sim's likelihood_threshold_triangulation is 0.3).
    camera_names: calibration camera of each folder; None = matched from folder names
        (:mod:`batgraph.formats.keypoints2d`). person: index in ``people`` (0 = first / only).
    reference_trc: Pose2Sim's own 3D (pose-3d/*.trc), kept as the session's reference_xyz.csv so
        reports compare against it. Pose2Sim writes Y-up TRCs (its zup2yup); batgraph's world is the
        calibration's (Z-up): world = trc[..., [2, 0, 1]]. TRC Frame# n is JSON frame n - 1.
    pixel_sigma_px: keypoint noise [px]; None (default): reconstruct measures it per camera.
    units: the calibration's translation units (see keypoints2d.load_rig).
    """
    fps = check_fps(fps)
    names = keypoint_names(keypoints)
    calib, rig = load_rig(calibration, units)
    if isinstance(json_dirs, str | Path):
        root = Path(json_dirs)
        if not root.is_dir():
            raise InputError(f"{root}: folder not found")
        dirs = sorted(p for p in root.iterdir() if p.is_dir())
        if not dirs:
            raise InputError(f"{root}: no camera sub-folders")
    else:
        dirs = [Path(d) for d in json_dirs]
    for d in dirs:
        if not d.is_dir():
            raise InputError(f"{d}: folder not found")
    cams = match_cameras(dirs, rig, camera_names, calib)
    tables = []
    for d, cam in zip(dirs, cams, strict=True):
        frames, uv, conf = read_openpose_folder(d, names, person)
        tables.append(observations_from_arrays(cam, frames, names, uv, conf, threshold))
    label = name or (Path(out).name if out is not None else dirs[0].parent.name)
    reference = None
    if reference_trc is not None:
        read_text(reference_trc)  # encoding, permission and existence through the reader layer; read_trc parses
        trc = read_trc(reference_trc)
        xyz = trc.xyz_m[..., [2, 0, 1]]  # undo Pose2Sim's zup2yup
        F, M = xyz.shape[:2]
        reference = pd.DataFrame({"frame": np.repeat(trc.frame - 1, M), "marker": np.tile(trc.markers, F),
                                  "x": xyz[..., 0].ravel(), "y": xyz[..., 1].ravel(), "z": xyz[..., 2].ravel()})
        reference = reference.dropna().reset_index(drop=True)
    return make_session(label, fps, rig, tables, names, out, ", ".join(map(str, dirs)), reference=reference,
                        pixel_sigma_px=pixel_sigma_px, skeleton=keypoint_skeleton(keypoints))
