"""Warnings through logging (issue 44): the command line says each kind of warning once and counts its repeats."""

import logging

import importlib

from wss_nlp.pipeline.cine import group_warnings, warning_kind

cli_main = importlib.import_module("wss_nlp.app.cli.main")  # the module (the package exports its main function)


def test_warning_kinds_differ_in_words_not_in_numbers():
    assert warning_kind("frame 3: failed: 12 NaN voxels") == warning_kind("frame 17: failed: 4 NaN voxels")
    assert warning_kind("frame 3: failed: NaN") != warning_kind("frame 3: failed: no vessel")
    lines = group_warnings([(2, "failed: 3 NaN"), (3, "failed: 5 NaN"), (4, "failed: 1 NaN"), (7, "other")], 8)
    assert lines == ["frames 2-4 (3 of 8): failed: 3 NaN", "frame 7: other"]


def test_the_log_says_a_warning_once_then_counts_its_repeats(monkeypatch, capsys):
    """A command whose library code warns per frame: stderr has the first of each kind as ``wss-nlp: warning:``,
    INFO lines indented, and after the command one line with the count of the repeats it held back."""
    log = logging.getLogger("wss_nlp.pipeline.test_only")

    def command(args):
        log.info("geometry sweep 1")
        for k in range(5):
            log.warning("frame %d: the band was not computed", k)
        log.warning("the venc is low")
        return 0

    parser = cli_main.build_parser()
    args = parser.parse_args(["table", "somewhere", "--rows", "h", "--cols", "m", "--metric", "wss_err"])
    args.func = command  # any subcommand's arguments, this command's body
    monkeypatch.setattr(parser, "parse_args", lambda argv: args)
    monkeypatch.setattr(cli_main, "build_parser", lambda: parser)
    assert cli_main.main([]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "  geometry sweep 1",
        "wss-nlp: warning: frame 0: the band was not computed",
        "wss-nlp: warning: the venc is low",
        "wss-nlp: warning: 4 more like 'frame 0: the band was not computed'",
    ]
    # the count belongs to one command: the next run says the warning again
    assert cli_main.main([]) == 0
    assert capsys.readouterr().err.count("frame 0: the band was not computed") == 2
