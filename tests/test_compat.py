"""Nothing users hold breaks with the 0.2 restructuring (issue 37): old module names, options, flags, study keys.

The frozen lists below are what version 0.1 declared (``schema.toml_keys`` and the reconstruction's arguments):
later versions may add to them, never drop or rename.
"""

import argparse
import json
import subprocess
import sys
import warnings

import pytest

from wss_nlp import MOVED
from wss_nlp.core import schema
from wss_nlp.parameters.options import ChoiceOptions
from wss_nlp.pipeline import ReconstructionOptions

#: Study keys of version 0.1.
STUDY_KEYS_0_1 = {
    "N", "acquisition", "alpha", "angular_order", "basis", "beta", "degree", "density", "dephasing_correction",
    "eta", "gamma", "heaviside", "inner_fraction", "kappa_alpha", "kappa_beta", "kspace_filter", "laplacian_power",
    "layer_scale", "max_eigenvalue", "method", "n_fourier", "n_phi", "near_wall", "prior", "quad_order", "sobolev",
    "tau_alpha", "tau_beta", "uncertainty", "velocity_weight", "viscosity", "zero_fill",
}  # fmt: skip
#: The reconstruction options' command-line flags of version 0.1.
FLAGS_0_1 = {
    "--acquisition", "--alpha", "--angular-order", "--basis", "--beta", "--blas-threads", "--cine-model",
    "--cine-walls", "--coupled-quad-order", "--degree", "--density", "--dephasing-beta", "--eta", "--gamma",
    "--geometry-solver", "--heaviside", "--hessian", "--inner-fraction", "--kappa-alpha", "--kappa-beta",
    "--kspace-filter", "--laplacian-power", "--layer-scale", "--max-eigenvalue", "--max-harmonics", "--method",
    "--n-fourier", "--n-phi", "--near-wall", "--no-dephasing-correction", "--no-uncertainty", "--no-unwrap",
    "--noise-magnitude", "--noise-sigma", "--noise-velocity", "--prior", "--quad-order", "--sobolev",
    "--stack-strategy", "--tau-alpha", "--tau-beta", "--velocity-solver", "--velocity-weight", "--vessel",
    "--viscosity", "--z-order", "--z-smoothing", "--zero-fill",
}  # fmt: skip


def test_study_keys_and_flags_of_0_1_are_kept():
    assert STUDY_KEYS_0_1 <= set(schema.toml_keys(ReconstructionOptions))
    p = argparse.ArgumentParser()
    schema.add_arguments(p, ReconstructionOptions)
    flags = {s for action in p._actions for s in action.option_strings if s.startswith("--")}
    assert FLAGS_0_1 <= flags
    # and they still set what they set: the choice's fields now live in options.choice
    o = schema.build(ReconstructionOptions, {"alpha": "auto", "beta": 1e-7, "tau_beta": 1.5})
    assert (o.choice.alpha_rule, o.choice.beta_rule, o.velocity.beta, o.choice.tau_beta) == (
        "balance",
        "fixed",
        1e-7,
        1.5,
    )


def test_old_module_names_are_the_moved_modules_with_a_warning():
    # one fresh interpreter for all (a module imported before would not be looked for again)
    code = (
        "import importlib, warnings\n"
        "from wss_nlp import MOVED\n"
        "for old, new in MOVED.items():\n"
        "    with warnings.catch_warnings(record=True) as w:\n"
        "        warnings.simplefilter('always')\n"
        "        a = importlib.import_module('wss_nlp.' + old)\n"
        "    assert a is importlib.import_module('wss_nlp.' + new), old\n"
        "    assert any(issubclass(x.category, DeprecationWarning) and new in str(x.message) for x in w), old\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    assert len(MOVED) >= 40


def test_the_0_1_readme_imports_still_work():
    code = (
        "import warnings; warnings.simplefilter('ignore', DeprecationWarning)\n"
        "from wss_nlp import files, metrics, phantoms\n"
        "from wss_nlp.reconstruct import ReconstructionOptions, reconstruct\n"
        "import wss_nlp.pipeline.driver as d\n"
        "assert reconstruct is d.reconstruct and files.Acquisition\n"
        "assert metrics.compare_slice and phantoms.make_phantom\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)


def test_choice_fields_by_their_0_1_names():
    with pytest.warns(DeprecationWarning, match="ReconstructionOptions.choice"):
        o = ReconstructionOptions(beta_rule="gcv", noise_velocity=0.02)
    assert o.choice == ChoiceOptions(beta_rule="gcv", noise_velocity=0.02)
    assert o.beta_rule == "gcv" and o.noise_velocity == 0.02  # read through to the choice
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the new spelling warns about nothing
        assert ReconstructionOptions(choice=ChoiceOptions(beta_rule="gcv")).beta_rule == "gcv"
    # the stored options keep the 0.1 keys at the root beside the nested choice
    stored = json.loads(json.dumps(o.as_dict(), default=str))
    assert stored["beta_rule"] == "gcv" and stored["choice"]["beta_rule"] == "gcv"
