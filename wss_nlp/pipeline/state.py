"""One slice's state as it goes through the steps of a segment (:mod:`wss_nlp.pipeline.driver`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from ..models import surround

if TYPE_CHECKING:
    from ..models import geometry as geo
    from ..models import near_wall as nw
    from ..models import preprocess as pp
    from ..models import velocity as vel
    from ..parameters.rules import ParameterChoice
    from .steps import SliceData


@dataclass
class DephasingRecord:
    """What the dephasing passes did on a slice (``SliceResult.dephasing``, stored as ``dephasing_json``).

    ``passes``: corrective passes run (absent: none was worth it); ``beta``: of the velocity fit that
    predicted the dephasing; ``min_factor``: the smallest predicted magnitude factor of the first check;
    ``next_move``: the predicted wall move of a further pass (k-space, in voxels).
    """

    passes: int | None = None
    beta: float | None = None
    min_factor: float = 1.0
    next_move: float | None = None

    def as_dict(self) -> dict:
        """The record as stored (keys of the fields that are set, as before 0.2)."""
        out: dict = {}
        if self.passes is not None:
            out["passes"] = self.passes
        if self.beta is not None:
            out["beta"] = self.beta
        if self.next_move is not None:
            out["next_move"] = self.next_move
        out["min_factor"] = self.min_factor
        return out


@dataclass
class SliceState:
    """The current geometry, velocity and choices of one slice of a segment, updated by each step.

    ``problem`` and ``velocity_image`` are what the current pass fits (the dephasing-corrected magnitude and
    velocity after a pass); ``lumen`` is preprocessing's, with the k-space model's predicted background tails.
    """

    data: SliceData
    problem: geo.GeometryProblem
    lumen: pp.Lumen
    velocity_image: np.ndarray
    # set by the fitter's first steps (geometry, then velocity); a state is only read after them
    geometry: geo.GeometryResult = None  # type: ignore[assignment]
    alpha_choice: ParameterChoice = None  # type: ignore[assignment]
    velocity_problem: vel.VelocityProblem = None  # type: ignore[assignment]
    near: nw.NearWallChoice | None = None  # None: --near-wall off
    beta_choice: ParameterChoice = None  # type: ignore[assignment]
    velocity: vel.VelocityResult = None  # type: ignore[assignment]
    dephasing: DephasingRecord = field(default_factory=DephasingRecord)
    factors: np.ndarray | None = None  # the first check's predicted magnitude factors of the wall voxels
    notes: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)

    @classmethod
    def start(cls, data: SliceData) -> SliceState:
        # the surround model's and the offset correction's notes (issue 39) come with the preprocessing
        return cls(data, data.problem, data.lumen, data.velocity, notes=surround.notes(data.lumen.tissue))

    def snapshot(self) -> SliceState:
        """A copy to return to when a pass is undone (the arrays and results themselves are not modified)."""
        return replace(self, dephasing=replace(self.dephasing), notes=list(self.notes), seconds=dict(self.seconds))
