"""The DLTdv importer on REAL rigs: DLTdv projects built from published calibrations and labels
(tests/real_dlt.py: the MCSC LED rig, 4 cameras, and the DANNCE mouse rig, 6 cameras), written in
several conventions, imported, reconstructed, and compared with the published 3D.

Variants (real_dlt.VARIANTS): "lower-left" (DLTdv's own convention: u + 1, H - v; right-handed world,
metres), "upper-left" (u + 1, v + 1), "mirrored" (lower-left pixels, world Z negated: left-handed),
"millimetres" (lower-left, world in mm, imported with units="mm").

Precision (measured by real_dlt's own linear DLT on the written files, independent of batgraph),
on the frames used here (MCSC frames 200-463, DANNCE the first 40 labelled frames):

* MCSC: the 50 published points (Xe.dat, aligned to metres) in those frames that keep >= 2 views once
  undistorted clicks outside the image are dropped: median 0.066 mm, p95 1.17 mm, max 3.09 mm (Xe is
  MCSC's bundle adjustment of the same clicks; the worst points have 2 views). batgraph on the same
  points, every variant alike: triangulate median 0.051, p95 1.12, max 3.09 mm; smoother median
  0.146, p95 1.54, max 3.03 mm. Bounds: median 0.3 mm, p95 2.5 mm, max 6 mm (about 2x the smoother's
  median and the DLT's p95 and max). A 1 px pixel-convention slip (0- vs 1-based) moves the DLT's
  points by median 0.58-1.20 mm: the median bound catches it; a wrong y flip by median 361 mm.
* DANNCE: data_2d are exact reprojections of data_3d, so the DLT reproduces data_3d to 1.1e-7 mm
  (6-decimal clicks) on 846 points. batgraph measured max 5.4e-7 mm for both methods.
  Bounds: 0.01 mm for triangulate, 0.05 mm for the smoother (room for a pixel-noise floor); a 1 px
  slip moves points by median 0.11-0.22 mm.

Points seen by one camera only (MCSC: 2 published points in these frames, 7 in all) are left out of
the bounds for the smoother: its depth along the single ray comes from the motion model alone
(measured 65-79 mm off here, 8-128 mm over all frames, for an LED that moves ~100 mm between
published frames).

The reconstructions are run through ``batgraph.cli.main`` in-process, every output written (the
recording off). Skipped when ../shared/data/real is absent.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import real_dlt as R

from batgraph.cli import main
from batgraph.errors import InputError
from batgraph.formats.dltdv import import_dltdv

pytestmark = pytest.mark.skipif(not R.REAL.is_dir(),
                                reason=f"real data {R.REAL} is absent (../shared/data/real next to the repository)")

RIGS = ("mcsc", "dannce")
VARIANTS = tuple(R.VARIANTS)
FRAMES = {"mcsc": slice(200, 464), "dannce": slice(0, 40)}  # the file under 60 s on 2 shared cores
# bounds on |batgraph - published| [mm] over points with >= 2 views (see the module docstring)
_MCSC = {"median": 0.3, "p95": 2.5, "max": 6.0}
BOUNDS_MM = {("mcsc", "triangulate"): _MCSC, ("mcsc", "smoother"): _MCSC, ("mcsc", "fixture"): _MCSC,
             ("dannce", "triangulate"): {"median": 0.01, "p95": 0.01, "max": 0.01},
             ("dannce", "smoother"): {"median": 0.05, "p95": 0.05, "max": 0.05},
             ("dannce", "fixture"): {"median": 0.001, "p95": 0.001, "max": 0.001}}
UNIT_WORDS = re.compile(r"unit|scale|millimet|\bmm\b|metre|meter", re.IGNORECASE)


# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------
def run_cli(argv: list[str], capsys=None) -> tuple[int, str, str]:
    """``batgraph ARGV`` in-process; (exit code, stdout, stderr)."""
    if capsys is not None:
        capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse: an option the CLI does not know
        rc = e.code if isinstance(e.code, int) else 2
    out, err = capsys.readouterr() if capsys is not None else ("", "")
    return rc, out, err


class Real:
    """Loads the rigs, writes projects, imports and reconstructs each once per test module."""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self._rigs, self._projects, self._runs = {}, {}, {}

    def rig(self, name: str) -> R.RealRig:
        if name not in self._rigs:
            rig = R.LOADERS[name]()  # skips when the folder is absent
            sl = FRAMES[name]
            if sl is not None:
                rig.uv, rig.xyz = rig.uv[sl], rig.xyz[sl]
            self._rigs[name] = rig
        return self._rigs[name]

    def project(self, name: str, variant: str, pixel_origin=None) -> dict:
        """Paths of the project (written once); pixel_origin overrides the variant's (per camera)."""
        key = (name, variant, None if pixel_origin is None else tuple(pixel_origin))
        if key not in self._projects:
            rig = self.rig(name)
            opts = dict(R.VARIANTS[variant])
            if pixel_origin is not None:
                opts["pixel_origin"] = list(pixel_origin)
            folder = self.tmp / f"{name}-{variant}{'-mixed' if pixel_origin is not None else ''}"
            self._projects[key] = R.write_dltdv_project(folder, rig.P, rig.uv, rig.image_hw, xyz=rig.xyz, **opts)
        return self._projects[key]

    def run(self, name: str, variant: str, *, pixel_origin=None, units=None,
            methods: str = "triangulate,smoother") -> dict:
        """Import (API) + ``batgraph reconstruct`` (CLI); cached. units None: the variant's own."""
        key = (name, variant, pixel_origin, units, methods)
        if key not in self._runs:
            rig, paths = self.rig(name), self.project(name, variant)
            units = R.VARIANTS[variant]["units"] if units is None else units
            tag = f"{name}-{variant}-{pixel_origin or 'detect'}-{units}-{methods.replace(',', '+')}"
            session_dir, out = self.tmp / f"S-{tag}", self.tmp / f"O-{tag}"
            session = import_dltdv(paths["xypts"], paths["dltCoefs"], rig.fps, session_dir, pixel_origin=pixel_origin,
                                   units=units, image_size=rig.image_wh, xyzpts=paths["xyzpts"])
            rc, _, err = run_cli(["reconstruct", session_dir, "--methods", methods, "--viewer", "none", "--quiet",
                                  "--out", out])
            self._runs[key] = {"session": session, "rc": rc, "stderr": err, "out": out, "paths": paths}
        return self._runs[key]


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    return Real(tmp_path_factory.mktemp("real_dltdv"))


def user_xyz_m(rig: R.RealRig, variant: str) -> np.ndarray:
    """The published 3D in the project's user frame, metres: (F, M, 3)."""
    return R.file_xyz(rig.xyz, mirror=R.VARIANTS[variant]["mirror"], units="m")


def trajectories(out: Path, method: str, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (F, M, 3) [m, user frame], n_views (F, M)) of one method from trajectories.csv."""
    t = pd.read_csv(out / "trajectories.csv")
    t = t[t["method"] == method]
    assert len(t), f"no {method} rows in {out / 'trajectories.csv'}"
    F, M = shape
    xyz, views = np.full((F, M, 3), np.nan), np.zeros((F, M), int)
    p = t["marker"].str.extract(r"^pt(\d+)$")[0].astype(int).to_numpy() - 1
    f = t["frame"].to_numpy()
    xyz[f, p] = t[["x", "y", "z"]].to_numpy()
    views[f, p] = t["n_views"].to_numpy()
    return xyz, views


def assert_close_to_published(name: str, method: str, got_m: np.ndarray, want_m: np.ndarray, where: np.ndarray,
                              what: str):
    ok = where & np.isfinite(want_m).all(-1)
    assert ok.sum() >= (40 if name == "mcsc" else 500), f"{what}: only {ok.sum()} points to compare"
    n_missing = int((~np.isfinite(got_m[ok]).all(-1)).sum())
    assert n_missing == 0, f"{what}: {n_missing} published points missing"
    fig = R.error_figures_mm(got_m[ok], want_m[ok])
    b = BOUNDS_MM[(name, method)]
    msg = (f"{what}: |batgraph - published| median {fig['median_mm']:.4f} mm, p95 {fig['p95_mm']:.4f} mm, "
           f"max {fig['max_mm']:.4f} mm over {fig['n']} points; bounds {b}")
    assert fig["median_mm"] < b["median"] and fig["p95_mm"] < b["p95"] and fig["max_mm"] < b["max"], msg


def import_info(session) -> dict:
    info = session.extra_toml.get("import", {})
    for k in ("pixel_origin", "pixel_origin_source", "world", "units"):
        assert k in info, f"extra_toml['import'] has no {k!r}: {info}"
    return info


def world_mirror(session) -> np.ndarray:
    m = np.asarray(session.world_mirror, float)
    assert m.shape == (3,) and np.all(np.abs(m) == 1), m
    return m


# ----------------------------------------------------------------------------------------------
# the fixtures themselves, checked without batgraph's importer
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", RIGS)
def test_fixture_dlt_reproduces_published_3d(real, name, variant):
    """The written files, triangulated by a plain linear DLT, give the published 3D; the coefficient
    signs are those of the convention written (det(M) * depth < 0 for DLTdv's lower-left pixels with
    a right-handed world, > 0 for upper-left or for lower-left with a mirrored world)."""
    rig, paths = real.rig(name), real.project(name, variant)
    opts = R.VARIANTS[variant]
    L = R.read_coefs(paths["dltCoefs"])
    uv = R.read_clicks(paths["xypts"], len(L))
    X = R.dlt_triangulate(L, uv) / R.UNITS[opts["units"]]
    want = user_xyz_m(rig, variant)
    two_views = np.isfinite(uv).all(-1).sum(-1) >= 2
    assert_close_to_published(name, "fixture", X, want, two_views, f"{name}/{variant} fixture DLT")
    ok = np.isfinite(want).all(-1)
    sign = R.depth_sign(R.coefs_to_P(L), R.file_xyz(rig.xyz[ok], mirror=opts["mirror"], units=opts["units"]))
    expect = -1 if (opts["pixel_origin"] == "lower-left") != opts["mirror"] else 1
    assert np.all(np.sign(sign) == expect)
    # the xyzpts file holds the published 3D in the project's frame and units
    xyz_file = pd.read_csv(paths["xyzpts"]).to_numpy(float).reshape(want.shape)
    np.testing.assert_allclose(xyz_file[ok] / R.UNITS[opts["units"]], want[ok], rtol=0, atol=1e-8)


# ----------------------------------------------------------------------------------------------
# (a) import with the origin detected + reconstruct: the published 3D, in the user's frame, metres
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", RIGS)
def test_import_and_reconstruct_give_published_3d(real, name, variant):
    rig = real.rig(name)
    r = real.run(name, variant)
    assert r["rc"] == 0, f"reconstruct exited {r['rc']}: {r['stderr']}"
    want = user_xyz_m(rig, variant)
    for method in ("triangulate", "smoother"):
        got, views = trajectories(r["out"], method, want.shape[:2])
        assert_close_to_published(name, method, got, want, views >= 2, f"{name}/{variant} {method}")


# ----------------------------------------------------------------------------------------------
# (b) the imported cameras: points in front, and each reproduces the file's own DLT
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", RIGS)
def test_imported_cameras_match_file_dlt_with_points_in_front(real, name, variant):
    rig = real.rig(name)
    r = real.run(name, variant)
    assert r["rc"] == 0, r["stderr"]
    session, opts = r["session"], R.VARIANTS[variant]
    mirror = world_mirror(session)
    info = import_info(session)
    # every reconstructed point (both methods, user frame) is in front of every camera
    pts = []
    for method in ("triangulate", "smoother"):
        xyz, _ = trajectories(r["out"], method, rig.xyz.shape[:2])
        pts.append(xyz[np.isfinite(xyz).all(-1)])
    internal = np.concatenate(pts) * mirror  # x_internal = world_mirror * x_user (its own inverse)
    for cam in session.rig:
        depth = cam.to_cam(internal)[:, 2]
        assert (depth > 0).all(), f"{cam.name}: {(depth <= 0).sum()} of {len(depth)} points behind the camera"
    # each camera, read back in the file's pixel convention, is the file's own DLT
    L = R.read_coefs(r["paths"]["dltCoefs"])
    ok = np.isfinite(rig.xyz).all(-1)
    user_m = user_xyz_m(rig, variant)[ok]
    want = R.dlt_project(L, user_m * R.UNITS[opts["units"]])  # (N, C, 2), file pixels
    for c, cam in enumerate(session.rig):
        uv_cv = cam.project(user_m * mirror, distort=False)
        uv_file = R.apply_affine(R.pixel_affine(info["pixel_origin"], cam.size_wh[1]), uv_cv)
        err = np.abs(uv_file - want[:, c]).max()
        assert err < 1e-6, f"{cam.name}: imported camera differs from the file's DLT by {err:.2e} px"


# ----------------------------------------------------------------------------------------------
# (c) what the importer says it detected; a forced origin that contradicts the coefficients
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", RIGS)
def test_detected_conventions(real, name, variant):
    """Lower-left and upper-left are told apart. Lower-left pixels with a mirrored world have the
    coefficient signs of upper-left pixels with a right-handed one: either reading is right (the 3D
    is the same, test (a)); only lower-left + right-handed would be wrong. Detection never needs a mirror."""
    r = real.run(name, variant)
    info = import_info(r["session"])
    assert info["pixel_origin_source"] == "detected"
    assert info["units"] == R.VARIANTS[variant]["units"]
    if variant == "mirrored":
        assert (info["pixel_origin"], info["world"]) in {("upper-left", "right-handed"), ("lower-left", "mirrored")}
        assert (info["world"] == "mirrored") == (np.prod(world_mirror(r["session"])) < 0)
    else:
        assert info["pixel_origin"] == R.VARIANTS[variant]["pixel_origin"]
        assert info["world"] == "right-handed"
        assert np.all(world_mirror(r["session"]) == 1)


FORCED = [  # (variant written, pixel origin given, world the importer must then report)
    ("lower-left", "lower-left", "right-handed"),
    ("lower-left", "upper-left", "mirrored"),
    ("upper-left", "upper-left", "right-handed"),
    ("upper-left", "lower-left", "mirrored"),
    ("mirrored", "lower-left", "mirrored"),
    ("mirrored", "upper-left", "right-handed"),
]


@pytest.mark.parametrize(("variant", "given", "world"), FORCED)
@pytest.mark.parametrize("name", RIGS)
def test_given_pixel_origin(real, name, variant, given, world):
    """A given origin is used as given; where the coefficients then describe a left-handed world the
    import says "mirrored" (and only then), and the 3D still comes back in the file's frame."""
    rig = real.rig(name)
    r = real.run(name, variant, pixel_origin=given, methods="triangulate")
    info = import_info(r["session"])
    assert (info["pixel_origin"], info["pixel_origin_source"], info["world"]) == (given, "given", world)
    assert (np.prod(world_mirror(r["session"])) < 0) == (world == "mirrored")
    assert r["rc"] == 0, r["stderr"]
    want = user_xyz_m(rig, variant)
    got, views = trajectories(r["out"], "triangulate", want.shape[:2])
    assert_close_to_published(name, "triangulate", got, want, views >= 2,
                              f"{name}/{variant} given {given} triangulate")


@pytest.mark.parametrize("name", RIGS)
def test_cli_import_prints_the_pixel_origin(real, name, tmp_path, capsys):
    rig, paths = real.rig(name), real.project(name, "lower-left")
    base = ["import", "dltdv", "--xypts", paths["xypts"], "--coefs", paths["dltCoefs"], "--fps", rig.fps,
            "--image-size", *rig.image_wh, "--xyzpts", paths["xyzpts"]]
    rc, out, err = run_cli([*base, "--out", tmp_path / "detected"], capsys)
    assert rc == 0, err
    assert "lower-left" in out, out
    rc, out, err = run_cli([*base, "--out", tmp_path / "given", "--pixel-origin", "upper-left", "--units", "m"], capsys)
    assert rc == 0, err
    assert "upper-left" in out and "mirror" in out.lower(), out


# ----------------------------------------------------------------------------------------------
# (d) one camera in another convention: exit 2, one line naming it
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", RIGS)
def test_camera_in_another_convention_is_named(real, name, tmp_path, capsys):
    rig = real.rig(name)
    origins = ["lower-left"] * len(rig.P)
    origins[1] = "upper-left"  # camera 2
    paths = real.project(name, "lower-left", pixel_origin=origins)
    argv = ["import", "dltdv", "--xypts", paths["xypts"], "--coefs", paths["dltCoefs"], "--fps", rig.fps,
            "--image-size", *rig.image_wh, "--out", tmp_path / "S"]
    rc, out, err = run_cli(argv, capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, f"exit {rc}; stdout {out!r}; stderr {err!r}"
    assert len(lines) == 1, f"expected one line on stderr, got {lines}"
    assert re.search(r"\bcam(?:era)?[ _]?2\b", lines[0]), lines[0]
    assert not re.search(r"\bcam(?:era)?[ _]?[13-9]\b", re.sub(r"\S*/\S*", "", lines[0])), lines[0]  # only it
    with pytest.raises(InputError, match=r"\bcam(?:era)?[ _]?2\b"):
        import_dltdv(paths["xypts"], paths["dltCoefs"], rig.fps, tmp_path / "S2", image_size=rig.image_wh)


# ----------------------------------------------------------------------------------------------
# (e) a millimetre world read as metres is loud
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", RIGS)
def test_millimetres_read_as_metres_is_loud(real, name, tmp_path, capsys):
    """Either the import/reconstruct exits 2, or summary.json warns about units/scale naming a camera."""
    rig, paths = real.rig(name), real.project(name, "millimetres")
    argv = ["import", "dltdv", "--xypts", paths["xypts"], "--coefs", paths["dltCoefs"], "--fps", rig.fps,
            "--image-size", *rig.image_wh, "--out", tmp_path / "S"]
    rc, out, err = run_cli(argv, capsys)
    if rc == 2:
        assert UNIT_WORDS.search(err), err
        return
    assert rc == 0, err
    rc, out, err = run_cli(["reconstruct", tmp_path / "S", "--methods", "triangulate", "--viewer", "none",
                            "--quiet", "--out", tmp_path / "O"], capsys)
    if rc == 2:
        assert UNIT_WORDS.search(err), err
        return
    assert rc == 0, err
    warnings = json.loads((tmp_path / "O" / "summary.json").read_text())["warnings"]
    names = [f"cam{c + 1}" for c in range(len(rig.P))]  # the importer's default camera names
    loud = [w for w in warnings if UNIT_WORDS.search(w) and any(re.search(rf"\b{n}\b", w) for n in names)]
    assert loud, f"no warning about units/scale naming a camera; warnings: {warnings}"
