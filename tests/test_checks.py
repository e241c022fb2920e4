"""The check helpers themselves: they pass on correct derivatives and adjoints and fail on wrong ones."""

import numpy as np
import pytest

from wss_nlp.core import checks


def test_dottest_passes_and_fails():
    a = np.random.default_rng(1).normal(size=(7, 4))
    rng = np.random.default_rng(2)
    assert checks.dottest(lambda x: a @ x, lambda y: a.T @ y, 4, 7, rng) < 1e-14
    with pytest.raises(AssertionError, match="dot test failed"):
        checks.dottest(lambda x: a @ x, lambda y: a[:, ::-1].T @ y, 4, 7, rng)


def test_taylor_passes_and_fails():
    def f(x):
        return np.array([np.sin(x[0]) * x[1], x[0] ** 3])

    def jvp(x, d):
        return np.array([np.cos(x[0]) * x[1] * d[0] + np.sin(x[0]) * d[1], 3 * x[0] ** 2 * d[0]])

    x, d = np.array([0.3, 1.2]), np.array([0.7, -0.4])
    assert np.allclose(checks.assert_taylor(f, jvp, x, d), 4.0, atol=0.5)
    with pytest.raises(AssertionError, match="Taylor test failed"):  # a derivative 1 % off is first order
        checks.assert_taylor(f, lambda x, d: 1.01 * jvp(x, d), x, d)
