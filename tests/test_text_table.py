"""The command line's text tables (wss_nlp.app.table, issue 44): tabulate lays out the cells, never their digits."""

from wss_nlp.app.cli.report import _chosen_table, _error_table
from wss_nlp.app.table import LEFT, RIGHT, text_table


def test_cells_keep_their_digits_and_numbers_align_right():
    rows = [("radius max. error [mm]", "0.0500"), ("beta (balance)", "7.63e-08"), ("mean WSS rel. error", "-0.42%")]
    lines = _error_table(rows).splitlines()
    assert lines[0].split() == ["quantity", "value"]
    assert set(lines[1].replace(" ", "")) == {"-"}  # the rule under the header
    body = lines[2:]
    # the preformatted strings arrive unchanged (tabulate's number parsing would print "0.0500" as "0.05")
    for (name, value), line in zip(rows, body):
        assert line.startswith(name) and line.endswith(value)
    assert len({len(line) for line in lines}) == 1  # right-aligned: every line ends at the value column's edge


def test_short_rows_indent_and_alignment():
    text = text_table([("a", "1"), ("bb", "-2", "<- chosen")], headers=("x", "y", ""), align=(LEFT, RIGHT, LEFT),
                      indent="    ")  # fmt: skip
    lines = text.splitlines()
    assert all(line.startswith("    ") for line in lines)
    assert lines[2] == "    a      1"  # the missing cell is empty and the trailing blanks are gone
    assert lines[3] == "    bb    -2  <- chosen"
    # without headers: no rule
    assert text_table([("a", "1")]).splitlines() == ["a  1"]


def test_chosen_table_sorts_by_criterion_and_marks_the_chosen_model():
    text = _chosen_table({"plain": 523.891, "exponential": 543.776, "wall_law": 500.0}.items(), "plain",
                         ("model", "criterion"), ".2f", indent="")  # fmt: skip
    body = text.splitlines()[2:]
    assert [line.split()[0] for line in body] == ["wall_law", "plain", "exponential"]
    assert body[1].split() == ["plain", "523.89", "<-", "chosen"]
    assert "chosen" not in body[0] + body[2]
