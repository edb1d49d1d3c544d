"""Association scored against the truth of a test scene (batgraph.associate.scenes): how many detections of real
markers got their own name, how many a wrong one, identity switches, and how many spurious blobs stayed unnamed.
"""

from __future__ import annotations

import numpy as np
import pandas as pd


def score(truth: pd.DataFrame, frame: np.ndarray, marker: np.ndarray, fps: float, n_markers: int) -> dict:
    """Figures of one association.

    truth: per detection ``marker`` and ``kind`` (scenes.Scene.truth); frame (N,) each detection's frame; marker
    (N,) the name given ('' where none). Switches: per true marker, in frame order, the name most of its
    detections got on each frame it was named (ties: the first in name order); every change counts, per 100
    marker-seconds (markers x the frames spanned / fps).
    """
    kind = truth["kind"].to_numpy()
    true = truth["marker"].to_numpy().astype(str)
    given = np.asarray(marker).astype(str)
    real, fake, merged = kind == "marker", kind == "spurious", kind == "merged"
    named = given != ""
    right = given == true
    out = {
        "n_real": int(real.sum()), "n_spurious": int(fake.sum()), "n_merged": int(merged.sum()),
        "real_correct": float(right[real].mean()) if real.any() else float("nan"),
        "real_wrong": float((named & ~right)[real].mean()) if real.any() else float("nan"),
        "real_unnamed": float((~named)[real].mean()) if real.any() else float("nan"),
        "spurious_unnamed": float((~named)[fake].mean()) if fake.any() else float("nan"),
        "merged_unnamed": float((~named)[merged].mean()) if merged.any() else float("nan"),
        "merged_one_of_two": float(np.mean([g in t.split("+") for g, t in zip(given[merged], true[merged],
                                                                               strict=True)])) if merged.any()
        else float("nan"),
    }
    df = pd.DataFrame({"frame": frame[real & named], "true": true[real & named], "given": given[real & named]})
    per = df.groupby(["true", "frame"])["given"].agg(lambda g: g.value_counts().sort_index().idxmax())
    switches = int(sum((v.to_numpy()[1:] != v.to_numpy()[:-1]).sum() for _, v in per.groupby(level="true")))
    seconds = n_markers * (int(frame.max()) - int(frame.min()) + 1) / fps
    out.update(switches=switches, marker_seconds=seconds, switches_per_100_marker_s=100.0 * switches / seconds)
    return out
