r"""Measurement models: how a voxel's value arises from the signal of the vessel it sees.

Every forward model of the method goes through one :class:`MeasurementModel`:

* :class:`VoxelMeans` (the paper's, Sec. 7): a voxel's value is the mean of the signal over the voxel,
  :math:`F_i(R) = |V_i|^{-1}\int_{V_i} H_\gamma(R(\phi) - |x - c|)\,dx` for the magnitude and the mean of
  :math:`v \circ \phi_R^{-1}` over :math:`V_i \cap \Omega` for the velocity; voxels' noise is independent;
* :class:`KSpace`: a Cartesian acquisition's point-spread function (:mod:`wss_nlp.models.kspace`): the filtered,
  zero-filled image of the signal, whose noise is correlated between voxels.

A model carries the magnitude model (its setup on a grid and its CasADi expression, with the exact Jacobian
and second-order term), the velocity averager (the operator of the velocity fit), the noise correlation and
the preprocessing rule that goes with it. The geometry, velocity, dephasing and coupled steps call these
methods instead of branching on the acquisition; the 4D flow model on the volume's own voxels
(:mod:`wss_nlp.vessel`) is one more model of this kind, on three-dimensional voxels. The uncertainty layer
dispatches its parameter derivatives on the model's type.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import kspace
from . import measurement as meas


class MeasurementModel:
    """The interface of a voxel's measurement model (see the module notes)."""

    #: The acquisition model's name in records and options (``--acquisition``).
    name = ""
    #: Whether preprocessing may clip the normalized magnitude at 1 (voxel means cannot exceed the lumen's
    #: level; a PSF's ringing can).
    clip_upper = True
    #: Whether the model's image of the lumen reaches into the background (a PSF's tails), which the noise
    #: estimates there must then subtract.
    background_tails = False
    #: Most dephasing passes (:mod:`wss_nlp.pipeline.driver`): with voxel means the factors hardly move after
    #: one; a PSF mixes phases further than a wall voxel, so its passes repeat, each judged by how well it
    #: explains the magnitude.
    dephasing_passes = 1
    #: Why the surround model (:mod:`wss_nlp.models.surround`: lumen, wall ring and outside levels mixed by the
    #: lumen fraction) may not replace Appendix B's two-level normalization on this acquisition; "": it may
    #: (each voxel the mean of the complex signal over the voxel, the surround model's own assumption).
    two_level_only = ""

    @property
    def blur_voxels(self) -> float:
        """How many image voxels one voxel's signal spreads over (1 for voxel means; a zero-filled acquisition's
        acquired voxel spans ``zero_fill`` image voxels): the reach of a vessel's signal, and phase, beyond its
        wall, which the static tissue of the offset correction keeps away from (:mod:`wss_nlp.models.offset`)."""
        return 1.0

    @property
    def psf(self) -> kspace.PSF | None:
        """The point-spread function, or None for voxel means."""
        return None

    def magnitude_setup(self, grid, center, r0: float, r1: float, q: int, gamma: float):
        """What the magnitude model needs on this grid and radius box: the fitted voxels (``.annulus``), those
        fully inside (``.inside``) and the sub-voxel points."""
        raise NotImplementedError

    def magnitude_model(self, setup, c, width, heaviside: str, **kwargs):
        """The model's normalized magnitude on ``setup.annulus`` for radius coefficients ``c`` (NumPy or CasADi),
        with ``jacobian`` / ``second_order`` as :func:`wss_nlp.models.measurement.magnitude_model`."""
        raise NotImplementedError

    def velocity_operator(self, grid, voxels, basis, rho, t, q: int):
        """``(operator, weights, averager)`` of the velocity fit: each fitted voxel's model value of the basis
        functions at the reference-disk points ``(rho, t)`` of its sub-voxel points inside the lumen, its misfit
        weight (mm^2), and the averager the near-wall layer's columns reuse (None: the voxels' means)."""
        raise NotImplementedError

    def noise_correlation(self, grid_shape, index):
        """The correlation of the image noise on the voxels ``index`` (None: independent voxels)."""
        return None

    def correlation_factors(self, grid_shape):
        """``(R_y, R_x, shape)``: the noise correlation's separable factors (None: independent voxels)."""
        return None

    def highpass_noise_variance(self, grid_shape) -> float:
        """Variance, per unit noise variance, of ``a - (mean of the 4 neighbours)`` on pure noise: 1.25 for
        independent voxels, less where the noise is correlated (``sum_ab c_a c_b rho(x_a - x_b)`` over the
        stencil ``c``): what a noise estimate from such residuals (:func:`wss_nlp.models.surround.lumen_noise_sigma`)
        divides by."""
        factors = self.correlation_factors(grid_shape)
        if factors is None:
            return 1.25
        ry, rx, _ = factors
        stencil = [((0, 0), 1.0)] + [((dy, dx), -0.25) for dy, dx in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        # the correlations depend on the offset alone (periodic tables): read them off row 0
        return float(
            sum(ca * cb * ry[0, (a[0] - b[0]) % ry.shape[1]] * rx[0, (a[1] - b[1]) % rx.shape[1]]
                for a, ca in stencil for b, cb in stencil)
        )  # fmt: skip

    def describe(self) -> dict:
        """What the result records about the acquisition model."""
        return {"model": self.name}


@dataclass(frozen=True)
class VoxelMeans(MeasurementModel):
    """Each voxel the mean of the signal over the voxel (the paper's model, Sec. 7); independent noise."""

    name = "box"

    def magnitude_setup(self, grid, center, r0, r1, q, gamma):
        return meas.annulus_model(grid, center, r0, r1, q)

    def magnitude_model(self, setup, c, width, heaviside, **kwargs):
        return meas.magnitude_model(setup, c, width, heaviside, **kwargs)

    def velocity_operator(self, grid, voxels, basis, rho, t, q):
        operator = basis.evaluate(rho * np.cos(t), rho * np.sin(t), average=voxels.mean_matrix())
        return operator, voxels.fraction * grid.voxel_area, None


@dataclass(frozen=True)
class KSpace(MeasurementModel):
    """A Cartesian acquisition's point-spread function (:mod:`wss_nlp.models.kspace`): filtered and zero-filled."""

    point_spread: kspace.PSF
    name = "kspace"
    clip_upper = False
    background_tails = True
    dephasing_passes = 3
    two_level_only = "k-space acquisition (its PSF tails are modelled with two levels)"

    @property
    def psf(self) -> kspace.PSF:
        return self.point_spread

    @property
    def blur_voxels(self) -> float:
        return float(max(self.point_spread.zero_fill))

    def magnitude_setup(self, grid, center, r0, r1, q, gamma):
        return kspace.magnitude_setup(grid, center, r0, r1, q, gamma, self.point_spread)

    def magnitude_model(self, setup, c, width, heaviside, **kwargs):
        return kspace.magnitude_model(setup, c, width, heaviside, **kwargs)

    def velocity_operator(self, grid, voxels, basis, rho, t, q):
        averager = kspace.Averager(grid, voxels.index, q, self.point_spread)
        signal = averager(voxels.inside.astype(float))
        keep = signal >= MIN_KSPACE_SIGNAL
        # the PSF (linear) on the unnormalized functions, the basis's transform on the small result
        raw = basis.evaluate_raw(rho * np.cos(t), rho * np.sin(t))
        values = np.zeros(voxels.inside.shape + (raw.shape[1],))
        values[voxels.inside] = raw
        averaged = averager(values) @ basis.transform
        operator = np.where(keep[:, None], averaged / np.where(keep, signal, 1.0)[:, None], 0.0)
        weights = np.where(keep, signal, 0.0) * grid.voxel_area  # weight 0: the voxel's points still radiate
        return operator, weights, averager

    def noise_correlation(self, grid_shape, index):
        return kspace.NoiseCorrelation(grid_shape, self.point_spread, index)

    def correlation_factors(self, grid_shape):
        (ny, nx), psf = grid_shape, self.point_spread
        return (
            kspace.noise_correlation(ny, psf.zero_fill[0], psf.filter),
            kspace.noise_correlation(nx, psf.zero_fill[1], psf.filter),
            (ny, nx),
        )

    def describe(self) -> dict:
        return self.point_spread.describe()


#: Smallest modeled signal (K * chi)_i, relative to the lumen's, of a voxel in the k-space velocity fit.
MIN_KSPACE_SIGNAL = 0.02


def of(psf: kspace.PSF | None) -> MeasurementModel:
    """The measurement model of an acquisition resolved to a PSF (:meth:`kspace.AcquisitionOptions.psf`): voxel
    means for None."""
    return VOXEL_MEANS if psf is None else KSpace(psf)


VOXEL_MEANS = VoxelMeans()
