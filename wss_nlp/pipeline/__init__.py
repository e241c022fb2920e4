"""One reconstruction from input to result: screening, the steps every segment goes through, the driver, results,
cine.

``from wss_nlp.pipeline import ReconstructionOptions, reconstruct`` gives the options and the driver
(:mod:`wss_nlp.pipeline.options`, :mod:`wss_nlp.pipeline.driver`); ``reconstruct_cine`` the cine driver
(:mod:`wss_nlp.pipeline.cine`). Before 0.2 ``wss_nlp.pipeline`` was the module now called
:mod:`wss_nlp.pipeline.steps`; its names are still found here, with a :class:`DeprecationWarning`.
"""

_EXPORTS = {
    "ReconstructionOptions": "options",
    "reconstruct": "driver",
    "Results": "driver",
    "reconstruct_cine": "cine",
    "SliceResult": "results",
}


def __getattr__(name: str):
    import importlib
    import warnings

    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    steps = importlib.import_module(f"{__name__}.steps")
    if name.startswith("__") or not hasattr(steps, name):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"wss_nlp.pipeline.{name} moved to wss_nlp.pipeline.steps.{name} in wss-nlp 0.2",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(steps, name)


__all__ = list(_EXPORTS)
