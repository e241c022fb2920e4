"""The one-decomposition Tikhonov object against per-beta Cholesky solves (two independent solvers)."""

import numpy as np
import pytest
import scipy.linalg

from wss_nlp.parameters import rules as pr
from wss_nlp.synthetic import phantoms
from wss_nlp.models import velocity as vel
from wss_nlp.models import wss as wss_mod
from wss_nlp.pipeline import ReconstructionOptions, reconstruct
from wss_nlp.core.tikhonov import LinearTikhonov

BETAS = pr.geometric_grid(1e-2, 1e-14)


def _reference(op, weights, data, gram, betas, functional, sigma):
    """The former implementation: one Cholesky factorization per beta, noise through a Cholesky root."""
    w = weights / np.sum(weights)
    tw = op * w[:, None]
    ktk, rhs = tw.T @ op, tw.T @ data
    noise_gram = (tw * sigma[:, None] ** 2).T @ tw
    jitter = 1e-14 * np.trace(noise_gram) / len(noise_gram)
    root = np.linalg.cholesky(noise_gram + jitter * np.eye(len(noise_gram)))
    est, noise, res, gcv, pen = [], [], [], [], []
    for beta in betas:
        h = ktk + beta / np.pi * gram
        cho = scipy.linalg.cho_factor(h)
        c = scipy.linalg.cho_solve(cho, rhs)
        est.append(functional @ c)
        noise.append((functional @ scipy.linalg.cho_solve(cho, root)).ravel())
        r2 = float(np.sum(w * (op @ c - data) ** 2))
        res.append(np.sqrt(r2))
        tr = float(np.trace(np.linalg.solve(h, ktk)))
        gcv.append(data.size * r2 / (data.size - tr) ** 2)
        pen.append(float(c @ gram @ c / np.pi))
    est, noise = np.array(est), np.array(noise)
    return est @ est.T, noise @ noise.T, np.array(res), np.array(gcv), np.array(pen)


@pytest.fixture(scope="module", params=[("laminar", 1.0, 71), ("turbulent", 0.6, 72)])
def problem(request):
    case, h, seed = request.param
    acq, _ = phantoms.make_phantom(case, h_mm=h, snr=25, seed=seed)
    res = reconstruct(acq, ReconstructionOptions(uncertainty=False))[0]
    opts = vel.VelocityOptions()
    vp = vel.assemble(acq.grid, acq.velocity_images()[0], res.geometry.coefficients, res.geometry.center, opts)
    smat, _ = wss_mod.wss_matrix(vp.basis, vp.disk_map, 3.5e-3, 360)
    sigma = np.random.default_rng(seed).uniform(0.005, 0.05, vp.data.size)
    return vp, smat, sigma


def test_pencil_equals_per_beta_cholesky(problem):
    vp, smat, sigma = problem
    tik = LinearTikhonov(vp.operator, vp.weights, vp.data, vp.gram)
    g_est, g_noise, res, gcv, pen = _reference(vp.operator, vp.weights, vp.data, vp.gram, BETAS, smat, sigma)
    e, n, r = tik.balance_grams(BETAS, smat, sigma)
    # relative to the largest entry: both are double-precision solves of the same systems (cond <= ~1e12)
    assert np.max(np.abs(e - g_est)) <= 1e-10 * np.max(np.abs(g_est))
    assert np.max(np.abs(n - g_noise)) <= 1e-10 * np.max(np.abs(g_noise))
    assert np.allclose(r, res, rtol=1e-10, atol=0)
    g2, r2, p2 = tik.gcv(BETAS)
    assert np.allclose(g2, gcv, rtol=1e-9) and np.allclose(r2, res, rtol=1e-10) and np.allclose(p2, pen, rtol=1e-8)
    for k in (0, len(BETAS) // 2, len(BETAS) - 1):
        c = tik.coefficients(BETAS[k : k + 1])[0]
        assert np.allclose(c, tik.solve(BETAS[k]), rtol=0, atol=1e-9 * np.max(np.abs(c)))


def test_fast_balancing_choice_equals_the_former_one(problem):
    vp, smat, sigma = problem
    g_est, g_noise, _, _, _ = _reference(vp.operator, vp.weights, vp.data, vp.gram, BETAS, smat, sigma)
    j_ref, ratio_ref = pr.balancing_principle(g_est, g_noise, 2.5)
    j, ratio, _ = pr.wss_balance(vp.tikhonov, BETAS, smat, sigma, 2.5)
    assert j == j_ref
    # the ratio is |x_j - x_k| / s_jk from Gram entries, |x_j - x_k|^2 = G_jj + G_kk - 2 G_jk: it inherits a
    # cancellation error of about eps |x|^2 / |x_j - x_k|^2 (~1e-8 between neighbouring large betas) from either
    # solver, so it is compared at 1e-6; the Gram matrices themselves agree to 1e-10 (test above)
    finite = np.isfinite(ratio_ref)
    assert np.allclose(ratio[finite], ratio_ref[finite], rtol=1e-6, atol=0)


def test_rank_deficient_normal_matrix():
    # fewer data than unknowns: K is singular, the pencil still holds (B = K + b0 G is definite)
    rng = np.random.default_rng(73)
    op = rng.normal(size=(6, 10))
    root = rng.normal(size=(10, 10))
    gram = root @ root.T
    tik = LinearTikhonov(op, rng.uniform(0.5, 1, 6), rng.normal(size=6), gram)
    for beta in (1e-2, 1e-5, 1e-8):  # where cond(H) <= ~1e10, so both solutions carry >= 6 digits
        assert np.allclose(tik.coefficients([beta])[0], tik.solve(beta), rtol=1e-6, atol=1e-9)


def test_bordered_problem_equals_the_full_one_solved_directly():
    """Appended unpenalized columns through the original's pencils: the same coefficients and traces as the full
    problem's Cholesky solves and explicit traces (rounding: 1e-12 relative), on a semi-definite penalty."""
    from wss_nlp.core.tikhonov import BorderedTikhonov

    rng = np.random.default_rng(21)
    n, m, k = 300, 40, 5
    op, extra = rng.standard_normal((n, m)), rng.standard_normal((n, k))
    w, u = rng.uniform(0.2, 1, n), rng.standard_normal(n)
    root = rng.standard_normal((m, m))
    gram = root @ root.T
    gram[:3], gram[:, :3] = 0, 0
    full = LinearTikhonov(np.hstack([op, extra]), w, u, np.pad(gram, ((0, k), (0, k))))
    betas = 10.0 ** -np.arange(1, 14, 0.5)
    coef, traces = BorderedTikhonov(LinearTikhonov(op, w, u, gram), extra).coefficients_and_traces(betas)
    ref = np.array([full.solve(b) for b in betas])
    np.testing.assert_allclose(coef, ref, rtol=0, atol=1e-12 * np.max(np.abs(ref)))
    ref_tr = [np.trace(np.linalg.solve(full.hessian(b), full.normal)) for b in betas]
    np.testing.assert_allclose(traces, ref_tr, rtol=1e-12, atol=1e-11)


def test_bordered_normal_equations_equal_the_full_problems():
    """LinearTikhonov.bordered (the normal matrix by blocks from the plain one's) gives the normal matrix,
    right-hand side and solutions of the problem formed from [T, E] directly, to rounding (1e-13 relative)."""
    rng = np.random.default_rng(22)
    n, m, k = 400, 30, 4
    op, extra = rng.standard_normal((n, m)), rng.standard_normal((n, k))
    w, u = rng.uniform(0.2, 1, n), rng.standard_normal(n)
    root = rng.standard_normal((m + k, m + k))
    gram = root @ root.T
    full = LinearTikhonov(np.hstack([op, extra]), w, u, gram)
    bordered = LinearTikhonov(op, w, u, gram[:m, :m]).bordered(np.hstack([op, extra]), w, gram)
    scale = np.max(np.abs(full.normal))
    np.testing.assert_allclose(bordered.normal, full.normal, rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(bordered.rhs, full.rhs, rtol=0, atol=1e-13 * np.max(np.abs(full.rhs)))
    for beta in (1e-2, 1e-6):
        ref = full.solve(beta)
        np.testing.assert_allclose(bordered.solve(beta), ref, rtol=0, atol=1e-11 * np.max(np.abs(ref)))


def test_with_data_shares_the_pencils_and_equals_a_fresh_problem(problem):
    """LinearTikhonov.with_data (the frames of a cine slice on one wall): with other data (seeded) it gives the
    same numbers as a problem built afresh from them: coefficients, residuals and traces bit for bit (the same
    operations on the same normal matrix and pencil), while the normal matrix and the pencil dictionary are the
    first problem's objects (formed once: a pencil one problem computes serves the other)."""
    vp, _, _ = problem
    first = LinearTikhonov(vp.operator, vp.weights, vp.data, vp.gram)
    other_data = vp.data * 0.7 + 0.01 * np.random.default_rng(73).standard_normal(vp.data.size)
    shared, fresh = first.with_data(other_data), LinearTikhonov(vp.operator, vp.weights, other_data, vp.gram)
    assert shared.normal is first.normal and shared._pencils is first._pencils
    first.traces(BETAS)  # the pencils now exist, computed on the first data
    assert np.array_equal(shared.rhs, fresh.rhs)
    assert np.array_equal(shared.coefficients(BETAS), fresh.coefficients(BETAS))
    assert np.array_equal(shared.gcv(BETAS)[1], fresh.gcv(BETAS)[1])
    assert np.array_equal(shared.traces(BETAS), fresh.traces(BETAS))
