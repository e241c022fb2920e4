"""The command line a demanding user meets (issue 44): help with a description and working examples for every
subcommand, one name per phantom case, documented exit codes, a closed pipe, ``--quiet``, ``analyze --slice``,
NIfTI folders, what ``phantom --dicom/--nifti`` wrote, enhanced DICOM named as such, warnings once with a count."""

import io
import shlex
from types import SimpleNamespace

import numpy as np
import pytest

from wss_nlp.app.cli import main
from wss_nlp.app.cli import parser as cli_parser
from wss_nlp.pipeline.cine import group_warnings
from wss_nlp.errors import InputError, SolverError
from wss_nlp.io import files as wio
from wss_nlp.synthetic import phantoms


def _subparsers():
    p = cli_parser.build_parser()
    (action,) = [a for a in p._actions if a.dest == "command"]
    return p, action.choices


def test_every_subcommand_has_a_description_and_examples_that_parse():
    p, subs = _subparsers()
    assert set(subs) == set(cli_parser.EXAMPLES)  # a new subcommand needs its examples
    for name, sp in subs.items():
        assert sp.description and len(sp.description) > 40, name
        text = sp.format_help()
        assert "examples:" in text and f"wss-nlp {name}" in text, name
        for example in cli_parser.EXAMPLES[name]:
            words = shlex.split(example)
            assert words[:2] == ["wss-nlp", name]
            args = p.parse_args(words[1:])  # argparse exits (SystemExit) on an example that no longer parses
            assert args.command == name


def test_phantom_help_explains_every_case_and_cine_is_one_name_with_womersley_its_alias():
    _, subs = _subparsers()
    text = " ".join(subs["phantom"].format_help().split())
    for cases in (phantoms.CASES, phantoms.STACK_CASES):
        for case, (_, description) in cases.items():
            assert f"{case} {' '.join(description.split())}" in text, case
    assert "cine Womersley flow" in text and "alias: womersley" in text
    p = cli_parser.build_parser()
    for command in ("phantom", "demo"):
        extra = ["-o", "x.h5"] if command == "phantom" else []
        assert p.parse_args([command, "--case", "womersley", *extra]).case == "cine"
        assert p.parse_args([command, "--case", "cine", *extra]).case == "cine"


@pytest.mark.parametrize(
    "error, code",
    [(None, 0), (SolverError("no fit"), 1), (InputError("bad file"), 2), (RuntimeError("bug"), 3)],
)
def test_exit_codes_are_the_documented_ones(monkeypatch, capsys, error, code):
    def command(args):
        if error is not None:
            raise error
        return 0

    monkeypatch.setattr("wss_nlp.app.cli.parser.cmd_compare", command)
    assert main(["compare", "r.h5", "t.h5"]) == code
    err = capsys.readouterr().err
    assert (code == 3) == ("internal error" in err)
    help_text = cli_parser.build_parser().format_help()
    for k, text in cli_parser.EXIT_CODES.items():
        assert f"{k}  {text}" in help_text


def test_a_closed_pipe_ends_quietly_with_success(monkeypatch, capsys):
    def command(args):
        print("first line")
        raise BrokenPipeError(32, "Broken pipe")  # what print raises once the reader (head) has gone

    monkeypatch.setattr("wss_nlp.app.cli.parser.cmd_compare", command)
    assert main(["compare", "r.h5", "t.h5"]) == 0
    assert capsys.readouterr().err == ""


@pytest.fixture(scope="module")
def two_slices(tmp_path_factory):
    """A two-slice stack reconstructed quietly with fixed alpha and beta, no z-tie, band or
    near-wall choice (the command line, not the method, is under test)."""
    d = tmp_path_factory.mktemp("polish")
    assert main(["phantom", "--stack", "tapered", "--nz", "2", "--h", "2", "--seed", "3", "-o", str(d / "in.h5")]) == 0
    return d


def test_quiet_reconstruct_and_analyze_one_slice(two_slices, capsys):
    d = two_slices
    capsys.readouterr()
    argv = [
        "reconstruct",
        str(d / "in.h5"),
        "-o",
        str(d / "out.h5"),
        "--beta",
        "5e-8",
        "--z-smoothing",
        "0",
        "--no-uncertainty",
        "--near-wall",
        "off",
        "-q",
    ]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "slice 1/2" not in captured.err and "voxels" not in captured.err  # no progress, no information
    assert "slice 1: mean WSS" in captured.out  # the results are still printed
    assert main(["analyze", str(d / "out.h5"), "--slice", "1"]) == 0
    text = capsys.readouterr().out
    assert "slice_001:" in text and "slice_000" not in text
    assert main(["analyze", str(d / "out.h5"), "--slice", "2"]) == 2
    assert "no slice 2 (--slice); the file has slices 0 to 1" in capsys.readouterr().err


def test_nifti_folder_imports_as_its_files_and_phantom_says_what_it_wrote(tmp_path, capsys):
    argv = ["phantom", "--case", "circle", "--h", "2", "--seed", "5", "-o", str(tmp_path / "in.h5")]
    argv += ["--nifti", str(tmp_path / "nii"), "--dicom", str(tmp_path / "dcm"), "--vendor", "enhanced"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert f"wrote {tmp_path / 'nii'}: the same images as NIfTI" in out and "mag.nii.gz" in out
    assert f"wrote {tmp_path / 'dcm'}: the same images as DICOM, enhanced convention, one enhanced" in out
    folder, files = tmp_path / "a.h5", tmp_path / "b.h5"
    assert main(["import", str(tmp_path / "nii"), "-o", str(folder)]) == 0
    nii = sorted(str(p) for p in (tmp_path / "nii").glob("*.nii.gz"))
    assert main(["import", *nii, "-o", str(files)]) == 0
    a, b = wio.read_acquisition(folder), wio.read_acquisition(files)
    assert np.array_equal(a.magnitude, b.magnitude) and np.array_equal(a.velocity_images(), b.velocity_images())
    capsys.readouterr()
    assert main(["import", str(tmp_path / "dcm"), "-o", str(tmp_path / "c.h5")]) == 0
    assert "DICOM enhanced multi-frame (Siemens)" in capsys.readouterr().out
    assert wio.read_acquisition(tmp_path / "c.h5").magnitude.shape == a.magnitude.shape  # the same images


def test_repeated_warnings_are_written_once_with_where_they_came_from():
    # messages differing only in their numbers are one kind; the line names the frames it came from
    lines = group_warnings(
        [
            (0, "venc low"),
            (1, "venc low"),
            (3, "venc low"),
            (2, "one frame only"),
            (4, "alpha 1e-3"),
            (5, "alpha 2e-3"),
        ],
        6,
    )
    assert lines == [
        "frames 0-1, 3 (3 of 6): venc low",
        "frame 2: one frame only",
        "frames 4-5 (2 of 6): alpha 1e-3",
    ]


def test_cine_phantom_as_dicom_and_nifti_imports_back_to_the_same_frames(tmp_path, capsys):
    """`phantom --case cine --dicom/--nifti` (issue 44: cine phantoms writable from the command line): both imports
    give the frames of the HDF5 input. Tolerances: both writers store the scanner's 12-bit integers (velocity in
    steps of venc/2048, so rounding moves it by at most venc/4096; magnitude scaled to 4095, so at most 0.5/4095 of
    the maximum, twice that after normalizing both images by their maxima)."""
    argv = ["phantom", "--case", "cine", "--frames", "3", "--h", "2", "--seed", "7", "-o", str(tmp_path / "c.h5")]
    assert main([*argv, "--dicom", str(tmp_path / "dcm"), "--nifti", str(tmp_path / "nii")]) == 0
    assert "the same images as DICOM" in capsys.readouterr().out
    frames, times, _ = wio.read_frames(str(tmp_path / "c.h5"))
    for folder in ("dcm", "nii"):
        assert main(["import", str(tmp_path / folder), "-o", str(tmp_path / f"{folder}.h5")]) == 0
        back, back_times, _ = wio.read_frames(str(tmp_path / f"{folder}.h5"))
        assert np.allclose(back_times, times)
        for a, b in zip(frames, back):
            venc = a.venc_m_s
            assert np.max(np.abs(b.velocity_images() - a.velocity_images())) <= 1.01 * venc / 4096, folder
            shape = np.abs(b.magnitude / np.max(b.magnitude) - a.magnitude / np.max(a.magnitude))
            assert np.max(shape) <= 1.01 / 4095, folder


def test_progress_is_a_bar_on_a_terminal_and_a_line_per_slice_in_a_log():
    from wss_nlp.app.cli.reconstruct import _progress

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    res = SimpleNamespace(converged=True, wss=SimpleNamespace(mean=0.25))
    log, tty = io.StringIO(), Terminal()
    for stream in (log, tty):
        report = _progress(stream)
        report(1, 2, res)
        report(2, 2, res)
    assert [line.split(", ")[0] for line in log.getvalue().splitlines()] == [
        "  slice 1/2: mean WSS 0.25 Pa",
        "  slice 2/2: mean WSS 0.25 Pa",
    ]
    bar = tty.getvalue()
    assert "\r" in bar and "2/2" in bar and ("slice/s" in bar or "s/slice" in bar)  # tqdm's bar, redrawn in place
    quiet = io.StringIO()
    _progress(quiet, quiet=True)(1, 1, res)
    assert quiet.getvalue() == ""
