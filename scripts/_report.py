"""Shared by the study scripts: write a Markdown table and echo it."""

import os


def write_report(folder: str, name: str, lines: list[str]) -> str:
    """Write ``lines`` to ``folder/name`` (creating the folder) and print them; returns the text."""
    text = "\n".join(lines)
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, name), "w") as fh:
        fh.write(text + "\n")
    print(text)
    return text
