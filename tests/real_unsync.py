"""Real genlocked data made into an unsynchronised rig with exactly known offsets (for the timing tests).

:func:`unsynchronise` keeps every n-th frame of a session whose cameras expose together, with a different phase per
camera: camera c keeps the frames f = n j + p_c, its own frame j, so at the new rate fps / n its frames are exposed
``p_c / fps`` after the reference camera's (p_c = 0, 1, 2, 3 and n = 5: 0, 0.2, 0.4, 0.6 of a new frame). That
is what synchronising cameras to the nearest whole frame leaves, with the truth known exactly.

The real rigs: :func:`mcsc_session` (the MCSC LED rig: 4 cameras, one LED waved through the volume, 464 frames in
which it moves 13 px per frame (median) against 0.3 px of detection noise: the one real set here with enough
frames and motion; the issue's 700 fps bat rig is not available) and :func:`pose2sim_session` (100 frames of a
person balancing, OpenPose keypoints: slow and 5-16 px noisy, the check of a quiet result).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import real_dlt

from batgraph.camera import Camera, Rig
from batgraph.session import Session, retime

REAL = real_dlt.REAL


def mcsc_session() -> Session:
    """The MCSC LED rig as a session: pinholes from its projection matrices (undistorted clicks, OpenCV pixels),
    its published 3D as the reference (on the frames MCSC triangulated), 100 fps nominal (its rate is not known)."""
    return dlt_rig_session(real_dlt.load_mcsc(), "mcsc")


def dlt_rig_session(rig: real_dlt.RealRig, name: str) -> Session:
    """A session of a real DLT rig (tests/real_dlt.RealRig): pinholes from its projection matrices, its undistorted
    clicks as observations (markers m0.., "led" for one), its published 3D as the reference, its nominal fps."""
    h, w = rig.image_hw
    cams = [Camera.from_dlt(f"cam{c + 1}", (rig.P[c] / rig.P[c][2, 3]).reshape(-1)[:11], (w, h))
            for c in range(len(rig.P))]
    F, M, C = rig.uv.shape[:3]
    names = np.array(["led"] if M == 1 else [f"m{k}" for k in range(M)])
    f, m, c = np.nonzero(np.isfinite(rig.uv[..., 0]))
    obs = pd.DataFrame({"frame": f.astype(np.int64), "camera": np.array([k.name for k in cams])[c],
                        "marker": names[m], "u": rig.uv[f, m, c, 0], "v": rig.uv[f, m, c, 1], "weight": 1.0})
    obs = obs.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True)
    ff, mm = np.nonzero(np.isfinite(rig.xyz[..., 0]))
    ref = pd.DataFrame({"frame": ff.astype(np.int64), "marker": names[mm], "x": rig.xyz[ff, mm, 0],
                        "y": rig.xyz[ff, mm, 1], "z": rig.xyz[ff, mm, 2]})
    return Session(name, rig.fps, Rig(cams), obs, pixel_sigma_px=None, marker_names=list(names), reference=ref)


def pose2sim_session(tmp: Path) -> Session:
    """The Pose2Sim demo (4 cameras, 100 frames at 60 fps) imported as a user would, into ``tmp``."""
    from batgraph.formats.pose2sim import import_pose2sim

    base = real_dlt.real_folder("pose2sim_demo_4cam_human")
    trial = base / "S00_P00_SingleParticipant" / "S00_P00_T01_BalancingTrial"
    dirs = sorted((trial / "pose-associated").iterdir())
    trc = sorted((trial / "pose-3d").glob("*_0-100.trc"))[0]
    return import_pose2sim(dirs, base / "S00_Calibration" / "Calib_qualisys.toml", 60.0, Path(tmp) / "pose2sim",
                           reference_trc=trc)


def unsynchronise(session: Session, n: int = 5, phases: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[Session, Session]:
    """(the offsets given, the offsets ignored): every n-th frame of a synchronised session, camera c at phase
    ``phases[c % len(phases)]`` (module docstring). Both sessions hold each camera's own new frame numbers, at
    fps / n; the first's rig states ``time_offset_s = phase / fps``, the second's nothing. The reference 3D keeps
    the frames of the new session clock (old frame n k is new frame k)."""
    fps = session.fps
    obs = session.observations
    names = session.rig.names
    phase = {name: int(phases[c % len(phases)]) for c, name in enumerate(names)}
    p = obs["camera"].map(phase).to_numpy()
    keep = (obs["frame"].to_numpy() - p) % n == 0
    own = obs[keep].assign(frame=(obs["frame"].to_numpy()[keep] - p[keep]) // n)
    own = own[own["frame"] >= 0].reset_index(drop=True)
    if "camera_frame" in own:
        own = own.drop(columns="camera_frame")
    ref = None
    if session.reference is not None:
        r = session.reference
        ref = r[r["frame"] % n == 0].assign(frame=lambda t: t["frame"] // n).reset_index(drop=True)
    ignored = Session(f"{session.name}_unsync", fps / n, Rig([Camera(c.name, c.size_wh, c.K, c.dist, c.rvec, c.tvec)
                                                              for c in session.rig], session.rig.world_mirror),
                      own.sort_values(["frame", "camera", "marker"], kind="stable").reset_index(drop=True),
                      pixel_sigma_px=session.pixel_sigma_px, marker_names=list(session.marker_names),
                      skeleton=list(session.skeleton), reference=ref)
    given_rig = Rig([Camera(c.name, c.size_wh, c.K, c.dist, c.rvec, c.tvec, time_offset_s=phase[c.name] / fps)
                     for c in ignored.rig], ignored.rig.world_mirror)
    return retime(ignored, given_rig), ignored
