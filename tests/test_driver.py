"""One driver for every layout (issue 37): slices, stacks, cine frames and stacks of cines go through the same steps.

Each layout is run with each group of features (the decoupled method with a near-wall choice, alpha chosen
by a rule, the dephasing pass and the band; the coupled method; the k-space measurement model; the in-plane
velocity components of 4D flow), and the results are checked for what each feature must leave behind. A slice
that a stack solves as a segment of its own equals the slice reconstructed alone, bit for bit.
"""

from dataclasses import replace

import numpy as np
import pytest

from wss_nlp.io.files import Acquisition, FailedSlice
from wss_nlp.models import kspace
from wss_nlp.models import stack
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.pipeline import ReconstructionOptions, reconstruct, reconstruct_cine
from wss_nlp.pipeline.results import SliceResult
from wss_nlp.synthetic import phantoms

#: The feature groups: name -> (options, whether the acquisition is k-space, whether it has in-plane components).
FEATURES = {
    "decoupled": (ReconstructionOptions(choice=ChoiceOptions(alpha_rule="balance")), False, False),
    "coupled": (ReconstructionOptions(method="coupled"), False, False),
    "kspace": (ReconstructionOptions(uncertainty=False), True, False),
    "inplane": (ReconstructionOptions(uncertainty=False), False, True),
}
LAYOUTS = ("slice", "stack", "cine", "stack of cines")


def _frames(n_frames: int, nz: int, kspace_data: bool, inplane: bool) -> list[Acquisition]:
    """``n_frames`` acquisitions of the tapered tube (fresh noise each), ``nz`` slices 2 mm apart."""
    psf = kspace.PSF("hamming", (1.5, 1.5)) if kspace_data else None
    swirl = 4.0 if inplane else None
    return [
        phantoms.make_stack(
            "tapered", nz=nz, h_mm=1.5, spacing_mm=2.0, snr=30, seed=40 + k, swirl_per_s=swirl, psf=psf
        )[0]
        for k in range(n_frames)
    ]


def _slices(layout: str, feature: str):
    options, kspace_data, inplane = FEATURES[feature]
    nz = 2 if "stack" in layout else 1
    n_frames = 1 if "cine" not in layout else 2 if "stack" in layout else 3  # (the cycle's models need two)
    frames = _frames(n_frames, nz, kspace_data, inplane)
    if kspace_data:
        options = replace(options, acquisition=kspace.AcquisitionOptions("kspace", "hamming"))
    if "cine" not in layout:
        results = reconstruct(frames[0], options)
        return list(results), options, results
    cine = reconstruct_cine(frames, np.arange(n_frames) * 300.0, 900.0, options)
    return [r for frame in cine.frames for r in frame], options, cine


@pytest.mark.parametrize("feature", list(FEATURES))
@pytest.mark.parametrize("layout", LAYOUTS)
def test_the_driver_runs_every_feature_on_every_layout(layout, feature):
    results, options, whole = _slices(layout, feature)
    assert results and all(isinstance(r, SliceResult) for r in results)
    for r in results:
        assert np.all(np.isfinite(r.wss.tau)) and r.wss.tau.size == options.n_phi
        assert r.method == options.method and r.alpha_choice is not None and r.beta_choice is not None
    if feature == "decoupled":
        # alpha by its rule on every slice (a z-tied segment takes the median of its slices' choices)
        assert all(r.alpha_choice.rule == "balance" for r in results)
        assert all(r.dephasing.passes in (None, 0, 1) for r in results)
    if feature == "coupled":
        assert all(r.coupled_info.get("velocity_weight", 0) > 0 for r in results)
    if feature in ("decoupled", "coupled"):  # the band: computed, or left for the cycle's model (cine)
        banded = [r for r in results if r.wss.tau_std is not None and np.all(np.isfinite(r.wss.tau_std))]
        explained = [r for r in results if any("no band for this frame's own fit" in n for n in r.notes)]
        assert len(banded) + len(explained) == len(results)
        assert banded or "cine" in layout
    if feature == "kspace":
        psf = whole.psf if hasattr(whole, "psf") else None
        assert psf is None or psf.filter == "hamming"
        assert all(r.dephasing.min_factor <= 1.0 for r in results)
    if feature == "inplane":  # the WSS vector from the in-plane components, on slices and stacks alike
        for r in results:
            assert r.wss.vector is not None and r.wss.vector.vector.shape == (options.n_phi, 3)
            assert np.all(np.isfinite(r.wss.vector.circumferential))
    if layout == "stack" or layout == "slice":
        assert (whole.stack is not None) == (layout == "stack")


def test_a_slice_solved_alone_in_a_stack_equals_the_slice():
    """A stack whose neighbours of slice 1 are unusable solves slice 1 as a segment of its own: the same steps,
    fitter and numbers as the slice reconstructed alone (bit for bit), the others reported as failed."""
    acq, _ = phantoms.make_stack("tapered", nz=3, h_mm=1.5, spacing_mm=2.0, snr=25, seed=7)
    mag = acq.magnitude.copy()
    mag[[0, 2]] = np.nan
    broken = replace(acq, magnitude=mag)
    alone = replace(acq, magnitude=acq.magnitude[1:2], phase=acq.phase[1:2], slice_spacing_mm=None)
    options = ReconstructionOptions()
    in_stack = reconstruct(broken, options)
    single = reconstruct(alone, options)[0]
    assert isinstance(in_stack[0], FailedSlice) and isinstance(in_stack[2], FailedSlice)
    r = in_stack[1]
    np.testing.assert_array_equal(r.geometry.coefficients, single.geometry.coefficients)
    np.testing.assert_array_equal(r.velocity.coefficients, single.velocity.coefficients)
    np.testing.assert_array_equal(r.wss.tau, single.wss.tau)
    np.testing.assert_array_equal(r.wss.tau_std, single.wss.tau_std)


def test_independent_slices_of_a_stack_equal_the_slices_alone():
    """``--z-smoothing 0``: each slice is a segment of its own, equal bit for bit to the slice reconstructed alone
    (the stack adds nothing but the order)."""
    acq, _ = phantoms.make_stack("curved", nz=2, h_mm=1.5, spacing_mm=2.0, snr=25, seed=8)
    options = ReconstructionOptions(uncertainty=False, stack=stack.StackOptions(z_smoothing_mm=0.0))
    both = reconstruct(acq, options)
    assert both.stack is None
    for k in range(2):
        alone = replace(acq, magnitude=acq.magnitude[k : k + 1], phase=acq.phase[k : k + 1], slice_spacing_mm=None)
        single = reconstruct(alone, options)[0]
        np.testing.assert_array_equal(both[k].wss.tau, single.wss.tau)
        np.testing.assert_array_equal(both[k].geometry.coefficients, single.geometry.coefficients)
