"""Real genlocked data (the MCSC LED rig) made into an unsynchronised rig with exactly known offsets."""

from __future__ import annotations

import numpy as np
import pytest
import real_dlt
import real_unsync

from batgraph import timing as T
from batgraph.checks import preflight
from batgraph.session import dense_observations
from batgraph.triangulate import triangulate_ideal

pytestmark = pytest.mark.skipif(not (real_dlt.REAL / real_dlt.MCSC).is_dir(), reason="real data absent")
PHASES = (0, 1, 2, 3)


@pytest.fixture(scope="module")
def mcsc():
    return real_unsync.mcsc_session()


@pytest.fixture(scope="module")
def unsync(mcsc):
    return real_unsync.unsynchronise(mcsc, 5, PHASES)


def _ideal(session):
    dense = dense_observations(session)
    return dense, preflight(session, dense).ideal


def test_every_fifth_frame_at_its_phase(mcsc, unsync):
    given, ignored = unsync
    assert given.fps == ignored.fps == mcsc.fps / 5
    assert [c.time_offset_s for c in given.rig] == [p / mcsc.fps for p in PHASES]
    assert all(c.time_offset_s == 0 for c in ignored.rig)
    full = mcsc.observations.set_index(["frame", "camera", "marker"])
    for c, name in enumerate(mcsc.rig.names):
        mine = ignored.observations[ignored.observations["camera"] == name]
        old = 5 * mine["frame"].to_numpy() + PHASES[c]  # camera c's frame j is the genlocked frame 5 j + phase
        back = full.loc[list(zip(old, [name] * len(old), mine["marker"], strict=True)), ["u", "v"]].to_numpy()
        assert np.array_equal(back, mine[["u", "v"]].to_numpy())
        n_all = int((mcsc.observations["camera"] == name).sum())
        assert abs(len(mine) - n_all / 5) <= n_all / 5 * 0.2 + 2
    dense = dense_observations(given)
    fracs = {round(float(x), 9) for c in range(4) for x in np.unique(dense.time_frac[c][dense.seen[c]])}
    assert fracs == {0.0, 0.2, 0.4, -0.4}  # phase 3 (0.6 frame) is nearest to the next frame
    ref = given.reference
    assert np.array_equal(ref["frame"] * 5, mcsc.reference[mcsc.reference["frame"] % 5 == 0]["frame"].to_numpy())


def test_the_genlocked_rig_is_quiet(mcsc):
    dense, ideal = _ideal(mcsc)
    xyz, _ = triangulate_ideal(mcsc.rig, ideal)
    chk = T.timing_check(mcsc.rig, ideal, xyz, np.gradient(xyz, axis=0) * mcsc.fps, mcsc.fps)
    assert chk.warnings == [] and np.all(np.abs(chk.table["step_s"]) < 1e-4)
    scan = T.scan_lags(mcsc.rig, ideal, dense.frames, mcsc.fps)
    assert (scan.table["lag_frames"] == 0).all()


def test_lag_scan_finds_the_phases(unsync):
    """Offsets ignored, the scan puts each camera within half a frame of its true offset; given, nothing is left."""
    given, ignored = unsync
    dense, ideal = _ideal(ignored)
    scan = T.scan_lags(ignored.rig, ideal, dense.frames, ignored.fps)
    ref = ignored.rig.names.index(scan.reference)
    true = (np.array(PHASES) - PHASES[ref]) / 5
    assert np.all(np.abs(scan.table["offset_frames"] - true) < 0.15)
    assert np.array_equal(scan.table["lag_frames"], np.ceil(true - 0.5))
    dense, ideal = _ideal(given)
    scan = T.scan_lags(given.rig, ideal, dense.frames, given.fps)
    assert (scan.table["lag_frames"] == 0).all() and np.all(np.abs(scan.table["offset_frames"]) < 0.15)
