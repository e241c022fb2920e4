"""MkDocs hook: a site that works offline, from what pip installed.

The formulas are rendered by MathJax 3 in the browser, and the code is highlighted by Pygments when the
site is built; nothing is fetched from a CDN, neither when building nor when reading. MathJax comes from
the PyPI package ``django-static-mathjax`` (MathJax's own release files, Apache-2.0; it needs no Django),
which the ``[docs]`` extra installs: its self-contained SVG bundle ``es5/tex-svg-full.js`` (every TeX
extension, the glyphs inside, no font files) is copied into the site as ``js/mathjax/tex-svg-full.js`` with
MathJax's licence beside it. The Pygments stylesheet for the highlighted code (``.highlight``, as
mkdocstrings' signatures and ``codehilite`` write it) is ``css/pygments.css``. The theme's own highlight.js
(loaded from a CDN) is switched off in ``mkdocs.yml``.
"""

from __future__ import annotations

import importlib.util
import json
import os

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

MATHJAX_BUNDLE = "es5/tex-svg-full.js"
SITE_MATHJAX = "js/mathjax/tex-svg-full.js"
SITE_PYGMENTS = "css/pygments.css"


def mathjax_dir() -> str:
    """MathJax's release folder inside the installed ``django-static-mathjax`` (PluginError if missing)."""
    spec = importlib.util.find_spec("mathjax")
    folder = os.path.join(os.path.dirname(spec.origin), "static", "mathjax") if spec and spec.origin else ""
    if not os.path.isfile(os.path.join(folder, MATHJAX_BUNDLE)):
        raise PluginError(
            "MathJax is missing: the docs render formulas offline with the copy the [docs] extra installs; "
            "run: python -m pip install -e '.[docs]'"
        )
    with open(os.path.join(folder, "package.json"), encoding="utf-8") as fh:
        version = json.load(fh).get("version", "")
    if not version.startswith("3."):
        raise PluginError(f"MathJax {version} found; the docs need MathJax 3 (python -m pip install -e '.[docs]')")
    return folder


def on_files(files, config, **kwargs):
    """Add MathJax (bundle and licence) and the Pygments stylesheet to the site's files."""
    from pygments.formatters import HtmlFormatter

    folder = mathjax_dir()
    files.append(File.generated(config, SITE_MATHJAX, abs_src_path=os.path.join(folder, MATHJAX_BUNDLE)))
    files.append(File.generated(config, "js/mathjax/LICENSE", abs_src_path=os.path.join(folder, "LICENSE")))
    css = HtmlFormatter(style="default").get_style_defs(".highlight")
    files.append(File.generated(config, SITE_PYGMENTS, content=css))
    return files
