"""The reconstruction methods as objects: what ``--method`` selects.

* :class:`Decoupled` (the paper's): geometry from the magnitude, then the velocity on that lumen;
* :class:`Coupled`: the decoupled solution refined by the coupled NLP (:mod:`wss_nlp.models.coupled`), in which
  the velocity data inform the wall too;
* :class:`Baseline`: a classical estimator (:mod:`wss_nlp.models.baselines`), fitted slice by slice on its own
  segmentation; none of the pipeline's steps apply.

The driver asks a method for what it adds to a segment's decoupled states (:meth:`Method.refine`); a baseline
reconstructs an acquisition itself.
"""

from __future__ import annotations

from ..errors import InputError, WssNlpError
from ..io.files import FailedSlice
from ..models import baselines as bl


class Method:
    """A reconstruction method; ``name`` is its ``--method`` word."""

    name = ""
    #: Whether a stack's slices can be tied along z (Sec. 5): the z-penalty needs the velocity model of every
    #: slice, which the classical baselines do not have (they fit each slice on its own segmentation).
    ties_slices = True

    def refine(self, states, fitter) -> tuple:
        """``(results, records)`` of what the method adds to the decoupled states (None, empty records: nothing);
        the states take the refined geometry and velocity."""
        return None, [{} for _ in states]


class Decoupled(Method):
    name = "decoupled"


class Coupled(Method):
    name = "coupled"

    def refine(self, states, fitter):
        results, records = fitter.coupled(states)
        for s, c in zip(states, results):
            s.geometry, s.velocity = c.geometry, c.velocity
        return results, records


class Baseline(Method):
    """A classical estimator of :mod:`wss_nlp.models.baselines` (``oyre`` or ``stalder``)."""

    ties_slices = False

    def __init__(self, name: str):
        self.name = name

    def reconstruct(self, acq, mu: float, options, progress=None) -> list:
        """Every slice of ``acq`` by the estimator (a slice that fails is a FailedSlice in a stack, raised alone)."""
        velocity = acq.velocity_images()
        bad = set(acq.nonfinite_slices())
        out: list = []
        for iz in range(acq.nz):
            res: bl.BaselineResult | FailedSlice
            try:
                if iz in bad:
                    raise InputError(f"{acq.source} slice {iz}: the images contain NaN or Inf")
                res = bl.reconstruct_slice(
                    acq.magnitude[iz], velocity[iz], acq.grid, mu, self.name, options.baseline, options.n_phi,
                    acq.source, iz, options.screen.vessel,
                )  # fmt: skip
            except WssNlpError as exc:
                if acq.nz == 1:
                    raise
                res = FailedSlice(iz, str(exc), options.n_phi, options.geometry.n_fourier)
            out.append(res)
            if progress is not None:
                progress(iz + 1, acq.nz, res)
        if all(isinstance(r, FailedSlice) for r in out):
            raise WssNlpError(f"{acq.source}: no slice could be reconstructed: " + "; ".join(r.reason for r in out))
        return out


#: The methods by their ``--method`` words.
REGISTRY: dict[str, Method] = {
    "decoupled": Decoupled(),
    "coupled": Coupled(),
    **{name: Baseline(name) for name in bl.METHODS},
}


def of(options) -> Method:
    """The method ``options.method`` names."""
    return REGISTRY[options.method]
