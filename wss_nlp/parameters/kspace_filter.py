"""The scanner's k-space filter from the data (``--kspace-filter auto``), which the DICOM headers do not state."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from ..models import geometry as geo
from ..models import kspace
from ..models import preprocess as pp

#: Relative margin of the magnitude misfit below which the k-space filter choice counts as ambiguous.
FILTER_MARGIN = 0.05


def kspace_filter(magnitudes, grid, template: kspace.PSF, gopt: geo.GeometryOptions, vessel, where: str) -> kspace.PSF:
    """``--kspace-filter auto``: the filter whose geometry fit leaves the smallest magnitude misfit (``vessel``:
    the screen's choice of vessel, :attr:`wss_nlp.pipeline.plausibility.ScreenOptions.vessel`).

    Notes
    -----
    The standard DICOM headers do not state the scanner's k-space filter,
    and a wrong one is not harmless (``scripts/results/kspace.md``: 2-600 %
    WSS errors). The filters differ in the Gibbs ringing and the edge width
    they put into the magnitude image, which the geometry fit sees: the
    geometry step is solved once per filter (alpha fixed) on the first slice
    that preprocesses, and the filter with the smallest rms misfit on the
    window about the wall is taken (the window depends on the zero-filling
    only, so the misfits compare like with like). The record (misfits,
    runner-up, relative margin) goes with every slice; a margin under
    :data:`FILTER_MARGIN` is reported as ambiguous ("none" and "fermi",
    which differ only above 0.9 k_max, are often that close).
    """
    last: Exception | None = None
    for iz, image in enumerate(magnitudes):
        if not np.all(np.isfinite(image)):
            continue
        try:
            _, m, lumen = pp.preprocess(image, grid, where, vessel, clip_upper=False)
        except InputError as exc:
            last = exc
            continue
        misfits = {}
        for name in kspace.FILTERS:
            psf = replace(template, filter=name)
            problem = geo.GeometryProblem(grid, m, lumen.center, lumen.r0, lumen.r1, lumen.r_area, psf=psf)
            misfits[name] = float(geo.solve(problem, gopt).annulus_residual_norm)
        best, second = sorted(misfits, key=misfits.__getitem__)[:2]
        margin = misfits[second] / max(misfits[best], 1e-300) - 1
        record = {
            "criterion": "smallest rms magnitude misfit of the geometry fit on the window about the wall",
            "misfits_mm": misfits,
            "chosen": best,
            "runner_up": second,
            "margin": margin,
            "ambiguous": bool(margin < FILTER_MARGIN),
            "slice": iz,
        }
        return replace(template, filter=best, choice=record)
    raise InputError(f"{where}no slice to choose the k-space filter on ({last}); pass --kspace-filter")
