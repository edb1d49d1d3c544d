"""Draw the README's picture from a reconstruct result of the bundled flight sample.

    batgraph reconstruct data/samples/flight_5cam --out out/flight_5cam --viewer none --quiet
    python docs/make_figure.py data/samples/flight_5cam out/flight_5cam docs/images/flight.png

Left: the smoother's 3D of every marker with the skeleton and each marker's track over +-12 frames, on a
frame with most markers seen by >= 2 cameras and the wings spread. Right: one wrist marker's height over the
flight with its 95 % band, the simulator's truth, and the frames where fewer than two cameras saw it.
"""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

STATUS_COLOURS = {"observed": "#2ca02c", "single_view": "#ff9f1c", "unobserved": "#d62728"}


def _wings_spread(sm: pd.DataFrame) -> int:
    """A frame where >= 90 % of the markers are seen by >= 2 cameras (else the best), wings spread widest."""
    seen = sm.groupby("frame")["status"].apply(lambda s: (s == "observed").mean())
    good = seen.index[seen >= min(0.9, seen.max())]
    xyz = sm[sm["frame"].isin(good)].pivot(index="frame", columns="marker", values=["x", "y", "z"])
    width = xyz["y"].max(axis=1) - xyz["y"].min(axis=1)
    return int(width.idxmax())


def main(session: Path, out: Path, png: Path) -> None:
    traj = pd.read_csv(out / "trajectories.csv")
    sm = traj[traj["method"] == "smoother"]
    markers = list(dict.fromkeys(sm["marker"]))
    skeleton = tomllib.loads((session / "session.toml").read_text()).get("markers", {}).get("skeleton", [])
    frame = _wings_spread(sm)
    fig = plt.figure(figsize=(11, 4.4), dpi=100)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    near = sm[(sm["frame"] - frame).abs() <= 12]
    for m in markers:
        one = near[near["marker"] == m]
        ax.plot(one["x"], one["y"], one["z"], color="0.6", linewidth=0.6)
    now = sm[sm["frame"] == frame].set_index("marker")
    for a, b in skeleton:
        ax.plot(*now.loc[[a, b], ["x", "y", "z"]].to_numpy().T, color="k", linewidth=1.2)
    for status, colour in STATUS_COLOURS.items():
        pts = now[now["status"] == status]
        if len(pts):
            ax.scatter(pts["x"], pts["y"], pts["z"], color=colour, s=12, label=status.replace("_", " "))
    ax.set_title(f"the smoother's 3D at frame {frame}: skeleton and tracks of +-12 frames", fontsize=9)
    for label, set_label in (("x [m]", ax.set_xlabel), ("y [m]", ax.set_ylabel), ("z [m]", ax.set_zlabel)):
        set_label(label, fontsize=8)
    ax.tick_params(labelsize=7)
    ax.set_box_aspect(np.ptp(near[["x", "y", "z"]].dropna().to_numpy(), axis=0))
    ax.view_init(elev=35, azim=-125)
    ax.legend(fontsize=7, loc="upper left", frameon=False)

    marker = "wrist_r" if "wrist_r" in markers else markers[0]
    one = sm[sm["marker"] == marker].sort_values("frame")
    t = one["time_s"].to_numpy()
    z, sd = one["z"].to_numpy() * 1e3, np.sqrt(one["cov_zz"].to_numpy()) * 1e3
    bx = fig.add_subplot(1, 2, 2)
    for status, colour in STATUS_COLOURS.items():
        if status == "observed":
            continue
        hit = (one["status"] == status).to_numpy()
        if not hit.any():
            continue
        bx.fill_between(t, 0, 1, where=hit, color=colour, alpha=0.25, step="mid", linewidth=0,
                        transform=bx.get_xaxis_transform(), label=f"{status.replace('_', ' ')} frames")
    bx.fill_between(t, z - 1.96 * sd, z + 1.96 * sd, color="#1f77b4", alpha=0.3, linewidth=0, label="95 % band")
    bx.plot(t, z, color="#1f77b4", linewidth=1.2, label="smoother")
    truth_path = session / "truth.csv"
    if truth_path.is_file():
        truth = pd.read_csv(truth_path)
        truth = truth[truth["marker"] == marker]
        fps = len(one) / (t[-1] - t[0] + t[1] - t[0]) if len(t) > 1 else 1.0
        bx.plot(truth["frame"] / fps, truth["z"] * 1e3, "k.", markersize=2, label="truth")
        bx.set_ylim(truth["z"].min() * 1e3 - 120, truth["z"].max() * 1e3 + 120)
    bx.set_xlabel("time [s]", fontsize=8)
    bx.set_ylabel(f"{marker} height z [mm]", fontsize=8)
    bx.tick_params(labelsize=7)
    bx.legend(fontsize=7, loc="best", frameon=False)
    bx.set_title(f"{marker}: estimate, 95 % band and truth through the gaps", fontsize=9)
    fig.tight_layout()
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=100)
    from PIL import Image

    image = Image.open(png).convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE)
    image.save(png, optimize=True)  # a palette: ~4x smaller, the same look


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
