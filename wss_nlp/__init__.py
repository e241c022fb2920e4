"""wss-nlp: vessel geometry, velocity and wall shear stress from phase-contrast MRI."""

__version__ = "0.1.0"


def __getattr__(name: str):
    # ``wss_nlp.io`` was renamed ``wss_nlp.files`` (it shadowed the standard library's io); old imports still work
    if name == "io":
        import warnings

        from . import files

        warnings.warn("wss_nlp.io is now wss_nlp.files; the old name will be removed", DeprecationWarning, stacklevel=2)
        return files
    raise AttributeError(f"module 'wss_nlp' has no attribute {name!r}")
