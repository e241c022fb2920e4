"""End-to-end accuracy on phantoms with default options (issue targets).

Seeds 21-22 were not used when the basis and penalty were chosen (that
sweep used seeds 1-2); they did inform kappa_beta = 2.5 (seed 22 failed the
WSS target with kappa = 2; README, "Choosing alpha and beta"), so the
phantoms and seeds of ``scripts/accuracy.py --unseen`` are the unseen check.
Targets from the issue: radius error <= 0.5 % and laminar WSS error <= 5 % at
h = 1.0 and 0.3 mm, SNR 25.
"""

import pytest

from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.analysis import metrics
from wss_nlp.synthetic import phantoms
from wss_nlp.pipeline import ReconstructionOptions, reconstruct


@pytest.mark.parametrize("h", [1.0, 0.3])
@pytest.mark.parametrize("seed", [21, 22])
def test_laminar_geometry_and_wss(h, seed):
    acq, truth = phantoms.make_phantom("laminar", h_mm=h, snr=25, seed=seed)
    res = reconstruct(acq)[0]
    err = metrics.compare_slice(res, truth)
    assert res.converged
    assert err.radius_rel_l2 <= 0.005
    assert err.wss_rel_l2 <= 0.05
    assert abs(err.mean_wss_rel) <= 0.05


@pytest.mark.parametrize("h", [1.5, 1.0, 0.3])
def test_turbulent_geometry(h):
    acq, truth = phantoms.make_phantom("turbulent", h_mm=h, snr=25, seed=21)
    res = reconstruct(acq)[0]
    assert metrics.compare_slice(res, truth).radius_rel_l2 <= 0.005


def test_dephasing_prediction_from_gcv_fit_reduces_turbulent_radius_error():
    """At h = 1.5 mm the boundary layer dephases wall voxels; predicting that from the over-smoothed WSS fit
    (``same``) leaves a larger radius bias than from the GCV fit (measured 0.84 % vs 0.45 % worst over seeds 0-4)."""
    acq, truth = phantoms.make_phantom("turbulent", h_mm=1.5, snr=25, seed=21)
    errs = {
        rule: metrics.compare_slice(
            reconstruct(acq, ReconstructionOptions(choice=ChoiceOptions(dephasing_beta_rule=rule)))[0], truth
        ).radius_rel_l2
        for rule in ("gcv", "same")
    }
    assert errs["gcv"] < errs["same"]
    assert errs["gcv"] <= 0.005


def test_manufactured_flow_on_three_lobed_wall():
    """A shape and flow outside the ellipse family: WSS within 5 % at h = 0.6 mm."""
    acq, truth = phantoms.make_phantom("manufactured", h_mm=0.6, snr=25, seed=21)
    err = metrics.compare_slice(reconstruct(acq)[0], truth)
    assert err.radius_rel_l2 <= 0.005
    assert err.wss_rel_l2 <= 0.05
