"""One reconstruction from input to result: screening, the steps every segment goes through, the driver, results,
cine.

Before 0.2 ``wss_nlp.pipeline`` was a module (now :mod:`wss_nlp.pipeline.steps`); its names are still found
here, with a :class:`DeprecationWarning`.
"""


def __getattr__(name: str):
    import importlib
    import warnings

    steps = importlib.import_module(f"{__name__}.steps")
    if name.startswith("__") or not hasattr(steps, name):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(
        f"wss_nlp.pipeline.{name} moved to wss_nlp.pipeline.steps.{name} in wss-nlp 0.2",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(steps, name)
