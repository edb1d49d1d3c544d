"""Test scenes for association: a simulated session's observations with their labels stripped, spurious blobs
added and the blobs of two markers merged where they overlap in an image; with the truth of every detection.

Takes a :class:`batgraph.session.Session` from either generator (batgraph.simulate, batgraph.wingbeat) and
returns detections as a detector would write them, the true label of each, and a seed frame as a user would
click it. All randomness comes from the ``np.random.Generator`` passed in. Scores nothing (batgraph.associate.score).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ..formats.csv_text import write_csv
from ..session import Session, write_session

BLOB_AREA_PX2 = 8.0  # a marker blob of ~3 px across (5 mm at 1 m, 640 px focal length)
NEAR_FRACTION = 0.5  # spurious blobs inside the bat's box in the image (reflections on it); the rest anywhere


@dataclass
class SceneOptions:
    """spurious_rate: spurious blobs per real detection; merge_px: two markers whose blobs' centres are closer than
    this in an image give one blob at their mean (0: never); seed_frames: the frames a user labels, or how many
    (:func:`seed_frames` picks them)."""

    spurious_rate: float = 0.02
    merge_px: float = 3.0
    seed_frames: int | tuple[int, ...] = 1


@dataclass
class Scene:
    """detections: frame, camera, u, v, size (a detector's output, in frame order).
    truth: per detection row, ``marker`` (its true marker; '' for a spurious blob; 'a+b' for a merged one) and
    ``kind`` ('marker', 'spurious', 'merged'). seed: frame, camera, marker, u, v of every real, unmerged
    detection on the seed frames."""

    detections: pd.DataFrame
    truth: pd.DataFrame
    seed: pd.DataFrame


def _merge(obs: pd.DataFrame, merge_px: float) -> tuple[pd.DataFrame, np.ndarray]:
    """Blobs closer than merge_px in one camera and frame merged pairwise (closest first): (rows, kind)."""
    rows, kinds = [], []
    for (_, _), g in obs.groupby(["frame", "camera"], sort=False):
        uv = g[["u", "v"]].to_numpy()
        d = np.hypot(*(uv[:, None] - uv[None]).transpose(2, 0, 1))
        np.fill_diagonal(d, np.inf)
        used = np.zeros(len(g), bool)
        markers = g["marker"].to_numpy()
        for k in np.argsort(d, axis=None):
            i, j = divmod(int(k), len(g))
            if d[i, j] >= merge_px:
                break
            if used[i] or used[j]:
                continue
            used[i] = used[j] = True
            a, b = sorted((markers[i], markers[j]))
            rows.append((g["frame"].iloc[0], g["camera"].iloc[0], *((uv[i] + uv[j]) / 2), 1.6 * BLOB_AREA_PX2,
                         f"{a}+{b}"))
            kinds.append("merged")
        for i in np.flatnonzero(~used):
            rows.append((g["frame"].iloc[0], g["camera"].iloc[0], uv[i, 0], uv[i, 1], BLOB_AREA_PX2, markers[i]))
            kinds.append("marker")
    out = pd.DataFrame(rows, columns=["frame", "camera", "u", "v", "size", "marker"])
    return out, np.array(kinds, dtype=object)


def _spurious(obs: pd.DataFrame, session: Session, n: int, rng: np.random.Generator) -> pd.DataFrame:
    """n blobs on random (frame, camera) slots that have detections: NEAR_FRACTION inside the box of that
    slot's blobs (grown by 20 %), the rest uniform over the image."""
    slots = obs.groupby(["frame", "camera"], sort=False)[["u", "v"]].agg(["min", "max"]).reset_index()
    pick = slots.iloc[rng.integers(0, len(slots), n)]
    wh = np.array([session.rig[c].size_wh for c in pick["camera"]], float)
    lo = np.stack([pick[("u", "min")], pick[("v", "min")]], axis=1)
    hi = np.stack([pick[("u", "max")], pick[("v", "max")]], axis=1)
    pad = 0.1 * (hi - lo) + 5.0
    near = lo - pad + rng.random((n, 2)) * (hi - lo + 2 * pad)
    anywhere = rng.random((n, 2)) * wh - 0.5
    uv = np.where((rng.random(n) < NEAR_FRACTION)[:, None], near, anywhere)
    uv = np.clip(uv, -0.5, wh - 0.5)
    return pd.DataFrame({"frame": pick["frame"].to_numpy(), "camera": pick["camera"].to_numpy(), "u": uv[:, 0],
                         "v": uv[:, 1], "size": rng.uniform(0.3, 2.0, n) * BLOB_AREA_PX2, "marker": ""})


def seed_frame(obs: pd.DataFrame) -> int:
    """The frame a user would label: where the most markers are seen by three cameras or more (of equals, the one
    nearest the middle of the recording)."""
    views = obs.groupby(["frame", "marker"]).size()
    per_frame = (views >= 3).groupby(level="frame").sum()
    best = per_frame[per_frame == per_frame.max()].index.to_numpy()
    middle = (obs["frame"].min() + obs["frame"].max()) / 2
    return int(best[np.argmin(np.abs(best - middle))])


def seed_frames(obs: pd.DataFrame, n: int) -> list[int]:
    """The frames a user labels to name the markers from n frames: the recording cut into n equal parts, and in each
    the frame :func:`seed_frame` picks (n = 1: that frame)."""
    cuts = np.linspace(obs["frame"].min(), obs["frame"].max() + 1, n + 1)
    parts = zip(cuts[:-1], cuts[1:], strict=True)
    return [seed_frame(obs[(obs["frame"] >= a) & (obs["frame"] < b)]) for a, b in parts]


def strip_labels(session: Session, seed_at: int | None = None) -> Scene:
    """A labelled session (real data: its identities are the truth) as a scene: its observations without their
    markers, in frame order, and every observation of one frame as the seed (``seed_at``, default
    :func:`seed_frame`)."""
    obs = session.observations
    table = pd.DataFrame({"frame": obs["frame"].to_numpy(), "camera": obs["camera"].to_numpy(),
                          "u": obs["u"].to_numpy(), "v": obs["v"].to_numpy(), "marker": obs["marker"].to_numpy(),
                          "kind": "marker"}).sort_values("frame", kind="stable").reset_index(drop=True)
    frame = seed_frame(obs) if seed_at is None else int(seed_at)
    seed = table[table["frame"] == frame][["frame", "camera", "marker", "u", "v"]]
    return Scene(table[["frame", "camera", "u", "v"]], table[["marker", "kind"]],
                 seed.sort_values(["camera", "marker"]).reset_index(drop=True))


def make_scene(session: Session, rng: np.random.Generator, options: SceneOptions | None = None) -> Scene:
    """Detections, truth and a seed from a simulated session (see module docstring)."""
    o = options or SceneOptions()
    obs = session.observations[["frame", "camera", "marker", "u", "v"]].copy()
    if o.merge_px > 0:
        real, kind = _merge(obs, o.merge_px)
    else:
        real = obs.assign(size=BLOB_AREA_PX2)[["frame", "camera", "u", "v", "size", "marker"]]
        kind = np.full(len(real), "marker", dtype=object)
    real = real.assign(kind=kind)
    n_spurious = int(round(o.spurious_rate * len(real)))
    fake = _spurious(obs, session, n_spurious, rng).assign(kind="spurious") if n_spurious else real.iloc[:0]
    table = pd.concat([real, fake], ignore_index=True)
    table = table.iloc[rng.permutation(len(table))]  # a detector lists blobs in no particular order within a frame
    table = table.sort_values("frame", kind="stable").reset_index(drop=True)
    frames = seed_frames(obs, o.seed_frames) if isinstance(o.seed_frames, int) else list(o.seed_frames)
    seed = table[table["frame"].isin(frames) & (table["kind"] == "marker")][["frame", "camera", "marker", "u", "v"]]
    return Scene(table[["frame", "camera", "u", "v", "size"]], table[["marker", "kind"]],
                 seed.sort_values(["frame", "camera", "marker"]).reset_index(drop=True))


def write_scene(session: Session, scene: Scene, folder) -> None:
    """A session folder of the scene as a user would have it: session.toml, calibration.toml, detections.csv,
    seed_labels.csv, truth.csv (the 3D truth) and truth_labels.csv (each detection's true marker and kind, in
    detections.csv's order)."""
    folder = Path(folder)
    write_session(session, folder)
    (folder / "observations.csv").unlink()
    write_csv(folder / "detections.csv", scene.detections, "%.6f")
    write_csv(folder / "seed_labels.csv", scene.seed, "%.6f")
    scene.truth.to_csv(folder / "truth_labels.csv", index=False)
