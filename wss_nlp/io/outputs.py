"""Output paths: checked before any solving, written only when complete.

Every command that writes checks all its output paths first
(:func:`check_outputs`), so a bad path costs no computation and leaves
nothing behind: an existing directory where a file is wanted (or the
reverse), a folder that does not exist or cannot be written, an output that
is one of the inputs, two outputs that are the same file, and any existing
path that is not a regular file (a device such as ``/dev/full``, a FIFO, a
socket): an output only ever replaces a regular file. Files are written
through :func:`wss_nlp.io.files.atomic_h5` / :func:`wss_nlp.io.files.atomic_write`
(:func:`write_bytes`: a temporary file renamed into place when complete, so a
full disk or any other OS error leaves nothing behind); figure folders are
filled through :class:`StagedFolder`, so a failure half way through a figure
set removes what that run wrote.

Temporary files and staged folders carry the writing process's id
(``.wss-nlp-<pid>-*.part``, ``.wss-nlp-part-<pid>-*``). A run killed where it
could not clean up (SIGKILL, a power cut) leaves them; the next run that
writes to the same folder removes those whose process is gone
(:func:`remove_stale`). SIGTERM and SIGINT unwind the command line's writes
like any error (:func:`wss_nlp.app.cli.main.main`).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import stat
import tempfile
import time

from ..errors import InputError

#: Prefix of the temporary files of atomic writes and of staged folders (followed by the writer's process id).
TEMP_PREFIX = ".wss-nlp-"
STAGE_PREFIX = ".wss-nlp-part-"
#: Leftovers named before process ids were part of the name are removed once they are this old (seconds).
LEGACY_AGE_S = 24 * 3600.0
_OWNED = re.compile(r"^\.wss-nlp-(?:part-)?(\d+)-")


def _kind(mode: int) -> str:
    """What a non-regular file is, in words."""
    for test, word in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return word
    return "not a regular file"


def check_replaceable(path: str, label: str = "") -> None:
    """InputError unless ``path`` does not exist or is a regular file (or a link to one): an output only ever
    replaces a regular file, never a device, a FIFO, a socket or a directory."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return
    except OSError as exc:
        raise InputError(f"{label + ' ' if label else ''}{path}: cannot be checked ({exc.strerror})") from None
    if not stat.S_ISREG(mode):
        raise InputError(
            f"{label + ' ' if label else ''}{path}: exists and is {_kind(mode)}, not a regular file; wss-nlp "
            "writes regular files only and never replaces anything else: name a new file"
        )


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale(folder: str) -> list[str]:
    """Remove the temporary files and staged folders that killed runs left in ``folder``; returns their paths.

    Only names this package makes are touched, and only when the process named in them is gone (or, for the
    names of older versions without a process id, when they are older than :data:`LEGACY_AGE_S`).
    """
    removed: list[str] = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    now = time.time()
    for name in names:
        if not name.startswith(TEMP_PREFIX):
            continue
        path = os.path.join(folder, name)
        m = _OWNED.match(name)
        try:
            if m is not None:
                if _alive(int(m.group(1))):
                    continue
            elif not (name.startswith(STAGE_PREFIX) and now - os.lstat(path).st_mtime > LEGACY_AGE_S):
                continue
            if os.path.isdir(path) and not os.path.islink(path):
                shutil.rmtree(path)
            else:
                os.remove(path)
            removed.append(path)
        except OSError:  # another run removed it first, or it is not ours to remove
            continue
    return removed


def write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, synced, renamed into place.

    ``path`` may be new or a regular file (:func:`check_replaceable`). Any OS error (a full disk, a quota, a
    folder that became read-only) is one :class:`InputError` line naming the file, and nothing is left behind.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"{path}: output folder {folder} does not exist")
    check_replaceable(path)
    remove_stale(folder)
    tmp = ""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{os.getpid()}-", suffix=".part", dir=folder)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)  # mkstemp creates 0600; give the file the permissions a plain open() would
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:
        raise InputError(os_error_text(exc, path)) from None
    finally:
        if tmp and os.path.exists(tmp):
            os.remove(tmp)


def os_error_text(exc: OSError, path=None) -> str:
    """One line for an OS error while writing ``path``: the file, what happened, what to do; nothing was written."""
    where = os.fspath(path) if path is not None else os.fspath(exc.filename or "") or "wss-nlp"
    what = exc.strerror or str(exc)
    fix = {
        errno.ENOSPC: "the disk is full: free some space or write elsewhere",
        errno.EDQUOT: "the disk quota is exhausted: free some space or write elsewhere",
        errno.EFBIG: "the file is larger than this file system or process allows: write elsewhere",
        errno.EROFS: "the file system is read-only: write elsewhere",
        errno.EACCES: "permission denied: choose a folder you can write to",
        errno.EPERM: "not permitted: choose a folder you can write to",
        errno.EIO: "an input/output error of the device: check the disk",
    }.get(exc.errno or 0, "check the path and the disk")
    if path is None:  # an OS error the command line caught: the writes unwound, so nothing was left either
        return f"{where}: {what}; {fix}"
    return f"{where}: cannot write ({what}); {fix}; nothing was written"


def _nearest_existing(path: str) -> str:
    """The path itself or its closest existing ancestor."""
    path = os.path.abspath(path)
    while not os.path.exists(path):
        parent = os.path.dirname(path)
        if parent == path:
            break
        path = parent
    return path


def _writable_folder(folder: str, label: str, path: str) -> None:
    if not os.path.isdir(folder):
        raise InputError(f"{label} {path}: {folder} is not a folder")
    try:  # a real probe: permission bits say nothing for root, read-only mounts or special file systems
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise InputError(
            f"{label} {path}: folder {folder} is not writable ({exc.strerror or exc}); choose another place"
        ) from None


def check_output_file(path: str, label: str = "-o") -> str:
    """Raise :class:`InputError` unless ``path`` can be written as a file; return its absolute path.

    The parent folder must exist (we never create a tree for a single file:
    a typo in a folder name should not silently create it).
    """
    if not path:
        raise InputError(f"{label}: empty output path")
    full = os.path.abspath(path)
    if os.path.isdir(full):
        raise InputError(
            f"{label} {path}: is an existing directory; name a file inside it, e.g. {os.path.join(path, 'result.h5')}"
        )
    check_replaceable(full, label)
    folder = os.path.dirname(full)
    if not os.path.exists(folder):
        raise InputError(f"{label} {path}: output folder {folder} does not exist; create it first")
    _writable_folder(folder, label, path)
    if os.path.exists(full) and not os.access(full, os.W_OK):
        raise InputError(f"{label} {path}: the file exists and is read-only; remove it or choose another name")
    return full


def check_output_folder(path: str, label: str) -> str:
    """Raise :class:`InputError` unless ``path`` is (or can be created as) a writable folder."""
    if not path:
        raise InputError(f"{label}: empty folder path")
    full = os.path.abspath(path)
    if os.path.exists(full) and not os.path.isdir(full):
        raise InputError(f"{label} {path}: is an existing file, not a folder; name a folder")
    _writable_folder(_nearest_existing(full), label, path)
    return full


def _same(a: str, b: str) -> bool:
    if os.path.exists(a) and os.path.exists(b):
        return os.path.samefile(a, b)
    return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(files: dict | None = None, folders: dict | None = None, inputs=()) -> None:
    """Check every output path of a command before it computes anything.

    Parameters
    ----------
    files : dict
        ``{label: path}`` of output files (None values are skipped).
    folders : dict
        ``{label: path}`` of output folders (None values are skipped).
    inputs : iterable of str
        Files the command reads; no output may be one of them (an input is
        never modified), nor lie inside an output folder's place.
    """
    files = {k: v for k, v in (files or {}).items() if v}
    folders = {k: v for k, v in (folders or {}).items() if v}
    for label, path in files.items():
        check_output_file(path, label)
        remove_stale(os.path.dirname(os.path.abspath(path)))
    for label, path in folders.items():
        check_output_folder(path, label)
        remove_stale(_nearest_existing(os.path.dirname(os.path.abspath(path))))
    for inp in inputs:
        for label, path in list(files.items()) + list(folders.items()):
            if _same(inp, path):
                raise InputError(
                    f"{label} {path}: is the input file {inp}; inputs are never overwritten, choose another output name"
                )
    outs = list(files.items()) + list(folders.items())
    for i, (la, a) in enumerate(outs):
        for lb, b in outs[i + 1 :]:
            if _same(a, b):
                raise InputError(f"{la} and {lb} both name {a}; give them different paths")


class StagedFolder:
    """Files written into a temporary folder and moved into ``target`` only on :meth:`commit`.

    Use as a context manager: leaving it with an exception removes the
    temporary folder (and ``target`` too when this run created it), so a
    failed figure set leaves nothing behind. Files already in ``target``
    with other names are never touched; same-named ones are replaced at
    commit. ``target=None`` stages nothing (``path`` is None, commit a no-op).
    """

    def __init__(self, target: str | None):
        self.target = "" if target is None else os.path.abspath(target)
        self.path: str | None = None
        self._created = False
        if target is not None:
            self._created = not os.path.exists(self.target)
            parent = _nearest_existing(self.target)
            remove_stale(parent)
            self.path = tempfile.mkdtemp(prefix=f"{STAGE_PREFIX}{os.getpid()}-", dir=parent)

    def __enter__(self) -> StagedFolder:
        return self

    def commit(self) -> list[str]:
        """Move the staged files into ``target``; return their final paths."""
        if self.path is None:
            return []
        os.makedirs(self.target, exist_ok=True)
        out = []
        for name in sorted(os.listdir(self.path)):
            dst = os.path.join(self.target, name)
            check_replaceable(dst)
            os.replace(os.path.join(self.path, name), dst)
            out.append(dst)
        return out

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.path is None:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        if exc_type is not None and self._created and os.path.isdir(self.target) and not os.listdir(self.target):
            os.rmdir(self.target)
