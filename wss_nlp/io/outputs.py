"""Output paths: checked before any solving, written only when complete.

Every command that writes checks all its output paths first
(:func:`check_outputs`), so a bad path costs no computation and leaves
nothing behind: an existing directory where a file is wanted (or the
reverse), a folder that does not exist or cannot be written, an output that
is one of the inputs, two outputs that are the same file. Files are written
through :func:`wss_nlp.io.files.atomic_h5` / :func:`wss_nlp.io.files.atomic_write`;
figure folders are filled through :class:`StagedFolder`, so a failure half
way through a figure set removes what that run wrote.
"""

from __future__ import annotations

import os
import shutil
import tempfile

from ..errors import InputError


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
    for label, path in folders.items():
        check_output_folder(path, label)
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
            self.path = tempfile.mkdtemp(prefix=".wss-nlp-part-", dir=_nearest_existing(self.target))

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
            os.replace(os.path.join(self.path, name), dst)
            out.append(dst)
        return out

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.path is None:
            return
        shutil.rmtree(self.path, ignore_errors=True)
        if exc_type is not None and self._created and os.path.isdir(self.target) and not os.listdir(self.target):
            os.rmdir(self.target)
