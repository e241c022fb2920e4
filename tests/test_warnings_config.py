"""The suite's warning filters (pyproject.toml, issue 44): the package's own warnings and CasADi's FutureWarning on
NumPy-on-CasADi calls fail a test, while deliberate checks of a DeprecationWarning still see theirs."""

import warnings

import numpy as np
import pytest

import casadi as ca
from wss_nlp.core import checks


def test_a_warning_of_the_package_fails_the_test():
    with pytest.raises(UserWarning, match="ours"):
        warnings.warn_explicit("ours", UserWarning, "wss_nlp/core/checks.py", 1, module="wss_nlp.core.checks")
    # another package's warning is left to the default filters: no error here
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")  # record it rather than let the once-per-location registry drop it
        warnings.warn_explicit("theirs", UserWarning, "other/mod.py", 1, module="other.mod")
    assert [str(w.message) for w in seen] == ["theirs"]


def test_numpy_on_a_casadi_value_fails_and_the_checks_avoid_it():
    if not hasattr(ca.casadi, "_warn_preserve_type"):
        pytest.skip("this CasADi has no legacy-numpy notice (before 3.8)")
    with pytest.raises(FutureWarning, match="numpy function was called on a casadi value"):
        np.ravel(ca.DM([1.0, 2.0]))
    # what the Taylor and dot tests do with a function returning a DM (the call sites the suite tripped over)
    a = np.array([[2.0, 1.0], [0.0, 3.0]])
    assert checks.dottest(lambda x: ca.DM(a @ x), lambda y: ca.DM(a.T @ y), 2, 2, np.random.default_rng(0)) < 1e-12


def test_a_deliberate_check_of_a_deprecation_still_sees_it():
    from wss_nlp.parameters.options import ChoiceOptions
    from wss_nlp.pipeline import ReconstructionOptions

    with pytest.warns(DeprecationWarning, match="ReconstructionOptions.choice"):
        opts = ReconstructionOptions(beta_rule="balance")
    assert opts.choice == ChoiceOptions(beta_rule="balance")
