"""Outputs under faults (wss_nlp.io.outputs): only regular files are replaced, temporary files carry their writer's
process id and are removed once it is gone, and a failed write leaves nothing."""

import errno
import os
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from wss_nlp.errors import InputError
from wss_nlp.io import files as wio
from wss_nlp.io import outputs


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_only_regular_files_are_replaced(tmp_path):
    (tmp_path / "old.h5").write_bytes(b"x")
    outputs.check_replaceable(str(tmp_path / "old.h5"))
    outputs.check_replaceable(str(tmp_path / "new.h5"))
    os.mkfifo(tmp_path / "fifo")
    for path, kind in ((tmp_path / "fifo", "FIFO"), (tmp_path, "a directory"), ("/dev/null", "character device")):
        with pytest.raises(InputError, match=kind):
            outputs.check_replaceable(str(path), "-o")
        with pytest.raises(InputError, match=kind):
            outputs.write_bytes(str(path), b"data")  # refused before anything is opened (a FIFO would block)
    assert sorted(os.listdir(tmp_path)) == ["fifo", "old.h5"]


def test_leftovers_of_dead_writers_go_and_those_of_live_ones_stay(tmp_path):
    dead, me = _dead_pid(), os.getpid()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        names = {
            f".wss-nlp-{dead}-a.part": False,  # False: removed
            f".wss-nlp-part-{dead}-b": False,
            f".wss-nlp-{me}-c.part": True,
            f".wss-nlp-part-{live.pid}-d": True,
            ".wss-nlp-part-oldname": False,  # no process id (older versions): removed when a day old
            ".wss-nlp-part-newname": True,
            "result.h5": True,
        }
        for name in names:
            p = tmp_path / name
            p.mkdir() if "part-" in name else p.write_bytes(b"x")
        day = time.time() - outputs.LEGACY_AGE_S - 60
        os.utime(tmp_path / ".wss-nlp-part-oldname", (day, day))
        removed = outputs.remove_stale(str(tmp_path))
        assert sorted(os.path.basename(p) for p in removed) == sorted(n for n, keep in names.items() if not keep)
        assert sorted(os.listdir(tmp_path)) == sorted(n for n, keep in names.items() if keep)
    finally:
        live.kill()
        live.wait()


@pytest.mark.parametrize(
    "code, words", [(errno.ENOSPC, "the disk is full"), (errno.EDQUOT, "quota"), (errno.EIO, "input/output error")]
)
def test_a_failed_write_leaves_nothing_and_names_the_file(code, words, tmp_path, monkeypatch):
    def fail(fd):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(outputs.os, "fsync", fail)
    (tmp_path / "keep.h5").write_bytes(b"the previous result")
    with pytest.raises(InputError, match=rf"keep\.h5: cannot write .*{words}.*nothing was written"):
        wio.write_acquisition(tmp_path / "keep.h5", _acquisition())
    assert sorted(os.listdir(tmp_path)) == ["keep.h5"] and (tmp_path / "keep.h5").read_bytes() == b"the previous result"


def _acquisition():
    return wio.Acquisition(magnitude=np.ones((1, 8, 8)), phase=np.zeros((1, 8, 8)), venc_m_s=1.0)


def test_atomic_h5_writes_a_complete_file_once(tmp_path, monkeypatch):
    """The HDF5 file is built in memory: the disk sees one write of the whole file, renamed into place."""
    writes = []
    real = outputs.write_bytes
    monkeypatch.setattr(outputs, "write_bytes", lambda path, data: (writes.append(len(data)), real(path, data)))
    wio.write_acquisition(tmp_path / "in.h5", _acquisition())
    assert len(writes) == 1 and os.path.getsize(tmp_path / "in.h5") == writes[0]
    with h5py.File(tmp_path / "in.h5", "r") as f:
        assert f["magnitude"].shape == (1, 8, 8)
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(tmp_path / "in.h5").st_mode & 0o777 == 0o666 & ~umask  # a plain file's permissions, not mkstemp's
