"""Sphinx roles in the package's docstrings, rendered as links when the docs are built.

The docstrings are written for Sphinx: ``:func:`name```, ``:class:`~pkg.Name```, ``:math:`x```,
``.. math::`` blocks. mkdocstrings renders Markdown, where these stay raw text. This file turns them,
at build time and without touching the sources, into what mkdocstrings renders:

* a cross-reference role (``func``, ``meth``, ``class``, ``mod``, ``data``, ``attr``, ``exc``, ``obj``,
  ``const``) whose target is an object the API reference shows becomes an autorefs link
  ``[`text`][wss_nlp.full.path]``; the target is resolved as Sphinx would, against the object that
  carries the docstring, its class, its module (with the names it imports), the packages above it,
  then by a unique ending of a full name. ``~`` shows the last name only; a leading ``.`` is
  relative; functions and methods get ``()``. A target that is not found, lies outside the package or
  is not shown on any page (private, no docstring, no API page) becomes inline code, never a raw role;
* ``:math:`x``` becomes ``$x$`` and a ``.. math::`` block a ``$$`` block (pymdownx.arithmatex);
* any other role becomes inline code;
* the names of files a user's clone does not have (``shared/spec/data-format.md``, the paper's source)
  become links to the docs sections that hold their content (:func:`repoint`).

One more thing happens to the loaded package: the fields of every dataclass are listed on their class
with their types and defaults. An option (``core.schema.option``) without a docstring gets one: its
help text, its command-line flag and its study keys, shown with its default value (not the
``option(...)`` call). Any other field without a docstring that the class's docstring does not
describe becomes a row of the class's Attributes table: its type, the comment written above or beside
it, its default.

The file is three things: :func:`convert` (text in, text out; no dependencies, tested in
``tests/test_docs_roles.py``), a Griffe extension (``SphinxRoles``, loaded by mkdocstrings-python from
``mkdocs.yml``) that applies it to every docstring once the package is loaded, and an MkDocs hook
(``on_page_markdown``) that applies it to the Markdown pages (``docs/layout.md`` quotes the modules'
first sentences).
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import textwrap
from collections.abc import Callable, Iterator
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PACKAGE = "wss_nlp"

#: Roles that name a Python object.
XREF_ROLES = {"func", "meth", "class", "mod", "data", "attr", "exc", "obj", "const", "type", "any"}
#: Roles whose text Sphinx shows with ``()``.
CALLABLE_ROLES = {"func", "meth"}
#: A role, optionally in the ``py`` domain: ``:func:`x```, ``:py:class:`~a.B```.
ROLE_RE = re.compile(r":(?:py:)?(?P<role>[a-z]+):`(?P<body>[^`]+)`")
#: ``title <target>`` inside a role.
TITLED_RE = re.compile(r"^(?P<title>.*?)\s*<(?P<target>[^<>]+)>$", flags=re.DOTALL)
#: What the built site must not contain (the CI check greps for it).
RAW_ROLE_RE = re.compile(r":(?:py:)?(?:func|meth|class|mod|data|attr|exc|obj|const|math):`?")


def role_target(body: str) -> tuple[str, str, bool]:
    """``(display text, target, relative)`` of a cross-reference role's text, as Sphinx reads it.

    ``title <target>`` shows the title; ``~a.b.c`` shows ``c``; ``.c`` is relative (searched from the
    current scope outwards); anything else shows the target as written.
    """
    body = body.strip()
    titled = TITLED_RE.match(body)
    if titled and titled["title"]:
        target = titled["target"].strip()
        return titled["title"], target.lstrip("~").lstrip("."), target.lstrip("~").startswith(".")
    short = body.startswith("~")
    target = body.lstrip("~")
    relative = target.startswith(".")
    target = target.lstrip(".")
    shown = target.rsplit(".", 1)[-1] if short else target
    return shown, target, relative


def _math(body: str) -> str:
    # a docstring that is not a raw string turns "\t" (as in \top) into a tab: give MathJax its backslash back
    body = body.replace("\t", "\\t").strip()
    # arithmatex's $...$ needs no space inside the dollars and no backslash before the closing one
    if body and "$" not in body and not body.endswith("\\"):
        return f"${body}$"
    return f"\\({body}\\)"


def _math_blocks(text: str) -> str:
    """``.. math::`` directives (their indented block) -> ``$$`` blocks at the directive's indentation."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = re.match(r"^(?P<indent>\s*)\.\. math::\s*(?P<inline>.*)$", lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent = m["indent"]
        block = [m["inline"]] if m["inline"].strip() else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)):
            block.append(lines[i])
            i += 1
        trailing = 0
        while block and not block[-1].strip():
            block.pop()
            trailing += 1
        body = textwrap.dedent("\n".join(block)).strip("\n").replace("\t", "\\t")
        if out and out[-1].strip():
            out.append("")
        out += [indent + "$$", *[indent + line if line else "" for line in body.split("\n")], indent + "$$"]
        out += [""] * max(trailing, 1) if i < len(lines) else []
    return "\n".join(out)


#: Files outside the repository that docstrings name, and the docs section that holds their content instead.
REPOINTED = {
    "shared/spec/data-format.md": ("the file contract", "the-file-contract"),
    "shared/paper/egger-teschner-wss.tex": ("the paper (summarized in The method)", "the-method"),
}
_REPOINT_RE = re.compile(r"``?(?:\.\./)?(?P<path>" + "|".join(re.escape(p) for p in REPOINTED) + r")``?")


def repoint(text: str) -> str:
    """Names of files a user's clone does not have (``shared/...``) -> links to the docs section with their content."""

    def repl(m: re.Match) -> str:
        title, anchor = REPOINTED[m["path"]]
        return f"[{title}][{anchor}]"

    return _REPOINT_RE.sub(repl, text)


def convert(text: str, resolve: Callable[[str, bool], str | None]) -> str:
    """The docstring ``text`` with its Sphinx roles in the Markdown mkdocstrings renders.

    Parameters
    ----------
    text : str
        A docstring, or a Markdown page.
    resolve : callable
        ``resolve(target, relative)`` -> the full path of the object a cross-reference names, if the
        API reference shows it (a link to it then resolves), else None.

    Returns
    -------
    str
        The text with every role replaced: ``[`text`][full.path]`` for a resolved cross-reference,
        ```text``` for any other, ``$x$`` for ``:math:``; ``.. math::`` blocks become ``$$`` blocks.
    """

    def repl(m: re.Match) -> str:
        role, body = m["role"], m["body"]
        if role == "math":
            return _math(body)
        if role not in XREF_ROLES:
            return f"`{body.strip()}`"
        shown, target, relative = role_target(body)
        if role in CALLABLE_ROLES and not shown.endswith(")") and not TITLED_RE.match(body.strip()):
            shown += "()"
        path = resolve(target, relative) if target else None
        return f"[`{shown}`][{path}]" if path else f"`{shown}`"

    def plain(m: re.Match) -> str:  # a type in a numpydoc item line is shown as written, not as Markdown
        if m["role"] not in XREF_ROLES:
            return m["body"].strip()
        return role_target(m["body"])[0]

    if ".. math::" in text:
        text = _math_blocks(text)
    lines = text.split("\n")
    for i in _item_lines(lines):
        name, sep, kind = lines[i].partition(" : ")
        lines[i] = name + sep + ROLE_RE.sub(plain, kind) if sep else ROLE_RE.sub(plain, lines[i])
    return ROLE_RE.sub(repl, "\n".join(lines))


#: numpydoc sections whose entries are ``name : type`` (or ``type``) lines followed by indented descriptions.
ITEM_SECTIONS = {"Parameters", "Other Parameters", "Returns", "Yields", "Receives", "Raises", "Warns", "Attributes"}


def _item_lines(lines: list[str]) -> list[int]:
    """Indices of the entry lines (``name : type``) of numpydoc item sections: their types are not Markdown."""
    out: list[int] = []
    base: int | None = None
    for i, line in enumerate(lines):
        indent = len(line) - len(line.lstrip())
        underline = i + 1 < len(lines) and re.fullmatch(r"\s*-{3,}\s*", lines[i + 1]) is not None
        if line.strip() and underline:  # a section header
            base = indent if line.strip() in ITEM_SECTIONS else None
            continue
        if base is None or not line.strip() or re.fullmatch(r"\s*-{3,}\s*", line):
            continue
        if indent < base:
            base = None
        elif indent == base:
            out.append(i)
    return out


def api_pages(docs: str = os.path.join(ROOT, "docs")) -> dict[str, str]:
    """``{module path: page}`` of the API reference: every ``docs/api/*.md`` rendering ``::: wss_nlp.X``."""
    pages = {}
    folder = os.path.join(docs, "api")
    for name in sorted(os.listdir(folder)) if os.path.isdir(folder) else []:
        if name.endswith(".md"):
            with open(os.path.join(folder, name), encoding="utf-8") as fh:
                for ident in re.findall(r"^:::\s*([\w.]+)\s*$", fh.read(), flags=re.MULTILINE):
                    pages[ident] = f"api/{name}"
    return pages


# ---------------------------------------------------------------------------------------------------------------
# the MkDocs hook: roles in the Markdown pages (absolute targets only; modules link to their API page)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any, **kwargs: Any) -> str:
    """Roles in a page's own Markdown (``docs/layout.md`` and the API index quote docstrings' first sentences)."""
    markdown = repoint(markdown)
    if not ROLE_RE.search(markdown) and ".. math::" not in markdown:
        return markdown
    pages = api_pages(config["docs_dir"])
    here = os.path.dirname(page.file.src_uri)

    def repl(m: re.Match) -> str:
        role = m["role"]
        if role not in XREF_ROLES:
            return convert(m[0], lambda target, relative: None)
        shown, target, _ = role_target(m["body"])
        if target in pages:  # a module: a link to its page (no object anchors are known to a page's text)
            return f"[`{shown}`]({os.path.relpath(pages[target], here or '.')})"
        return convert(m[0], lambda target, relative: None)

    return ROLE_RE.sub(repl, markdown)


# ---------------------------------------------------------------------------------------------------------------
# the Griffe extension: roles in every docstring of the package, dataclass fields listed

try:
    import griffe
except ImportError:  # convert() and the tests of it need no griffe; the docs build has it (the [docs] extra)
    griffe = None  # type: ignore[assignment]


def _walk(obj: Any) -> Iterator[Any]:
    """Every object defined in ``obj`` (imports excluded), ``obj`` first."""
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)


def _lookup(root: Any, path: str) -> Any | None:
    """The object at ``path`` (imported names followed to what they name), or None."""
    parts = path.split(".")
    if parts[0] != root.name:
        return None
    obj = root
    for name in parts[1:]:
        member = obj.members.get(name) if hasattr(obj, "members") else None
        if member is None:
            return None
        if member.is_alias:
            try:
                member = member.final_target
            except Exception:  # an import from outside the package, or one griffe cannot follow
                return None
        obj = member
    return obj if obj.path == root.name or obj.path.startswith(root.name + ".") else None


def _kept(name: str) -> bool:
    # mkdocstrings-python's default filter "!^_[^_]": no private names (special ones stay)
    return not re.match(r"^_[^_]", name)


class _Resolver:
    """Finds the full path of a role's target from a docstring's owner, and whether the reference shows it."""

    def __init__(self, root: Any, pages: dict[str, str]):
        self.root = root
        self.pages = pages
        self.paths = [o.path for o in _walk(root)]

    def shown(self, obj: Any) -> bool:
        """Whether mkdocstrings renders ``obj`` (so that an autorefs link to it resolves)."""
        if obj.is_module:
            return obj.path in self.pages
        if obj.module.path not in self.pages:
            return False
        o = obj
        while o is not None and not o.is_module:
            parent = o.parent
            # private names and objects without any docstring are not rendered (show_if_no_docstring: false)
            if not _kept(o.name) or not o.has_docstrings or parent is None or parent.members.get(o.name) is not o:
                return False
            o = parent
        return True

    def candidates(self, target: str, owner: Any) -> Iterator[str]:
        if target.startswith(self.root.name + ".") or target == self.root.name:
            yield target
        scope = owner
        while scope is not None:  # the owner, its class, its module, the packages above (imports followed)
            yield f"{scope.path}.{target}"
            scope = scope.parent

    def link(self, obj: Any) -> str | None:
        """Where a reference to ``obj`` links: the object, or the class that lists it (a field in a table)."""
        if self.shown(obj):
            return obj.path
        parent = obj.parent
        if parent is not None and parent.is_class and _kept(obj.name) and self.shown(parent):
            return parent.path
        return None

    def __call__(self, target: str, relative: bool, owner: Any) -> str | None:
        for path in self.candidates(target, owner):
            obj = _lookup(self.root, path)
            if obj is not None:
                return self.link(obj)
        # last: a unique object whose full name ends with the target (Sphinx's search for ".name")
        ends = [p for p in self.paths if p.endswith("." + target)]
        if len(ends) == 1:
            obj = _lookup(self.root, ends[0])
            return self.link(obj) if obj is not None else None
        return None


def _field_comment(attr: Any) -> str:
    """The ``#`` comment above a field (contiguous lines) or beside it, as one sentence."""
    try:
        lines = attr.module.lines
    except Exception:
        return ""
    if not lines or attr.lineno is None:
        return ""
    i = attr.lineno - 2
    above: list[str] = []
    while i >= 0 and lines[i].strip().startswith("#"):
        above.insert(0, lines[i].strip().lstrip("#").strip())
        i -= 1
    if above:
        return " ".join(above)
    line = lines[attr.lineno - 1]
    beside = re.search(r"\s#\s(?P<text>[^\"']*)$", line)
    return beside["text"].strip() if beside else ""


def _sphinx_comment(attr: Any) -> str:
    """Sphinx's documentation comment of an attribute: ``#:`` lines right above it, or ``#: text`` beside it."""
    try:
        lines = attr.module.lines
    except Exception:
        return ""
    if not lines or attr.lineno is None:
        return ""
    i = attr.lineno - 2
    above: list[str] = []
    while i >= 0 and lines[i].strip().startswith("#:"):
        above.insert(0, lines[i].strip()[2:].strip())
        i -= 1
    if above:
        return "\n".join(above)
    beside = re.search(r"\s#:\s(?P<text>[^\"']*)$", lines[attr.lineno - 1])
    return beside["text"].strip() if beside else ""


def document_comments(root: Any, like: Any = None) -> int:
    """Attributes documented the Sphinx way (``#:`` comments) get that text as their docstring; returns how many."""
    how = {"parser": like.parser, "parser_options": like.parser_options} if like is not None else {}
    done = 0
    for obj in _walk(root):
        if obj.is_attribute and obj.docstring is None and (text := _sphinx_comment(obj)):
            obj.docstring = griffe.Docstring(text, parent=obj, **how)
            done += 1
    return done


def shorten_values(root: Any, width: int = 80) -> int:
    """Long attribute values (tables of cases, ...) shown elided in their headings; returns how many."""
    done = 0
    for obj in _walk(root):
        if obj.is_attribute and obj.value is not None and len(text := str(obj.value)) > width:
            obj.value = {"{": "{...}", "[": "[...]", "(": "(...)"}.get(text[0], text[: width - 3].rstrip() + "...")
            done += 1
    return done


def _documented_in_class(cls: Any) -> set[str]:
    """Names the class docstring's Attributes / Parameters sections already describe."""
    if cls.docstring is None:
        return set()
    names = set()
    try:
        for section in cls.docstring.parsed:
            if section.kind.value in ("attributes", "parameters", "other parameters"):
                names |= {item.name for item in section.value}
    except Exception:
        return set()
    return names


def _runtime_class(cls: Any) -> Any | None:
    try:
        obj: Any = importlib.import_module(cls.module.path)
        for name in cls.path[len(cls.module.path) + 1 :].split("."):
            obj = getattr(obj, name)
    except Exception:
        return None
    return obj if dataclasses.is_dataclass(obj) else None


def _default_text(f: dataclasses.Field) -> str | None:
    if f.default is not dataclasses.MISSING:
        return repr(f.default)
    factory = f.default_factory
    if factory is not dataclasses.MISSING:
        name = getattr(factory, "__name__", "")
        return f"{name}()" if name and name != "<lambda>" else None
    return None


def _with_attributes(doc: str, rows: list[str]) -> str:
    """The numpydoc docstring ``doc`` with ``rows`` added to its Attributes section (made if it has none)."""
    lines = doc.rstrip("\n").split("\n")
    heads = [i for i in range(len(lines) - 1) if lines[i].strip() and re.fullmatch(r"\s*-{3,}\s*", lines[i + 1])]
    mine = [i for i in heads if lines[i].strip() == "Attributes"]
    if not mine:
        return "\n".join([*lines, "", "Attributes", "----------", *rows]) + "\n"
    after = [i for i in heads if i > mine[0]]
    at = after[0] if after else len(lines)
    while at > mine[0] + 2 and not lines[at - 1].strip():
        at -= 1
    return "\n".join([*lines[:at], *rows, *lines[at:]]) + "\n"


def document_fields(cls: Any, like: Any = None) -> int:
    """List the fields of the dataclass ``cls`` (a griffe class) on it; returns how many were added.

    An option field (``core.schema.option``) without a docstring gets one: its help text, its command-line
    flag and study keys; its shown value becomes its default. Any other field that neither has a docstring
    nor is described in the class docstring's Attributes or Parameters section becomes a row of the class's
    Attributes table: its type, the comment written above or beside it, its default. ``like``: a docstring
    whose parser (and its options) new docstrings use.
    """
    like = cls.docstring or like
    how = {"parser": like.parser, "parser_options": like.parser_options} if like is not None else {}
    runtime = _runtime_class(cls)
    if runtime is None:
        return 0
    in_class = _documented_in_class(cls)
    rows: list[str] = []
    done = 0
    for f in dataclasses.fields(runtime):
        attr = cls.members.get(f.name)
        if attr is None or attr.is_alias or attr.docstring is not None:
            continue
        meta = f.metadata.get(PACKAGE)
        shown = _default_text(f)
        if meta is None:
            if f.name in in_class:
                continue
            text = _field_comment(attr)
            factory = f.default_factory
            if not text and dataclasses.is_dataclass(factory) and isinstance(factory, type):
                text = f"The :class:`~{factory.__module__}.{factory.__qualname__}` part"
            if text and not text.endswith((".", ")", ":")):
                text += "."
            if shown is not None:
                text = (text + " " if text else "") + f"Default: `{shown}`."
            annotation = str(attr.annotation) if attr.annotation is not None else ""
            rows.append(f"{f.name} : {annotation}" if annotation else f.name)
            rows.append(f"    {text}" if text else "    ")
            done += 1
            continue
        text = meta.get("help") or _field_comment(attr)
        where = []
        if meta.get("cli"):
            where.append(f"command line `{meta['cli']}`")
        if meta.get("toml"):
            keys = ", ".join(f"`{k}`" for k in meta["toml"])
            where.append(("study keys " if len(meta["toml"]) > 1 else "study key ") + keys)
        if text and not text.endswith("."):
            text += "."
        if where:
            text = (text + " " if text else "") + "; ".join(where).capitalize() + "."
        if shown is not None:
            attr.value = shown
        attr.docstring = griffe.Docstring(text, parent=attr, **how)
        done += 1
    if rows:
        doc = cls.docstring.value if cls.docstring else ""
        cls.docstring = griffe.Docstring(_with_attributes(doc, rows), parent=cls, **how)
    return done


if griffe is not None:

    class SphinxRoles(griffe.Extension):
        """Griffe extension: Sphinx roles to autorefs links in every docstring of the package; fields documented."""

        def on_package(self, *, pkg: Any, **kwargs: Any) -> None:
            if pkg.name != PACKAGE:
                return
            document_comments(pkg, like=pkg.docstring)
            for obj in _walk(pkg):
                if obj.is_class and "dataclass" in obj.labels:
                    document_fields(obj, like=pkg.docstring)
            shorten_values(pkg)
            resolver = _Resolver(pkg, api_pages())
            for obj in _walk(pkg):
                doc = obj.docstring
                if doc is None:
                    continue
                text = repoint(doc.value)
                if ROLE_RE.search(text) or ".. math::" in text:
                    text = convert(text, lambda target, relative, owner=obj: resolver(target, relative, owner))
                if text == doc.value:
                    continue
                doc.value = text
                doc.__dict__.pop("parsed", None)  # parsed lazily; drop a parse of the old text, if any
