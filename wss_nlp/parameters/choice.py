"""Deprecated home of the parameter rules applied to the problems (before 0.2); its names live in
:mod:`~wss_nlp.parameters.alpha`, :mod:`~wss_nlp.parameters.beta`, :mod:`~wss_nlp.parameters.layer`,
:mod:`~wss_nlp.parameters.kspace_filter` and :mod:`~wss_nlp.parameters.options` now, and take the options they
use (``ChoiceOptions``, ``GeometryOptions``, ``VelocityOptions``) instead of the whole ``ReconstructionOptions``.
"""

import warnings

from .alpha import ALPHA_STOP, balance_alpha, choose_alpha  # noqa: F401
from .beta import BALANCE_TAIL, BETA_STOP, choose_beta, gcv_beta, geometric_median, segment_beta  # noqa: F401
from .beta import velocity_beta  # noqa: F401
from .kspace_filter import FILTER_MARGIN, kspace_filter  # noqa: F401
from .layer import (  # noqa: F401
    CRITERION_BETAS,
    GOLDEN_STEPS,
    LAYER_RATIOS,
    NO_ROOT,
    ROOT_RESOLUTION,
    PlainCriterion,
    blasius_scale,
    choose_layer,
    layer_model,
)
from .options import ALPHA_RULES, AUTO_RULE, BETA_RULES, DEPHASING_BETA_RULES, parse_rule  # noqa: F401

warnings.warn(
    "wss_nlp.parameters.choice is split into parameters.alpha, .beta, .layer, .kspace_filter and .options since "
    "wss-nlp 0.2; import from those",
    DeprecationWarning,
    stacklevel=2,
)
