"""Files in and out: the HDF5 contract's layouts, scanner exports (DICOM, NIfTI), planes cut from volumes, VTK
export and output paths.

Before 0.2 ``wss_nlp.io`` named the HDF5 module (now :mod:`wss_nlp.io.files`); its names are still found here,
with a :class:`DeprecationWarning`.
"""


def __getattr__(name: str):
    import importlib
    import warnings

    files = importlib.import_module(f"{__name__}.files")
    if name.startswith("__") or not hasattr(files, name):
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    warnings.warn(f"wss_nlp.io.{name} moved to wss_nlp.io.files.{name}", DeprecationWarning, stacklevel=2)
    return getattr(files, name)
