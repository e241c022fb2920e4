"""The docs build turns the docstrings' Sphinx roles into links, code and math (docs/hooks/sphinx_roles.py, issue 44).

The converter is tested on its own (no docs dependencies) and on every docstring of the package; the
Griffe extension (resolution against the loaded package, dataclass fields listed) where griffe is
installed (the ``[docs]`` extra). The built site itself is checked by ``.ci/run`` (no raw role in
``build/site``).
"""

from __future__ import annotations

import ast
import importlib.util
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("sphinx_roles_hook", ROOT / "docs" / "hooks" / "sphinx_roles.py")
roles = importlib.util.module_from_spec(spec)
spec.loader.exec_module(roles)


def _table(known: dict[str, str]):
    """A resolver that knows ``known`` ({target as written: full path}) and records the relative flags."""
    seen: list[tuple[str, bool]] = []

    def resolve(target: str, relative: bool) -> str | None:
        seen.append((target, relative))
        return known.get(target)

    return resolve, seen


def test_cross_references_become_links_or_code_as_sphinx_shows_them():
    resolve, seen = _table(
        {
            "wss_nlp.models.geometry.fit": "wss_nlp.models.geometry.fit",
            "Lumen": "wss_nlp.models.preprocess.Lumen",
            "rules": "wss_nlp.parameters.rules",
            "Solver.solve": "wss_nlp.core.solver.Solver.solve",
        }
    )
    text = (
        ":func:`~wss_nlp.models.geometry.fit` and :class:`Lumen`, :mod:`.rules`, "
        ":py:meth:`Solver.solve`, :data:`NOT_THERE`, :func:`the fit <wss_nlp.models.geometry.fit>`"
    )
    assert roles.convert(text, resolve) == (
        "[`fit()`][wss_nlp.models.geometry.fit] and [`Lumen`][wss_nlp.models.preprocess.Lumen], "
        "[`rules`][wss_nlp.parameters.rules], [`Solver.solve()`][wss_nlp.core.solver.Solver.solve], "
        "`NOT_THERE`, [`the fit`][wss_nlp.models.geometry.fit]"
    )
    # "~" only shortens the text; a leading "." marks a relative target (searched from the docstring's owner out)
    assert ("wss_nlp.models.geometry.fit", False) in seen and ("rules", True) in seen


def test_math_and_other_roles():
    never = _table({})[0]
    assert (
        roles.convert(r"the prior :math:`\beta\|\Delta^t v\|^2` here", never)
        == r"the prior $\beta\|\Delta^t v\|^2$ here"
    )
    # a docstring that is not raw turned "\t" of \top into a tab: MathJax gets the backslash back
    assert roles.convert(":math:`A^{-\top}`", never) == r"$A^{-\top}$"
    assert roles.convert("set :envvar:`OMP_NUM_THREADS`", never) == "set `OMP_NUM_THREADS`"
    doc = "Text\n\n    .. math::\n\n        J = \\int f\n            + g\n\n    after\n"
    assert roles.convert(doc, never) == "Text\n\n    $$\n    J = \\int f\n        + g\n    $$\n\n    after\n"


def test_types_of_numpydoc_entries_stay_plain_text():
    resolve = _table({"wss_nlp.core.velocity_basis": "wss_nlp.core.velocity_basis"})[0]
    doc = (
        "Build it.\n\n    Parameters\n    ----------\n    base : basis of :mod:`wss_nlp.core.velocity_basis`\n"
        "        The part of :mod:`wss_nlp.core.velocity_basis` that is penalized.\n"
    )
    out = roles.convert(doc, resolve)
    assert "base : basis of wss_nlp.core.velocity_basis\n" in out  # a type is not Markdown: no link syntax
    assert "The part of [`wss_nlp.core.velocity_basis`][wss_nlp.core.velocity_basis] that" in out


def test_files_outside_the_repository_point_at_the_docs():
    text = "Reading the HDF5 formats of ``shared/spec/data-format.md``; see `../shared/paper/egger-teschner-wss.tex`."
    out = roles.repoint(text)
    assert "shared/" not in out
    assert "[the file contract][the-file-contract]" in out and "][the-method]" in out


def _docstrings():
    for path in sorted((ROOT / "wss_nlp").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
                doc = ast.get_docstring(node, clean=False)
                if doc:
                    yield f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}", doc


def test_no_docstring_keeps_a_raw_role_after_conversion():
    """Every role form the package's docstrings use is handled (the site check in .ci/run greps the same)."""
    never = _table({})[0]
    count = 0
    for where, doc in _docstrings():
        count += len(roles.ROLE_RE.findall(doc))
        out = roles.convert(doc, never)
        assert not roles.RAW_ROLE_RE.search(out), (where, roles.RAW_ROLE_RE.search(out))
        assert ".. math::" not in out, where
    assert count > 100  # the package does write Sphinx roles: the test sees them
    ci = (ROOT / ".ci" / "run").read_text()
    assert "build/site" in ci and "grep" in ci and ":(py:)?(func|meth|class|mod|data|attr|exc|obj|const|math):" in ci


@pytest.fixture(scope="module")
def package():
    griffe = pytest.importorskip("griffe")
    return griffe.load(
        "wss_nlp",
        search_paths=[str(ROOT)],
        docstring_parser="numpy",
        extensions=griffe.load_extensions(roles.SphinxRoles),
    )


def test_extension_links_resolve_to_objects_the_reference_shows(package):
    options = package["pipeline.options.ReconstructionOptions"]
    assert "[`GeometryOptions`][wss_nlp.models.geometry.GeometryOptions]" in options.docstring.value
    pages = roles.api_pages()
    resolver = roles._Resolver(package, pages)
    links = 0
    for obj in roles._walk(package):
        if obj.docstring is None:
            continue
        assert not roles.RAW_ROLE_RE.search(obj.docstring.value), obj.path
        for target in re.findall(r"\]\[(wss_nlp[\w.]*)\]", obj.docstring.value):
            found = roles._lookup(package, target)
            assert found is not None and resolver.shown(found), (obj.path, target)
            links += 1
    assert links > 500


def test_imported_names_and_relative_targets_resolve_from_the_docstrings_owner(package):
    resolver = roles._Resolver(package, roles.api_pages())
    owner = package["models.geometry"]
    # "rad" is "from ..core import radius as rad" in models.geometry: followed to the module it names
    assert resolver("rad", False, owner) == "wss_nlp.core.radius"
    assert resolver("GeometryOptions", True, package["pipeline.options.ReconstructionOptions"]) == (
        "wss_nlp.models.geometry.GeometryOptions"
    )
    assert resolver("DeprecationWarning", False, owner) is None  # not in the package: shown as code


def test_dataclass_fields_are_listed_with_types_and_defaults(package):
    choice = package["parameters.options.ChoiceOptions"]
    kappa = choice.members["kappa_beta"]
    assert str(kappa.value) == "2.5" and str(kappa.annotation) == "float"
    assert "WSS differences allowed" in kappa.docstring.value and "`--kappa-beta`" in kappa.docstring.value
    n_phi = package["pipeline.options.ReconstructionOptions"].members["n_phi"]
    assert str(n_phi.value) == "360" and "`--n-phi`" in n_phi.docstring.value
    # a field without help or docstring becomes a row of the class's Attributes table
    options = package["pipeline.options.ReconstructionOptions"]
    rows = [s for s in options.docstring.parsed if s.kind.value == "attributes"]
    assert rows and "geometry" in {item.name for item in rows[0].value}
