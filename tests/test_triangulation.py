"""batgraph.geometry.triangulation.linear_points, the one linear triangulation, and its two callers.

The callers are batgraph.triangulate.dlt_points (ideal pixels in normalised coordinates, rows weighted by
fx fy) and the DLTdv importer's convention check (a file's raw DLT matrices, every row at unit norm). Each is
held to the formula it used before it shared this function, written out here as a reference: the eigenvector
of the focal-weighted normal matrix, and the SVD of the stacked unit rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import real_dlt as R

from batgraph.formats import dltdv
from batgraph.geometry import pinhole, pose
from batgraph.geometry.triangulation import linear_points
from batgraph.measurement import ideal_observations
from batgraph.session import dense_observations, read_session
from batgraph.triangulate import dlt_points

SAMPLES = Path(__file__).resolve().parents[1] / "data" / "samples"
_IU4 = np.triu_indices(4)


def _focal_weighted_eigh(rig, ideal) -> np.ndarray:
    """The reference for dlt_points: per camera, rows in normalised coordinates times fx fy summed into the
    4x4 normal matrix; the eigenvector of its smallest eigenvalue. (F, M, 3), NaN where < 2 views."""
    C, F, M = ideal.uv_px.shape[:3]
    seen = ideal.seen
    N = np.zeros((F, M, 10))
    for c, cam in enumerate(rig):
        s = seen[c]
        xy = pinhole.normalized_from_pixels(ideal.uv_px[c][s], np.linalg.inv(cam.K))
        Pn = np.hstack([cam.R, cam.tvec[:, None]])
        a = xy[:, :1] * Pn[2] - Pn[0]
        b = xy[:, 1:] * Pn[2] - Pn[1]
        i, j = _IU4
        N[s] += cam.K[0, 0] * cam.K[1, 1] * (a[:, i] * a[:, j] + b[:, i] * b[:, j])
    ok = seen.sum(axis=0) >= 2
    xyz = np.full((F, M, 3), np.nan)
    A = np.zeros((int(ok.sum()), 4, 4))
    A[:, _IU4[0], _IU4[1]] = A[:, _IU4[1], _IU4[0]] = N[ok]
    X = np.linalg.eigh(A)[1][:, :, 0]
    xyz[ok] = X[:, :3] / X[:, 3:4]
    return xyz


def _unit_rows_svd(P: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """The reference for the DLTdv check: rows of raw P (C, 3, 4) and pixels uv (C, N, 2) scaled to unit norm,
    stacked (2C, 4) per point; the right singular vector of the smallest singular value. (N, 3)."""
    seen = np.isfinite(uv[..., 0])
    u = np.where(seen, uv[..., 0], 0.0)[..., None]
    v = np.where(seen, uv[..., 1], 0.0)[..., None]
    rows = np.concatenate([u * P[:, None, 2] - P[:, None, 0], v * P[:, None, 2] - P[:, None, 1]])
    norm = np.linalg.norm(rows, axis=-1, keepdims=True)
    rows = np.where(np.concatenate([seen, seen])[..., None], rows / np.where(norm > 0, norm, 1.0), 0.0)
    ok = seen.sum(axis=0) >= 2
    xyz = np.full((uv.shape[1], 3), np.nan)
    X = np.linalg.svd(np.moveaxis(rows[:, ok], 1, 0))[2][:, -1]
    xyz[ok] = X[:, :3] / X[:, 3:4]
    return xyz


def _max_difference(a: np.ndarray, b: np.ndarray) -> float:
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.isfinite(a).any()
    return float(np.nanmax(np.abs(a - b)))


@pytest.mark.parametrize("sample", ["flight_5cam", "ear_2cam"])
def test_dlt_points_as_before_on_the_bundled_samples(sample):
    session = read_session(SAMPLES / sample)
    ideal = ideal_observations(session.rig, dense_observations(session), 1.0)
    assert _max_difference(dlt_points(session.rig, ideal), _focal_weighted_eigh(session.rig, ideal)) <= 1e-12


@pytest.mark.skipif(not R.REAL.is_dir(), reason=f"real data {R.REAL} is absent")
@pytest.mark.parametrize("rig_name", ["mcsc", "dannce"])
def test_dltdv_convention_check_as_before_on_real_rigs(rig_name, tmp_path, monkeypatch):
    """Every variant of a real DLTdv project, imported: the points the convention check triangulates from the
    file's own coefficients are the unit-row SVD's to 1e-12 m where the file is in metres. In millimetres the
    normal matrix's columns are graded by 1e3 and its eigenvector loses ~1e-11 relative (measured 2.5e-11 m on
    MCSC, 5.9e-13 m on DANNCE); the SVD's error there is 9e-15 m, so the bound is 1e-10 m."""
    calls = []

    def recorded(P, uv, weight=None):
        calls.append((P, uv, linear_points(P, uv, weight)))
        return calls[-1][2]

    monkeypatch.setattr(dltdv, "linear_points", recorded)
    rig = R.LOADERS[rig_name]()
    for variant, opts in R.VARIANTS.items():
        paths = R.write_dltdv_project(tmp_path / variant, rig.P, rig.uv, rig.image_hw, xyz=rig.xyz, **opts)
        calls.clear()
        dltdv.import_dltdv(paths["xypts"], paths["dltCoefs"], rig.fps, tmp_path / f"{variant}_session",
                           units=opts["units"], xyzpts=paths["xyzpts"])
        (P, uv, xyz), = calls
        metres = 1.0 / R.UNITS[opts["units"]]
        bound = 1e-12 if opts["units"] == "m" else 1e-10
        assert _max_difference(xyz, _unit_rows_svd(P, uv)) * metres <= bound, variant


def _random_rig(rng: np.random.Generator, n_cameras: int) -> tuple[np.ndarray, np.ndarray]:
    """P = K [R | t] (C, 3, 4) of cameras ~3 m from the origin looking at it, and K (C, 3, 3)."""
    Ks, Ps = [], []
    for _ in range(n_cameras):
        K = np.array([[rng.uniform(700, 1200), 0.5, 640.0], [0.0, rng.uniform(700, 1200), 360.0], [0, 0, 1.0]])
        centre = rng.normal(size=3)
        Rm, t = pose.look_at(3.0 * centre / np.linalg.norm(centre), np.zeros(3), rng.normal(size=3))
        Ks.append(K)
        Ps.append(pinhole.projection_matrix(K, Rm, t))
    return np.stack(Ps), np.stack(Ks)


def test_linear_points_recovers_exact_points_and_needs_two_views():
    rng = np.random.default_rng(3)
    P, _ = _random_rig(rng, 4)
    truth = rng.uniform(-0.5, 0.5, (200, 3))
    uv = np.stack([pinhole.project_ideal(p, truth) for p in P])  # (C, N, 2)
    uv[1:, :10] = np.nan  # seen by camera 0 only
    uv[2:, 10:20] = np.nan  # seen by cameras 0 and 1
    for weight in (None, rng.uniform(0.5, 2.0, 4)):
        xyz = linear_points(P, uv, weight)
        assert np.isnan(xyz[:10]).all()
        assert np.abs(xyz[10:] - truth[10:]).max() < 1e-9


def test_linear_points_weighs_cameras_as_told():
    """With noisy pixels, a camera weighted 1e8 times the others is met almost exactly (its rows are in
    pixel units, so its reprojection error goes to ~0), and unweighted rows give another point."""
    rng = np.random.default_rng(4)
    P, _ = _random_rig(rng, 3)
    truth = rng.uniform(-0.5, 0.5, (100, 3))
    uv = np.stack([pinhole.project_ideal(p, truth) for p in P]) + rng.normal(0.0, 2.0, (3, 100, 2))
    heavy = linear_points(P, uv, np.array([1e8, 1.0, 1.0]))
    plain = linear_points(P, uv, np.ones(3))
    err = lambda xyz: np.linalg.norm(pinhole.project_ideal(P[0], xyz) - uv[0], axis=-1)  # noqa: E731
    assert err(heavy).max() < 1e-3 < np.median(err(plain))
    assert np.abs(linear_points(P, uv) - plain).max() > 1e-6  # unit rows weigh the views otherwise
