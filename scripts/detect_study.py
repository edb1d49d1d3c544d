#!/usr/bin/env python3
"""Footage to names: simulated scenes rendered as video (batgraph.render), `batgraph detect`, `batgraph associate`.

Per case: a simulated session's observations (the blobs' true centres, 1 px of noise) drawn as Gaussian blobs into
every camera's frames (a textured background with static lamps, 2 gray levels of noise; FFV1, lossless, or with
``--codec mp4`` MPEG-4, lossy); `batgraph detect` finds the blobs; each detection takes the marker whose centre lies
within 1 px ('merged' where two or more lie within 8 px and none within 1 px, else 'spurious'); every blob of one
marker on one seed frame is clicked; `batgraph associate` names them, and `reconstruct --methods smoother` runs on the
names and on the true observations. The same case through the generator's detections (batgraph.associate.scenes:
2 % spurious, blobs within 3 px merged) is the baseline, in the same run. Also: OpenCV's SimpleBlobDetector's centres
on the same background-subtracted frames of the first camera, against detect's.

Usage: ``python scripts/detect_study.py [--scenes flight14,flight24,wingbeat] [--seeds 0,1,2] [--codec avi|mp4]``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from batgraph.associate import scenes, score  # noqa: E402
from batgraph.cli import main  # noqa: E402
from batgraph.detect import MIN_THRESHOLD, NOISE_SIGMAS, BlobOptions, background_of, contrast  # noqa: E402
from batgraph.formats.csv_text import write_csv  # noqa: E402
from batgraph.frames import Recording  # noqa: E402
from batgraph.render import render_session  # noqa: E402
from batgraph.session import write_session  # noqa: E402

sys.path.insert(0, str(ROOT / "scripts"))
from associate_study import cases, row_line, run_case, simulate, smoother_rmse  # noqa: E402

ALONE_PX = 8.0  # a blob with no other marker's centre this near is alone (its detection is not a merge)


def truth_of(detections: pd.DataFrame, obs: pd.DataFrame) -> tuple[pd.DataFrame, np.ndarray]:
    """Per detection: (marker, kind) as scenes.Scene.truth, and its distance to the nearest true centre [px]."""
    marker = np.full(len(detections), "", object)
    kind = np.full(len(detections), "spurious", object)
    dist = np.full(len(detections), np.inf)
    obs_by = {k: g for k, g in obs.groupby(["frame", "camera"])}
    for key, g in detections.groupby(["frame", "camera"]):
        o = obs_by.get(key)
        if o is None:
            continue
        tree = cKDTree(o[["u", "v"]].to_numpy())
        uv = g[["u", "v"]].to_numpy()
        d, j = tree.query(uv)
        rows = detections.index.get_indexer(g.index)
        dist[rows] = d
        names = o["marker"].to_numpy()
        for r, dd, jj, p in zip(rows, d, j, uv, strict=True):
            if dd < 1.0:
                marker[r], kind[r] = names[jj], "marker"
            else:
                near = tree.query_ball_point(p, ALONE_PX)
                if len(near) >= 2:
                    marker[r], kind[r] = "+".join(sorted(names[near])), "merged"
    return pd.DataFrame({"marker": marker, "kind": kind}), dist


def alone(obs: pd.DataFrame) -> np.ndarray:
    """Mask of the observations with no other marker's centre within ALONE_PX in their camera and frame."""
    out = np.zeros(len(obs), bool)
    for _, g in obs.groupby(["frame", "camera"]):
        uv = g[["u", "v"]].to_numpy()
        d = np.hypot(*(uv[:, None] - uv[None]).transpose(2, 0, 1))
        np.fill_diagonal(d, np.inf)
        out[obs.index.get_indexer(g.index)] = d.min(axis=1) > ALONE_PX
    return out


def centre_errors(obs: pd.DataFrame, found: pd.DataFrame) -> np.ndarray:
    """Each lone observation's distance to the nearest of ``found`` in its camera and frame [px] (inf: none)."""
    lone = obs[alone(obs)]
    out = np.full(len(lone), np.inf)
    for key, g in lone.groupby(["frame", "camera"]):
        d = found[(found["frame"] == key[0]) & (found["camera"] == key[1])]
        if len(d):
            out[lone.index.get_indexer(g.index)] = cKDTree(d[["u", "v"]].to_numpy()).query(g[["u", "v"]].to_numpy())[0]
    return out


def simple_blob_detector(path: Path, camera: str) -> pd.DataFrame:
    """OpenCV's SimpleBlobDetector on detect's contrast images (the same background subtracted), its defaults
    but the shape filters off and detect's threshold and area bounds."""
    opts = BlobOptions()
    rec = Recording.open(path)
    background, noise = background_of(rec, opts)
    threshold = max(NOISE_SIGMAS * noise, MIN_THRESHOLD)  # detect's default, as it finds it for this camera
    p = cv2.SimpleBlobDetector_Params()
    p.minThreshold, p.maxThreshold, p.thresholdStep = threshold, 255.0, 10.0
    p.filterByColor, p.blobColor = True, 255
    p.filterByArea, p.minArea, p.maxArea = True, float(opts.min_area_px), float(opts.max_area_px)
    p.filterByCircularity = p.filterByConvexity = p.filterByInertia = False
    det = cv2.SimpleBlobDetector_create(p)
    rows = []
    for k, frame in rec.frames():
        img = np.clip(contrast(frame, background, "bright"), 0, 255).astype(np.uint8)
        rows += [(k, camera, kp.pt[0], kp.pt[1]) for kp in det.detect(img)]
    return pd.DataFrame(rows, columns=["frame", "camera", "u", "v"])


def run_footage(scene: str, seed: int, work: Path, codec: str) -> dict:
    session = simulate(scene, seed)
    obs = session.observations.reset_index(drop=True)
    case = work / f"{scene}_{seed}"
    t0 = time.perf_counter()
    footage = render_session(session.rig, obs, int(obs["frame"].max()) + 1, case / "footage",
                             np.random.default_rng(2000 + seed), video=f".{codec}")
    render_s = time.perf_counter() - t0
    folder = case / "input"
    write_session(session, folder)
    (folder / "observations.csv").unlink()
    t0 = time.perf_counter()
    assert main(["detect", *map(str, footage), "--out", str(folder / "detections.csv"), "--quiet"]) == 0
    detect_s = time.perf_counter() - t0
    det = pd.read_csv(folder / "detections.csv")
    size_mb = sum(p.stat().st_size for p in footage) / 1e6
    truth, _ = truth_of(det, obs)
    err = centre_errors(obs, det)
    seed_frame = scenes.seed_frames(obs, 1)[0]
    one = (truth["kind"] == "marker").to_numpy() & (det["frame"] == seed_frame).to_numpy()
    # every blob of one marker on the seed frame clicked (a merged one is not), as the generator's scenes do
    click = det[one].assign(marker=truth["marker"][one].to_numpy())[["frame", "camera", "marker", "u", "v"]]
    write_csv(folder / "seed_labels.csv", click, "%.6f")
    t0 = time.perf_counter()
    assert main(["associate", str(folder), "--out", str(case / "associated")]) == 0
    associate_s = time.perf_counter() - t0
    labels = pd.read_csv(case / "associated" / "labels.csv", keep_default_na=False)
    figures = score.score(truth, det["frame"].to_numpy(), labels["marker"].astype(str).to_numpy(), session.fps,
                          len(session.marker_names))
    right = (labels["marker"].astype(str).to_numpy() == truth["marker"].to_numpy()) & (truth["kind"] == "marker")
    write_session(session, case / "true_labels")
    rmse_true = smoother_rmse(case / "true_labels", case / "true_labels" / "out")
    rmse = smoother_rmse(case / "associated", case / "associated" / "out")
    cam = session.rig.names[0]
    sbd = simple_blob_detector(footage[0], cam)
    mine = obs["camera"] == cam
    sbd_err = centre_errors(obs[mine].reset_index(drop=True), sbd)
    own_err = centre_errors(obs[mine].reset_index(drop=True), det)
    shutil.rmtree(case / "footage")  # 300 MB a case
    return {"scene": scene, "seed": seed, "codec": codec, "footage_MB": size_mb, "render_s": render_s,
            "detect_s": detect_s, "associate_s": associate_s, "observations": len(obs), "detections": len(det),
            "lone_found": float((np.isfinite(err) & (err < 1.0)).mean()),
            "centre_err_median_px": float(np.median(err[np.isfinite(err)])),
            "centre_err_p95_px": float(np.percentile(err[np.isfinite(err)], 95)),
            "sbd_err_median_px": float(np.median(sbd_err[sbd_err < 2])), "sbd_err_p95_px":
                float(np.percentile(sbd_err[sbd_err < 2], 95)), "own_err_median_px_cam1": float(np.median(
                    own_err[own_err < 2])),
            "named_correctly_of_observations": float(right.sum() / len(obs)), **figures,
            "rmse_ratio": rmse / rmse_true}


def main_study(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", default="flight14,flight24,wingbeat")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--codec", choices=["avi", "mp4"], default="avi", help="avi: FFV1 (lossless); mp4: MPEG-4 (lossy)")
    p.add_argument("--out", help="keep the case folders here, less their footage (default: a temporary folder)")
    p.add_argument("--no-baseline", action="store_true", help="skip the generator's detections (the baseline)")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        for scene, seed in cases(args.scenes, args.seeds):
            row = run_footage(scene, seed, work, args.codec)
            if not args.no_baseline:
                base = run_case(scene, seed, work / "generator")
                row.update(base_correct=base["real_correct"], base_wrong=base["real_wrong"],
                           base_rmse_ratio=base["rmse_ratio"], base_associate_s=base["associate_s"])
            rows.append(row)
            print(row_line(row), flush=True)
    table = pd.DataFrame(rows)
    cols = ["lone_found", "centre_err_median_px", "centre_err_p95_px", "sbd_err_median_px",
            "own_err_median_px_cam1", "named_correctly_of_observations", "real_correct", "real_wrong",
            "spurious_unnamed", "rmse_ratio", "base_correct", "base_wrong", "base_rmse_ratio", "detect_s",
            "associate_s", "base_associate_s"]
    print("\nmedians over seeds:")
    cols = [c for c in cols if c in table]
    print(table.groupby("scene")[cols].median().T.to_string(float_format=lambda x: f"{x:.4g}"))
    return 0


if __name__ == "__main__":
    sys.exit(main_study())
