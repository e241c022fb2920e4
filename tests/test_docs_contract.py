"""The docs state the file contract in full (issue 44): a user's clone has no ``../shared/spec/data-format.md``.

Where the contract's source is at hand (a developer's checkout, CI), every line of it must appear unchanged
in ``docs/guide/file-formats.md`` (its section headings one level deeper, under "The file contract").
"""

import importlib.util
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
CONTRACT = ROOT.parent / "shared" / "spec" / "data-format.md"
PAGE = ROOT / "docs" / "guide" / "file-formats.md"


@pytest.mark.skipif(not CONTRACT.exists(), reason="the contract's source is not beside this checkout")
def test_the_file_formats_page_holds_every_line_of_the_contract():
    page = PAGE.read_text(encoding="utf-8").splitlines()
    body = CONTRACT.read_text(encoding="utf-8").splitlines()[1:]  # without its title
    section = page.index("## The file contract")
    later = page[section:]
    missing = []
    for line in body:
        if not line.strip():
            continue
        wanted = "#" + line if line.startswith("## ") else line  # its sections are subsections on the page
        if wanted not in later:
            missing.append(line)
    assert not missing, missing


def test_docs_and_readme_point_at_no_file_outside_the_repository():
    """Pages quoting a docstring that names ``shared/spec/...`` are repointed when built (as the build does here)."""
    spec = importlib.util.spec_from_file_location("sphinx_roles_hook", ROOT / "docs" / "hooks" / "sphinx_roles.py")
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        if "gallery" in path.parts:
            continue
        text = path.read_text(encoding="utf-8")
        text = hook.repoint(text) if path.name != "README.md" else text
        assert "../shared/" not in text and "shared/paper/" not in text and "shared/spec/" not in text, path
