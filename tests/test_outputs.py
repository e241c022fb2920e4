"""Output paths are checked before solving; staged folders leave nothing behind on failure."""

import os

import pytest

from wss_nlp.io import outputs
from wss_nlp.errors import InputError


def test_file_checks(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "in.h5").write_bytes(b"x")
    ok = outputs.check_output_file(str(tmp_path / "new.h5"))
    assert ok == str(tmp_path / "new.h5")
    with pytest.raises(InputError, match="existing directory"):
        outputs.check_output_file(str(tmp_path / "d"))
    with pytest.raises(InputError, match="does not exist; create it first"):
        outputs.check_output_file(str(tmp_path / "missing" / "x.h5"))
    with pytest.raises(InputError, match="not writable"):
        outputs.check_output_file("/proc/wss-nlp-test.h5")  # a real probe: permission bits lie for root
    with pytest.raises(InputError, match="is the input file"):
        outputs.check_outputs(files={"-o": str(tmp_path / "." / "in.h5")}, inputs=[str(tmp_path / "in.h5")])
    os.symlink(tmp_path / "in.h5", tmp_path / "link.h5")
    with pytest.raises(InputError, match="is the input file"):
        outputs.check_outputs(files={"-o": str(tmp_path / "link.h5")}, inputs=[str(tmp_path / "in.h5")])
    with pytest.raises(InputError, match="both name"):
        outputs.check_outputs(files={"-o": str(tmp_path / "a.h5"), "--truth": str(tmp_path / "a.h5")})


def test_folder_checks(tmp_path):
    (tmp_path / "f").write_bytes(b"x")
    assert outputs.check_output_folder(str(tmp_path / "a" / "b"), "--figures")  # created later, parent writable
    with pytest.raises(InputError, match="existing file, not a folder"):
        outputs.check_output_folder(str(tmp_path / "f"), "--figures")
    with pytest.raises(InputError, match="not a folder"):
        outputs.check_output_folder(str(tmp_path / "f" / "sub"), "--figures")


def test_staged_folder_commits_or_leaves_nothing(tmp_path):
    target = tmp_path / "figs"
    with outputs.StagedFolder(str(target)) as st:
        (open(os.path.join(st.path, "a.png"), "wb")).close()
        assert not target.exists()  # nothing visible before the commit
        paths = st.commit()
    assert [os.path.basename(p) for p in paths] == ["a.png"] and (target / "a.png").exists()
    assert sorted(os.listdir(tmp_path)) == ["figs"]  # the staging folder is gone
    other = tmp_path / "other"
    with pytest.raises(RuntimeError):
        with outputs.StagedFolder(str(other)) as st:
            (open(os.path.join(st.path, "b.png"), "wb")).close()
            raise RuntimeError("plotting failed")
    assert sorted(os.listdir(tmp_path)) == ["figs"]
