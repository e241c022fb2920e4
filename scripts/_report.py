"""Shared by the study scripts: the common phantom-study options, and writing a Markdown table."""

import argparse
import os

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def study_parser(doc: str, seeds: int, h: str, snr: str | None = None) -> argparse.ArgumentParser:
    """``--seeds``, ``--cases``, ``--h``, ``--out`` (and ``--snr`` as a comma list if given) with these defaults."""
    p = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=seeds)
    p.add_argument("--cases", default="laminar,turbulent")
    p.add_argument("--h", default=h)
    if snr is not None:
        p.add_argument("--snr", default=snr)
    p.add_argument("--out", default=RESULTS)
    return p


def write_report(folder: str, name: str, lines: list[str]) -> str:
    """Write ``lines`` to ``folder/name`` (creating the folder) and print them; returns the text."""
    text = "\n".join(lines)
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, name), "w") as fh:
        fh.write(text + "\n")
    print(text)
    return text
