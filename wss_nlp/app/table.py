"""Plain-text tables for the command line (``analyze``, ``compare``, ``sensitivity``, ``demo``), through tabulate.

The cells arrive as strings already formatted with the digits each quantity deserves ("0.0500", "+1.23e-03",
"-0.42%"): tabulate only lays them out. Its number parsing is switched off, so that it never rewrites a value
("0.0500" would become "0.05") and the digits a test or the README quotes stay the ones the caller chose.
"""

from __future__ import annotations

from collections.abc import Sequence

from tabulate import tabulate

#: Text columns to the left, numbers to the right (the usual layout of a table of results).
LEFT, RIGHT = "left", "right"


def text_table(
    rows: Sequence[Sequence[str]],
    headers: Sequence[str] = (),
    align: Sequence[str] | None = None,
    indent: str = "",
) -> str:
    """Rows of preformatted cells as a plain-text table: a header line, a rule of dashes, one line per row.

    Parameters
    ----------
    rows : sequence of sequences of str
        The cells, each already formatted; a row may be shorter than the header (its last cells empty).
    headers : sequence of str
        Column titles; none gives a table without a header and rule.
    align : sequence of str, optional
        ``"left"`` or ``"right"`` per column (default: the first column left, the others right).
    indent : str
        Put before every line (a table inside a record's block of text).

    Returns
    -------
    str
        The table, lines joined by newlines, no trailing newline; trailing blanks are removed from every line.
    """
    ncol = max([len(headers), *(len(r) for r in rows)]) if rows or headers else 0
    cells = [[str(c) for c in r] + [""] * (ncol - len(r)) for r in rows]
    colalign = tuple(align) if align is not None else (LEFT,) + (RIGHT,) * (ncol - 1)
    text = tabulate(
        cells,
        headers=list(headers) + [""] * (ncol - len(headers)) if headers else (),
        colalign=colalign,
        disable_numparse=True,  # the caller chose the digits; "0.0500" must not become "0.05"
        tablefmt="simple" if headers else "plain",
    )
    return "\n".join(indent + line.rstrip() for line in text.splitlines())
