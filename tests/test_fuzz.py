"""Hostile-but-realistic input to every command: each bad input is exit code 2 with exactly one line on stderr
naming the file and key (or the option), no traceback, the inputs unchanged and nothing written.

Table-driven: :data:`BAD` holds one :class:`Case` per input. Every case runs in-process through
``batgraph.cli.main`` in its own copy of one small simulated session (3 cameras, 14 markers, 20 frames,
made once per module with one reconstruct output for export/view), and fails before any estimation,
so the file stays fast. :data:`GOOD` holds odd inputs that must succeed (UTF-8 BOM, CRLF, Parquet).
"""

from __future__ import annotations

import builtins
import errno
import hashlib
import io
import json
import os
import shutil
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import tomli_w

from batgraph.cli import main

# ----------------------------------------------------------------------------------------------
# shared inputs, made once
# ----------------------------------------------------------------------------------------------
DLC_PARTS = ["nose", "ear"]
BODY_25B = 25


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A folder with: s/ (simulated session), r/ (its triangulate reconstruct output), dlt/ (a DLTdv trial),
    dlc/ (DeepLabCut CSVs + calibration), pose/ (OpenPose JSON folders)."""
    root = tmp_path_factory.mktemp("fuzz_base")
    assert main(["simulate", "flight", str(root / "s"), "--cameras", "3", "--markers", "14", "--frames", "20",
                 "--seed", "0"]) == 0
    assert main(["reconstruct", str(root / "s"), "--out", str(root / "r"), "--methods", "triangulate",
                 "--viewer", "none", "--quiet"]) == 0
    from batgraph.formats import dltdv
    from batgraph.session import read_session

    session = read_session(root / "s")
    obs = session.observations
    cams = {n: i for i, n in enumerate(session.rig.names)}
    pts = {n: i for i, n in enumerate(session.markers)}
    table = pd.DataFrame({"frame": obs["frame"], "camera_index": obs["camera"].map(cams),
                          "point_index": obs["marker"].map(pts), "u": obs["u"], "v": obs["v"]})
    table[["u", "v"]] = dltdv.from_opencv_px(table[["u", "v"]].to_numpy(), "lower-left", 720)
    (root / "dlt").mkdir()
    dltdv.write_xypts(root / "dlt" / "xypts.csv", table, n_cams=3, n_points=len(pts), n_frames=20)
    dltdv.write_dlt_coefs(root / "dlt" / "dltCoefs.csv", session.rig, "lower-left", (1280, 720))
    # DeepLabCut: one CSV per camera, named after the calibration cameras
    (root / "dlc").mkdir()
    shutil.copy(root / "s" / "calibration.toml", root / "dlc" / "calibration.toml")
    for cam in session.rig.names:
        head = ["scorer," + ",".join(["DLC"] * 3 * len(DLC_PARTS)),
                "bodyparts," + ",".join(p for p in DLC_PARTS for _ in range(3)),
                "coords," + ",".join(["x", "y", "likelihood"] * len(DLC_PARTS))]
        rows = [f"{f}," + ",".join(f"{600 + f},{300 + 2 * f + j},0.9" for j in range(len(DLC_PARTS)))
                for f in range(10)]
        (root / "dlc" / f"{cam}.csv").write_text("\n".join(head + rows) + "\n")
    # OpenPose JSON, one folder per camera
    for cam in session.rig.names:
        d = root / "pose" / cam
        d.mkdir(parents=True)
        for f in range(5):
            kp = [v for k in range(BODY_25B) for v in (600.0 + k, 300.0 + f, 0.9)]
            (d / f"{cam}_{f:012d}_keypoints.json").write_text(json.dumps({"people": [{"pose_keypoints_2d": kp}]}))
    return root


class W:
    """One case's workspace: a private copy of the base inputs under ``root``; paths as str for argv."""

    def __init__(self, base: Path, root: Path):
        self.base, self.root = base, root

    def copy(self, name: str) -> Path:
        dst = self.root / name
        if not dst.exists():
            shutil.copytree(self.base / name, dst)
        return dst

    @property
    def s(self) -> Path:
        return self.copy("s")

    @property
    def r(self) -> Path:
        return self.copy("r")

    def p(self, *parts) -> str:
        return str(self.root.joinpath(*parts))


def _tree_hash(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# ----------------------------------------------------------------------------------------------
# editing helpers
# ----------------------------------------------------------------------------------------------
LATIN1 = "café".encode("latin-1")


def write(path: Path, content: str | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    return path


def edit_toml(path: Path, edit: Callable[[dict], None]) -> None:
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    edit(doc)
    path.write_text(tomli_w.dumps(doc), encoding="utf-8")


def recode(path: Path, encoding: str) -> None:
    path.write_bytes(path.read_text(encoding="utf-8").encode(encoding))


def binary(path: Path) -> None:
    path.write_bytes(bytes(range(256)) * 8)


def latin1_line(path: Path, line_no: int = 2) -> None:
    lines = path.read_bytes().split(b"\n")
    lines[line_no - 1] = lines[line_no - 1].replace(b"cam", b"c\xe9m", 1) if b"cam" in lines[line_no - 1] \
        else lines[line_no - 1] + b" # " + LATIN1
    path.write_bytes(b"\n".join(lines))


def set_cell(path: Path, line_no: int, col: str, value: str) -> None:
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[line_no - 1].split(",")
    cells[header.index(col)] = value
    lines[line_no - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


def append_line(path: Path, line: str) -> None:
    with open(path, "a") as f:
        f.write(line + "\n")


def replace_text(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, (path, old)
    path.write_text(text.replace(old, new, 1))


def semicolons(path: Path) -> None:
    path.write_text(path.read_text().replace(",", ";"))


def deny_read(monkeypatch, name: str) -> None:
    """Opening any file called ``name`` for reading raises PermissionError (as chmod 000 would; tests run
    as root, where chmod does not stop a read)."""
    real_open, real_io_open = builtins.open, io.open

    def guard(real):
        def opener(file, mode="r", *args, **kwargs):
            if isinstance(file, str | os.PathLike) and Path(file).name == name and "r" in mode:
                raise PermissionError(errno.EACCES, "Permission denied", str(file))
            return real(file, mode, *args, **kwargs)
        return opener

    monkeypatch.setattr(builtins, "open", guard(real_open))
    monkeypatch.setattr(io, "open", guard(real_io_open))


def deny_write(monkeypatch) -> None:
    """Every existing folder is read-only (root ignores chmod, so the check's probe is replaced)."""
    import batgraph.inputs as inputs
    monkeypatch.setattr(inputs, "_can_write", lambda folder: False, raising=False)


def fail_writes(monkeypatch, code: int) -> None:
    """Every atomic write fails with ``code`` (ENOSPC: a full disk, EROFS: a read-only file system)."""
    import batgraph.atomic as atomic

    def fail(path, *a, **k):
        raise OSError(code, os.strerror(code), str(path))
    monkeypatch.setattr(atomic, "write_text", fail)
    monkeypatch.setattr(atomic, "write_bytes", fail)


# ----------------------------------------------------------------------------------------------
# the cases
# ----------------------------------------------------------------------------------------------
@dataclass
class Case:
    """argv(w) prepares the workspace and returns the command line; words must all be in the message
    (case-insensitive); patch(monkeypatch, w) simulates an OS condition; out (relative to the workspace)
    must not exist afterwards unless it existed before (then unchanged)."""

    id: str
    argv: Callable[[W], list[str]]
    words: tuple[str, ...]
    patch: Callable | None = None
    writes_fail: bool = False  # the failure happens while writing: the output folder may exist, empty


def rec(*extra):
    """reconstruct of the workspace's session, triangulation only, no viewer."""
    def argv(w):
        return ["reconstruct", str(w.s), "--methods", "triangulate", "--viewer", "none", "--quiet", *extra]
    return argv


def rec_edit(fn, *extra):
    def argv(w):
        fn(w)
        return rec(*extra)(w)
    return argv


def toml_edit(name, edit):
    return lambda w: edit_toml(w.s / name, edit)


def sess(edit):
    return toml_edit("session.toml", edit)


def cal(edit):
    return toml_edit("calibration.toml", edit)


def inverted(doc):
    import cv2
    for key, t in doc.items():
        if key.startswith("cam_"):
            R = cv2.Rodrigues(np.array(t["rotation"]))[0]
            t["rotation"] = cv2.Rodrigues(R.T)[0].ravel().tolist()
            t["translation"] = (-R.T @ np.array(t["translation"])).tolist()


def _dup_marker(d):
    d["markers"]["names"][1] = d["markers"]["names"][0]


def obs_cell(line, col, value):
    return lambda w: set_cell(w.s / "observations.csv", line, col, value)


def obs_append(line):
    return lambda w: append_line(w.s / "observations.csv", line)


def to_parquet(fn=None):
    def prep(w):
        df = pd.read_csv(w.s / "observations.csv")
        if fn:
            df = fn(df)
        df.to_parquet(w.s / "observations.parquet")
        (w.s / "observations.csv").unlink()
    return prep


def drop_cols(*cols):
    return lambda df: df.drop(columns=list(cols))


SESSION_CASES = [
    # ---- session.toml: encoding, permission, syntax
    Case("session-binary", rec_edit(lambda w: binary(w.s / "session.toml")), ("session.toml", "binary")),
    Case("session-latin1", rec_edit(lambda w: replace_text(w.s / "session.toml", 'name = "flight_3cam"',
                                                             'name = "flight_3cam"  # café') or
                                    recode(w.s / "session.toml", "latin-1")), ("session.toml", "line 2", "utf-8")),
    Case("session-utf16", rec_edit(lambda w: recode(w.s / "session.toml", "utf-16")), ("session.toml", "utf-16")),
    Case("session-utf16le-nobom", rec_edit(lambda w: recode(w.s / "session.toml", "utf-16-le")),
         ("session.toml", "utf-16")),
    Case("session-utf32", rec_edit(lambda w: recode(w.s / "session.toml", "utf-32")), ("session.toml", "utf-")),
    Case("session-unreadable", rec(), ("session.toml", "permission"),
         patch=lambda mp, w: deny_read(mp, "session.toml")),
    Case("session-is-folder", rec_edit(lambda w: (w.s / "session.toml").unlink() or (w.s / "session.toml").mkdir()),
         ("session.toml", "folder")),
    Case("session-missing", rec_edit(lambda w: (w.s / "session.toml").unlink()), ("session.toml", "not found")),
    Case("session-empty", rec_edit(lambda w: write(w.s / "session.toml", "")), ("session.toml", "[session]")),
    Case("session-not-toml", rec_edit(lambda w: write(w.s / "session.toml", "[session\nfps = 1\n")),
         ("session.toml", "toml", "line 1")),
    Case("session-dup-key", rec_edit(lambda w: write(w.s / "session.toml", "[session]\nfps = 1\nfps = 2\n")),
         ("session.toml", "toml")),
    # ---- session.toml: keys
    Case("fps-zero", rec_edit(sess(lambda d: d["session"].update(fps=0.0))), ("session.toml", "fps", "> 0")),
    Case("fps-negative", rec_edit(sess(lambda d: d["session"].update(fps=-120.0))), ("session.toml", "fps")),
    Case("fps-string", rec_edit(sess(lambda d: d["session"].update(fps="120"))), ("session.toml", "fps", "number")),
    Case("fps-nan", rec_edit(sess(lambda d: d["session"].update(fps=float("nan")))), ("session.toml", "fps")),
    Case("fps-inf", rec_edit(sess(lambda d: d["session"].update(fps=float("inf")))), ("session.toml", "fps")),
    Case("fps-bool", rec_edit(sess(lambda d: d["session"].update(fps=True))), ("session.toml", "fps")),
    Case("fps-missing", rec_edit(sess(lambda d: d["session"].pop("fps"))), ("session.toml", "fps")),
    Case("session-not-table", rec_edit(lambda w: write(w.s / "session.toml", "session = 3\n")),
         ("session.toml", "[session]")),
    Case("motion-model", rec_edit(sess(lambda d: d["motion"].update(model="brownian"))),
         ("session.toml", "[motion] model", "brownian")),
    Case("motion-span-negative", rec_edit(sess(lambda d: d["motion"].update(span_m=-0.5))),
         ("session.toml", "span_m")),
    Case("motion-flap-string", rec_edit(sess(lambda d: d["motion"].update(flap_hz="4"))),
         ("session.toml", "flap_hz")),
    Case("motion-sigma-zero", rec_edit(sess(lambda d: d["motion"].update(sigma_m=0.0))),
         ("session.toml", "sigma_m")),
    Case("motion-psd-nan", rec_edit(sess(lambda d: d["motion"].update(accel_psd_m2_s3=float("nan")))),
         ("session.toml", "accel_psd_m2_s3")),
    Case("motion-not-table", rec_edit(lambda w: write(w.s / "session.toml", 'motion = "x"\n[session]\nfps = 9.0\n')),
         ("session.toml", "motion")),
    Case("noise-negative", rec_edit(sess(lambda d: d["noise"].update(pixel_sigma_px=-1.0))),
         ("session.toml", "pixel_sigma_px")),
    Case("noise-string", rec_edit(sess(lambda d: d["noise"].update(pixel_sigma_px="1"))),
         ("session.toml", "pixel_sigma_px")),
    Case("markers-duplicate", rec_edit(sess(_dup_marker)), ("session.toml", "[markers] names", "body1")),
    Case("markers-not-list", rec_edit(sess(lambda d: d["markers"].update(names="body1"))),
         ("session.toml", "[markers] names")),
    Case("markers-number", rec_edit(sess(lambda d: d["markers"]["names"].append(3))),
         ("session.toml", "[markers] names")),
    Case("markers-empty-name", rec_edit(sess(lambda d: d["markers"]["names"].append(""))),
         ("session.toml", "[markers] names")),
    Case("skeleton-single", rec_edit(sess(lambda d: d["markers"].update(skeleton=[["body1"]]))),
         ("session.toml", "skeleton[0]")),
    Case("skeleton-numbers", rec_edit(sess(lambda d: d["markers"].update(skeleton=[[1, 2]]))),
         ("session.toml", "skeleton[0]")),
    Case("skeleton-not-list", rec_edit(sess(lambda d: d["markers"].update(skeleton="body1-body2"))),
         ("session.toml", "skeleton")),
    Case("skeleton-unknown-marker", rec_edit(sess(lambda d: d["markers"]["skeleton"].append(["body1", "tail"]))),
         ("session.toml", "skeleton", "tail")),
    # ---- calibration.toml
    Case("cal-binary", rec_edit(lambda w: binary(w.s / "calibration.toml")), ("calibration.toml", "binary")),
    Case("cal-latin1", rec_edit(lambda w: replace_text(w.s / "calibration.toml", 'name = "cam1"', 'name = "cäm1"')
                                or recode(w.s / "calibration.toml", "latin-1")), ("calibration.toml", "utf-8")),
    Case("cal-utf16", rec_edit(lambda w: recode(w.s / "calibration.toml", "utf-16")), ("calibration.toml", "utf-16")),
    Case("cal-unreadable", rec(), ("calibration.toml", "permission"),
         patch=lambda mp, w: deny_read(mp, "calibration.toml")),
    Case("cal-is-folder", rec_edit(lambda w: (w.s / "calibration.toml").unlink() or
                                   (w.s / "calibration.toml").mkdir()), ("calibration.toml", "folder")),
    Case("cal-missing", rec_edit(lambda w: (w.s / "calibration.toml").unlink()), ("calibration.toml", "not found")),
    Case("cal-not-toml", rec_edit(lambda w: write(w.s / "calibration.toml", "[cam_0\n")), ("calibration.toml", "toml")),
    Case("cal-empty", rec_edit(lambda w: write(w.s / "calibration.toml", "")), ("calibration.toml", "camera")),
    Case("cal-missing-key", rec_edit(cal(lambda d: d["cam_1"].pop("translation"))),
         ("calibration.toml", "[cam_1]", "translation")),
    Case("cal-matrix-shape", rec_edit(cal(lambda d: d["cam_0"].update(matrix=[[1.0, 0.0], [0.0, 1.0]]))),
         ("calibration.toml", "[cam_0] matrix")),
    Case("cal-matrix-negative-f", rec_edit(cal(lambda d: d["cam_0"]["matrix"][0].__setitem__(0, -600.0))),
         ("calibration.toml", "[cam_0] matrix")),
    Case("cal-matrix-strings", rec_edit(cal(lambda d: d["cam_0"].update(matrix=[["a"] * 3] * 3))),
         ("calibration.toml", "[cam_0] matrix")),
    Case("cal-matrix-last-row", rec_edit(cal(lambda d: d["cam_0"]["matrix"][2].__setitem__(2, 2.0))),
         ("calibration.toml", "[cam_0] matrix")),
    Case("cal-rotation-shape", rec_edit(cal(lambda d: d["cam_2"].update(rotation=[0.1, 0.2]))),
         ("calibration.toml", "[cam_2] rotation")),
    Case("cal-rotation-nan", rec_edit(cal(lambda d: d["cam_2"].update(rotation=[0.1, float("nan"), 0.2]))),
         ("calibration.toml", "[cam_2] rotation")),
    Case("cal-rotation-bools", rec_edit(cal(lambda d: d["cam_2"].update(rotation=[True, False, True]))),
         ("calibration.toml", "[cam_2] rotation")),
    Case("cal-translation-inf", rec_edit(cal(lambda d: d["cam_1"].update(translation=[0.0, float("inf"), 1.0]))),
         ("calibration.toml", "[cam_1] translation")),
    Case("cal-size-zero", rec_edit(cal(lambda d: d["cam_1"].update(size=[1280, 0]))), ("calibration.toml", "size")),
    Case("cal-size-fraction", rec_edit(cal(lambda d: d["cam_1"].update(size=[1280.5, 720]))),
         ("calibration.toml", "size")),
    Case("cal-distortions-six", rec_edit(cal(lambda d: d["cam_1"].update(distortions=[0.0] * 6))),
         ("calibration.toml", "distortions")),
    Case("cal-distortions-strings", rec_edit(cal(lambda d: d["cam_1"].update(distortions=["a", "b"]))),
         ("calibration.toml", "distortions")),
    Case("cal-cov-not-pd", rec_edit(cal(lambda d: d["cam_0"].update(pose_covariance=(-np.eye(6)).tolist()))),
         ("calibration.toml", "[cam_0] pose_covariance", "positive")),
    Case("cal-cov-asymmetric", rec_edit(cal(lambda d: d["cam_0"].update(
        pose_covariance=(np.eye(6) * 1e-6 + np.eye(6, k=1)).tolist()))), ("calibration.toml", "pose_covariance")),
    Case("cal-cov-shape", rec_edit(cal(lambda d: d["cam_0"].update(pose_covariance=np.eye(3).tolist()))),
         ("calibration.toml", "pose_covariance")),
    Case("cal-cov-nan", rec_edit(cal(lambda d: d["cam_0"].update(pose_covariance=(np.eye(6) * np.nan).tolist()))),
         ("calibration.toml", "pose_covariance")),
    Case("cal-duplicate-camera", rec_edit(cal(lambda d: d["cam_1"].update(name="cam1"))),
         ("calibration.toml", "cam1")),
    Case("cal-units", rec_edit(cal(lambda d: d.setdefault("metadata", {}).update(units="inch"))),
         ("calibration.toml", "units")),
    Case("cal-mirror", rec_edit(cal(lambda d: d.setdefault("metadata", {}).update(world_mirror=[1, 1, 2]))),
         ("calibration.toml", "world_mirror")),
    Case("cal-fisheye", rec_edit(cal(lambda d: d["cam_0"].update(fisheye=True))), ("calibration.toml", "fisheye")),
    Case("cal-inverted-poses", rec_edit(cal(inverted)), ("calibration.toml", "behind")),
    Case("cal-name-number", rec_edit(cal(lambda d: d["cam_0"].update(name=[1, 2]))), ("calibration.toml", "name")),
    Case("calibration-option-missing", lambda w: rec("--calibration", w.p("nope.toml"))(w), ("nope.toml", "not found")),
    Case("calibration-option-folder", lambda w: rec("--calibration", str(w.root))(w), ("folder",)),
    Case("calibration-option-utf16", lambda w: (write(w.root / "c.toml", (w.s / "calibration.toml").read_text()
                                                      .encode("utf-16")), rec("--calibration", w.p("c.toml"))(w))[1],
         ("c.toml", "utf-16")),
    # ---- observations.csv
    Case("obs-binary", rec_edit(lambda w: binary(w.s / "observations.csv")), ("observations.csv", "binary")),
    Case("obs-latin1", rec_edit(lambda w: latin1_line(w.s / "observations.csv", 3)),
         ("observations.csv", "line 3", "utf-8")),
    Case("obs-utf16", rec_edit(lambda w: recode(w.s / "observations.csv", "utf-16")), ("observations.csv", "utf-16")),
    Case("obs-semicolons", rec_edit(lambda w: semicolons(w.s / "observations.csv")),
         ("observations.csv", "line 1", "semicolon")),
    Case("obs-tabs", rec_edit(lambda w: write(w.s / "observations.csv",
                                              (w.s / "observations.csv").read_text().replace(",", "\t"))),
         ("observations.csv", "tab")),
    Case("obs-empty", rec_edit(lambda w: write(w.s / "observations.csv", "")), ("observations.csv", "empty")),
    Case("obs-blank-lines", rec_edit(lambda w: write(w.s / "observations.csv", "\n\n\n")),
         ("observations.csv", "empty")),
    Case("obs-header-only", rec_edit(lambda w: write(w.s / "observations.csv", "frame,camera,marker,u,v\n")),
         ("observations.csv", "header only")),
    Case("obs-missing-column", rec_edit(lambda w: replace_text(w.s / "observations.csv", ",v\n", ",w\n")),
         ("observations.csv", "'v'")),
    Case("obs-misspelt-column", rec_edit(lambda w: replace_text(w.s / "observations.csv", "marker", "markr")),
         ("observations.csv", "'marker'", "markr")),
    Case("obs-duplicate-column", rec_edit(lambda w: replace_text(w.s / "observations.csv", ",u,v\n", ",u,u\n")),
         ("observations.csv", "line 1", "'u'")),
    Case("obs-u-text", rec_edit(obs_cell(5, "u", "abc")), ("observations.csv", "line 5", "u", "abc")),
    Case("obs-u-decimal-comma", rec_edit(obs_cell(5, "u", '"12,5"')), ("observations.csv", "line 5", "u")),
    Case("obs-v-inf", rec_edit(obs_cell(4, "v", "inf")), ("observations.csv", "line 4", "v", "infinite")),
    Case("obs-frame-negative", rec_edit(obs_cell(6, "frame", "-1")), ("observations.csv", "line 6", "frame")),
    Case("obs-frame-fraction", rec_edit(obs_cell(6, "frame", "1.5")), ("observations.csv", "line 6", "frame")),
    Case("obs-frame-empty", rec_edit(obs_cell(6, "frame", "")), ("observations.csv", "line 6", "frame")),
    Case("obs-frame-nan", rec_edit(obs_cell(6, "frame", "nan")), ("observations.csv", "line 6", "frame")),
    Case("obs-frame-text", rec_edit(obs_cell(6, "frame", "one")), ("observations.csv", "line 6", "frame")),
    Case("obs-frame-gap", rec_edit(obs_append("2000000,cam1,body1,600,300")),
         ("observations.csv", "frame 2000000", "gap")),
    Case("obs-frame-gap-just-over", rec_edit(obs_append("100020,cam1,body1,600,300")),
         ("observations.csv", "frame 100020")),
    Case("obs-frame-1e9", rec_edit(obs_append("1000000000,cam1,body1,600,300")),
         ("observations.csv", "frame", "1000000000")),
    Case("obs-frame-1e20", rec_edit(obs_append("100000000000000000000,cam1,body1,600,300")),
         ("observations.csv", "frame")),
    Case("obs-frame-1e400", rec_edit(obs_append("1e400,cam1,body1,600,300")), ("observations.csv", "frame")),
    Case("obs-camera-unknown", rec_edit(obs_cell(5, "camera", "cam9")), ("observations.csv", "line 5", "cam9")),
    Case("obs-marker-empty", rec_edit(obs_cell(5, "marker", "")), ("observations.csv", "line 5", "marker")),
    Case("obs-weight-big", rec_edit(lambda w: write(w.s / "observations.csv", pd.read_csv(
        w.s / "observations.csv").assign(weight=1.5).to_csv(index=False))), ("observations.csv", "weight")),
    Case("obs-weight-zero", rec_edit(lambda w: write(w.s / "observations.csv", pd.read_csv(
        w.s / "observations.csv").assign(weight=0.0).to_csv(index=False))), ("observations.csv", "weight")),
    Case("obs-weight-text", rec_edit(lambda w: write(w.s / "observations.csv", pd.read_csv(
        w.s / "observations.csv").assign(weight="high").to_csv(index=False))), ("observations.csv", "weight")),
    Case("obs-half-uv", rec_edit(obs_cell(3, "v", "")), ("observations.csv", "line 3", "u, v")),
    Case("obs-duplicate-row", rec_edit(lambda w: append_line(w.s / "observations.csv",
                                                            (w.s / "observations.csv").read_text().splitlines()[1])),
         ("observations.csv", "line 2", "duplicate")),
    Case("obs-extra-field", rec_edit(lambda w: replace_text(w.s / "observations.csv", "\n0,cam1,body2,",
                                                            "\n0,cam1,body2,7,")), ("observations.csv", "line 3")),
    Case("obs-unterminated-quote", rec_edit(obs_append('3,"cam1,body1,600,300')), ("observations.csv",)),
    Case("obs-all-empty-uv", rec_edit(lambda w: write(w.s / "observations.csv", "frame,camera,marker,u,v\n"
                                                      "0,cam1,body1,,\n")), ("observations.csv", "no observations")),
    Case("obs-missing", rec_edit(lambda w: (w.s / "observations.csv").unlink()), ("observations.csv", "not found")),
    Case("obs-is-folder", rec_edit(lambda w: (w.s / "observations.csv").unlink() or
                                   (w.s / "observations.csv").mkdir()), ("observations.csv", "folder")),
    Case("obs-unreadable", rec(), ("observations.csv", "permission"),
         patch=lambda mp, w: deny_read(mp, "observations.csv")),
    Case("parquet-garbage", rec_edit(lambda w: (binary(w.s / "observations.parquet"),
                                                (w.s / "observations.csv").unlink())), ("observations.parquet",)),
    Case("parquet-missing-column", rec_edit(to_parquet(drop_cols("u"))), ("observations.parquet", "'u'")),
    Case("parquet-frame-negative", rec_edit(to_parquet(lambda df: df.assign(frame=df["frame"] - 5))),
         ("observations.parquet", "row 0", "frame")),
    Case("parquet-frame-gap", rec_edit(to_parquet(lambda df: df.assign(frame=df["frame"] * 1_000_000))),
         ("observations.parquet", "frame")),
    # ---- truth.csv, truth_mislabels.csv, reference_xyz.csv, calibration_true.toml
    Case("truth-semicolons", rec_edit(lambda w: semicolons(w.s / "truth.csv")), ("truth.csv", "semicolon")),
    Case("truth-missing-z", rec_edit(lambda w: write(w.s / "truth.csv", "frame,marker,x,y\n0,body1,1,2\n")),
         ("truth.csv", "'z'")),
    Case("truth-x-text", rec_edit(lambda w: set_cell(w.s / "truth.csv", 4, "x", "abc")), ("truth.csv", "line 4", "x")),
    Case("truth-frame-negative", rec_edit(lambda w: set_cell(w.s / "truth.csv", 4, "frame", "-2")),
         ("truth.csv", "line 4", "frame")),
    Case("truth-frame-huge", rec_edit(lambda w: set_cell(w.s / "truth.csv", 4, "frame", "1e12")),
         ("truth.csv", "line 4", "frame")),
    Case("truth-binary", rec_edit(lambda w: binary(w.s / "truth.csv")), ("truth.csv", "binary")),
    Case("truth-utf16", rec_edit(lambda w: recode(w.s / "truth.csv", "utf-16")), ("truth.csv", "utf-16")),
    Case("mislabels-semicolons", rec_edit(lambda w: write(w.s / "truth_mislabels.csv",
                                                          "frame;camera;marker\n1;cam1;body1\n")),
         ("truth_mislabels.csv", "semicolon")),
    Case("mislabels-missing-column", rec_edit(lambda w: write(w.s / "truth_mislabels.csv", "frame,camera\n1,cam1\n")),
         ("truth_mislabels.csv", "'marker'")),
    Case("mislabels-frame-text", rec_edit(lambda w: write(w.s / "truth_mislabels.csv",
                                                          "frame,camera,marker\nx,cam1,body1\n")),
         ("truth_mislabels.csv", "line 2", "frame")),
    Case("mislabels-binary", rec_edit(lambda w: binary(w.s / "truth_mislabels.csv")), ("truth_mislabels.csv",)),
    Case("mislabels-empty", rec_edit(lambda w: write(w.s / "truth_mislabels.csv", "")),
         ("truth_mislabels.csv", "empty")),
    Case("reference-bad-column", rec_edit(lambda w: write(w.s / "reference_xyz.csv", "frame,marker,x\n0,a,1\n")),
         ("reference_xyz.csv", "'y'")),
    Case("calibration-true-not-toml", rec_edit(lambda w: write(w.s / "calibration_true.toml", "[[[")),
         ("calibration_true.toml", "toml")),
    # ---- the session folder and reconstruct's options
    Case("session-folder-missing", lambda w: ["reconstruct", w.p("nope"), "--quiet"], ("nope", "not found")),
    Case("session-folder-is-file", lambda w: ["reconstruct", str(write(w.root / "f.txt", "x")), "--quiet"],
         ("f.txt",)),
    Case("accel-psd-negative", rec("--accel-psd", "-1"), ("--accel-psd",)),
    Case("accel-psd-nan", rec("--accel-psd", "nan"), ("--accel-psd",)),
    Case("accel-psd-zero", rec("--accel-psd", "0"), ("--accel-psd",)),
    Case("accel-psd-inf", rec("--accel-psd", "inf"), ("--accel-psd",)),
    Case("accel-psd-text", rec("--accel-psd", "lots"), ("--accel-psd",)),
    Case("robust-k-zero", rec("--robust-k", "0"), ("--robust-k",)),
    Case("robust-k-negative", rec("--robust-k", "-2"), ("--robust-k",)),
    Case("robust-k-nan", rec("--robust-k", "nan"), ("--robust-k",)),
    Case("workers-zero", rec("--workers", "0"), ("--workers",)),
    Case("workers-negative", rec("--workers", "-3"), ("--workers",)),
    Case("workers-fraction", rec("--workers", "1.5"), ("--workers",)),
    Case("methods-unknown", rec("--methods", "bogus"), ("bogus",)),
    Case("motion-choice", rec("--motion", "brownian"), ("--motion",)),
    Case("viewer-choice", rec("--viewer", "maybe"), ("--viewer",)),
    Case("unknown-option", rec("--frobnicate"), ("--frobnicate",)),
    Case("out-is-file", lambda w: rec("--out", str(write(w.root / "o.txt", "keep")))(w), ("o.txt", "file")),
    Case("out-under-file", lambda w: rec("--out", str(write(w.root / "o.txt", "keep")) + "/sub")(w),
         ("o.txt", "file")),
    Case("out-not-writable", lambda w: rec("--out", w.p("o"))(w), ("o", "cannot write"),
         patch=lambda mp, w: deny_write(mp)),
    Case("default-out-is-file", lambda w: (write(w.s / "out", "keep"), rec()(w))[1], ("out", "file")),
    Case("memory-too-small", rec(), ("observations.csv", "GiB"),
         patch=lambda mp, w: mp.setattr("batgraph.inputs.physical_memory_bytes", lambda: 10_000)),
    Case("rec-disk-full", lambda w: rec("--out", w.p("o"))(w), ("o", "no space"),
         patch=lambda mp, w: fail_writes(mp, errno.ENOSPC), writes_fail=True),
    Case("rec-read-only-fs", lambda w: rec("--out", w.p("o"))(w), ("o", "read-only"),
         patch=lambda mp, w: fail_writes(mp, errno.EROFS), writes_fail=True),
]

VALIDATE_CASES = [
    Case("validate-robust-k", lambda w: ["validate", str(w.s), "--robust-k", "-1"], ("--robust-k",)),
    Case("validate-workers", lambda w: ["validate", str(w.s), "--workers", "0"], ("--workers",)),
    Case("validate-accel-psd", lambda w: ["validate", str(w.s), "--accel-psd", "nan"], ("--accel-psd",)),
    Case("validate-out-file", lambda w: ["validate", str(w.s), "--out", str(write(w.root / "o.txt", "x"))],
         ("o.txt", "file")),
    Case("validate-missing", lambda w: ["validate", w.p("nope")], ("nope", "not found")),
    Case("validate-obs-utf16", lambda w: (recode(w.s / "observations.csv", "utf-16"), ["validate", str(w.s)])[1],
         ("observations.csv", "utf-16")),
]


def sim(*extra, out="new"):
    return lambda w: ["simulate", "flight", w.p(out), "--frames", "5", *extra]


SIMULATE_CASES = [
    Case("sim-fps-zero", sim("--fps", "0"), ("--fps",)),
    Case("sim-fps-negative", sim("--fps", "-5"), ("--fps",)),
    Case("sim-fps-nan", sim("--fps", "nan"), ("--fps",)),
    Case("sim-rot-nan", sim("--calib-rot-deg", "nan"), ("--calib-rot-deg",)),
    Case("sim-rot-inf", sim("--calib-rot-deg", "inf"), ("--calib-rot-deg",)),
    Case("sim-trans-nan", sim("--calib-trans-mm", "nan"), ("--calib-trans-mm",)),
    Case("sim-trans-negative", sim("--calib-trans-mm", "-1"), ("--calib-trans-mm",)),
    Case("sim-noise-negative", sim("--noise-px", "-1"), ("--noise-px",)),
    Case("sim-noise-nan", sim("--noise-px", "nan"), ("--noise-px",)),
    Case("sim-outliers-one", sim("--outlier-rate", "1"), ("--outlier-rate",)),
    Case("sim-outliers-nan", sim("--outlier-rate", "nan"), ("--outlier-rate",)),
    Case("sim-frames-zero", sim("--frames", "0"), ("--frames",)),
    Case("sim-frames-huge", sim("--frames", "1000000000"), ("--frames",)),
    Case("sim-cameras-zero", sim("--cameras", "0"), ("--cameras",)),
    Case("sim-cameras-many", sim("--cameras", "31"), ("--cameras",)),
    Case("sim-markers-few", sim("--markers", "5"), ("--markers",)),
    Case("sim-seed-negative", sim("--seed", "-1"), ("--seed",)),
    Case("sim-seed-text", sim("--seed", "abc"), ("--seed",)),
    Case("sim-scene", lambda w: ["simulate", "moth", w.p("new")], ("moth",)),
    Case("sim-out-is-file", lambda w: sim(out="f.txt")(w) if write(w.root / "f.txt", "x") else None, ("f.txt", "file")),
    Case("sim-out-under-file", lambda w: sim(out="f.txt/sub")(w) if write(w.root / "f.txt", "x") else None,
         ("f.txt", "file")),
    Case("sim-out-not-writable", sim(), ("new", "cannot write"), patch=lambda mp, w: deny_write(mp)),
    Case("sim-out-not-empty", lambda w: sim(out="s")(w) if w.s else None, ("--force",)),
    Case("sim-disk-full", sim(), ("new", "no space"), patch=lambda mp, w: fail_writes(mp, errno.ENOSPC),
         writes_fail=True),
    Case("sim-read-only-fs", sim(), ("new", "read-only"), patch=lambda mp, w: fail_writes(mp, errno.EROFS),
         writes_fail=True),
]


def calib(*extra):
    return lambda w: ["calibrate", str(w.s), "--quiet", *extra]


CALIBRATE_CASES = [
    Case("wand-negative", calib("--wand", "body1", "body2", "-0.5"), ("--wand",)),
    Case("wand-nan", calib("--wand", "body1", "body2", "nan"), ("--wand",)),
    Case("wand-zero", calib("--wand", "body1", "body2", "0"), ("--wand",)),
    Case("wand-text", calib("--wand", "body1", "body2", "half"), ("--wand",)),
    Case("wand-unknown-marker", calib("--wand", "tail", "body2", "0.5"), ("--wand", "tail")),
    Case("wand-same-marker", calib("--wand", "body1", "body1", "0.5"), ("--wand", "body1")),
    Case("calibrate-out-folder", lambda w: calib("--out", str(w.root))(w), ("folder",)),
    Case("calibrate-out-under-file", lambda w: calib("--out", str(write(w.root / "f.txt", "x")) + "/c.toml")(w),
         ("f.txt", "file")),
    Case("calibrate-ref-negative", calib("--ref-camera", "-1"), ("--ref-camera",)),
    Case("calibrate-ref-too-big", calib("--ref-camera", "99"), ("99",)),
    Case("calibrate-gauge", calib("--gauge", "world"), ("--gauge",)),
    Case("calibrate-session-toml-wand", lambda w: (edit_toml(w.s / "session.toml", lambda d: d.update(
        wand={"ends": ["body1", "body2"], "length_m": -1.0})), calib()(w))[1], ("session.toml", "[wand]", "length_m")),
    Case("calibrate-session-binary", lambda w: (binary(w.s / "session.toml"), calib()(w))[1],
         ("session.toml", "binary")),
    Case("calibrate-out-not-writable", lambda w: calib("--out", w.p("c.toml"))(w), ("cannot write",),
         patch=lambda mp, w: deny_write(mp)),
    Case("intrinsics-square-zero", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "checkerboard",
                                              "--cols", "9", "--rows", "6", "--square-m", "0", "--out", w.p("c.toml")],
         ("--square-m",)),
    Case("intrinsics-square-nan", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "checkerboard",
                                             "--cols", "9", "--rows", "6", "--square-m", "nan", "--out", w.p("c.toml")],
         ("--square-m",)),
    Case("intrinsics-cols-zero", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "checkerboard",
                                            "--cols", "0", "--rows", "6", "--square-m", "0.02", "--out", w.p("c.toml")],
         ("--cols",)),
    Case("intrinsics-marker-negative", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "charuco",
                                                  "--cols", "9", "--rows", "6", "--square-m", "0.02", "--marker-m",
                                                  "-1", "--out", w.p("c.toml")], ("--marker-m",)),
    Case("intrinsics-every-nth-zero", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "checkerboard",
                                                 "--cols", "9", "--rows", "6", "--square-m", "0.02", "--every-nth", "0",
                                                 "--out", w.p("c.toml")], ("--every-nth",)),
    Case("intrinsics-out-folder", lambda w: ["calibrate-intrinsics", w.p("a.png"), "--board", "checkerboard",
                                             "--cols", "9", "--rows", "6", "--square-m", "0.02", "--out", str(w.root)],
         ("folder",)),
]


def dlt(*extra, xypts="xypts.csv", coefs="dltCoefs.csv", out="new"):
    def argv(w):
        w.copy("dlt")
        return ["import", "dltdv", "--xypts", w.p("dlt", xypts), "--coefs", w.p("dlt", coefs), "--fps", "100",
                "--out", w.p(out), *extra]
    return argv


def dlt_edit(fn, *extra, **kw):
    def argv(w):
        a = dlt(*extra, **kw)(w)
        fn(w.root / "dlt")
        return a
    return argv


IMPORT_CASES = [
    Case("dlt-fps-zero", dlt("--fps", "0"), ("--fps",)),
    Case("dlt-fps-nan", dlt("--fps", "nan"), ("--fps",)),
    Case("dlt-fps-negative", dlt("--fps", "-1"), ("--fps",)),
    Case("dlt-image-size-zero", dlt("--image-size", "0", "720"), ("--image-size",)),
    Case("dlt-image-size-negative", dlt("--image-size", "-1280", "720"), ("--image-size",)),
    Case("dlt-pixel-sigma-negative", dlt("--pixel-sigma", "-1"), ("--pixel-sigma",)),
    Case("dlt-pixel-sigma-nan", dlt("--pixel-sigma", "nan"), ("--pixel-sigma",)),
    Case("dlt-xypts-missing", dlt(xypts="nope.csv"), ("nope.csv", "not found")),
    Case("dlt-xypts-folder", dlt(xypts="."), ("dlt", "folder")),
    Case("dlt-xypts-binary", dlt_edit(lambda d: binary(d / "xypts.csv")), ("xypts.csv", "binary")),
    Case("dlt-xypts-utf16", dlt_edit(lambda d: recode(d / "xypts.csv", "utf-16")), ("xypts.csv", "utf-16")),
    Case("dlt-xypts-latin1", dlt_edit(lambda d: write(d / "xypts.csv", (d / "xypts.csv").read_bytes()
                                                      .replace(b"\n", b"\n\xe9", 1))), ("xypts.csv", "utf-8")),
    Case("dlt-xypts-semicolons", dlt_edit(lambda d: semicolons(d / "xypts.csv")), ("xypts.csv", "semicolon")),
    Case("dlt-xypts-bad-header", dlt_edit(lambda d: replace_text(d / "xypts.csv", "pt1_cam1_X", "point1")),
         ("xypts.csv", "line 1", "point1")),
    Case("dlt-xypts-duplicate-column", dlt_edit(lambda d: replace_text(d / "xypts.csv", "pt1_cam1_Y", "pt1_cam1_X")),
         ("xypts.csv", "line 1", "pt1_cam1_X")),
    Case("dlt-xypts-text-cell", dlt_edit(lambda d: set_cell(d / "xypts.csv", 2, "pt1_cam1_X", "abc")),
         ("xypts.csv", "line 2", "abc")),
    Case("dlt-xypts-empty", dlt_edit(lambda d: write(d / "xypts.csv", "")), ("xypts.csv", "empty")),
    Case("dlt-xypts-header-only", dlt_edit(lambda d: write(d / "xypts.csv", (d / "xypts.csv").read_text()
                                                           .splitlines()[0] + "\n")), ("xypts.csv",)),
    Case("dlt-xypts-unreadable", dlt(), ("xypts.csv", "permission"), patch=lambda mp, w: deny_read(mp, "xypts.csv")),
    Case("dlt-coefs-10-rows", dlt_edit(lambda d: write(d / "dltCoefs.csv", "\n".join(
        (d / "dltCoefs.csv").read_text().splitlines()[:10]) + "\n")), ("dltCoefs.csv", "11 rows")),
    Case("dlt-coefs-text", dlt_edit(lambda d: write(d / "dltCoefs.csv", "x" + (d / "dltCoefs.csv").read_text())),
         ("dltCoefs.csv", "line 1")),
    Case("dlt-coefs-latin1", dlt_edit(lambda d: write(d / "dltCoefs.csv", b"\xe9" + (d / "dltCoefs.csv").read_bytes())),
         ("dltCoefs.csv", "utf-8")),
    Case("dlt-coefs-empty", dlt_edit(lambda d: write(d / "dltCoefs.csv", "")), ("dltCoefs.csv", "empty")),
    Case("dlt-coefs-zero", dlt_edit(lambda d: write(d / "dltCoefs.csv", "0,0,0\n" * 11)),
         ("dltCoefs.csv", "degenerate")),
    Case("dlt-coefs-semicolons", dlt_edit(lambda d: semicolons(d / "dltCoefs.csv")), ("dltCoefs.csv", "semicolon")),
    Case("dlt-xyzpts-garbage", dlt_edit(lambda d: write(d / "xyz.csv", "hello\n1\n"), "--xyzpts", "XYZ"),
         ("xyz",)),
    Case("dlt-out-is-file", lambda w: dlt(out="f.txt")(w) if write(w.root / "f.txt", "x") else None,
         ("f.txt", "file")),
    Case("dlt-out-under-file", lambda w: dlt(out="f.txt/s")(w) if write(w.root / "f.txt", "x") else None,
         ("f.txt", "file")),
    Case("dlt-out-not-writable", dlt(), ("new", "cannot write"), patch=lambda mp, w: deny_write(mp)),
    Case("dlt-disk-full", dlt(), ("no space",), patch=lambda mp, w: fail_writes(mp, errno.ENOSPC), writes_fail=True),
]
# the xyzpts case names the file by a relative-looking option: make it a real path
IMPORT_CASES[[c.id for c in IMPORT_CASES].index("dlt-xyzpts-garbage")] = Case(
    "dlt-xyzpts-garbage", lambda w: dlt_edit(lambda d: write(d / "xyz.csv", "hello\n1\n"), "--xyzpts",
                                             w.p("dlt", "xyz.csv"))(w), ("xyz.csv",))


def dlc(*extra, out="new", files=None):
    def argv(w):
        d = w.copy("dlc")
        fs = files or ["cam1.csv", "cam2.csv", "cam3.csv"]
        return ["import", "deeplabcut", *[str(d / f) for f in fs], "--calibration", str(d / "calibration.toml"),
                "--fps", "100", "--out", w.p(out), *extra]
    return argv


def dlc_edit(fn, *extra, **kw):
    def argv(w):
        a = dlc(*extra, **kw)(w)
        fn(w.root / "dlc")
        return a
    return argv


def pose(*extra, out="new"):
    def argv(w):
        d = w.copy("pose")
        w.copy("dlc")
        return ["import", "pose2sim", str(d / "cam1"), str(d / "cam2"), str(d / "cam3"), "--calibration",
                w.p("dlc", "calibration.toml"), "--fps", "100", "--out", w.p(out), *extra]
    return argv


def pose_edit(fn, *extra):
    def argv(w):
        a = pose(*extra)(w)
        fn(w.root / "pose")
        return a
    return argv


def first_json(d: Path) -> Path:
    return sorted((d / "cam2").glob("*.json"))[0]


def anipose(*extra, project="ani"):
    def argv(w):
        d = w.copy("dlc")
        p = w.root / "ani"
        (p / "pose-2d").mkdir(parents=True, exist_ok=True)
        (p / "calibration").mkdir(exist_ok=True)
        shutil.copy(d / "calibration.toml", p / "calibration" / "calibration.toml")
        for c, letter in zip(("cam1", "cam2", "cam3"), "ABC", strict=True):
            shutil.copy(d / f"{c}.csv", p / "pose-2d" / f"trial-cam{letter}.csv")
        return ["import", "anipose", w.p(project), "--fps", "100", "--out", w.p("new"), "--calibration",
                w.p("dlc", "calibration.toml"), *extra]
    return argv


def anipose_edit(fn, *extra):
    def argv(w):
        a = anipose(*extra)(w)
        fn(w.root / "ani")
        return a
    return argv


IMPORT_CASES += [
    Case("dlc-header", dlc_edit(lambda d: replace_text(d / "cam2.csv", "bodyparts", "parts")),
         ("cam2.csv", "line 2", "bodyparts")),
    Case("dlc-binary", dlc_edit(lambda d: binary(d / "cam2.csv")), ("cam2.csv",)),
    Case("dlc-utf16", dlc_edit(lambda d: recode(d / "cam2.csv", "utf-16")), ("cam2.csv", "utf-16")),
    Case("dlc-latin1", dlc_edit(lambda d: write(d / "cam2.csv", (d / "cam2.csv").read_bytes()
                                                .replace(b"DLC", b"DL\xc9", 1))), ("cam2.csv", "utf-8")),
    Case("dlc-text-cell", dlc_edit(lambda d: replace_text(d / "cam2.csv", "\n3,", "\n3,abc")),
         ("cam2.csv", "line 7", "abc")),
    Case("dlc-frame-negative", dlc_edit(lambda d: replace_text(d / "cam2.csv", "\n3,", "\n-3,")),
         ("cam2.csv", "line 7")),
    Case("dlc-frame-huge", dlc_edit(lambda d: replace_text(d / "cam2.csv", "\n3,", "\n300000000,")),
         ("cam2.csv", "line 7")),
    Case("dlc-frame-gap", dlc_edit(lambda d: replace_text(d / "cam2.csv", "\n9,", "\n9000000,")),
         ("cam2.csv", "line 13", "9000000")),
    Case("dlc-empty", dlc_edit(lambda d: write(d / "cam2.csv", "")), ("cam2.csv",)),
    Case("dlc-threshold-big", dlc("--threshold", "1.5"), ("--threshold",)),
    Case("dlc-threshold-nan", dlc("--threshold", "nan"), ("--threshold",)),
    Case("dlc-fps-zero", dlc("--fps", "0"), ("--fps",)),
    Case("dlc-calibration-missing", dlc_edit(lambda d: (d / "calibration.toml").unlink()),
         ("calibration.toml", "not found")),
    Case("dlc-calibration-utf16", dlc_edit(lambda d: recode(d / "calibration.toml", "utf-16")),
         ("calibration.toml", "utf-16")),
    Case("dlc-file-missing", dlc(files=["cam1.csv", "cam2.csv", "nope.csv"]), ("nope.csv", "not found")),
    Case("dlc-h5-garbage", dlc_edit(lambda d: binary(d / "cam3.h5"), files=["cam1.csv", "cam2.csv", "cam3.h5"]),
         ("cam3.h5",)),
    Case("dlc-out-is-file", lambda w: dlc(out="f.txt")(w) if write(w.root / "f.txt", "x") else None,
         ("f.txt", "file")),
    Case("dlc-unreadable", dlc(), ("cam3.csv", "permission"), patch=lambda mp, w: deny_read(mp, "cam3.csv")),
    Case("anipose-missing", anipose(project="nope"), ("nope", "not found")),
    Case("anipose-config-not-toml", anipose_edit(lambda p: write(p / "config.toml", "[[[")), ("config.toml", "toml")),
    Case("anipose-config-binary", anipose_edit(lambda p: binary(p / "config.toml")), ("config.toml", "binary")),
    Case("anipose-config-threshold", anipose_edit(lambda p: write(p / "config.toml",
                                                                  "[triangulation]\nscore_threshold = 'high'\n")),
         ("config.toml", "score_threshold")),
    Case("anipose-cam-regex", anipose("--cam-regex", "("), ("cam_regex",)),
    Case("anipose-threshold", anipose("--threshold", "-0.1"), ("--threshold",)),
    Case("anipose-fps", anipose("--fps", "nan"), ("--fps",)),
    Case("pose-missing-dir", pose_edit(lambda d: shutil.rmtree(d / "cam2")), ("cam2", "not found")),
    Case("pose-not-json", pose_edit(lambda d: write(first_json(d), "{people: ")), ("cam2", ".json", "json")),
    Case("pose-json-utf16", pose_edit(lambda d: recode(first_json(d), "utf-16")), ("cam2", ".json", "utf-16")),
    Case("pose-json-binary", pose_edit(lambda d: binary(first_json(d))), ("cam2", ".json", "binary")),
    Case("pose-json-no-people", pose_edit(lambda d: write(first_json(d), '{"persons": []}')),
         ("cam2", ".json", "people")),
    Case("pose-json-list", pose_edit(lambda d: write(first_json(d), "[1, 2]")), ("cam2", ".json", "people")),
    Case("pose-json-text-keypoint", pose_edit(lambda d: write(first_json(d), json.dumps(
        {"people": [{"pose_keypoints_2d": ["a"] * 75}]}))), ("cam2", ".json")),
    Case("pose-json-person-not-object", pose_edit(lambda d: write(first_json(d), '{"people": [3]}')),
         ("cam2", ".json", "people")),
    Case("pose-person-negative", pose("--person", "-1"), ("--person",)),
    Case("pose-threshold-nan", pose("--threshold", "nan"), ("--threshold",)),
    Case("pose-keypoints", pose("--keypoints", "BODY_99"), ("BODY_99",)),
    Case("pose-fps", pose("--fps", "-5"), ("--fps",)),
    Case("pose-pixel-sigma", pose("--pixel-sigma", "0"), ("--pixel-sigma",)),
    Case("pose-trc-missing", lambda w: pose("--reference-trc", w.p("nope.trc"))(w), ("nope.trc", "not found")),
    Case("pose-trc-utf16", lambda w: pose("--reference-trc", str(write(w.root / "a.trc", "PathFileType\t4\n"
                                                                        .encode("utf-16"))))(w), ("a.trc", "utf-16")),
    Case("pose-frame-gap", pose_edit(lambda d: shutil.copy(first_json(d), d / "cam2" / "cam2_000009000000.json")),
         ("cam2", "9000000")),
    Case("import-format", lambda w: ["import", "vicon", "x"], ("vicon",)),
]


def exp(fmt, *extra):
    return lambda w: ["export", fmt, str(w.r), *extra]


def exp_edit(fn, fmt, *extra):
    def argv(w):
        a = exp(fmt, *extra)(w)
        fn(w.r)
        return a
    return argv


def traj_cell(line, col, value):
    return lambda r: set_cell(r / "trajectories.csv", line, col, value)


EXPORT_CASES = [
    Case("export-missing", lambda w: ["export", "c3d", w.p("nope")], ("nope",)),
    Case("export-traj-empty", exp_edit(lambda r: write(r / "trajectories.csv", ""), "dltdv"),
         ("trajectories.csv", "empty")),
    Case("export-traj-garbage", exp_edit(lambda r: binary(r / "trajectories.csv"), "c3d"),
         ("trajectories.csv", "binary")),
    Case("export-traj-text", exp_edit(lambda r: write(r / "trajectories.csv", "hello world\n"), "trc"),
         ("trajectories.csv", "column")),
    Case("export-traj-header-only", exp_edit(lambda r: write(r / "trajectories.csv", (
        r / "trajectories.csv").read_text().splitlines()[0] + "\n"), "trc"), ("trajectories.csv",)),
    Case("export-traj-utf16", exp_edit(lambda r: recode(r / "trajectories.csv", "utf-16"), "c3d"),
         ("trajectories.csv", "utf-16")),
    Case("export-traj-semicolons", exp_edit(lambda r: semicolons(r / "trajectories.csv"), "c3d"),
         ("trajectories.csv", "semicolon")),
    Case("export-traj-missing-column", exp_edit(lambda r: replace_text(r / "trajectories.csv", "cov_zz", "cov_qq"),
                                                "dltdv"), ("trajectories.csv", "cov_zz")),
    Case("export-frame-negative", exp_edit(traj_cell(2, "frame", "-3"), "dltdv"), ("trajectories.csv", "line 2")),
    Case("export-frame-huge", exp_edit(traj_cell(2, "frame", "1000000000"), "dltdv"), ("trajectories.csv", "line 2")),
    Case("export-frame-gap", exp_edit(traj_cell(2, "frame", "5000000"), "dltdv"), ("trajectories.csv", "5000000")),
    Case("export-x-text", exp_edit(traj_cell(3, "x", "abc"), "c3d"), ("trajectories.csv", "line 3", "x")),
    Case("export-reproj-missing", exp_edit(lambda r: (r / "reprojection.csv").unlink(), "dltdv"),
         ("reprojection.csv", "not found")),
    Case("export-reproj-garbage", exp_edit(lambda r: binary(r / "reprojection.csv"), "dltdv"),
         ("reprojection.csv", "binary")),
    Case("export-reproj-err-text", exp_edit(lambda r: set_cell(r / "reprojection.csv", 2, "err_px", "big"), "dltdv"),
         ("reprojection.csv", "line 2", "err_px")),
    Case("export-summary-not-json", exp_edit(lambda r: write(r / "summary.json", "{fps: 120"), "c3d"),
         ("summary.json", "json")),
    Case("export-summary-no-fps", exp_edit(lambda r: write(r / "summary.json", "{}"), "trc"), ("summary.json", "fps")),
    Case("export-summary-fps-negative", exp_edit(lambda r: write(r / "summary.json", '{"fps": -1}'), "trc"),
         ("summary.json", "fps")),
    Case("export-summary-fps-text", exp_edit(lambda r: write(r / "summary.json", '{"fps": "fast"}'), "c3d"),
         ("summary.json", "fps")),
    Case("export-summary-list", exp_edit(lambda r: write(r / "summary.json", "[120]"), "c3d"), ("summary.json",)),
    Case("export-summary-missing", exp_edit(lambda r: (r / "summary.json").unlink(), "c3d"),
         ("summary.json", "--fps")),
    Case("export-summary-binary-dltdv", exp_edit(lambda r: binary(r / "summary.json"), "dltdv"),
         ("summary.json", "binary")),
    Case("export-summary-import-units", exp_edit(lambda r: write(r / "summary.json", json.dumps(
        {**json.loads((r / "summary.json").read_text()), "import": {"units": "furlong"}})), "dltdv"),
         ("summary.json", "units")),
    Case("export-fps-zero", exp("c3d", "--fps", "0"), ("--fps",)),
    Case("export-fps-negative", exp("trc", "--fps", "-5"), ("--fps",)),
    Case("export-fps-nan", exp("trc", "--fps", "nan"), ("--fps",)),
    Case("export-to-folder", lambda w: exp("c3d", "--to", str(w.root))(w), ("folder",)),
    Case("export-to-under-file", lambda w: exp("trc", "--to", str(write(w.root / "f.txt", "x")) + "/a.trc")(w),
         ("f.txt", "file")),
    Case("export-to-not-writable", lambda w: exp("c3d", "--to", w.p("x.c3d"))(w), ("cannot write",),
         patch=lambda mp, w: deny_write(mp)),
    Case("export-method", exp("c3d", "--method", "kalman"), ("kalman",)),
    Case("export-format", exp("fbx"), ("fbx",)),
    Case("export-disk-full", exp("dltdv"), ("no space",), patch=lambda mp, w: fail_writes(mp, errno.ENOSPC)),
    Case("view-missing", lambda w: ["view", w.p("nope")], ("nope", "not found")),
    Case("view-no-recording", lambda w: ["view", str(w.r)], ("recording.rrd",)),
    Case("view-rrd-missing", lambda w: ["view", w.p("x.rrd")], ("x.rrd",)),
    Case("view-no-display", lambda w: ["view", str(write(w.root / "x.rrd", b"RRF2"))], ("display",),
         patch=lambda mp, w: (mp.delenv("DISPLAY", raising=False), mp.delenv("WAYLAND_DISPLAY", raising=False))),
]

BAD = SESSION_CASES + VALIDATE_CASES + SIMULATE_CASES + CALIBRATE_CASES + IMPORT_CASES + EXPORT_CASES


def test_the_table_is_large_and_ids_unique():
    ids = [c.id for c in BAD]
    assert len(ids) >= 150 and len(set(ids)) == len(ids)


@pytest.mark.parametrize("case", BAD, ids=[c.id for c in BAD])
def test_bad_input_is_one_line_exit_2(case: Case, base, tmp_path, capsys, monkeypatch):
    w = W(base, tmp_path / "w")
    w.root.mkdir()
    argv = case.argv(w)
    before = _tree_hash(w.root)
    if case.patch:
        case.patch(monkeypatch, w)
    capsys.readouterr()
    rc = main(argv)
    monkeypatch.undo()
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip()]
    assert rc == 2, (rc, captured.err[-2000:])
    assert "Traceback" not in captured.err
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("batgraph"), lines[0]
    for word in case.words:
        assert word.lower() in lines[0].lower(), (word, lines[0])
    after = _tree_hash(w.root)
    if case.writes_fail:  # the output folder may have been created; no file in it
        after = {k: v for k, v in after.items() if not (v == "dir" and k not in before)}
    assert after == before, "inputs changed or output written"


# ----------------------------------------------------------------------------------------------
# odd but legitimate input
# ----------------------------------------------------------------------------------------------
def _bom(path: Path) -> None:
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())


def _crlf(path: Path) -> None:
    path.write_bytes(path.read_bytes().replace(b"\n", b"\r\n"))


GOOD = [
    ("bom-everywhere", lambda w: [_bom(w.s / n) for n in ("session.toml", "calibration.toml", "observations.csv",
                                                            "truth.csv", "truth_mislabels.csv")]),
    ("crlf-everywhere", lambda w: [_crlf(w.s / n) for n in ("session.toml", "calibration.toml", "observations.csv",
                                                              "truth.csv")]),
    ("parquet-observations", to_parquet()),
    ("utf8-marker-names", lambda w: [replace_text(w.s / n, "body1", "körper1") for n in
                                     ("session.toml", "session.toml", "observations.csv", "truth.csv")]),
]


@pytest.mark.parametrize("prep", [g[1] for g in GOOD], ids=[g[0] for g in GOOD])
def test_odd_but_valid_input_succeeds(prep, base, tmp_path, capsys):
    w = W(base, tmp_path / "w")
    w.root.mkdir()
    prep(w)
    before = _tree_hash(w.s)
    rc = main(["reconstruct", str(w.s), "--out", w.p("o"), "--methods", "triangulate", "--viewer", "none", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert (w.root / "o" / "trajectories.csv").is_file()
    assert _tree_hash(w.s) == before


def test_export_with_bom_and_crlf_result(base, tmp_path, capsys):
    w = W(base, tmp_path / "w")
    w.root.mkdir()
    for n in ("trajectories.csv", "reprojection.csv", "summary.json"):
        _bom(w.r / n)
        _crlf(w.r / n)
    assert main(["export", "trc", str(w.r), "--to", w.p("a.trc")]) == 0, capsys.readouterr().err
    assert main(["export", "dltdv", str(w.r), "--to", w.p("d_")]) == 0, capsys.readouterr().err
    assert (w.root / "a.trc").is_file() and (w.root / "d_xyzpts.csv").is_file()


def test_import_dltdv_and_deeplabcut_with_bom_and_crlf(base, tmp_path, capsys):
    """Excel's "CSV UTF-8" starts with a byte-order mark and Windows ends lines with CRLF: both are read."""
    w = W(base, tmp_path / "w")
    w.root.mkdir()
    d, k = w.copy("dlt"), w.copy("dlc")
    for p in (d / "xypts.csv", d / "dltCoefs.csv", k / "cam1.csv", k / "calibration.toml"):
        _bom(p)
        _crlf(p)
    assert main(["import", "dltdv", "--xypts", str(d / "xypts.csv"), "--coefs", str(d / "dltCoefs.csv"),
                 "--fps", "100", "--out", w.p("a")]) == 0, capsys.readouterr().err
    assert main(["import", "deeplabcut", *(str(k / f"cam{i}.csv") for i in (1, 2, 3)), "--calibration",
                 str(k / "calibration.toml"), "--fps", "100", "--out", w.p("b")]) == 0, capsys.readouterr().err
