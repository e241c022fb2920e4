"""Options checked before any work (wss_nlp.pipeline.limits): refusals in the user's words, and the size estimate."""

import numpy as np
import pytest

from wss_nlp.app.cli.arguments import options_from_args
from wss_nlp.app.cli.parser import build_parser
from wss_nlp.app.sweep import options_for
from wss_nlp.core.velocity_basis import _zernike_terms
from wss_nlp.errors import InputError
from wss_nlp.models.velocity import VelocityOptions
from wss_nlp.pipeline import ReconstructionOptions, limits


def _cli(*extra):
    return options_from_args(build_parser().parse_args(["reconstruct", "in.h5", "-o", "out.h5", *extra]))


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--quad-order", "0"], "--quad-order 0: must be a whole number >= 1"),
        (["--sobolev", "-1"], "--sobolev -1: must be a whole number in 0-4"),
        (["--degree", "0"], "--degree 0: must be a whole number >= 4"),
        (["--gamma", "0"], "--gamma 0: must be a number above 0"),
        (["--n-phi", "100"], "--n-phi 100: must be a whole number >= 360"),
        (["--noise-sigma", "-1"], "--noise-sigma -1"),
        (["--max-eigenvalue", "-5"], "--max-eigenvalue -5"),
        (["--tau-beta", "0.5"], "--tau-beta 0.5: must be a number in 1-100"),
        (["--alpha", "nan"], "--alpha nan"),
        (["--viscosity", "3.5"], "--viscosity: viscosity 3.5 Pa s is 1000x blood's"),
        (["--density", "1.06"], "--density: density 1.06 kg/m^3"),
        (["--allow-unphysical", "frob"], "--allow-unphysical frob: unknown quantity"),
    ],
)
def test_a_refusal_names_the_option_as_written(extra, words):
    with pytest.raises(InputError) as exc:
        _cli(*extra)
    assert words in str(exc.value), str(exc.value)


def test_study_keys_are_named_as_written():
    with pytest.raises(InputError, match="quad_order 0: must be a whole number"):
        options_for({"quad_order": 0})
    with pytest.raises(InputError, match="N 2.5: must be a whole number|2.5 is not a whole number"):
        options_for({"N": 2.5})
    assert options_for({"N": 6.0}).geometry.n_fourier == 6  # a TOML float that is a whole number is one


def test_allowed_quantities_pass_and_integers_may_be_written_as_floats():
    assert _cli("--viscosity", "0.05", "--allow-unphysical", "viscosity").viscosity_pa_s == 0.05
    assert _cli("--viscosity", "0.05", "--allow-unphysical").screen.allow_unphysical == ("all",)
    assert _cli("--n-phi", "3.6e3").n_phi == 3600


@pytest.mark.parametrize("degree, order", [(0, 6), (3, 6), (7, 6), (8, 6), (20, 6), (20, None), (31, 0), (30, 20)])
def test_basis_size_in_closed_form_counts_the_zernike_terms(degree, order):
    options = ReconstructionOptions(velocity=VelocityOptions(degree=degree, angular_order=order))
    assert limits.basis_size(options) == (len(_zernike_terms(degree, order)), degree)


def test_the_estimate_grows_with_every_option_that_scales_the_problem():
    base = limits.reconstruction_cost(_cli(), (1, 30, 30))
    for extra in (["--degree", "40"], ["--n-fourier", "32"], ["--quad-order", "12"], ["--n-phi", "3600"],
                  ["--angular-order", "20"]):  # fmt: skip
        c = limits.reconstruction_cost(_cli(*extra), (1, 30, 30))
        assert c.seconds > base.seconds and c.memory_bytes > base.memory_bytes, extra
    # the measured defaults (scripts/results/option_costs.md: 9 s, 138 MB on this phantom) within a factor 2
    assert 4.5 < base.seconds < 18 and 69 < base.memory_bytes / 2**20 < 276


def test_what_would_not_fit_is_refused_and_what_is_slow_asks_for_allow_large(monkeypatch):
    monkeypatch.setattr(limits, "available_memory", lambda: 16.0 * 2**30)
    with pytest.raises(InputError, match=r"in\.h5: these options need about 3\d{3}\.\d GB of memory"):
        limits.check_cost(_cli("--n-phi", "1e8"), (1, 30, 30), "in.h5")
    with pytest.raises(InputError, match=r"would take about [\d.]+ h a slice.*pass --allow-large"):
        limits.check_cost(_cli("--degree", "1000"), (1, 30, 30), "in.h5")  # the hang of issue 42
    cost = limits.check_cost(_cli("--degree", "1000", "--allow-large"), (1, 30, 30), "in.h5")
    assert cost.functions == len(_zernike_terms(1000, 6))
    with pytest.raises(InputError, match="--n-fourier"):
        limits.check_cost(_cli("--n-fourier", "500"), (1, 30, 30), "in.h5")
    limits.check_cost(_cli(), (1, 512, 512), "in.h5", lumen_voxels=300)  # a large image, a small vessel: fine


def test_phantom_memory():
    with pytest.raises(InputError, match="--h 0.001 mm"):
        limits.check_phantom(20.0, 0.001, 1, "--h")
    assert limits.check_phantom(20.0, 1.0, 1) == 40
    assert np.isfinite(limits.available_memory())
