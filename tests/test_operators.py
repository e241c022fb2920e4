"""BLAS-evaluated linear maps inside CasADi graphs (wss_nlp.core.operators) against CasADi's own products."""

import numpy as np
import pytest

import casadi as ca
from wss_nlp.core import checks, operators
from wss_nlp.models import measurement as meas
from wss_nlp.core import radius as rad

# rounding only: the sums have at most a few hundred terms of size O(1)
RTOL = 1e-12


def _same_graph(mine, plain, x, x0):
    """Values, Jacobian (forward mode), gradient (reverse mode) and Hessian (forward over reverse) of a nonlinear
    graph around each map, with ``mine`` and with CasADi's product ``plain``."""
    outs = []
    for inner in (mine, plain):
        y = ca.sin(ca.vec(inner)) + ca.vec(inner) ** 2
        f = ca.sumsqr(y)
        fun = ca.Function("f", [x], [y, ca.jacobian(y, x), ca.gradient(f, x), ca.hessian(f, x)[0]])
        outs.append([np.asarray(v) for v in fun(x0)])
    for a, b in zip(*outs):
        assert np.max(np.abs(a - b)) <= RTOL * max(1.0, np.max(np.abs(b)))


def test_matrix_product_equals_casadi_product_with_exact_derivatives_and_passes_a_dot_test():
    """MatrixProduct (one and several columns) has the values and first and second derivatives of ca.mtimes;
    the map and its adjoint pass a dot test."""
    rng = np.random.default_rng(11)
    a = rng.normal(size=(13, 5))
    for cols in (1, 3):
        op = operators.MatrixProduct(a, cols)
        x = ca.MX.sym("x", 5, cols)
        _same_graph(op(x), ca.mtimes(ca.DM(a), x), x, rng.normal(size=(5, cols)))
    op, adj = operators.MatrixProduct(a), operators.MatrixProduct(a, adjoint=True)
    checks.dottest(lambda v: op.apply(v[:, None]), lambda w: adj.apply(w[:, None]), 5, 13, rng)


def test_grouped_weighted_sum_equals_its_formula_with_exact_derivatives_and_passes_a_dot_test():
    """GroupedWeightedSum s -> M diag(s) B (M the mean over groups of 4 rows) against the same map written with
    CasADi's products; adjoint by a dot test; rows that do not split into groups are refused."""
    rng = np.random.default_rng(12)
    group, k, n = 4, 3, 5
    b = rng.normal(size=(group * k, n))
    mean = np.kron(np.eye(k), np.ones((1, group)) / group)
    op = operators.GroupedWeightedSum(b, group)
    s = ca.MX.sym("s", group * k)
    plain = ca.vec(ca.mtimes(ca.DM(mean), ca.repmat(s, 1, n) * ca.DM(b)))
    _same_graph(op(s), plain, s, rng.normal(size=group * k))
    adj = operators.GroupedWeightedSum(b, group, adjoint=True)
    checks.dottest(lambda v: op.apply(v[:, None]), lambda w: adj.apply(w[:, None]), group * k, k * n, rng)
    with pytest.raises(ValueError, match="groups of 5"):
        operators.GroupedWeightedSum(b, 5)


def test_gram_equals_casadi_product_with_exact_derivatives():
    """Gram J -> J^T J against ca.mtimes(J.T, J): values and derivatives of a nonlinear graph around it."""
    rng = np.random.default_rng(13)
    j, gram = ca.MX.sym("j", 9, 4), operators.Gram(9, 4)  # a callback must outlive the graphs that use it
    _same_graph(gram(j), ca.mtimes(j.T, j), j, rng.normal(size=(9, 4)))


@pytest.mark.parametrize("factored", [False, True])
def test_block_gram_equals_the_products_of_the_assembled_matrix(factored):
    """BlockGram (A, B, C, r1, r2) -> (J^T J, J^T r) with J = [[A, 0], [sqrt(w) B, sqrt(w) C F]] and
    r = [r1; sqrt(w) r2] (F = right, or the identity; C in two column blocks with F), against the dense
    products of the assembled J."""
    rng = np.random.default_rng(14)
    k = 6 if factored else 5
    a, b, c, w = rng.normal(size=(7, 3)), rng.normal(size=(11, 3)), rng.normal(size=(11, k)), 2.7
    r1, r2 = rng.normal(size=7), rng.normal(size=11)
    right = rng.normal(size=(k, 5)) if factored else None
    widths = (4, 2) if factored else (5,)
    gram = operators.BlockGram(7, 3, 11, 5, w, right=right, widths=widths)
    blocks = [c[:, :4], c[:, 4:]] if factored else [c]
    cf = c if right is None else c @ right
    j = np.block([[a, np.zeros((7, 5))], [np.sqrt(w) * b, np.sqrt(w) * cf]])
    r = np.concatenate([r1, np.sqrt(w) * r2])
    jtj, jtr = (np.asarray(v) for v in gram(a, b, *blocks, r1, r2))
    # a few BLAS products in another order than the assembled ones: equal to rounding
    np.testing.assert_allclose(jtj, j.T @ j, rtol=0, atol=1e-13 * np.max(np.abs(j.T @ j)))
    np.testing.assert_allclose(jtr.ravel(), j.T @ r, rtol=0, atol=1e-13 * np.max(np.abs(j.T @ r)))
    # an output nobody reads is skipped (CasADi passes no buffer for it)
    shapes = [(7, 3), (11, 3), *[(11, wd) for wd in widths], (7, 1), (11, 1)]
    x = [ca.MX.sym(f"x{i}", *shape) for i, shape in enumerate(shapes)]
    only = ca.Function("only", x, [gram(*x)[0]])
    np.testing.assert_array_equal(np.asarray(only(a, b, *blocks, r1, r2)), jtj)
    with pytest.raises(ValueError, match="right factor"):
        operators.BlockGram(7, 3, 11, 4, w, right=np.ones((k, 5)))
    with pytest.raises(ValueError, match="column blocks"):
        operators.BlockGram(7, 3, 11, 5, w, right=right, widths=(k, 1))


@pytest.mark.parametrize("kind", meas.HEAVISIDES)
def test_box_magnitude_jacobian_by_the_chain_rule_equals_casadi_ad(kind):
    """The box magnitude model's Gauss-Newton Jacobian (magnitude_model(jacobian=True)) equals CasADi's AD of
    the same model, and the model's values equal its NumPy evaluation, on an off-centre lumen."""
    grid = meas.VoxelGrid((24, 24), (1.0, 1.0), (-11.5, -11.5))
    model = meas.annulus_model(grid, (0.3, -0.2), 6.0, 10.0, 3)
    c0 = np.zeros(rad.n_coefficients(4))
    c0[0], c0[1], c0[6] = 8.0, 0.5, -0.3
    c = ca.MX.sym("c", c0.size)
    value, jac = meas.magnitude_model(model, c, 1.0 / 3, kind, jacobian=True)
    fun = ca.Function("f", [c], [value, jac, ca.jacobian(value, c)])
    v, j1, j2 = (np.asarray(a) for a in fun(c0))
    np.testing.assert_allclose(v.ravel(), meas.magnitude_model(model, c0, 1.0 / 3, kind), rtol=0, atol=1e-14)
    assert np.max(np.abs(j1 - j2)) <= RTOL * np.max(np.abs(j2))


def test_scattered_blocks_equal_casadi_scatter_with_exact_derivatives_and_pass_a_dot_test():
    """ScatteredBlocks s -> [P diag(s) b_j]_j (rows scattered into column-major images, side by side) against the
    same map with CasADi's sparse products; adjoint by a dot test on one and on two columns."""
    rng = np.random.default_rng(14)
    fy, fx, m, n = 5, 4, 7, 3
    index = rng.choice(fy * fx, m, replace=False)
    b = rng.normal(size=(m, n))
    op = operators.ScatteredBlocks(b, index, (fy, fx))
    scatter = np.zeros((fy * fx, m))
    scatter[index, np.arange(m)] = 1.0
    s = ca.MX.sym("s", m)
    plain = ca.reshape(ca.mtimes(ca.DM(scatter), ca.repmat(s, 1, n) * ca.DM(b)), fy, fx * n)
    _same_graph(op(s), plain, s, rng.normal(size=m))
    for cols in (1, 2):
        fwd = operators.ScatteredBlocks(b, index, (fy, fx), cols)
        adj = operators.ScatteredBlocks(b, index, (fy, fx), cols, adjoint=True)

        def apply(cb, v, size):
            out = np.zeros(size)
            cb.eval_buffer([np.ascontiguousarray(v)], [out])
            return out

        checks.dottest(
            lambda v: apply(fwd, v, fy * fx * n * cols),
            lambda w: apply(adj, w, m * cols),
            m * cols,
            fy * fx * n * cols,
            rng,
        )
