"""The README's Python example runs as printed (documentation that cannot rot silently)."""

import pathlib
import re

import pytest

README = pathlib.Path(__file__).resolve().parent.parent / "README.md"


def _block(after: str) -> str:
    text = README.read_text()
    return re.search(r"```python\n(.*?)```", text[text.index(after) :], re.S).group(1)


def test_python_example_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    exec(compile(_block("## Python"), "README.md", "exec"), {})
    assert (tmp_path / "out.h5").exists()
    assert "wss_rel_l2" in capsys.readouterr().out


def test_own_data_example_writes_a_readable_input(tmp_path, monkeypatch):
    from wss_nlp.io import files
    from wss_nlp.synthetic import phantoms

    acq, _ = phantoms.make_phantom("circle", h_mm=1.5, snr=25, seed=81)
    monkeypatch.chdir(tmp_path)
    exec(compile(_block("## Your own data"), "README.md", "exec"), {"mag": acq.magnitude[0], "phase": acq.phase[0]})
    back = files.read_acquisition("scan1.h5")
    assert back.venc_m_s == 1.5 and back.voxel_size_mm == (0.8, 0.8)


def test_own_data_commands_run_on_a_phantom_dicom_folder(tmp_path, monkeypatch):
    """The README's three commands (import, reconstruct, export) run as printed on a phantom written as DICOM."""
    import shlex

    pytest.importorskip("pydicom")
    pytest.importorskip("meshio")
    from wss_nlp.app.cli import main

    text = README.read_text()
    block = re.search(r"```bash\n(.*?)```", text[text.index("## Your own data") :], re.S).group(1)
    commands = [shlex.split(line.split("#")[0]) for line in block.splitlines() if line.strip()]
    assert [c[:2] for c in commands] == [["wss-nlp", "import"], ["wss-nlp", "reconstruct"], ["wss-nlp", "export"]]
    monkeypatch.chdir(tmp_path)
    assert (
        main(["phantom", "--case", "circle", "--h", "1.5", "--seed", "82", "-o", "p.h5", "--dicom", "scan1_dicom"]) == 0
    )
    for argv in commands:
        assert main(argv[1:]) == 0, argv
    assert (tmp_path / "scan1_wall.vtu").exists()
