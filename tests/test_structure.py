"""Package structure: no import cycles (function-level imports included), every module imports on its own."""

import ast
import pathlib
import subprocess
import sys

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "wss_nlp"
#: Every module as its dotted name below the package ("geometry", "parameters.choice"), subpackages included.
MODULES = sorted(
    ".".join(p.relative_to(PACKAGE).with_suffix("").parts) for p in PACKAGE.rglob("*.py") if p.stem != "__init__"
)


def _resolve(module: str, node: ast.ImportFrom) -> list:
    """Dotted package names an ``ImportFrom`` in ``module`` refers to (modules, or packages' members)."""
    if node.level == 0:
        if not (node.module or "").startswith("wss_nlp."):
            return []
        base = node.module.split(".")[1:]
    else:
        package = module.split(".")[:-1]
        base = package[: len(package) - (node.level - 1)] + (node.module.split(".") if node.module else [])
    stem = ".".join(base)
    # "from .parameters import noise" names the module parameters.noise; "from .geometry import x" the module
    return [f"{stem}.{a.name}" if stem else a.name for a in node.names] + ([stem] if stem else [])


def _imports(module: str, type_checking: bool = False) -> set:
    """Package modules that ``module`` imports anywhere in its code, except under ``if TYPE_CHECKING:`` (unless
    ``type_checking``)."""
    tree = ast.parse((PACKAGE / (module.replace(".", "/") + ".py")).read_text())
    skip = set()
    for node in ast.walk(tree):
        if not type_checking and isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for n in ast.walk(node))
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.ImportFrom):
            out.update(_resolve(module, node))
        elif isinstance(node, ast.Import):
            out.update(".".join(a.name.split(".")[1:]) for a in node.names if a.name.startswith("wss_nlp."))
    return {m for m in out if m in MODULES and m != module}


def _cycle(graph: dict):
    """One import cycle as a list of modules, or None."""
    state: dict = {}

    def visit(m, path):
        state[m] = "open"
        for n in sorted(graph[m]):
            if state.get(n) == "open":
                return path[path.index(n) :] + [n]
            if n not in state:
                found = visit(n, path + [n])
                if found:
                    return found
        state[m] = "done"
        return None

    for m in MODULES:
        if m not in state:
            found = visit(m, [m])
            if found:
                return found
    return None


def test_no_import_cycles():
    graph = {m: _imports(m) for m in MODULES}
    assert graph["models.stack"] and graph["pipeline.driver"]  # the parser sees imports at all
    # subpackages too
    assert "parameters.alpha" in graph["pipeline.fitters"] and "models.geometry" in graph["parameters.alpha"]
    assert _cycle(graph) is None, " -> ".join(_cycle(graph))


#: The package's layers, lowest first (docs/architecture.md): a module imports from its own layer and the ones
#: before it only, function-level and TYPE_CHECKING imports included.
LAYERS = (
    ("errors", "_lazy", "core"),
    ("models",),
    ("uncertainty",),
    ("parameters",),
    ("io",),
    ("synthetic",),
    ("pipeline",),
    ("vessel",),
    ("analysis",),
    ("app",),
)
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}


def test_every_module_belongs_to_a_layer():
    assert {m.split(".")[0] for m in MODULES} <= set(RANK), set(m.split(".")[0] for m in MODULES) - set(RANK)


def test_no_module_imports_from_a_higher_layer():
    upward = [
        f"{m} -> {t}"
        for m in MODULES
        for t in sorted(_imports(m, type_checking=True))
        if RANK[t.split(".")[0]] > RANK[m.split(".")[0]]
    ]
    assert not upward, upward


def test_the_layer_check_sees_type_checking_imports():
    graph = {m: _imports(m, type_checking=True) for m in MODULES}
    assert "models.velocity" in graph["parameters.beta"]
    assert "pipeline.options" in _imports("pipeline.band", type_checking=True)
    assert "pipeline.options" not in _imports("pipeline.band")  # it is a TYPE_CHECKING import there


def test_the_cycle_detector_finds_a_cycle():
    assert _cycle({**{m: set() for m in MODULES}, MODULES[0]: {MODULES[1]}, MODULES[1]: {MODULES[0]}})


@pytest.mark.parametrize("module", MODULES)
def test_module_imports_in_a_fresh_interpreter(module):
    subprocess.run([sys.executable, "-c", f"import wss_nlp.{module}"], check=True, capture_output=True)


def test_the_command_line_starts_without_scipy():
    """`wss-nlp --help` imports no SciPy module (they cost more than the rest of its start-up; issue 19), and the
    package's stand-in imports one when it is first used, attributes of the package itself too."""
    code = (
        "import sys; import wss_nlp.app.cli; from wss_nlp.app.cli import main; "
        "assert not [m for m in sys.modules if m.split('.')[0] == 'scipy'], 'scipy imported at start-up'; "
        "from wss_nlp._lazy import scipy; assert scipy.linalg.norm([3.0, 4.0]) == 5.0; "
        "assert 'scipy.linalg' in sys.modules and isinstance(scipy.__version__, str)"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


def test_no_module_shadows_the_standard_library():
    assert not {m.split(".")[-1] for m in MODULES} & set(sys.stdlib_module_names)


def test_blas_threads_limit_is_applied_and_restored():
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from wss_nlp.pipeline.driver import blas_threads

    def blas():
        return [i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas"]

    import scipy.linalg  # noqa: F401  (SciPy's own BLAS, which blas_threads loads before limiting)

    before = blas()
    if not before:
        pytest.skip("no BLAS visible to threadpoolctl")
    with blas_threads(1):
        assert set(blas()) == {1}
    assert blas() == before
    with blas_threads(0):
        assert blas() == before


def test_blas_threads_limits_a_blas_loaded_after_the_call():
    # a fresh process: SciPy's BLAS is not loaded yet when the limit is asked for; the first solve of a sweep or a
    # batch ran unlimited (and rounded differently from every later one) until blas_threads loaded it first
    pytest.importorskip("threadpoolctl")
    code = (
        "import numpy, threadpoolctl\n"
        "from wss_nlp.pipeline.driver import blas_threads\n"
        "with blas_threads(1):\n"
        "    import scipy.linalg\n"
        "    n = [i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']\n"
        "print(n)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert set(eval(out)) == {1}
