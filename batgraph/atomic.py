"""Atomic writes: a crash never leaves a half-written file under its final name, nor a half-replaced result folder.

Files: :func:`atomic_path`, :func:`write_text`, :func:`write_bytes` write a temporary beside the file and
rename it over the final name.

Folders: :func:`result_folder` stages one result's files in a hidden folder beside the target (same file
system) and swaps it in by renames (tmp -> ``.NAME.batgraph-new``, NAME -> ``.NAME.batgraph-old``, new ->
NAME, remove old), so a kill leaves NAME holding the previous complete result or the new one; the next
:func:`result_folder` (or :func:`recover_folder`) removes dead processes' temporaries and finishes a half-done
swap. Files of the folder outside the set (the user's notes, exports) are carried over as hard links; a file
of the set this run does not write is not, so the folder never mixes two results. Where the folder cannot be
renamed (the working directory, a mount point, a read-only parent), its files are renamed in one at a time:
each stays whole, but a kill can leave a mix. docs/formats.md tells users the same.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
import uuid
from collections.abc import Iterable, Iterator
from pathlib import Path

from .errors import InputError

TMP_TAG = ".batgraph-tmp-"
NEW_TAG = ".batgraph-new"
OLD_TAG = ".batgraph-old"


def _umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    For writers that want a file name (ezc3d, rerun, matplotlib). The temporary keeps the
    final suffix so that libraries choosing a format by extension still work. The file gets the
    permissions of an ordinary new file (0666 less the umask), not mkstemp's 0600. On a full file
    system (:func:`disk_full`) it raises ENOSPC before any writer starts, and a writer's failure there
    becomes ENOSPC naming ``path``.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    if disk_full(final.parent):  # not started at all: a writer that meets a full disk may hang (Rerun's file sink)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(final))
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=final.suffix, dir=final.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        if tmp_path.exists():
            os.chmod(tmp_path, 0o666 & ~_umask())
        os.replace(tmp_path, final)
    except OSError as e:  # name the file the user asked for, not our temporary (or nothing)
        if e.filename in (None, tmp, str(tmp_path)) and e.errno is not None:
            raise OSError(e.errno, e.strerror, str(final)) from e
        raise
    except Exception as e:  # a library's own words for a full disk (Rerun: "File-writer thread shut down")
        if disk_full(final.parent):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(final)) from e
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


FULL_BYTES = 1 << 20
"""Free space [bytes] under which a file system counts as full when a writer fails without saying why."""


def disk_full(folder: str | os.PathLike) -> bool:
    """Whether the file system holding ``folder`` is full: less than :data:`FULL_BYTES` free for this process
    (the root-reserved blocks count for root only), or no file entry (inode) left. For writers that report a
    full disk in their own words, or not at all (Rerun's file sink raises RuntimeError)."""
    try:
        st = os.statvfs(folder)
    except (OSError, AttributeError):  # gone, or no statvfs (Windows): cannot tell
        return False
    blocks = st.f_bfree if hasattr(os, "geteuid") and os.geteuid() == 0 else st.f_bavail
    return blocks * st.f_frsize < FULL_BYTES or (st.f_files > 0 and st.f_favail == 0)


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


# ----------------------------------------------------------------------------------------------
# result folders
# ----------------------------------------------------------------------------------------------
def _siblings(target: Path) -> tuple[Path, Path]:
    """(new, old) hidden siblings of a result folder."""
    return target.parent / f".{target.name}{NEW_TAG}", target.parent / f".{target.name}{OLD_TAG}"


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # someone else's process (or unknowable): leave its folder alone
    return True


def _stale_temporaries(folder: Path, prefix: str) -> list[Path]:
    """``prefix<pid>-<random>`` entries of ``folder`` whose process is gone."""
    pat = re.compile(re.escape(prefix) + r"(\d+)-[0-9a-f]+$")
    out = []
    try:
        entries = list(folder.iterdir())
    except (FileNotFoundError, NotADirectoryError):
        return out
    for p in entries:
        m = pat.fullmatch(p.name)
        if m and not _pid_alive(int(m.group(1))):
            out.append(p)
    return out


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def _is_leftover_of(name: str, owned: set[str]) -> bool:
    """A temporary of :func:`atomic_path` for a file of the set (``.stem.XXXX.suffix``), left by a kill."""
    for o in owned:
        stem, suffix = os.path.splitext(o)
        if re.fullmatch(rf"\.{re.escape(stem)}\.[A-Za-z0-9_]{{8}}{re.escape(suffix)}", name):  # mkstemp's name
            return True
    return name.startswith(TMP_TAG)


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst, follow_symlinks=False)
    except OSError:
        shutil.copy2(src, dst, follow_symlinks=False)


def _carry(src: Path, dst: Path, owned: set[str]) -> list[str]:
    """Hard-link (or copy) the entries of ``src`` that are not in the set and not yet in ``dst``; returns names."""
    carried = []
    for p in sorted(src.iterdir()):
        if p.name in owned or _is_leftover_of(p.name, owned) or os.path.lexists(dst / p.name):
            continue
        if p.is_symlink():
            os.symlink(os.readlink(p), dst / p.name)
        elif p.is_dir():
            shutil.copytree(p, dst / p.name, symlinks=True, copy_function=_link_or_copy)
        else:
            _link_or_copy(str(p), str(dst / p.name))
        carried.append(p.name)
    return carried


def recover_folder(target: str | os.PathLike, owned: Iterable[str] = ()) -> list[str]:
    """Clean up after a killed :func:`result_folder` on ``target``; returns what was done (for messages).

    Removes the staging folders of processes that no longer run (beside and inside ``target``), then
    finishes a half-done swap: a complete ``.NAME.batgraph-new`` becomes ``NAME`` (files of ``NAME`` or
    ``.NAME.batgraph-old`` outside the set ``owned`` carried over), a lone ``.NAME.batgraph-old`` is
    restored as ``NAME``, and one beside a complete ``NAME`` is removed.
    """
    target = Path(os.path.realpath(target))
    owned = set(owned)
    done = []
    for p in _stale_temporaries(target.parent, f".{target.name}{TMP_TAG}") + _stale_temporaries(target, TMP_TAG):
        _remove(p)
        done.append(f"removed the unfinished {p.name} of a killed run")
    new, old = _siblings(target)
    if new.is_dir():
        if target.is_dir():  # killed after new was complete, before target moved aside
            _remove(old)
            os.rename(target, old)
        if old.is_dir():
            _carry(old, new, owned)
        os.rename(new, target)
        done.append(f"finished replacing {target.name} by the complete result of a killed run")
    if old.is_dir():
        if target.is_dir():
            _carry(old, target, owned)  # a file added while the swap was half done
            _remove(old)
        else:
            os.rename(old, target)
            done.append(f"restored the previous {target.name} of a killed run")
    elif os.path.lexists(old):
        _remove(old)
    return done


def _renamable(target: Path) -> bool:
    """Whether ``target`` can be swapped by renaming (see the module doc for when it cannot)."""
    try:
        cwd = Path(os.path.realpath(os.getcwd()))
    except OSError:
        cwd = None
    if cwd is not None and (cwd == target or target in cwd.parents):
        return False
    if target.is_dir() and os.path.ismount(target):
        return False
    return os.access(target.parent, os.W_OK | os.X_OK)


def _folder_mode(target: Path) -> int:
    return (target.stat().st_mode & 0o7777) if target.is_dir() else (0o777 & ~_umask())


@contextlib.contextmanager
def result_folder(target: str | os.PathLike, owned: Iterable[str], in_place: bool = False) -> Iterator[Path]:
    """Yield an empty staging folder; when the block completes, it replaces ``target`` as a whole.

    owned: names of the files that make one result (everything else in ``target`` is carried over).
    in_place: stage inside ``target`` and rename file by file (used when ``target`` is, e.g., the
        session folder itself); also chosen automatically when ``target`` cannot be renamed.
    If the block raises (or the process is killed), ``target`` is left as it was. A half-done swap
    of a killed earlier run is finished first (:func:`recover_folder`).
    """
    final = Path(os.path.realpath(target))
    owned = set(owned)
    if os.path.lexists(final) and not final.is_dir():
        raise InputError(f"{target}: exists and is not a folder")
    final.parent.mkdir(parents=True, exist_ok=True)
    recover_folder(final, owned)
    in_place = in_place or not _renamable(final)
    tag = f"{TMP_TAG}{os.getpid()}-{uuid.uuid4().hex[:12]}"
    if in_place:
        final.mkdir(exist_ok=True)
        stage = final / tag
    else:
        stage = final.parent / f".{final.name}{tag}"
    existed = final.is_dir()
    stage.mkdir()
    try:
        try:
            yield stage
            if not in_place:
                _commit_swap(stage, final, owned)  # restores the previous folder where its last rename fails
        except Exception as e:  # noqa: BLE001 - re-raised; an OS error names the folder the user gave
            told = _left_as_it_was(e, stage, final, existed)
            if told is e:
                raise
            raise told from e
        if in_place:
            _commit_in_place(stage, final, owned)
    finally:
        if stage.exists():
            _remove(stage)


def _left_as_it_was(e: Exception, stage: Path, final: Path, existed: bool) -> Exception:
    """``e``, raised while ``final`` was being staged (and so left as it was), told in the user's words: an OS
    error naming the file under ``final`` (not under the staging folder), and any error at a full disk as
    ENOSPC (writers in child processes and libraries report it their own way). The OSError returned carries
    ``unchanged = (final, existed)`` for :func:`batgraph.inputs.os_error_message`; other errors pass as they are."""
    if not isinstance(e, OSError):
        if not disk_full(final.parent if not final.is_dir() else final):
            return e
        e = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(final))
    name = e.filename if isinstance(e.filename, str) else None
    if name is not None and (name == str(stage) or name.startswith(str(stage) + os.sep)):
        name = str(final) + name[len(str(stage)):]
    out = OSError(e.errno, e.strerror, name) if e.errno is not None else OSError(*e.args)
    out.unchanged = (str(final), existed)
    return out


def _commit_swap(stage: Path, final: Path, owned: set[str]) -> None:
    new, old = _siblings(final)
    if final.is_dir():
        _carry(final, stage, owned)
    os.chmod(stage, _folder_mode(final))
    os.rename(stage, new)  # the new result is complete
    if final.is_dir():
        os.rename(final, old)
    try:
        os.rename(new, final)
    except OSError:
        if not final.exists() and old.is_dir():
            os.rename(old, final)
        raise
    _remove(old)


def _commit_in_place(stage: Path, final: Path, owned: set[str]) -> None:
    written = {p.name for p in stage.iterdir()}
    for name in sorted(written):
        dst = final / name
        if dst.is_dir() and not dst.is_symlink():
            shutil.rmtree(dst)
        os.replace(stage / name, dst)
    for name in owned - written:
        with contextlib.suppress(FileNotFoundError):
            _remove(final / name)
    try:
        stage.rmdir()
    except OSError as e:
        if e.errno not in (errno.ENOENT,):
            raise
