"""wss-nlp: vessel geometry, velocity and wall shear stress from phase-contrast MRI.

The package is organized in layers, each importing only from the ones before it (``docs/architecture.md``):
``core`` (numerics), ``models`` (the paper's forward models and fits), ``parameters`` (everything chosen from
the data), ``uncertainty`` (sensitivities, the band), ``io`` (files in and out), ``synthetic`` (phantoms),
``pipeline`` (one reconstruction from input to result), ``vessel`` (4D flow volumes), ``analysis`` (errors
against a truth) and ``app`` (command line, sweeps, figures).

Modules that lived at the top level before version 0.2 (``wss_nlp.geometry``, ``wss_nlp.reconstruct``,
``wss_nlp.files``, ...) are still importable by their old names, as the same module objects, with a
:class:`DeprecationWarning` naming the new home (:data:`MOVED`).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__version__ = "0.2.0.dev0"

#: Old top-level module (below ``wss_nlp``) -> its home since 0.2.
MOVED = {
    "radius": "core.radius",
    "operators": "core.operators",
    "elementwise": "core.elementwise",
    "chebyshev": "core.chebyshev",
    "tikhonov": "core.tikhonov",
    "solver": "core.solver",
    "checks": "core.checks",
    "schema": "core.schema",
    "mapping": "core.mapping",
    "velocity_basis": "core.velocity_basis",
    "measurement": "models.measurement",
    "kspace": "models.kspace",
    "preprocess": "models.preprocess",
    "geometry": "models.geometry",
    "velocity": "models.velocity",
    "near_wall": "models.near_wall",
    "wss": "models.wss",
    "dephasing": "models.dephasing",
    "coupled": "models.coupled",
    "stack": "models.stack",
    "womersley": "models.womersley",
    "temporal": "models.temporal",
    "baselines": "models.baselines",
    "sensitivity": "uncertainty.sensitivity",
    "stack_band": "uncertainty.stack_band",
    "files": "io.files",
    "dicom": "io.dicom",
    "nifti": "io.nifti",
    "scanner": "io.scanner",
    "importing": "io.importing",
    "plane": "io.plane",
    "export": "io.export",
    "outputs": "io.outputs",
    "phantoms": "synthetic.phantoms",
    "pulsatile": "synthetic.pulsatile",
    "scanner_exports": "synthetic.scanner_exports",
    "reconstruct": "pipeline.legacy",
    "results": "pipeline.results",
    "cine": "pipeline.cine",
    "plausibility": "pipeline.plausibility",
    "metrics": "analysis.metrics",
    "cli": "app.cli",
    "sweep": "app.sweep",
    "plotting": "app.plotting",
}


def _moved_warning(old: str, new: str) -> None:
    warnings.warn(
        f"wss_nlp.{old} moved to wss_nlp.{new} in wss-nlp 0.2; import it from there (the old name will be removed)",
        DeprecationWarning,
        stacklevel=3,
    )


class _MovedModule(importlib.abc.Loader):
    """Loads an old module name as the module object of its new home (one object under two names)."""

    def __init__(self, old: str):
        self.old = old

    def create_module(self, spec):
        _moved_warning(self.old, MOVED[self.old])
        return importlib.import_module(f"{__name__}.{MOVED[self.old]}")

    def exec_module(self, module) -> None:  # already executed under its new name
        pass


class _MovedFinder(importlib.abc.MetaPathFinder):
    """Finds ``wss_nlp.<old>`` for the modules of :data:`MOVED`."""

    def find_spec(self, fullname, path, target=None):
        head, _, old = fullname.partition(".")
        if head != __name__ or old not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, _MovedModule(old))


if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
    sys.meta_path.insert(0, _MovedFinder())


def __getattr__(name: str):
    # ``wss_nlp.geometry`` as an attribute (``from wss_nlp import geometry``) before anything imported it
    if name in MOVED:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'wss_nlp' has no attribute {name!r}")
