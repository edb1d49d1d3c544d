"""Takes: a compacted frame axis. A stray frame number costs one take of its own, not memory for the
frames in between, and each take is solved on its own (batgraph.session.frame_axis, pipeline.run_by_take)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from batgraph import evaluate
from batgraph.errors import InputError
from batgraph.pipeline import run_methods
from batgraph.result import Options
from batgraph.session import dense_observations, frame_axis, read_session
from tests.conftest import write_tiny_session

STRAY = 60_000  # frames after the session's last one: dense, this would be 60k frames of arrays per method


def test_frame_axis_splits_at_long_empty_runs_and_keeps_frame_numbers():
    frames, takes = frame_axis(np.array([8, 5, 6, 5, 200, 201, 8]), gap_frames=10)
    assert frames.tolist() == [5, 6, 7, 8, 200, 201]  # frame 7 is inside a take: an empty frame is kept
    assert [(t.start, t.stop) for t in takes] == [(0, 4), (4, 6)]
    # a run of exactly gap_frames empty frames stays inside the take; one more splits it
    assert len(frame_axis(np.array([0, 11]), 10)[1]) == 1
    assert len(frame_axis(np.array([0, 12]), 10)[1]) == 2
    empty, none = frame_axis(np.zeros(0, int), 10)
    assert len(empty) == 0 and none == []


def test_take_of_recovers_the_takes_of_a_result_table():
    assert evaluate.take_of(np.array([3, 4, 5, 5, 90, 91, 3])).tolist() == [0, 0, 0, 0, 1, 1, 0]


@pytest.fixture(scope="module")
def stray_sessions(tmp_path_factory):
    """(plain session, the same with a stray copy of frames 3-5 at STRAY + 3..5), 4 cameras, 30 frames."""
    folder = write_tiny_session(tmp_path_factory.mktemp("takes") / "s", n_cams=4, n_frames=30, n_markers=3)
    plain = read_session(folder)
    obs = plain.observations
    stray = obs[obs["frame"].isin([3, 4, 5])].assign(frame=lambda d: d["frame"] + STRAY)
    return plain, dataclasses.replace(plain, observations=pd.concat([obs, stray], ignore_index=True))


def test_a_stray_frame_costs_its_own_take_not_the_frames_between(stray_sessions):
    plain, stray = stray_sessions
    dense = dense_observations(stray)
    assert dense.uv_px.shape[1] == 30 + 3  # not STRAY + 6 frames
    assert dense.frames[-3:].tolist() == [STRAY + 3, STRAY + 4, STRAY + 5]
    assert [(t.start, t.stop) for t in dense.take_slices] == [(0, 30), (30, 33)]
    assert len(dense_observations(plain).take_slices) == 1


def test_each_take_is_solved_on_its_own(stray_sessions):
    """The first take's answer is exactly the plain session's (no motion factor bridges the gap), and the
    stray take is estimated from its own frames; spans are per take."""
    plain, stray = stray_sessions
    methods = ["smoother", "filter", "ekf", "triangulate"]
    opts = Options(progress=False)
    a, b = run_methods(plain, methods, opts), run_methods(stray, methods, opts)
    tb = b.trajectories
    first = tb[tb["frame"] < STRAY].reset_index(drop=True)
    cols = ["x", "y", "z", "cov_xx", "cov_zz", "status", "span"]
    pd.testing.assert_frame_equal(first[["method", "frame", "marker", *cols]],
                                  a.trajectories[["method", "frame", "marker", *cols]], rtol=1e-9, atol=1e-12)
    late = tb[tb["frame"] > STRAY]
    assert late["frame"].nunique() == 3
    assert late.groupby("method")["x"].count().min() == 9  # every method, 3 frames x 3 markers
    truth = plain.truth.set_index(["frame", "marker"])
    late_s = late[late["method"] == "smoother"].assign(frame=lambda d: d["frame"] - STRAY)
    cells = list(zip(late_s["frame"], late_s["marker"], strict=True))
    err = late_s[["x", "y", "z"]].to_numpy() - truth.loc[cells].to_numpy()
    assert np.abs(err).max() < 0.01  # [m]: the stray take's positions are real estimates
    assert (late["span"] == "inside").all()  # seen by 4 cameras throughout its own take
    take = b.estimates["smoother"].info["takes"][1]
    assert (take["first_frame"], take["last_frame"]) == (STRAY + 3, STRAY + 5)


def test_take_gap_is_read_from_session_toml_and_checked(tmp_path):
    folder = write_tiny_session(tmp_path / "s", n_frames=10)
    obs = pd.read_csv(folder / "observations.csv")
    obs.loc[obs["frame"] == 9, "frame"] = 60  # 50 empty frames at 100 fps: 0.5 s
    obs.to_csv(folder / "observations.csv", index=False)
    assert len(read_session(folder).takes) == 1  # default take_gap_s = 1.0 s
    toml = (folder / "session.toml").read_text()
    (folder / "session.toml").write_text(toml.replace("[session]\n", "[session]\ntake_gap_s = 0.2\n", 1))
    assert [(t.start, t.stop) for t in read_session(folder).takes] == [(0, 9), (9, 10)]
    (folder / "session.toml").write_text(toml.replace("[session]\n", "[session]\ntake_gap_s = 1e308\n", 1))
    assert len(read_session(folder).takes) == 1  # huge (take_gap_s x fps overflows): one take, no error
    for bad in ("-1", "inf", '"1 s"'):
        (folder / "session.toml").write_text(toml.replace("[session]\n", f"[session]\ntake_gap_s = {bad}\n", 1))
        with pytest.raises(InputError, match=r"session.toml \[session\] take_gap_s"):
            read_session(folder)


def test_reconstruct_and_export_with_two_takes(tmp_path, capsys):
    """The whole command on a session with a stray take: one warning line naming the takes; the tables hold
    both takes' frames and none between; C3D / TRC hold one take (the longest, or --take N)."""
    import ezc3d

    from batgraph.cli import main
    from batgraph.formats.c3d_trc import read_trc

    folder = write_tiny_session(tmp_path / "s", n_cams=3, n_frames=12, n_markers=2)
    obs = pd.read_csv(folder / "observations.csv")
    stray = obs[obs["frame"].isin([3, 4])].assign(frame=lambda d: d["frame"] + STRAY)
    pd.concat([obs, stray]).to_csv(folder / "observations.csv", index=False)
    out = tmp_path / "o"
    assert main(["reconstruct", str(folder), "--out", str(out), "--viewer", "none", "--methods",
                 "smoother,triangulate"]) == 0
    err = capsys.readouterr().err
    assert f"2 takes (frames 0-11, {STRAY + 3}-{STRAY + 4})" in err, err
    traj = pd.read_csv(out / "trajectories.csv")
    assert sorted(traj["frame"].unique()) == [*range(12), STRAY + 3, STRAY + 4]
    c = ezc3d.c3d(str(out / "trajectories.c3d"))
    assert c["header"]["points"]["first_frame"] == 0 and c["data"]["points"].shape[2] == 12  # the longest take
    assert main(["export", "trc", str(out), "--take", "2", "--to", str(tmp_path / "t2.trc")]) == 0
    trc = read_trc(tmp_path / "t2.trc")
    assert trc.frame.tolist() == [STRAY + 4, STRAY + 5]  # Frame# = session frame + 1
    capsys.readouterr()
    assert main(["export", "c3d", str(out), "--take", "3"]) == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "take 3" in lines[0] and "2 takes" in lines[0], lines
