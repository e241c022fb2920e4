"""The reconstruction's Python entry points under their pre-0.2 module (``wss_nlp.reconstruct``).

The driver is :mod:`wss_nlp.pipeline.driver`, the options :mod:`wss_nlp.pipeline.options`; their names are
re-exported here so that ``from wss_nlp.reconstruct import ReconstructionOptions, reconstruct`` keeps working.
New code imports them from :mod:`wss_nlp.pipeline`.
"""

from __future__ import annotations

import numpy as np

from ..io.files import DEFAULT_DENSITY, Acquisition
from ..parameters.alpha import ALPHA_STOP, balance_alpha, choose_alpha  # noqa: F401
from ..parameters.beta import BETA_STOP, choose_beta, gcv_beta, velocity_beta  # noqa: F401
from ..parameters.kspace_filter import kspace_filter  # noqa: F401
from ..parameters.layer import layer_model  # noqa: F401
from ..parameters.options import ALPHA_RULES, AUTO_RULE, BETA_RULES, DEPHASING_BETA_RULES, parse_rule  # noqa: F401
from .driver import (  # noqa: F401
    KSPACE_PASS_PREDICTION,
    KSPACE_PASS_TOL,
    KSPACE_PASSES,
    RESAMPLED_MIN_RADIUS_VOXELS,
    RESAMPLED_NOTE,
    ZERO_FILL_TOLERANCE,
    ZERO_FILLED_NOTE,
    Results,
    blas_threads,
    reconstruct,
    stack_applies,
)
from .options import METHODS, WSS_GROUP, ReconstructionOptions  # noqa: F401
from .results import SliceResult  # noqa: F401


def reconstruct_slice(
    magnitude: np.ndarray,
    velocity_image: np.ndarray,
    grid,
    viscosity_pa_s: float,
    options: ReconstructionOptions,
    source: str = "<memory>",
    index: int = 0,
    venc: float | None = None,
    density: tuple[float, str] = (DEFAULT_DENSITY, "default (blood)"),
    noise_venc: float | None = None,
    psf=None,
    box=None,
    defer_band: bool = False,
) -> SliceResult:
    """One slice's geometry, velocity and WSS (before 0.2 the slice driver; now a segment of one slice of
    :func:`wss_nlp.pipeline.driver.run_segment`, without the acquisition's screening)."""
    from . import steps
    from .driver import run_segment
    from .fitters import Independent

    data = steps.prepare(
        magnitude, velocity_image, grid, index, source, options.screen.vessel, psf, venc, noise_venc, box,
        tissue=options.tissue,
    )  # fmt: skip
    return run_segment([data], Independent(options, viscosity_pa_s, density), options, viscosity_pa_s,
                       defer_band=defer_band)[0]  # fmt: skip


__all__ = ["Acquisition", "ReconstructionOptions", "Results", "reconstruct", "reconstruct_slice"]
