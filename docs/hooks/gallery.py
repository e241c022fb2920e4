"""MkDocs hook: run ``examples/plot_*.py`` and make the gallery pages (``docs/gallery/``) from them.

Each example is a script whose module docstring gives the title (first
line) and the text. The hook runs it in a fresh namespace (working
directory: a temporary folder), captures what it prints, and saves every
:class:`matplotlib.figure.Figure` left in its namespace (our figures are
made without pyplot, so there is no pyplot state to scrape). The page
shows the text, the code, the printed output and the figures. An example
that raises fails the build. Generated files live in ``docs/gallery/``
(ignored by git).
"""

from __future__ import annotations

import ast
import contextlib
import io
import os
import runpy
import tempfile
import time

from matplotlib.figure import Figure

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
EXAMPLES = os.path.join(ROOT, "examples")
OUT = os.path.join(ROOT, "docs", "gallery")


def _run(path: str) -> tuple[str, list[Figure], float]:
    out = io.StringIO()
    cwd = os.getcwd()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(out):
        os.chdir(tmp)
        try:
            namespace = runpy.run_path(path, run_name="__main__")
        finally:
            os.chdir(cwd)
    figures = []
    for value in namespace.values():
        items = value if isinstance(value, (list, tuple)) else [value]
        figures += [f for f in items if isinstance(f, Figure) and all(f is not g for g in figures)]
    return out.getvalue(), figures, time.perf_counter() - t0


def _page(name: str, source: str, printed: str, images: list[str], seconds: float) -> str:
    doc = ast.get_docstring(ast.parse(source)) or name
    title, _, text = doc.partition("\n")
    body = source.split('"""', 2)[2].lstrip("\n") if source.lstrip().startswith('"""') else source
    lines = [
        f"# {title.strip()}",
        "",
        text.strip(),
        "",
        f"Source: `examples/{name}.py` (ran in {seconds:.1f} s when these docs were built).",
        "",
        "```python",
        body.rstrip(),
        "```",
        "",
    ]
    if printed.strip():
        lines += ["Output:", "", "```text", printed.rstrip(), "```", ""]
    lines += [f"![{name} figure {i + 1}]({img})" for i, img in enumerate(images)]
    return "\n".join(lines) + "\n"


def _names() -> list[str]:
    return sorted(f[:-3] for f in os.listdir(EXAMPLES) if f.startswith("plot_") and f.endswith(".py"))


def on_config(config, **kwargs):
    """A "Gallery" section near the top of the navigation (after "Getting started"), one page per example.

    The pages are written by :func:`on_pre_build`; the section goes right after the first entries a new
    user reads, not after the API reference.
    """
    pages = [f"gallery/{name}.md" for name in _names()]
    nav = config["nav"]
    keys = [next(iter(item)) if isinstance(item, dict) else None for item in nav]
    at = keys.index("Getting started") + 1 if "Getting started" in keys else min(1, len(nav))
    nav.insert(at, {"Gallery": ["gallery/index.md", *pages]})
    return config


def on_pre_build(config, **kwargs):
    os.makedirs(OUT, exist_ok=True)
    names = _names()
    index = [
        "# Gallery",
        "",
        "Each example runs at a small size when the documentation is built; its printed",
        "numbers and figures below are from that run. The scripts are in `examples/`.",
        "",
        "| | example |",
        "|---|---|",
    ]
    for name in names:
        path = os.path.join(EXAMPLES, name + ".py")
        with open(path, encoding="utf-8") as fh:
            source = fh.read()
        printed, figures, seconds = _run(path)
        images = []
        for i, fig in enumerate(figures):
            image = f"{name}_{i + 1}.png"
            fig.savefig(os.path.join(OUT, image), dpi=80)
            images.append(image)
        with open(os.path.join(OUT, name + ".md"), "w", encoding="utf-8") as fh:
            fh.write(_page(name, source, printed, images, seconds))
        doc = ast.get_docstring(ast.parse(source)) or name
        title, _, text = doc.partition("\n")
        first = " ".join(text.strip().split("\n\n")[0].split())  # the text's first sentence, on one line
        first = first.split(". ")[0].rstrip(".") + "." if first else ""
        thumb = ""
        if figures:  # the first figure, small: the thumbnail
            thumb = f"thumb_{name}.png"
            figures[0].savefig(os.path.join(OUT, thumb), dpi=30)
            thumb = f"[![{title.strip()}]({thumb})]({name}.md)"
        index.append(f"| {thumb} | **[{title.strip()}]({name}.md)**<br>{first.replace('|', '&#124;')} |")
    with open(os.path.join(OUT, "index.md"), "w", encoding="utf-8") as fh:
        fh.write("\n".join(index) + "\n")
