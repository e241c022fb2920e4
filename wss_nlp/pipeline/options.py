"""The root of a reconstruction's options: one declaration per option, each part for the layer that uses it.

:class:`ReconstructionOptions` is what the command line, the study files (:mod:`wss_nlp.core.schema`) and the
Python API build, and what a result file stores (``options_json``). Every module below the driver receives only
its part: the geometry step ``options.geometry``, the parameter rules ``options.choice``, and so on.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import asdict, dataclass, field, replace

from ..core.schema import option
from ..errors import InputError
from ..io.files import check_density
from ..models import baselines as bl
from ..models import coupled as cpl
from ..models import geometry as geo
from ..models import kspace
from ..models import stack as stk
from ..models import surround
from ..models import velocity as vel
from ..models import womersley
from ..parameters.options import ChoiceOptions
from . import plausibility as plaus

#: The reconstruction methods (:mod:`wss_nlp.pipeline.methods`).
METHODS = ("decoupled", "coupled") + bl.METHODS
WSS_GROUP = "wall shear stress (Sec. 4)"


@dataclass(frozen=True)
class ReconstructionOptions:
    """Everything that controls a reconstruction (stored in the result file): the root of the options.

    Each part goes to the layer that uses it: ``geometry`` (:class:`~wss_nlp.models.geometry.GeometryOptions`),
    ``velocity`` (:class:`~wss_nlp.models.velocity.VelocityOptions`), ``choice`` (how alpha and beta are
    chosen, :class:`~wss_nlp.parameters.options.ChoiceOptions`), ``coupled``, ``baseline``, ``stack``,
    ``screen``, ``acquisition`` (box or k-space measurement model), ``cine``, ``tissue`` (the model of what
    surrounds the lumen and the background phase correction, :class:`~wss_nlp.models.surround.TissueOptions`);
    the fields on the root are the driver's own (method, WSS angles, viscosity and density overrides, the
    dephasing pass, the band).

    The choice fields were on the root before 0.2: ``ReconstructionOptions(beta_rule="gcv")`` still works
    (with a :class:`DeprecationWarning`), and ``options.beta_rule`` reads ``options.choice.beta_rule``.
    """

    schema_group = "method and parameter choice"

    geometry: geo.GeometryOptions = field(default_factory=geo.GeometryOptions)
    velocity: vel.VelocityOptions = field(default_factory=vel.VelocityOptions)
    method: str = option(
        "decoupled",
        "decoupled: geometry, then velocity (the paper's); coupled: both as one NLP "
        "started from the decoupled solution, so the velocity data inform the wall too; oyre / "
        "stalder: the classical baselines (cubic near-wall profile fits / smoothing B-spline on a "
        "50 % magnitude segmentation; docs, 'Classical baselines')",
        cli="--method",
        toml=("method",),
        choices=METHODS,
    )
    coupled: cpl.CoupledOptions = field(default_factory=cpl.CoupledOptions)
    baseline: bl.BaselineOptions = field(default_factory=bl.BaselineOptions)  # method "oyre" / "stalder"
    stack: stk.StackOptions = field(default_factory=stk.StackOptions)  # nz > 1: z-regularization (wss_nlp.models.stack)
    screen: plaus.ScreenOptions = field(default_factory=plaus.ScreenOptions)  # vessel choice, unwrapping
    acquisition: kspace.AcquisitionOptions = field(default_factory=kspace.AcquisitionOptions)  # box or k-space PSF
    cine: womersley.CineModelOptions = field(default_factory=womersley.CineModelOptions)  # frames tied in time
    tissue: surround.TissueOptions = field(default_factory=surround.TissueOptions)  # surround model, phase offset
    n_phi: int = option(360, "angles at which tau is reported, >= 360", cli="--n-phi", toml=("n_phi",), group=WSS_GROUP)
    viscosity_pa_s: float | None = option(
        None,
        "dynamic viscosity in Pa*s; overrides the file's 'viscosity_pa_s'",
        cli="--viscosity",
        toml=("viscosity",),
        group=WSS_GROUP,
    )
    density_kg_m3: float | None = option(
        None,
        "fluid density in kg/m^3, used by the law-of-the-wall layer (--near-wall); overrides the file's "
        "'density_kg_m3' (default: blood, 1060)",
        cli="--density",
        toml=("density",),
        group=WSS_GROUP,
    )
    dephasing_correction: bool = option(
        True,
        "skip the second pass that corrects the magnitude for intra-voxel dephasing (needs venc)",
        cli="--no-dephasing-correction",
        toml=("dephasing_correction",),
        flag_off=True,
        group=WSS_GROUP,
    )
    blas_threads: int = option(
        1,
        "BLAS threads for the small dense linear algebra of each slice; 0 leaves the BLAS as it is (more threads "
        "only add overhead at these matrix sizes: scripts/bench_blas.py)",
        cli="--blas-threads",
        group=WSS_GROUP,
    )
    uncertainty: bool = option(
        True,
        "skip the linearized WSS band and the sensitivities (about 1-3x the time of the solve)",
        cli="--no-uncertainty",
        toml=("uncertainty",),
        flag_off=True,
        group=WSS_GROUP,
    )
    noise_sigma: float | None = option(
        None,
        "complex noise per channel in raw magnitude units for the band (default: from the Rayleigh background)",
        cli="--noise-sigma",
        group=WSS_GROUP,
    )
    # last: its options join the groups the fields above open (the --help layout of before 0.2)
    choice: ChoiceOptions = field(default_factory=ChoiceOptions)  # alpha and beta from the data

    def __post_init__(self):
        if self.n_phi < 360:
            raise InputError(f"n_phi must be >= 360 (file format), got {self.n_phi}")
        if self.method not in METHODS:
            raise InputError(f"method must be one of {METHODS}, got {self.method!r}")
        self.choice.check_values(self.geometry.alpha, self.velocity.beta)
        check_density(self.density_kg_m3, "--density")
        if self.blas_threads < 0:
            raise InputError(f"blas_threads must be >= 0 (0: leave the BLAS as it is), got {self.blas_threads}")

    def as_dict(self) -> dict:
        """The options as stored in result files (``options_json``): nested as the dataclasses are, and the
        choice's fields also under their pre-0.2 names at the root, so that readers of older files keep working."""
        out = asdict(self)
        out.update({name: out["choice"][name] for name in ChoiceOptions.FIELDS})
        return out


def _legacy_init(init):
    """Accept the choice fields by their pre-0.2 names on the root (``ReconstructionOptions(beta_rule=...)``)."""

    @functools.wraps(init)
    def __init__(self, *args, **kwargs):
        legacy = {name: kwargs.pop(name) for name in ChoiceOptions.FIELDS if name in kwargs}
        if legacy:
            warnings.warn(
                f"ReconstructionOptions({', '.join(legacy)}=...): these are fields of "
                "ReconstructionOptions.choice since wss-nlp 0.2; pass choice=ChoiceOptions(...) (the old "
                "names will be removed)",
                DeprecationWarning,
                stacklevel=2,
            )
            kwargs["choice"] = replace(kwargs.get("choice", ChoiceOptions()), **legacy)
        init(self, *args, **kwargs)

    return __init__


ReconstructionOptions.__init__ = _legacy_init(ReconstructionOptions.__init__)  # type: ignore[method-assign]


def _choice_field(name: str) -> property:
    return property(lambda self: getattr(self.choice, name), doc=f"``choice.{name}`` (its name before 0.2)")


for _name in ChoiceOptions.FIELDS:  # the old names read the choice's fields
    setattr(ReconstructionOptions, _name, _choice_field(_name))
